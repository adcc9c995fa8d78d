"""Measure the vergence step on the live simulated rig: ``python -m fixego_ros.demo.vergence_check``.

``sim_rig_node`` runs in this process (so every rendered frame's true rig pose is known by its stamp), the two
``camera_node``s run as separate processes on the emulated VISCA heads' pseudo-terminals, as in ``fixego
demo``. Every ``/fixego/vergence`` message is compared with the simulator: the true distance is the ray cast
from the right camera centre along the published direction at the message's stamp. The left fixation's
interruption per step is measured from ``/fixego/left/fixation``: the time without a valid left fixation (its id
-1 "no valid fixation" messages do not count), and the time between the last frame of the left's own point before
the step and the first frame of its own new point after it (the partner point the step fixated is the id the left
camera had at the measurement's stamp).
Prints one line per step and a summary; ``--json`` writes them with the raw fixations, joint states, true poses
and true head angles per frame. The vergence-step figures in docs/results.md come from this.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import random
import sys
import time
from pathlib import Path

import numpy as np


def _key(stamp) -> tuple[int, int]:
    return int(stamp.sec), int(stamp.nanosec)


class _RecordingTrajectory:
    """Delegates to the simulator's trajectory and remembers the pose it rendered last."""

    def __init__(self, trajectory) -> None:
        self._tr = trajectory
        self.last = None

    def __getattr__(self, name: str):
        return getattr(self._tr, name)

    def pose_at(self, t: float):
        self.last = self._tr.pose_at(t)
        return self.last


def _interruptions(fixes: list[tuple[float, int]], partner_id: int, frame_s: float) -> tuple[float, float] | None:
    """For the step that fixated ``partner_id``: (time without a valid left fixation, time from the last frame
    of the left's own point before it to the first frame of its own new point after it); None when the run
    ended before the left camera had its own point again. A gap counts from one frame period after a frame."""
    before = [t for t, i in fixes if i < partner_id]
    after = [t for t, i in fixes if i > partner_id]
    if not before or not after:
        return None
    t0, t1 = max(before), min(after)
    ts = sorted(t for t, _ in fixes if t0 <= t <= t1)
    gaps = sum(max(0.0, b - a - frame_s) for a, b in itertools.pairwise(ts))
    return gaps, t1 - t0


def run(args: argparse.Namespace) -> dict:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Empty
    from std_srvs.srv import Trigger

    from fixego_ros.demo.launcher import Launcher, NodeSpec
    from fixego_ros.estimation.covariance import std_along
    from fixego_ros.geometry.rig import default_rig_path, load_rig
    from fixego_ros.nodes.common import LATCHED_QOS, RELIABLE_QOS, stamp_to_sec
    from fixego_ros.nodes.sim_rig_node import SimRigNode
    from fixego_ros.pipeline.params import SIM_RIG_NODE_PARAMS
    from fixego_ros.sim.vergence_measure import true_distance

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rig_path = out / 'rig.yaml'
    load_rig(args.rig or default_rig_path()).save(rig_path)
    domain = args.domain_id if args.domain_id is not None else random.Random(os.getpid()).randint(120, 200)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')})
    rclpy.init(args=[], domain_id=domain)
    extra = []
    for kv in args.sim_param:
        k, _, v = kv.partition(':=')
        extra.append(Parameter(k, value=type(SIM_RIG_NODE_PARAMS[k].default)(v)))
    sim = SimRigNode(parameter_overrides=[
        Parameter('trajectory', value=args.trajectory), Parameter('time_scale', value=float(args.time_scale)),
        Parameter('fps', value=float(args.fps)), Parameter('rig_file', value=str(rig_path)),
        Parameter('seed', value=int(args.seed)), Parameter('loop', value=True), Parameter('exit_at_end', value=False),
        Parameter('wait_for_start', value=True), Parameter('pty_file', value=str(out / 'ptys.json')), *extra])
    rec = _RecordingTrajectory(sim.trajectory)
    sim.trajectory = rec
    truth: dict[tuple[int, int], object] = {}
    publish_gt = sim.pub_gt.publish

    # the heads' true angles each frame was rendered with (to check the joint readings offline)
    true_joints: dict[tuple[int, int], dict[str, tuple[float, float]]] = {}
    last_joints: dict[str, tuple[float, float]] = {}
    for side, emu in sim.emulators.items():
        def angles(t=None, side=side, f=emu.pan_tilt_rad):
            last_joints[side] = f(t)
            return last_joints[side]
        emu.pan_tilt_rad = angles

    def gt(msg) -> None:
        truth[_key(msg.header.stamp)] = rec.last
        true_joints[_key(msg.header.stamp)] = dict(last_joints)
        publish_gt(msg)

    sim.pub_gt.publish = gt
    probe = rclpy.create_node('vergence_check')
    got: list[PoseWithCovarianceStamped] = []
    status: dict[str, str] = {}
    failures: list[str] = []
    probe.create_subscription(PoseWithCovarianceStamped, '/fixego/vergence', got.append, LATCHED_QOS)
    joints: dict[str, list[tuple[float, float, float]]] = {'right': [], 'left': []}
    for side in joints:
        probe.create_subscription(JointState, f'/fixego/{side}/joint_states',
                                  lambda m, s=side: joints[s].append((stamp_to_sec(m.header.stamp), *m.position)),
                                  RELIABLE_QOS)
    left_px: list[tuple[float, int, float, float]] = []
    probe.create_subscription(PointStamped, '/fixego/left/fixation',
                              lambda m: left_px.append((stamp_to_sec(m.header.stamp), int(m.point.z), m.point.x,
                                                        m.point.y)), RELIABLE_QOS)
    right_fixes: list[tuple[float, int, float, float]] = []
    probe.create_subscription(PointStamped, '/fixego/right/fixation',
                              lambda m: right_fixes.append((stamp_to_sec(m.header.stamp), int(m.point.z), m.point.x,
                                                            m.point.y)), RELIABLE_QOS)

    def on_diag(msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name.endswith('left: vergence'):
                status.clear()
                status.update({'message': s.message, **{kv.key: kv.value for kv in s.values}})
                if status.get('last_failure') and status['last_failure'] not in failures:
                    failures.append(status['last_failure'])

    probe.create_subscription(DiagnosticArray, '/diagnostics', on_diag, RELIABLE_QOS)
    request = probe.create_publisher(Empty, '/fixego/vergence_request', RELIABLE_QOS)
    launcher = Launcher(out / 'logs', env)
    common = {'rig_file': str(rig_path.resolve())}
    left_params = {'vergence_period_s': float(args.period), 'vergence_min_interval_s': float(args.min_interval)}
    for kv in args.left_param:
        k, _, v = kv.partition(':=')
        left_params[k] = v
    right_params = dict(kv.partition(':=')[::2] for kv in args.right_param)
    for side in ('right', 'left'):
        launcher.start(NodeSpec(f'{side}_camera_node', 'fixego_ros.nodes.camera_node',
                                {**common, 'side': side, 'port': sim.ptys[side],
                                 **(left_params if side == 'left' else right_params)}))
    ex = SingleThreadedExecutor()
    ex.add_node(sim)
    ex.add_node(probe)
    t0 = time.monotonic()
    started = False
    next_request = t0 + args.request_every if args.request_every > 0 else math.inf
    try:
        while time.monotonic() - t0 < args.run_s + args.settle_s:
            ex.spin_once(timeout_sec=0.005)
            if not started and time.monotonic() - t0 > args.settle_s:
                sim._srv_start(Trigger.Request(), Trigger.Response())    # start the trajectory (its ~/start)
                started = True
            if time.monotonic() >= next_request:
                request.publish(Empty())
                next_request += args.request_every
            if launcher.exited():
                raise RuntimeError(f'a camera node died: {launcher.exited()}\n'
                                   + launcher.log_tail('left_camera_node'))
    finally:
        launcher.stop_all()
        ex.shutdown()
        final_status = dict(status)
        probe.destroy_node()
        sim.destroy_node()
        rclpy.try_shutdown()
    fixes = [(t, i) for t, i, _, _ in left_px if i >= 0]      # id -1: the left's "no valid fixation" message
    fix_at = {round(t, 6): i for t, i in fixes}
    steps = []
    for m in got:
        ts = stamp_to_sec(m.header.stamp)
        pose = truth.get(_key(m.header.stamp))
        p = np.array([m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z])
        cov = np.array(m.pose.covariance).reshape(6, 6)[:3, :3]
        d = float(np.linalg.norm(p))
        std = std_along(p, cov)
        true_d = math.nan if pose is None else true_distance(sim.renderer.world, pose, p)
        steps.append({'stamp': ts, 'distance_m': d, 'true_m': float(true_d), 'std_m': std,
                      'error_pct': 100.0 * (d - true_d) / true_d, 'partner_id': fix_at.get(round(ts, 6))})
    for s in steps:
        it = _interruptions(fixes, s['partner_id'], 1.0 / args.fps) if s['partner_id'] is not None else None
        s['no_fixation_s'], s['away_s'] = it if it is not None else (None, None)
    return {'run': {k: v for k, v in vars(args).items()}, 'steps': steps, 'diagnostics': final_status,
            'failures': failures,
            'right_fixations': right_fixes, 'left_fixations': left_px, 'joints': joints,
            'truth': {f'{k[0]}.{k[1]:09d}': [*map(float, p.t), *map(float, p.R.ravel())] for k, p in truth.items()},
            'true_joints': {f'{k[0]}.{k[1]:09d}': v for k, v in true_joints.items()}}


def summary(res: dict) -> str:
    steps = res['steps']
    lines = [f'{len(steps)} vergence measurements; left node: {res["diagnostics"].get("message", "?")}']
    for s in steps:
        gap, away = s.get('no_fixation_s'), s.get('away_s')
        lines.append(f'  t={s["stamp"] % 1000:8.2f}  true {s["true_m"]:.3f} m  measured {s["distance_m"]:.3f} m  '
                     f'error {s["error_pct"]:+.2f} %  std {s["std_m"]:.3f} m '
                     f'({100 * s["std_m"] / s["distance_m"]:.2f} %)  '
                     f'z {(s["distance_m"] - s["true_m"]) / s["std_m"]:+.1f}'
                     + (f'  no left fixation {gap:.2f} s, own point left {away:.2f} s' if gap is not None else ''))
    ok = [s for s in steps if 2.0 <= s['true_m'] <= 4.0 and math.isfinite(s['error_pct'])]
    if ok:
        e = np.array([abs(s['error_pct']) for s in ok])
        z = np.array([(s['distance_m'] - s['true_m']) / s['std_m'] for s in ok])
        lines.append(f'  at 2-4 m ({len(ok)}): |error| mean {e.mean():.2f} %, max {e.max():.2f} %; '
                     f'RMS of error/std {math.sqrt(float(np.mean(z * z))):.2f}')
    gaps = [s['no_fixation_s'] for s in steps if s.get('no_fixation_s') is not None]
    away = [s['away_s'] for s in steps if s.get('away_s') is not None]
    if gaps:
        lines.append(f'  no valid left fixation published: mean {np.mean(gaps):.2f} s, max {np.max(gaps):.2f} s; '
                     f'own point left: mean {np.mean(away):.2f} s, max {np.max(away):.2f} s')
    lines += [f'  failure: {f}' for f in res.get('failures', [])]
    d = res['diagnostics']
    if d:
        lines.append('  diagnostics: ' + ', '.join(f'{k} {v}' for k, v in d.items() if k != 'message'))
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m fixego_ros.demo.vergence_check', description=__doc__.split('\n')[0])
    ap.add_argument('--trajectory', default='paper')
    ap.add_argument('--time-scale', type=float, default=1.0, help='0 freezes the rig')
    ap.add_argument('--fps', type=float, default=30.0)
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--rig', type=Path)
    ap.add_argument('--run-s', type=float, default=30.0, help='seconds of trajectory')
    ap.add_argument('--settle-s', type=float, default=8.0, help='rig held still this long first (start-up step)')
    ap.add_argument('--period', type=float, default=4.0, help='vergence_period_s of the left node')
    ap.add_argument('--min-interval', type=float, default=3.0, help='vergence_min_interval_s of the left node')
    ap.add_argument('--request-every', type=float, default=0.0, help='publish vergence_request this often (s)')
    ap.add_argument('--left-param', action='append', default=[], metavar='NAME:=VALUE',
                    help='a left camera_node parameter (also profile:=... for the heads: give --sim-param too)')
    ap.add_argument('--right-param', action='append', default=[], metavar='NAME:=VALUE')
    ap.add_argument('--sim-param', action='append', default=[], metavar='NAME:=VALUE',
                    help='a sim_rig_node parameter, e.g. start_pan_deg_right:=10.0')
    ap.add_argument('--domain-id', type=int)
    ap.add_argument('--out', default='/tmp/fixego_vergence_check')
    ap.add_argument('--json', type=Path)
    args = ap.parse_args(argv)
    res = run(args)
    print(summary(res))
    if args.json:
        args.json.write_text(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == '__main__':
    sys.exit(main())
