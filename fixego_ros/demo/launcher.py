"""A small stand-in for ``ros2 launch`` (not available as a wheel): start nodes as separate processes,
watch them, and stop them with bounded waits (SIGINT, then SIGTERM, then SIGKILL)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path


def ros_arg_value(v: object) -> str:
    """A parameter value in the ``-p name:=value`` (YAML) syntax."""
    if isinstance(v, bool):
        return 'true' if v else 'false'
    if isinstance(v, (int, float)):
        return repr(v)
    s = str(v)
    return "''" if s == '' else s


@dataclass
class NodeSpec:
    """One node process: ``python -P -m module --ros-args -r __node:=name -p k:=v ...``. ``-P``: the node imports the
    package this process imports (``PYTHONPATH`` or the installed one), not a ``fixego_ros`` folder in the working
    directory. Without it, ``fixego demo`` run from a checkout ran that checkout's nodes whatever ``PYTHONPATH`` said:
    stop 68's first comparison of two codes ran the same nodes on both sides."""

    name: str
    module: str
    params: dict[str, object] = field(default_factory=dict)

    def argv(self) -> list[str]:
        args = [sys.executable, '-P', '-m', self.module, '--ros-args', '-r', f'__node:={self.name}']
        for k, v in self.params.items():
            args += ['-p', f'{k}:={ros_arg_value(v)}']
        return args


class Launcher:
    """Owns the node processes of one run; logs go to ``log_dir/<name>.log``."""

    def __init__(self, log_dir: Path, env: dict[str, str] | None = None) -> None:
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.env = dict(os.environ if env is None else env)
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: list = []

    def start(self, spec: NodeSpec) -> subprocess.Popen:
        log = open(self.log_dir / f'{spec.name}.log', 'wb')  # noqa: SIM115 (closed in stop_all)
        self._logs.append(log)
        # own process group, so a Ctrl-C on the terminal reaches the demo first and it stops the nodes in order
        proc = subprocess.Popen(spec.argv(), stdout=log, stderr=subprocess.STDOUT, env=self.env,
                                start_new_session=True)
        self.procs[spec.name] = proc
        return proc

    def exited(self) -> dict[str, int]:
        """Names and exit codes of processes that have ended."""
        return {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}

    def log_tail(self, name: str, lines: int = 15) -> str:
        try:
            text = (self.log_dir / f'{name}.log').read_text(errors='replace')
        except OSError:
            return ''
        return '\n'.join(text.splitlines()[-lines:])

    def stop(self, name: str, timeout_s: float = 5.0) -> int | None:
        p = self.procs.get(name)
        if p is None:
            return None
        for sig, wait in ((signal.SIGINT, timeout_s), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
            if p.poll() is not None:
                break
            try:
                os.killpg(p.pid, sig)
            except ProcessLookupError:
                break
            try:
                p.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                continue
        return p.poll()

    def stop_all(self, timeout_s: float = 5.0) -> dict[str, int | None]:
        """Stop every process (in reverse start order); returns the exit codes."""
        codes = {n: self.stop(n, timeout_s) for n in reversed(list(self.procs))}
        for log in self._logs:
            log.close()
        self._logs.clear()
        return codes


def wait_for(predicate, timeout_s: float, step_s: float = 0.1, spin=None) -> bool:
    """Poll ``predicate`` (spinning ``spin(step_s)`` in between, if given) until true or ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        if spin is not None:
            spin(step_s)
        else:
            time.sleep(step_s)
    return bool(predicate())
