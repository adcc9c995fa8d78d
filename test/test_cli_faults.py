"""Bad options of ``fixego sim``, ``fixego paper-sim`` and ``fixego demo`` are refused up front.

Every refusal: exit code 2, exactly one stderr line ``fixego <cmd>: ...`` naming the option (and, for a
number, its value), no traceback, nothing created at ``--out`` or anywhere in the working directory (and,
for the demo, no process started: the check runs before the report folder and the launcher exist).

Each case is its own process with its own stdout, stderr and exit code. A fresh ``python -m fixego_ros.cli``
costs ~0.7 s of imports (scipy, OpenCV) and there are >130 cases, so most run in processes forked from one
interpreter that has imported the commands already (:data:`FORK_DRIVER`, bounded per case and overall); a
sample of them also runs as plain ``python -m fixego_ros.cli`` subprocesses, which covers the real entry point.
Also: a tiny valid ``fixego sim`` run still works, and a run that fails part way or is stopped by SIGTERM
leaves no partial bag behind, so the same ``--out`` works again.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

TIMEOUT_S = 60
SIM = ['sim', '--duration', '0.2', '--width', '64', '--height', '48', '--no-progress']
SIM_NO_DURATION = ['sim', '--width', '64', '--height', '48', '--no-progress']
PAPER = ['paper-sim', '--presets', 'dense', '--trials', '4', '--trials-seq', '2', '--jobs', '1']
DEMO = ['demo', '--quiet']


def _numeric(option: str, values: str) -> list[tuple[str, str, str]]:
    return [(option, v, f'{option}={v}') for v in values.split()]


# (option, value as typed, argument): the numbers of `fixego sim`
SIM_NUMBERS = [
    *_numeric('--fps', '0 nan inf -inf -1 1e308 0.01 1001'),
    *_numeric('--speed', '0 -1 nan inf 1e308 1e-9'),
    *_numeric('--texel', '0 -1 nan inf 1e308 1e-9 2'),
    *_numeric('--hfov', '-1 0 nan inf 1e308 180 179.9'),
    *_numeric('--duration', 'nan inf 1e308 -1 0 -inf'),
    *_numeric('--width', '-1 0 8193'),
    *_numeric('--height', '-1 0 5'),
    *_numeric('--seed', '-1 4294967296'),
    *_numeric('--noise', 'nan inf -inf 1e308 -1 256'),
    *_numeric('--wheel-odom-std', '1e308 nan inf -1 11'),
    *_numeric('--rest', 'nan inf -1 601'),
    *_numeric('--rest-end', 'nan inf -1 601'),
]
# id -> (argv without --out, option the error names, refused value as typed or None, prog): one case each
CASES: dict[str, tuple[list[str], str, str | None, str]] = {}
for opt, raw, arg in SIM_NUMBERS:
    CASES[f'sim{arg}'] = ([*SIM, arg], opt, raw, 'fixego sim')
for raw in ('-1', '131'):
    CASES[f'sim--steps={raw}'] = ([*SIM_NO_DURATION, f'--steps={raw}'], '--steps', raw, 'fixego sim')
CASES.update({
    'sim--steps-straight': ([*SIM_NO_DURATION, '--trajectory', 'straight', '--steps', '3'], '--steps', None,
                            'fixego sim'),
    'sim--width-alone-too-small-height': (['sim', '--duration', '0.2', '--width', '24', '--no-progress'], '--width',
                                          '24', 'fixego sim'),
    'sim--fps-abc': ([*SIM, '--fps', 'abc'], '--fps', 'abc', 'fixego sim'),
    'sim--fps-space-inf': ([*SIM, '--fps', '-inf'], '--fps', None, 'fixego sim'),
    'sim--seed-float': ([*SIM, '--seed', '1.5'], '--seed', '1.5', 'fixego sim'),
    'sim-duration-and-steps': ([*SIM, '--steps', '3'], '--steps', None, 'fixego sim'),
})
for n in ('-1', '0', '1000000001'):
    for opt in ('--trials', '--trials-seq'):
        CASES[f'paper{opt}={n}'] = ([*PAPER, f'{opt}={n}'], opt, n, 'fixego paper-sim')
for n in ('0', '-1', '100000', '65'):
    CASES[f'paper--jobs={n}'] = ([*PAPER, f'--jobs={n}'], '--jobs', n, 'fixego paper-sim')
CASES.update({
    'paper--seed=-1': ([*PAPER, '--seed=-1'], '--seed', '-1', 'fixego paper-sim'),
    'paper--presets=bogus': ([*PAPER, '--presets=bogus'], '--presets', 'bogus', 'fixego paper-sim'),
    'paper--presets=': ([*PAPER, '--presets='], '--presets', None, 'fixego paper-sim'),
    'paper--presets=,': ([*PAPER, '--presets=,'], '--presets', None, 'fixego paper-sim'),
    'paper--presets=dense,,paper': ([*PAPER, '--presets=dense,,paper'], '--presets', None, 'fixego paper-sim'),
    'paper--presets=dense,dense': ([*PAPER, '--presets=dense,dense'], '--presets', None, 'fixego paper-sim'),
    'paper--trials=abc': ([*PAPER, '--trials=abc'], '--trials', 'abc', 'fixego paper-sim'),
})
DEMO_NUMBERS = [
    *_numeric('--ready-timeout', 'nan inf -1 0 1e308'),
    *_numeric('--fps', '0 nan inf -1 1e308'),
    *_numeric('--duration', 'nan -1 inf 1e308'),
    *_numeric('--width', '-1 0 100000'),
    *_numeric('--height', '-1 0'),
    *_numeric('--domain-id', '233 -1'),
    *_numeric('--seed', '-1 4294967296'),
    *_numeric('--rest-end', 'nan -1 601'),
]
for opt, raw, arg in DEMO_NUMBERS:
    CASES[f'demo{arg}'] = ([*DEMO, arg], opt, raw, 'fixego demo')
CASES['demo--profile=evi_x'] = ([*DEMO, '--profile=evi_x'], '--profile', 'evi_x', 'fixego demo')

PLAY = ['play', str(Path(__file__).resolve().parents[1] / 'bags' / 'walk'), '--delay', '0']
for opt, raw, arg in [*_numeric('--rate', '1e-300 -1 nan inf 1e308'), *_numeric('--start-offset', '1e308 nan -1'),
                      *_numeric('--delay', 'inf -1'), *_numeric('--domain-id', '-1 233 99999999999999999999')]:
    CASES[f'play{arg}'] = ([*PLAY, arg], opt, raw, 'fixego play')
CASES['play--remap'] = ([*PLAY, '--remap', '/fixego/left/image_raw:=bad topic!'], '--remap', None, 'fixego play')
for opt, raw, arg in [*_numeric('--duration', 'inf 1e308 nan 0 -1'), *_numeric('--domain-id', '-1 233')]:
    CASES[f'record{arg}'] = (['record', 'rec', arg], opt, raw, 'fixego record')
CASES['record-topic'] = (['record', 'rec', 'bad topic!', '--duration', '1'], 'TOPIC', None, 'fixego record')

# --out of each command: (value, what the error names); 'afile' is a file in the working directory
OUT_CASES = {
    'sim': ([*SIM], [('/proc/x', '/proc/x'), ('afile/sub', 'afile'), ('', '--out'), ('afile', 'afile'),
                     ('.', '--out'), ('nodir/sub', 'nodir'), ('existing', 'existing')]),
    'paper': ([*PAPER], [('/proc/x', '/proc/x'), ('afile/sub', 'afile'), ('', '--out'), ('afile', 'afile')]),
    'demo': ([*DEMO], [('/proc/x', '/proc/x'), ('afile/sub', 'afile'), ('', '--out'), ('afile', 'afile'),
                       ('afile/a/b', 'afile')]),
}
# --rig: (file name, content or None for a special path)
RIG_CASES = {'garbage': b'\x89PNG\r\n\x1a\n\xff\xfe\x00binary' * 20, 'badyaml': b'right: [unclosed\n',
             'notarig': b'just: text\n', 'dir': None, '/dev/zero': None, 'missing': None}


def _fixego(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, MPLBACKEND='Agg', ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return subprocess.run([sys.executable, '-m', 'fixego_ros.cli', *args], cwd=cwd, capture_output=True, text=True,
                          timeout=TIMEOUT_S, env=env)


def _workdir(base: Path) -> Path:
    base.mkdir(parents=True)
    (base / 'afile').write_text('not a directory\n')
    (base / 'existing').mkdir()
    (base / 'garbage').write_bytes(RIG_CASES['garbage'])
    (base / 'badyaml').write_bytes(RIG_CASES['badyaml'])
    (base / 'notarig').write_bytes(RIG_CASES['notarig'])
    (base / 'dir').mkdir()
    return base


def _all_cases() -> dict[str, tuple[list[str], str, str | None, str, str | None]]:
    """id -> (args, option, raw value, prog, --out value checked for absence (None: the default 'out'))."""
    out: dict[str, tuple[list[str], str, str | None, str, str | None]] = {}
    for cid, (args, opt, raw, prog) in CASES.items():
        if prog in ('fixego play', 'fixego record'):       # no --out: record's BAG_DIR 'rec' must not appear
            out[cid] = (args, opt, raw, prog, 'rec' if prog == 'fixego record' else None)
            continue
        out[cid] = ([*args, '--out', 'out'], opt, raw, prog, 'out')
    for cmd, (args, values) in OUT_CASES.items():
        prog = {'sim': 'fixego sim', 'paper': 'fixego paper-sim', 'demo': 'fixego demo'}[cmd]
        for value, named in values:
            out[f'{cmd}--out={value!r}'] = ([*args, '--out', value], named, None, prog, None)
    for cmd, args in (('sim', SIM), ('demo', DEMO)):
        prog = f'fixego {cmd}'
        for name in RIG_CASES:
            out[f'{cmd}--rig={name}'] = ([*args, '--rig', name, '--out', 'out'], name, None, prog, 'out')
    return out


ALL = _all_cases()


# Runs each case in a process forked from this interpreter (the commands imported once): the child changes to the
# case's directory, points fds 1 and 2 at files and calls fixego_ros.cli.main like `python -m fixego_ros.cli`
# (an uncaught exception prints its traceback and exits 1, as the interpreter would). Prints {id: exit code}.
FORK_DRIVER = r"""
import importlib, json, os, signal, sys, time, traceback
from fixego_ros import cli
for m in ('fixego_ros.sim.cli', 'fixego_ros.sim.bag_writer', 'fixego_ros.demo.cli',
          'fixego_ros.experiments.paper_sim', 'fixego_ros.pipeline.params'):
    importlib.import_module(m)
cases = json.loads(open(sys.argv[1]).read())
codes = {}
for cid, (argv, cwd, out, err) in cases.items():
    sys.stdout.flush(); sys.stderr.flush()
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.chdir(cwd)
            for fd, path in ((1, out), (2, err)):
                f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
                os.dup2(f, fd)
                os.close(f)
            code = cli.main(argv)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else 0 if e.code is None else 1
            if not isinstance(e.code, (int, type(None))):
                print(e.code, file=sys.stderr)
        except BaseException:
            traceback.print_exc()
            code = 1
        finally:
            sys.stdout.flush(); sys.stderr.flush()
            os._exit(code)
    deadline = time.monotonic() + float(sys.argv[2])
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            codes[cid] = os.waitstatus_to_exitcode(status)
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            codes[cid] = 'timeout'
            break
        time.sleep(0.005)
print(json.dumps(codes))
"""
# a sample run as plain `python -m fixego_ros.cli` subprocesses (the real entry point, its imports included)
PLAIN = ['sim--fps=nan', 'sim--noise=1e308', "sim--out='/proc/x'", 'sim--rig=garbage', 'paper--presets=bogus',
         'paper--jobs=100000', 'demo--domain-id=233', 'demo--ready-timeout=nan']


@pytest.fixture(scope='module')
def results(tmp_path_factory) -> dict[str, tuple[subprocess.CompletedProcess, Path]]:
    """Every case run once, each in its own working directory: {id: (CompletedProcess-like, cwd)}."""
    import json
    root = tmp_path_factory.mktemp('cli_faults')
    logs = root / 'logs'
    logs.mkdir()
    dirs = {cid: _workdir(root / f'c{i}') for i, cid in enumerate(ALL)}
    spec = {cid: (ALL[cid][0], str(dirs[cid]), str(logs / f'{i}.out'), str(logs / f'{i}.err'))
            for i, cid in enumerate(ALL)}
    (root / 'cases.json').write_text(json.dumps(spec))
    env = dict(os.environ, MPLBACKEND='Agg', ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    driver = subprocess.run([sys.executable, '-c', FORK_DRIVER, str(root / 'cases.json'), '20'], capture_output=True,
                            text=True, timeout=TIMEOUT_S, env=env)
    assert driver.returncode == 0, driver.stderr
    codes = json.loads(driver.stdout.splitlines()[-1])
    out = {cid: (subprocess.CompletedProcess(ALL[cid][0], codes[cid], Path(spec[cid][2]).read_text(),
                                             Path(spec[cid][3]).read_text()), dirs[cid]) for cid in ALL}
    for cid in PLAIN:        # again, as plain subprocesses in fresh directories
        cwd = _workdir(root / f'plain{PLAIN.index(cid)}')
        out[f'plain:{cid}'] = (_fixego(ALL[cid][0], cwd), cwd)
    return out


def _shown(raw: str) -> set[str]:
    """Ways the refused value may be printed ('0' as 0.0, '1e308' as 1e+308)."""
    out = {raw}
    try:
        out.add(repr(float(raw)))
        if math.isfinite(float(raw)) and float(raw) == int(float(raw)):
            out.add(str(int(float(raw))))
    except ValueError:
        pass
    return out


@pytest.mark.parametrize('cid', [*ALL, *(f'plain:{c}' for c in PLAIN)])
def test_bad_option_refused_up_front(results, cid):
    _, option, raw, prog, out = ALL[cid.removeprefix('plain:')]
    proc, cwd = results[cid]
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert 'Traceback' not in proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f'{prog}: '), lines[0]
    assert option in lines[0], lines[0]
    if raw is not None:
        assert any(v in lines[0] for v in _shown(raw)), (raw, lines[0])
    assert proc.stdout == ''
    if out is not None:
        assert not (cwd / out).exists()
    # nothing new anywhere in the working directory (no bag, no report folder, no logs of started nodes)
    assert sorted(p.name for p in cwd.iterdir()) == sorted(['afile', 'existing', 'garbage', 'badyaml', 'notarig',
                                                           'dir'])
    assert list((cwd / 'existing').iterdir()) == []


def test_rig_garbage_names_the_file(results):
    proc, _ = results['sim--rig=garbage']
    assert 'garbage' in proc.stderr and 'UTF-8' in proc.stderr


def test_library_guards():
    """The library refuses the values that overflowed or exhausted memory too (for callers other than the CLI)."""
    from fixego_ros.sim.render import Renderer
    from fixego_ros.sim.run import SimSettings, resize_rig, rig_with_hfov
    from fixego_ros.sim.trajectories import make_trajectory
    from fixego_ros.sim.world import make_room
    for kw in ({'fps': math.nan}, {'fps': 0.0}, {'noise_sigma': math.inf}, {'texel': 1e-9}, {'speed': 1e308},
               {'duration': -1.0}, {'seed': -1}, {'steps': 131}, {'trajectory': 'nope'}):
        with pytest.raises(ValueError):
            SimSettings(**kw)
    with pytest.raises(ValueError):
        make_trajectory('paper', speed=0.0)
    with pytest.raises(ValueError):
        make_trajectory('paper', speed=1e-12)      # the grid would take terabytes
    with pytest.raises(ValueError):
        make_trajectory('random', duration=math.nan)
    with pytest.raises(ValueError):
        make_room(0, 1e-6)
    from fixego_ros.geometry.rig import make_rig
    rig = make_rig(64, 48)
    with pytest.raises(ValueError):
        resize_rig(rig, 0, 48)
    with pytest.raises(ValueError):
        rig_with_hfov(rig, math.nan)
    with pytest.raises(ValueError):
        Renderer(None, rig, noise_sigma=math.nan)   # checked before the world is touched


def test_tiny_sim_run_still_works(tmp_path):
    proc = _fixego([*SIM, '--out', 'bag'], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / 'bag' / 'metadata.yaml').exists()
    assert (tmp_path / 'bag' / 'sim.yaml').exists()
    assert 'wrote bag' in proc.stdout


def test_failed_sim_leaves_no_partial_bag_and_the_same_out_works_again(tmp_path):
    # 150 deg across 64 px: the servo finds no corner to fixate on, after the bag was opened
    proc = _fixego([*SIM, '--hfov', '150', '--out', 'bag'], tmp_path)
    lines = proc.stderr.splitlines()
    assert proc.returncode == 1, proc.stderr
    assert len(lines) == 1 and lines[0].startswith('fixego sim: ') and 'removed' in lines[0], proc.stderr
    assert 'Traceback' not in proc.stderr
    assert not (tmp_path / 'bag').exists()
    proc = _fixego([*SIM, '--out', 'bag'], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / 'bag' / 'metadata.yaml').exists()


def test_sigterm_mid_run_removes_the_partial_bag(tmp_path):
    # the random trajectory lasts the 600 s asked (paper and walk have their own, shorter, lengths)
    args = [sys.executable, '-m', 'fixego_ros.cli', 'sim', '--trajectory', 'random', '--width', '64', '--height', '48',
            '--no-progress', '--duration', '600', '--out', 'bag']
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not list(tmp_path.glob('bag/*.mcap')) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert list(tmp_path.glob('bag/*.mcap')), 'the bag was never started'
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert 'Traceback' not in err and 'SIGTERM' in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / 'bag').exists()


@pytest.mark.parametrize('args, expect', [
    (['replay', 'WALK', '--out', ''], '--out must name a file'),
    (['replay', 'WALK', '--out', '/proc/x/e.tum'], '--out /proc/x/e.tum: cannot write under /proc'),
    (['replay', 'WALK', '--out', 'WALK'], 'is a directory'),
    (['eval', 'GT', 'GT', '--rpe-delta-m', 'inf'], '--rpe-delta-m must be a finite number'),
    (['eval', 'GT', 'GT', '--max-dt', 'inf'], '--max-dt must be a finite number'),
])
def test_replay_and_eval_outputs_and_numbers_checked_first(tmp_path, args, expect):
    """Refused before the replay runs (a long bag must not fail at its end) or the evaluation starts."""
    walk = Path(__file__).resolve().parents[1] / 'bags' / 'walk'
    args = [str(walk) if a == 'WALK' else str(walk / 'ground_truth.tum') if a == 'GT' else a for a in args]
    if args[0] == 'eval':
        args += ['--out', str(tmp_path / 'ev')]
    p = subprocess.run([sys.executable, '-m', 'fixego_ros.cli', *args], capture_output=True, text=True, timeout=120,
                       cwd=tmp_path)
    assert p.returncode == 2 and expect in p.stderr and 'Traceback' not in p.stderr, p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and 'replayed' not in p.stdout


def test_a_signal_that_c_code_wraps_still_comes_out_as_the_interrupt():
    """SIGTERM landing inside pybind11 comes back as a TypeError caused by the Interrupted (seen once in
    ``fixego sim``): signals_interrupt re-raises it as the interrupt, so the command exits 128 + 15, not 1."""
    from fixego_ros.interrupt import Interrupted, signals_interrupt
    with pytest.raises(Interrupted) as info, signals_interrupt():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5.0)          # the handler raises at the next bytecode; bounded if it never comes
        except Interrupted as e:
            raise TypeError('Unable to convert function return value to a Python type!') from e
    assert info.value.signum == signal.SIGTERM
