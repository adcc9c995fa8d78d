"""``fixego demo``: the live pipeline on the simulated rig, end to end, as separate processes over DDS.

Starts ``sim_rig_node`` (two emulated VISCA heads on pseudo-terminals, rendered images), one
``camera_node`` per head on its pty (the left one runs its vergence steps, on by default: the rig measures
its own scale), ``flow_node`` and ``estimator_node``; waits until poses flow,
resets the estimator and starts the rig on its trajectory; when the rig stops, stops every node and
writes a report folder: TUM files (refined, raw, ground truth), ATE/RPE (evo), the trajectory plot and
error per step, the scale error (estimated / true path length - 1), the vergence steps (measurements seen,
the left camera node's attempts/successes and interruption), latency image -> pose and dropped frames, and
every node's log; and the estimator's inputs from the reset on (``estimator_inputs/``: the flow node's observations,
the vergence measurements and the ground truth, with the rig file), so ``fixego replay`` reproduces the run's
estimate offline without the images.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from fixego_ros.cli_options import ROS_DOMAIN_IDS, OptionError, check_float, check_int, one_line_errors, prepare_out_dir
from fixego_ros.sim.cli import image_size, read_rig
from fixego_ros.sim.run import DURATION_MAX, FPS_RANGE, SEED_MAX, SIZE_RANGE, resize_rig
from fixego_ros.sim.trajectories import NAMES, REST_RANGE
from fixego_ros.tracking.joint_prediction import MODES as JOINT_MODES
from fixego_ros.visca.profiles import PROFILES

PROG = 'fixego demo'
READY_TIMEOUT_MAX = 3600.0     # s
SMOOTHER_CATCH_UP_S = 15.0     # s: after the last pose, the smoother's last results (its lag, and a diagnostics period)
SCALE_AT_REST_TIMEOUT_S = 15.0  # s: the request may wait out the camera node's vergence_min_interval_s, then ~3 s
INPUTS_DIR = 'estimator_inputs'  # the estimator's inputs, a bag for fixego replay


def register(subparsers) -> None:
    p = subparsers.add_parser(
        'demo', help='run the live pipeline on the simulated rig and write a report',
        description='Simulated rig + two camera nodes over VISCA on pseudo-terminals + flow + estimator, '
                    'as separate processes over DDS; exits by itself and writes a report folder. Every option is '
                    'checked before any process is started (exit code 2, one line).')
    p.add_argument('--out', default='demo_out', help='report folder (default demo_out; reused if it exists)')
    p.add_argument('--trajectory', choices=NAMES, default='paper', help='rig trajectory (default paper)')
    p.add_argument('--duration', type=float, default=0.0,
                   help=f'stop the trajectory after this many seconds, in [0, {DURATION_MAX:g}] (0: whole, default)')
    p.add_argument('--rest-end', type=float, default=0.0, metavar='S',
                   help=f'the rig stands still S s at its last pose after the trajectory, S in [{REST_RANGE[0]:g}, '
                        f'{REST_RANGE[1]:g}] (default 0)')
    p.add_argument('--fps', type=float, default=30.0,
                   help=f'camera frame rate in [{FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}] (default 30)')
    p.add_argument('--rig', type=Path, help='rig file (default config/rig.yaml)')
    p.add_argument('--width', type=int, help=f'image width, {SIZE_RANGE[0]}..{SIZE_RANGE[1]} px (intrinsics scaled; '
                                             'default: the rig file\'s)')
    p.add_argument('--height', type=int, help=f'image height, {SIZE_RANGE[0]}..{SIZE_RANGE[1]} px')
    p.add_argument('--preset', choices=('paper', 'window', 'full'), help="flow points (default: flow_node's)")
    p.add_argument('--joint-mode', choices=JOINT_MODES,
                   help="camera nodes' joint states: predict (at once) or wait (for the next reading) (default: "
                        "camera_node's)")
    p.add_argument('--profile', choices=tuple(PROFILES),
                   help="VISCA camera model of the emulated heads and the camera nodes (their speeds bound how long "
                        "a vergence step interrupts the left fixation; default: camera_node's)")
    p.add_argument('--seed', type=int, default=0, help=f'seed of the simulated world, 0..{SEED_MAX}')
    p.add_argument('--domain-id', type=int,
                   help='ROS_DOMAIN_ID for every process, {}..{} (default: inherited)'.format(*ROS_DOMAIN_IDS))
    p.add_argument('--ready-timeout', type=float, default=90.0,
                   help=f'bound on start-up in s, in (0, {READY_TIMEOUT_MAX:g}] (default 90)')
    p.add_argument('--quiet', action='store_true', help='no progress lines')
    one_line_errors(p)
    p.set_defaults(func=run)


def check_args(args: argparse.Namespace):
    """Every option, before any process is started: the rig (resized when asked); raises OptionError (one line).
    ``--out`` is checked (and created) afterwards, by :func:`run`, once everything else is known to be usable."""
    check_float(args.duration, '--duration', 0.0, DURATION_MAX, unit='s', note=' (0: the whole trajectory)')
    check_float(args.rest_end, '--rest-end', *REST_RANGE, unit='s')
    check_float(args.fps, '--fps', *FPS_RANGE, unit='frames per second')
    check_int(args.seed, '--seed', 0, SEED_MAX)
    check_float(args.ready_timeout, '--ready-timeout', 0.0, READY_TIMEOUT_MAX, lo_open=True, unit='s')
    if args.domain_id is not None:
        check_int(args.domain_id, "--domain-id", *ROS_DOMAIN_IDS, note=' (ROS 2 domain ids)')
    if not args.out or not args.out.strip():
        raise OptionError('--out must name an output directory, got an empty path')
    rig = read_rig(args.rig)
    size = image_size(rig, args.width, args.height)
    return resize_rig(rig, *size) if size is not None else rig


def run(args: argparse.Namespace) -> int:
    try:
        rig = check_args(args)
        out = prepare_out_dir(args.out, '--out')     # last: creates the folder
    except (OptionError, ValueError) as e:
        print(f'{PROG}: {" ".join(str(e).split())}', file=sys.stderr)
        return 2
    rig_path = out / 'rig.yaml'
    try:
        rig.save(rig_path)
    except (OSError, ValueError) as e:
        print(f'{PROG}: cannot write {rig_path}: {" ".join(str(e).split())}', file=sys.stderr)
        return 2
    env = dict(os.environ)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if args.domain_id is not None:
        env['ROS_DOMAIN_ID'] = str(args.domain_id)
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE') if k in env})
    from fixego_ros.demo.launcher import Launcher
    launcher = Launcher(out / 'logs', env)
    try:
        return _run(args, out, rig_path, launcher)
    except KeyboardInterrupt:
        print('\nfixego demo: interrupted; stopping the nodes', file=sys.stderr)
        return 130
    finally:
        launcher.stop_all()


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(text, flush=True)


def _run(args: argparse.Namespace, out: Path, rig_path: Path, launcher) -> int:
    import rclpy

    from fixego_ros.demo.cpu import CpuSampler
    from fixego_ros.demo.launcher import NodeSpec, wait_for
    from fixego_ros.nodes.common import events_executor
    from fixego_ros.nodes.demo_recorder import Recorder

    pty_file = out / 'ptys.json'
    pty_file.unlink(missing_ok=True)
    given = lambda **kw: {k: v for k, v in kw.items() if v is not None}  # noqa: E731  (else the node's default)
    common = {'rig_file': str(rig_path.resolve())}
    launcher.start(NodeSpec('sim_rig_node', 'fixego_ros.nodes.sim_rig_node', {
        **common, 'trajectory': args.trajectory, 'duration': float(args.duration),
        'rest_end_s': float(args.rest_end), 'fps': float(args.fps),
        'seed': args.seed, 'pty_file': str(pty_file.resolve()), 'wait_for_start': True, 'exit_at_end': True,
        **given(profile=args.profile)}))
    _say(args, f'fixego demo: simulated rig starting (trajectory {args.trajectory}); logs in {out / "logs"}')
    t_ready = time.monotonic()

    def failed() -> str | None:
        """A node that died (the rig ending its trajectory with code 0 is how a run ends, not a failure)."""
        ex = {n: c for n, c in launcher.exited().items() if not (n == 'sim_rig_node' and c == 0)}
        return next((f'{n} exited with code {c}:\n{launcher.log_tail(n)}' for n, c in ex.items()), None)

    if not wait_for(lambda: pty_file.exists() or failed() is not None, args.ready_timeout):
        print(f'fixego demo: the simulated rig wrote no pty file within {args.ready_timeout:.0f} s',
              file=sys.stderr)
        return 1
    if (why := failed()) is not None:
        print(f'fixego demo: {why}', file=sys.stderr)
        return 1
    ptys = json.loads(pty_file.read_text())
    for side in ('right', 'left'):
        launcher.start(NodeSpec(f'{side}_camera_node', 'fixego_ros.nodes.camera_node',
                                {**common, 'side': side, 'port': ptys[side],
                                 **given(joint_mode=args.joint_mode, profile=args.profile)}))
    launcher.start(NodeSpec('flow_node', 'fixego_ros.nodes.flow_node', {**common, **given(preset=args.preset)}))
    launcher.start(NodeSpec('estimator_node', 'fixego_ros.nodes.estimator_node',
                            {**common, 'path_max_length': _path_length(args)}))

    rclpy.init()
    node = Recorder()
    ex = events_executor(node.context)
    ex.add_node(node)
    spin = lambda s: ex.spin_once(timeout_sec=s)  # noqa: E731
    try:
        ready = lambda: (len(node.poses) >= 15 and min(node.fixations['right'], node.fixations['left']) > 0)  # noqa: E731
        ok = wait_for(lambda: ready() or failed() is not None, args.ready_timeout, spin=spin)
        if (why := failed()) is not None or not ok:
            print(f'fixego demo: pipeline not ready within {args.ready_timeout:.0f} s '
                  f'(poses {len(node.poses)}, fixations {dict(node.fixations)})' + (f'; {why}' if why else ''),
                  file=sys.stderr)
            return 1
        _say(args, f'fixego demo: pipeline up in {time.monotonic() - t_ready:.1f} s; resetting the estimator and '
                   'starting the rig')
        _open_inputs(node, out / INPUTS_DIR)     # before the reset: creating the bag takes seconds on a loaded machine
        t_reset = node.get_clock().now().nanoseconds * 1e-9
        for client, what in ((node.reset_client, 'estimator reset'), (node.start_client, 'rig start')):
            if client is node.start_client:
                _scale_at_rest(args, node, t_reset, spin)
            success, message = node.call(client, ex, 10.0)
            if not success:
                print(f'fixego demo: {what} failed: {message}', file=sys.stderr)
                return 1
            if client is node.reset_client:
                node.clear()
                t_reset = node.get_clock().now().nanoseconds * 1e-9
                node.start_inputs()
        t_run = time.monotonic()
        last_print = last_cpu = 0.0
        cpu = CpuSampler({n: p.pid for n, p in launcher.procs.items()}, {'fixego demo (recorder)': os.getpid()})
        while 'sim_rig_node' not in launcher.exited():
            if time.monotonic() - last_cpu >= 1.0:
                last_cpu = time.monotonic()
                cpu.sample(last_cpu)
            spin(0.05)
            if (why := failed()) is not None:
                print(f'fixego demo: {why}', file=sys.stderr)
                return 1
            if time.monotonic() - last_print > 2.0:
                last_print = time.monotonic()
                _say(args, _progress(node, time.monotonic() - t_run))
        # let the last frames through the pipeline, and the smoother process finish them (bounded: on a loaded
        # machine it can be seconds behind, and the end of the path would be fast poses only)
        wait_for(lambda: node.poses and node.truth and node.poses[-1][0] >= node.truth[-1][0], 5.0, spin=spin)
        t_last = time.monotonic()
        est = 'fixego estimator_node'
        if wait_for(lambda: node.status_times.get(est, -math.inf) > t_last
                    and node.statuses[est].get('smoother_behind_s') == '0.00', SMOOTHER_CATCH_UP_S, spin=spin):
            node.smoother_catch_up_s = time.monotonic() - t_last
        spin(0.3)
        # the estimator publishes the paths at most once per period and once more when the poses stop: wait for
        # the paths that hold the last pose (bounded)
        if node.poses:
            last = node.poses[-1][0]
            wait_for(lambda: all((node.path_stamp(name) or -math.inf) >= last for name in ('path', 'path_raw')),
                     2 * _path_period() + 3.0, spin=spin)
        cpu.sample(time.monotonic())
        launcher.stop_all()
        from fixego_ros.demo.report import write_report
        inputs = _close_inputs(node, rig_path, out / INPUTS_DIR)
        report = write_report(out, node, t_reset, vars(args), cpu.shares(), inputs)
    finally:
        node.close_inputs()         # a failed run: the bag is still closed (idempotent)
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    _say(args, report['console'])
    return 0


def _open_inputs(node, bag: Path) -> None:
    """Create the bag of the estimator's inputs, ``bag`` (a previous run's in a reused --out is replaced), written
    from the reset on; a bag that cannot be created costs the run nothing but the bag (said once)."""
    from fixego_ros.bags.recorder import RecordError
    try:
        if bag.exists():
            shutil.rmtree(bag)
        node.open_inputs(bag)
    except (OSError, RecordError) as e:
        print(f'fixego demo: the estimator inputs are not recorded: {" ".join(str(e).split())}', file=sys.stderr)


def _close_inputs(node, rig_path: Path, bag: Path) -> dict | None:
    """Finish the inputs bag and put the rig file beside it (``fixego replay BAG`` finds it there); what the report
    says of it, None when none was written."""
    summary = node.close_inputs()
    if summary is None:
        return None
    error = summary.error
    if not error:
        try:
            shutil.copyfile(rig_path, bag / 'rig.yaml')
        except OSError as e:
            error = f'cannot copy the rig file: {e}'
    return {'bag': str(bag), 'messages': {t: c.written for t, c in summary.topics.items()}, 'error': error}


def _path_period() -> float:
    from fixego_ros.pipeline.params import ESTIMATOR_NODE_PARAMS
    return float(ESTIMATOR_NODE_PARAMS['path_publish_period_s'].default)


def _scale_at_rest(args: argparse.Namespace, node, t_reset: float, spin) -> None:
    """Before the rig moves: ask for a vergence step and wait (bounded) for its measurement, so the trajectory
    starts metric. The start-up step the left camera node made on its own came before the estimator reset, which
    forgets it; the request may wait out the camera node's vergence_min_interval_s."""
    from std_msgs.msg import Empty

    from fixego_ros.demo.launcher import wait_for
    from fixego_ros.nodes.common import RELIABLE_QOS
    node.create_publisher(Empty, 'vergence_request', RELIABLE_QOS).publish(Empty())
    if wait_for(lambda: any(t >= t_reset for t, _, _ in node.vergence), SCALE_AT_REST_TIMEOUT_S, spin=spin):
        _say(args, 'fixego demo: scale measured at rest (vergence step); starting the rig')
    else:
        _say(args, f'fixego demo: no vergence measurement within {SCALE_AT_REST_TIMEOUT_S:g} s of the request; '
                   'starting the rig without one (the scale waits for a step during the run)')


def _path_length(args: argparse.Namespace) -> int:
    """path_max_length for the estimator: the whole run (the report takes the raw trajectory from the last raw
    path), with a margin for the frames before the rig starts; at least the node's default."""
    from fixego_ros.pipeline.params import ESTIMATOR_NODE_PARAMS
    from fixego_ros.sim.trajectories import make_trajectory

    spec = ESTIMATOR_NODE_PARAMS['path_max_length']
    frames = make_trajectory(args.trajectory, seed=args.seed, duration=args.duration or None).then_rest(
        args.rest_end).frame_count(args.fps)
    return int(min(spec.max, max(int(spec.default), frames + math.ceil(10 * args.fps))))


def _progress(node, elapsed: float) -> str:
    sim = node.statuses.get('fixego: sim_rig', {})
    est = node.statuses.get('fixego estimator_node', {})
    lat = np.array(node.latency_s[-60:]) * 1e3 if node.latency_s else np.zeros(1)
    err = ''
    if node.poses and node.truth:
        truth = dict(node.truth)
        t, p = node.poses[-1]
        if t in truth:
            err = f'  position error {100 * np.linalg.norm(p.t - truth[t].t):.1f} cm'
    return (f'  t={sim.get("sim_time_s", "?")}/{sim.get("duration_s", "?")} s  poses {len(node.poses)}  '
            f'latency p50 {np.median(lat):.0f} ms  last step {est.get("last_status", "?")}{err}')
