"""CPU time per process of a demo run: where the machine's cores go while the pipeline runs.

The latency stages say when each node is done with a frame; this says how busy each process kept the cores doing
it. On a machine with few cores the nodes wait for each other's CPU, so a stage can take several times its own
compute. Read from Linux ``/proc/<pid>/stat`` (user + system time of every thread); a process's children (the
estimator's smoother process) are counted under ``<name>/child``. Elsewhere :meth:`CpuSampler.shares` is empty.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

PROC = Path('/proc')


def _stat(pid: int | str) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command name (state, ppid, ...), None when it is gone."""
    try:
        return (PROC / str(pid) / 'stat').read_text().rsplit(')', 1)[1].split()
    except (OSError, IndexError):
        return None


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time (s) of a process so far, None when it is gone or /proc is not there."""
    fields = _stat(pid)
    return None if fields is None else (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (a scan of /proc: the kernel's children lists are often not built)."""
    out = []
    try:
        entries = [e for e in os.listdir(PROC) if e.isdigit()]
    except OSError:
        return out
    for e in entries:
        fields = _stat(e)
        if fields is not None and fields[1] == str(pid):
            out.append(int(e))
    return out


@dataclass
class _Span:
    first: tuple[float, float]          # (wall clock, CPU s) at the first sample
    last: tuple[float, float]


@dataclass
class CpuSampler:
    """Call :meth:`sample` now and then while the run goes on (each process is measured between its own first and
    last sample, so one that exits early, like the simulated rig at the end, still counts)."""

    pids: dict[str, int]                                   # the nodes, with their children
    alone: dict[str, int] = field(default_factory=dict)    # without their children (the demo, whose are the nodes)
    spans: dict[str, _Span] = field(default_factory=dict)

    def sample(self, now: float) -> None:
        for name, pid in self.alone.items():
            self._record(name, pid, now)
        for name, pid in self.pids.items():
            self._record(name, pid, now)
            for k, child in enumerate(sorted(children(pid))):
                self._record(f'{name}/child' + (f'{k + 1}' if k else ''), child, now)

    def _record(self, name: str, pid: int, now: float) -> None:
        cpu = cpu_seconds(pid)
        if cpu is None:
            return
        span = self.spans.get(name)
        if span is None:
            self.spans[name] = _Span((now, cpu), (now, cpu))
        else:
            span.last = (now, cpu)

    def shares(self) -> dict[str, float]:
        """Per process, % of one core over its sampled span (spans under 1 s left out), and ``total``."""
        out = {}
        for name, s in self.spans.items():
            dt = s.last[0] - s.first[0]
            if dt >= 1.0:
                out[name] = round(100.0 * (s.last[1] - s.first[1]) / dt, 1)
        if out:
            out['total'] = round(sum(out.values()), 1)
        return out
