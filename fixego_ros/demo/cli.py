"""``fixego demo``: the live pipeline on the simulated rig, end to end, as separate processes over DDS.

Starts ``sim_rig_node`` (two emulated VISCA heads on pseudo-terminals, rendered images), one
``camera_node`` per head on its pty, ``flow_node`` and ``estimator_node``; waits until poses flow,
resets the estimator and starts the rig on its trajectory; when the rig stops, stops every node and
writes a report folder: TUM files (refined, raw, ground truth), ATE/RPE (evo), the trajectory plot and
error per step, latency image -> pose and dropped frames, and every node's log.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from fixego_ros.sim.trajectories import NAMES


def register(subparsers) -> None:
    p = subparsers.add_parser(
        'demo', help='run the live pipeline on the simulated rig and write a report',
        description='Simulated rig + two camera nodes over VISCA on pseudo-terminals + flow + estimator, '
                    'as separate processes over DDS; exits by itself and writes a report folder.')
    p.add_argument('--out', type=Path, default=Path('demo_out'), help='report folder (default demo_out)')
    p.add_argument('--trajectory', choices=NAMES, default='paper', help='rig trajectory (default paper)')
    p.add_argument('--duration', type=float, default=0.0, help='stop the trajectory after this many seconds')
    p.add_argument('--fps', type=float, default=30.0, help='camera frame rate (default 30)')
    p.add_argument('--rig', type=Path, help='rig file (default config/rig.yaml)')
    p.add_argument('--width', type=int, default=0, help='image width (intrinsics scaled; default: the rig file)')
    p.add_argument('--height', type=int, default=0, help='image height')
    p.add_argument('--preset', choices=('paper', 'window', 'full'), default='window', help='flow points')
    p.add_argument('--window', type=int, default=3, help='local BA frames n (0 disables; default 3)')
    p.add_argument('--mode', choices=('paper', 'joint'), default='paper', help='local BA mode')
    p.add_argument('--seed', type=int, default=0, help='seed of the simulated world')
    p.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID for every process (default: inherited)')
    p.add_argument('--ready-timeout', type=float, default=90.0, help='bound on start-up (s)')
    p.add_argument('--quiet', action='store_true', help='no progress lines')
    p.set_defaults(func=run)


def _rig_file(args: argparse.Namespace, out: Path) -> Path:
    """The rig all nodes use, written to the report folder (resized when asked)."""
    from fixego_ros.geometry.rig import default_rig_path, load_rig
    from fixego_ros.sim.run import resize_rig
    rig = load_rig(args.rig or default_rig_path())
    if args.width or args.height:
        w = args.width or round(rig.right.width * args.height / rig.right.height)
        h = args.height or round(rig.right.height * args.width / rig.right.width)
        rig = resize_rig(rig, w, h)
    path = out / 'rig.yaml'
    rig.save(path)
    return path


def run(args: argparse.Namespace) -> int:
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    try:
        rig_path = _rig_file(args, out)
    except (OSError, ValueError) as e:
        print(f'fixego demo: {e}', file=sys.stderr)
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
    from rclpy.executors import SingleThreadedExecutor

    from fixego_ros.demo.launcher import NodeSpec, wait_for
    from fixego_ros.nodes.demo_recorder import Recorder

    pty_file = out / 'ptys.json'
    pty_file.unlink(missing_ok=True)
    common = {'rig_file': str(rig_path.resolve())}
    launcher.start(NodeSpec('sim_rig_node', 'fixego_ros.nodes.sim_rig_node', {
        **common, 'trajectory': args.trajectory, 'duration': float(args.duration), 'fps': float(args.fps),
        'seed': args.seed, 'pty_file': str(pty_file.resolve()), 'wait_for_start': True, 'exit_at_end': True}))
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
                                {**common, 'side': side, 'port': ptys[side]}))
    launcher.start(NodeSpec('flow_node', 'fixego_ros.nodes.flow_node', {**common, 'preset': args.preset}))
    launcher.start(NodeSpec('estimator_node', 'fixego_ros.nodes.estimator_node',
                            {**common, 'window': args.window, 'mode': args.mode}))

    rclpy.init()
    node = Recorder()
    ex = SingleThreadedExecutor()
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
        for client, what in ((node.reset_client, 'estimator reset'), (node.start_client, 'rig start')):
            success, message = node.call(client, ex, 10.0)
            if not success:
                print(f'fixego demo: {what} failed: {message}', file=sys.stderr)
                return 1
            if client is node.reset_client:
                node.clear()
                t_reset = node.get_clock().now().nanoseconds * 1e-9
        t_run = time.monotonic()
        last_print = 0.0
        while 'sim_rig_node' not in launcher.exited():
            spin(0.05)
            if (why := failed()) is not None:
                print(f'fixego demo: {why}', file=sys.stderr)
                return 1
            if time.monotonic() - last_print > 2.0:
                last_print = time.monotonic()
                _say(args, _progress(node, time.monotonic() - t_run))
        # let the last frames through the pipeline (bounded)
        wait_for(lambda: node.poses and node.truth and node.poses[-1][0] >= node.truth[-1][0], 5.0, spin=spin)
        spin(0.3)
        launcher.stop_all()
        from fixego_ros.demo.report import write_report
        report = write_report(out, node, t_reset, vars(args))
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    _say(args, report['console'])
    return 0


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
