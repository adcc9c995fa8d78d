"""The demo's CPU share per process (/proc): a process's own time, its children's, and processes that are gone."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from fixego_ros.demo.cpu import CpuSampler, children, cpu_seconds

pytestmark = pytest.mark.skipif(not Path('/proc/self/stat').exists(), reason='needs Linux /proc')

# says "ready" once its interpreter has started (start-up costs tens of ms of CPU on a slow machine, which must
# not fall between the test's samples), then on a "go" line burns `cpu_s` more of its own CPU time (however long
# that takes on a busy machine), says "done", then waits for stdin to close
BURN = ('import sys, time\n'
        'print("ready", flush=True)\n'
        'sys.stdin.readline()\n'
        't = time.process_time() + {cpu_s}\n'
        'while time.process_time() < t:\n'
        '    pass\n'
        'print("done", flush=True)\n'
        'sys.stdin.read()\n')
# starts the burner as its child and prints its pid once the child is ready, passes "go" on, says when the child is done
PARENT = ('import subprocess, sys\n'
          'c = subprocess.Popen([sys.executable, "-c", {burn!r}], stdin=subprocess.PIPE, stdout=subprocess.PIPE, '
          'text=True)\n'
          'c.stdout.readline()\n'
          'print(c.pid, flush=True)\n'
          'c.stdin.write(sys.stdin.readline())\n'
          'c.stdin.flush()\n'
          'print(c.stdout.readline().strip(), flush=True)\n'
          'sys.stdin.read()\n'
          'c.stdin.close()\n'
          'c.wait(timeout=10)\n')


def _start(code: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, '-c', code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def _burn(p: subprocess.Popen) -> None:
    """Let the burner go and wait (bounded by the test's own timeout) for it to be done."""
    p.stdin.write('go\n')
    p.stdin.flush()
    assert p.stdout.readline().strip() == 'done'


def _stop(p: subprocess.Popen) -> None:
    p.stdin.close()
    p.wait(timeout=10)


def test_a_childs_cpu_time_is_counted_under_its_parent_and_kept_apart_from_the_parents_own():
    parent = _start(PARENT.format(burn=BURN.format(cpu_s=0.4)))
    try:
        child_pid = int(parent.stdout.readline())
        assert children(parent.pid) == [child_pid]
        sampler = CpuSampler({'node': parent.pid})
        sampler.sample(0.0)
        _burn(parent)                                            # the child burns 0.4 s
        sampler.sample(2.0)                                      # the caller's clock: 2 s between the samples
        shares = sampler.shares()
    finally:
        _stop(parent)
    assert 19.0 <= shares['node/child'] <= 22.0                  # 0.4 s (+ clock ticks, exit) over 2 s
    assert shares['node'] < 5.0                                  # the parent only waited
    assert shares['total'] == pytest.approx(shares['node'] + shares['node/child'], abs=0.11)


def test_a_process_that_exits_keeps_its_share_over_its_own_span_and_short_spans_are_left_out():
    p = _start(BURN.format(cpu_s=0.3))
    assert p.stdout.readline().strip() == 'ready'
    sampler = CpuSampler({}, {'alone': p.pid})
    sampler.sample(0.0)
    _burn(p)
    sampler.sample(1.0)
    _stop(p)
    assert cpu_seconds(p.pid) is None                            # gone: later samples skip it
    sampler.sample(5.0)
    assert 29.0 <= sampler.shares()['alone'] <= 32.0             # 0.3 s over its own span of 1 s, not 5 s
    brief = CpuSampler({}, {'me': os.getpid()})
    brief.sample(0.0)
    brief.sample(0.5)
    assert brief.shares() == {}                                  # a span under 1 s: no number, no total


def test_no_process_no_numbers():
    assert cpu_seconds(2**22 + 12345) is None
    sampler = CpuSampler({'gone': 2**22 + 12345})
    sampler.sample(0.0)
    sampler.sample(3.0)
    assert sampler.shares() == {}
