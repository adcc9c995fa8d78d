"""``fixego sim``: write an image-level bag from the simulated rig (DESIGN.md §6).

Exit codes: 0 the bag is written; 2 an option cannot be used: one ``fixego sim: ...`` line on stderr naming
the option, its value and what is allowed, printed before anything is simulated or created (the numbers
are checked for finiteness and range, the rig file is read, and ``--out`` is probed by creating and
removing the directory); 1 the simulation or the writing failed part way (one line): the incomplete bag
directory is removed, so the same ``--out`` can be used again; 128 + the signal number (130 Ctrl-C,
143 SIGTERM) when interrupted, also without leaving a partial bag. Never a traceback for these.

The option checks are :mod:`fixego_ros.cli_options`'s; :func:`read_rig` is shared with ``fixego demo``.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import shutil
import signal
import sys
from collections.abc import Iterator
from pathlib import Path

from fixego_ros.cli_options import (
    OptionError,
    check_float,
    check_int,
    check_new_dir,
    one_line_errors,
    why,
)
from fixego_ros.interrupt import signals_interrupt
from fixego_ros.sim.run import (
    DURATION_MAX,
    FPS_RANGE,
    HFOV_RANGE,
    MAX_FRAMES,
    NOISE_RANGE,
    REST_RANGE,
    SEED_MAX,
    SIZE_RANGE,
    SPEED_RANGE,
    STEPS_RANGE,
    TEXEL_RANGE,
    SimSettings,
    build_trajectory,
    resize_rig,
    rig_with_hfov,
)
from fixego_ros.sim.trajectories import NAMES
from fixego_ros.sim.vergence_measure import VERGENCE_MODES
from fixego_ros.sim.wheel_odometry import BIAS_MAX, RATE_MAX_HZ, WheelOdometry

PROG = 'fixego sim'
# upper limit of the wheel odometry noise (fixego_ros.sim.bag_writer only refuses negative/non-finite ones)
WHEEL_ODOM_STD_MAX = 10.0        # m/s: beyond it the "speed aid" is noise (and 1e308 overflows to inf)
VERGENCE_DEFAULT = 'physical'    # the rig verges at start-up and at each new right fixation, as a real one does


def read_rig(path: Path | None, option: str = '--rig'):
    """The rig of ``path`` (default: config/rig.yaml), or :class:`OptionError` naming the file
    (:func:`~fixego_ros.geometry.rig.load_rig` refuses what is not a small regular UTF-8 YAML rig file)."""
    from fixego_ros.geometry.rig import default_rig_path, load_rig
    rig_path = Path(path) if path is not None else default_rig_path()
    try:
        rig = load_rig(rig_path)
        rig.require_intrinsics(f'the simulator ({rig_path})')      # it renders: camera_info cannot stand in
        return rig
    except ValueError as e:              # RigError: names the file already
        msg = ' '.join(str(e).split())
        raise OptionError(f'{option}: {msg}' if path is not None else msg) from None


def image_size(rig, width: int | None, height: int | None) -> tuple[int, int] | None:
    """The (width, height) asked for (the missing one from the rig's aspect ratio), checked; None = the rig's."""
    lo, hi = SIZE_RANGE
    if width is not None:
        check_int(width, '--width', lo, hi, note=' px')
    if height is not None:
        check_int(height, '--height', lo, hi, note=' px')
    if width is None and height is None:
        return None
    w = width if width is not None else round(rig.right.width * height / rig.right.height)
    h = height if height is not None else round(rig.right.height * width / rig.right.width)
    for name, given, v in (('height', '--width', h), ('width', '--height', w)):
        if not lo <= v <= hi:
            raise OptionError(f'{given} {width if given == "--width" else height} gives an image {name} of {v} px '
                              f'with the rig\'s aspect ratio; the {name} must be in {lo}..{hi} px (pass both '
                              f'--width and --height)')
    return w, h


# ------------------------------------------------------------------------------------------------ command
def register(subparsers) -> None:
    p = subparsers.add_parser(
        'sim', help='write an image-level rosbag2/MCAP bag from the simulated rig',
        description='Simulate the rig (room, fixation servo, both cameras) along a trajectory and write '
                    'a rosbag2/MCAP bag with the topics of DESIGN.md §3 plus BAG_DIR/rig.yaml. Every option is '
                    'checked before anything is simulated (exit code 2, one line); a run that fails part way '
                    'removes its incomplete bag directory (exit code 1).')
    p.add_argument('--trajectory', choices=NAMES, default='paper', help='trajectory (default: paper)')
    p.add_argument('--out', required=True, metavar='BAG_DIR',
                   help='bag directory to create (must not exist; its parent must be a writable directory)')
    p.add_argument('--rig', type=Path, help='rig file (default: config/rig.yaml)')
    p.add_argument('--seed', type=int, default=0, help=f'seed of textures, noise and servo, 0..{SEED_MAX} (default 0)')
    p.add_argument('--fps', type=float, default=30.0,
                   help=f'frame rate in [{FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}] (default 30)')
    p.add_argument('--width', type=int,
                   help=f'image width, {SIZE_RANGE[0]}..{SIZE_RANGE[1]} px (intrinsics scaled, angle of view kept; '
                        'alone, the height follows the rig\'s aspect ratio; default: the rig file\'s)')
    p.add_argument('--height', type=int, help=f'image height, {SIZE_RANGE[0]}..{SIZE_RANGE[1]} px (intrinsics '
                                              'scaled)')
    p.add_argument('--hfov', type=float, help=f'horizontal angle of view in degrees, in [{HFOV_RANGE[0]:g}, '
                                              f'{HFOV_RANGE[1]:g}] (replaces the intrinsics)')
    p.add_argument('--encoding', choices=('mono8', 'rgb8'), default='mono8')
    p.add_argument('--noise', type=float, default=2.0,
                   help=f'sensor noise sigma in grey levels, in [0, {NOISE_RANGE[1]:g}] (default 2)')
    p.add_argument('--speed', type=float, help=f'rig speed in m/s, in [{SPEED_RANGE[0]:g}, {SPEED_RANGE[1]:g}] '
                                               '(default: the trajectory\'s)')
    g = p.add_mutually_exclusive_group()
    g.add_argument('--duration', type=float, help=f'stop after this many seconds, in (0, {DURATION_MAX:g}]')
    g.add_argument('--steps', type=int,
                   help=f'paper trajectory: stop at this step mark ({STEPS_RANGE[0]}..{STEPS_RANGE[1]})')
    p.add_argument('--rest', type=float, default=0.0, metavar='S',
                   help=f'the rig stands still S s at its first pose before the trajectory (--duration and --steps '
                        f'count the trajectory), S in [{REST_RANGE[0]:g}, {REST_RANGE[1]:g}] (default 0)')
    p.add_argument('--rest-end', type=float, default=0.0, metavar='S',
                   help=f'the rig stands still S s at its last pose after the trajectory, S in [{REST_RANGE[0]:g}, '
                        f'{REST_RANGE[1]:g}] (default 0)')
    p.add_argument('--texel', type=float, default=0.002,
                   help=f'texture resolution in m, in [{TEXEL_RANGE[0]:g}, {TEXEL_RANGE[1]:g}] (default 0.002)')
    p.add_argument('--wheel-odom-std', type=float, metavar='S',
                   help='also write /fixego/wheel/odom (nav_msgs/Odometry, one per frame): the true base_link '
                        'velocity plus seeded Gaussian noise of std S m/s, covariance S^2; S in '
                        f'[0, {WHEEL_ODOM_STD_MAX:g}] (default: off)')
    p.add_argument('--wheel-odom-rate', type=float, metavar='HZ',
                   help=f'with --wheel-odom-std: samples at HZ in (0, {RATE_MAX_HZ:g}] instead of one per frame')
    p.add_argument('--wheel-odom-bias', type=float, default=0.0, metavar='B',
                   help='with --wheel-odom-std: the velocity is scaled by 1 + B (a wheel radius off by B, not in the '
                        f'covariance), B in [-{BIAS_MAX:g}, {BIAS_MAX:g}] (default 0)')
    p.add_argument('--vergence', choices=VERGENCE_MODES, default=VERGENCE_DEFAULT,
                   help='the rig\'s vergence step, at the first frame and at each new right fixation: physical = '
                        'the left head verges on the right\'s fixation point and back (its images and joint states '
                        'show it) and /fixego/vergence (geometry_msgs/PoseWithCovarianceStamped) gets the point '
                        'triangulated from both heads\' quantised joint readings and noisy pixels; measurements = '
                        'the same messages, heads undisturbed (the images of off); off = neither '
                        f'(default: {VERGENCE_DEFAULT})')
    p.add_argument('--no-progress', action='store_true', help='no progress bar on stderr')
    one_line_errors(p)
    p.set_defaults(func=run)


def check_args(args: argparse.Namespace):
    """Every option, before anything is simulated or created: (rig, settings, out); :class:`OptionError`."""
    check_int(args.seed, '--seed', 0, SEED_MAX)
    check_float(args.fps, '--fps', *FPS_RANGE, unit='frames per second')
    if args.hfov is not None:
        check_float(args.hfov, '--hfov', *HFOV_RANGE, unit='degrees')
    check_float(args.noise, '--noise', *NOISE_RANGE, unit='grey levels')
    if args.speed is not None:
        check_float(args.speed, '--speed', *SPEED_RANGE, unit='m/s')
    if args.duration is not None:
        check_float(args.duration, '--duration', 0.0, DURATION_MAX, lo_open=True, unit='s')
    if args.steps is not None:
        check_int(args.steps, '--steps', *STEPS_RANGE, note=' (paper loop step marks)')
        if args.trajectory != 'paper':
            raise OptionError(f'--steps applies to the paper trajectory only, got --trajectory {args.trajectory} '
                              '(use --duration)')
    check_float(args.texel, '--texel', *TEXEL_RANGE, unit='m')
    check_float(args.rest, '--rest', *REST_RANGE, unit='s')
    check_float(args.rest_end, '--rest-end', *REST_RANGE, unit='s')
    if args.wheel_odom_std is not None:
        check_float(args.wheel_odom_std, '--wheel-odom-std', 0.0, WHEEL_ODOM_STD_MAX, unit='m/s')
    elif args.wheel_odom_rate is not None or args.wheel_odom_bias:
        raise OptionError('--wheel-odom-rate and --wheel-odom-bias need --wheel-odom-std')
    if args.wheel_odom_rate is not None:
        check_float(args.wheel_odom_rate, '--wheel-odom-rate', 0.0, RATE_MAX_HZ, lo_open=True, unit='Hz')
    check_float(args.wheel_odom_bias, '--wheel-odom-bias', -BIAS_MAX, BIAS_MAX)
    if args.out is not None and (not args.out or not args.out.strip()):
        raise OptionError('--out must name a directory to create, got an empty path')
    rig = read_rig(args.rig)
    size = image_size(rig, args.width, args.height)
    if size is not None:
        rig = resize_rig(rig, *size)
    if args.hfov is not None:
        rig = rig_with_hfov(rig, args.hfov)
    settings = SimSettings(trajectory=args.trajectory, seed=args.seed, fps=args.fps, encoding=args.encoding,
                           noise_sigma=args.noise, speed=args.speed, duration=args.duration, steps=args.steps,
                           texel=args.texel, vergence=args.vergence, rest_s=args.rest,
                           rest_end_s=args.rest_end)
    out = check_new_dir(args.out, '--out')     # the probe creates and removes the directory
    rests = args.rest + args.rest_end
    frames = None if args.duration is None else math.floor((args.duration + rests) * args.fps + 1e-9) + 1
    if frames is None or (frames > MAX_FRAMES and args.trajectory != 'random'):   # (random lasts --duration)
        frames = build_trajectory(settings).frame_count(settings.fps)
    if frames > MAX_FRAMES:
        raise OptionError(f'--fps {args.fps:g} over the {frames / settings.fps:.0f} s of the trajectory gives '
                          f'{frames} frames; at most {MAX_FRAMES} (lower --fps or --duration, or raise --speed)')
    return rig, settings, out


class _LineTracker:
    """sys.stderr that remembers whether its last text ended a line (a progress bar's line may still be open)."""

    def __init__(self, stream) -> None:
        self.stream, self.open = stream, False

    def write(self, text: str) -> int:
        if text:
            self.open = not text.endswith('\n')
        return self.stream.write(text)

    def __getattr__(self, name: str):
        return getattr(self.stream, name)


@contextlib.contextmanager
def _tracked_stderr() -> Iterator[_LineTracker]:
    tracker = _LineTracker(sys.stderr)
    sys.stderr = tracker       # type: ignore[assignment]
    try:
        yield tracker
    finally:
        sys.stderr = tracker.stream


def _remove_partial(out: Path) -> str:
    """Remove the incomplete bag directory ``out``; what happened, for the error line."""
    if not out.exists() and not out.is_symlink():
        return 'nothing was left behind'
    try:
        shutil.rmtree(out)
    except OSError as e:
        return f'the incomplete bag directory {out} could NOT be removed ({why(e)}): delete it before a re-run'
    return f'the incomplete bag directory {out} was removed'


def _say(err: _LineTracker, text: str) -> None:
    """One ``fixego sim: ...`` line on stderr, on a line of its own (after an open progress bar)."""
    err.write(f'{chr(10) if err.open else ""}{PROG}: {text}\n')
    err.flush()


def run(args: argparse.Namespace) -> int:
    """``fixego sim``; see the module docstring for the exit codes."""
    from fixego_ros.sim.bag_writer import write_bag

    try:
        rig, settings, out = check_args(args)
    except (OptionError, ValueError) as e:
        print(f'{PROG}: {" ".join(str(e).split())}', file=sys.stderr)
        return 2
    with _tracked_stderr() as err:
        try:
            with signals_interrupt():
                wheel = (None if args.wheel_odom_std is None else
                         WheelOdometry(args.wheel_odom_std, args.wheel_odom_rate, args.wheel_odom_bias))
                s = write_bag(out, rig, settings, progress=not args.no_progress, wheel_odom=wheel)
        except KeyboardInterrupt as e:
            signum = getattr(e, 'signum', signal.SIGINT)
            _say(err, f'interrupted by {signal.Signals(signum).name}: stopped; {_remove_partial(out)}')
            return 128 + signum
        except FileExistsError as e:     # made by someone else since the probe: not ours to remove
            _say(err, f'writing {out} failed: {" ".join(str(e).split())}')
            return 1
        except (OSError, ValueError, RuntimeError, MemoryError) as e:
            what = ' '.join(str(e).split()) or type(e).__name__
            _say(err, f'writing {out} failed: {what}; {_remove_partial(out)}')
            return 1
        except BaseException:
            _say(err, f'writing {out} failed (a bug: traceback below); {_remove_partial(out)}')
            raise
    verg = '' if settings.vergence == 'off' else f'; vergence ({settings.vergence}) measurements {s.vergence}'
    print(f'wrote {s.path}: {s.frames} frames ({s.duration_s:.1f} s), {s.messages} messages, '
          f'{s.bytes / 1e6:.1f} MB in {s.wall_s:.1f} s; fixation re-selections right {s.reselections["right"]}, '
          f'left {s.reselections["left"]}{verg}')
    return 0


