"""``fixego sim``: write an image-level bag from the simulated rig (DESIGN.md §6)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fixego_ros.sim.trajectories import NAMES


def register(subparsers) -> None:
    p = subparsers.add_parser(
        'sim', help='write an image-level rosbag2/MCAP bag from the simulated rig',
        description='Simulate the rig (room, fixation servo, both cameras) along a trajectory and write '
                    'a rosbag2/MCAP bag with the topics of DESIGN.md §3 plus BAG_DIR/rig.yaml.')
    p.add_argument('--trajectory', choices=NAMES, default='paper', help='trajectory (default: paper)')
    p.add_argument('--out', required=True, type=Path, metavar='BAG_DIR', help='bag directory to create')
    p.add_argument('--rig', type=Path, help='rig file (default: config/rig.yaml)')
    p.add_argument('--seed', type=int, default=0, help='seed of textures, noise and servo (default 0)')
    p.add_argument('--fps', type=float, default=30.0, help='frame rate (default 30)')
    p.add_argument('--width', type=int, help='image width (intrinsics scaled, angle of view kept)')
    p.add_argument('--height', type=int, help='image height (intrinsics scaled)')
    p.add_argument('--hfov', type=float, help='horizontal angle of view in degrees (replaces the intrinsics)')
    p.add_argument('--encoding', choices=('mono8', 'rgb8'), default='mono8')
    p.add_argument('--noise', type=float, default=2.0, help='sensor noise sigma in grey levels (default 2)')
    p.add_argument('--speed', type=float, help='rig speed in m/s (default: the trajectory\'s)')
    g = p.add_mutually_exclusive_group()
    g.add_argument('--duration', type=float, help='stop after this many seconds')
    g.add_argument('--steps', type=int, help='paper trajectory: stop at this step mark (0..130)')
    p.add_argument('--texel', type=float, default=0.002, help='texture resolution in m (default 0.002)')
    p.add_argument('--wheel-odom-std', type=float, metavar='S',
                   help='also write /fixego/wheel/odom (nav_msgs/Odometry, one per frame): the true base_link '
                        'velocity plus seeded Gaussian noise of std S m/s, covariance S^2 (default: off)')
    p.add_argument('--vergence-std', type=float, metavar='REL',
                   help='also write /fixego/vergence (geometry_msgs/PoseWithCovarianceStamped, one message at the '
                        'first frame): the right fixation point in the rig frame, its distance off by seeded '
                        'Gaussian relative error of std REL (e.g. 0.02 = 2 %%), as the start-up vergence step '
                        'would measure it (default: off)')
    p.add_argument('--no-progress', action='store_true', help='no progress bar on stderr')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fixego_ros.geometry.rig import RigError, default_rig_path, load_rig
    from fixego_ros.sim.bag_writer import write_bag
    from fixego_ros.sim.run import SimSettings, resize_rig, rig_with_hfov

    try:
        rig = load_rig(args.rig or default_rig_path())
    except RigError as e:
        print(f'fixego sim: {e}', file=sys.stderr)
        return 2
    if args.width or args.height:
        w = args.width or round(rig.right.width * args.height / rig.right.height)
        h = args.height or round(rig.right.height * args.width / rig.right.width)
        rig = resize_rig(rig, w, h)
    if args.hfov:
        rig = rig_with_hfov(rig, args.hfov)
    if args.steps is not None and args.trajectory != 'paper':
        print('fixego sim: --steps applies to the paper trajectory only (use --duration)', file=sys.stderr)
        return 2
    if args.wheel_odom_std is not None and not (0 <= args.wheel_odom_std < float('inf')):
        print(f'fixego sim: --wheel-odom-std must be a finite number >= 0, got {args.wheel_odom_std}',
              file=sys.stderr)
        return 2
    if args.vergence_std is not None and not (0 <= args.vergence_std < float('inf')):
        print(f'fixego sim: --vergence-std must be a finite number >= 0, got {args.vergence_std}', file=sys.stderr)
        return 2
    if args.out.exists():
        print(f'fixego sim: {args.out} exists already (bags are never overwritten)', file=sys.stderr)
        return 2
    settings = SimSettings(trajectory=args.trajectory, seed=args.seed, fps=args.fps, encoding=args.encoding,
                           noise_sigma=args.noise, speed=args.speed, duration=args.duration, steps=args.steps,
                           texel=args.texel)
    s = write_bag(args.out, rig, settings, progress=not args.no_progress, wheel_odom_std=args.wheel_odom_std,
                  vergence_std=args.vergence_std)
    print(f'wrote {s.path}: {s.frames} frames ({s.duration_s:.1f} s), {s.messages} messages, '
          f'{s.bytes / 1e6:.1f} MB in {s.wall_s:.1f} s; fixation re-selections right {s.reselections["right"]}, '
          f'left {s.reselections["left"]}')
    return 0
