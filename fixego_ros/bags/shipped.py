"""The bags shipped in ``bags/`` and how to regenerate them exactly: ``python -m fixego_ros.bags.shipped``.

Each is written by ``fixego sim`` (seeded, so the bytes are the same on every run with the same
library versions) and gets ``rig.yaml``, ``sim.yaml`` and ``ground_truth.tum`` next to the MCAP file.
Images are raw ``sensor_msgs/Image`` (DESIGN.md §3) and barely compress (the room's texture and
the sensor noise are high-entropy), so to stay within the 30 MB budget the bags are smaller than a
real rig's stream (640x480 at 30 Hz is ~18 MB per second):

* ``paper``: the papers' stadium loop (5.0 m, 25.5 s) at 320x240 and 5.1 Hz, about one frame per
  step of the papers' 130-step run, with the rig's physical vergence step (``/fixego/vergence``: one
  measurement at start-up and one per new right fixation; the left head really moves);
* ``walk``: the first 4 s of the wearable ``walk`` sequence (head bob, sway, wobble) at 320x240, 10 Hz,
  without vergence (as it was recorded before the step existed).

Use ``--check`` to regenerate into a temporary folder and compare every message with the shipped bag: exactly
for stamps, topics, integers and strings, within stated tolerances for floats and image bytes (other CPUs
round the last bit differently; see :data:`FLOAT_TOL`).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from fixego_ros.sim.run import SimSettings
from fixego_ros.sim.wheel_odometry import WheelOdometry

BAGS_DIR = Path(__file__).resolve().parents[2] / 'bags'


@dataclass(frozen=True)
class ShippedBag:
    name: str
    settings: SimSettings
    width: int
    height: int
    about: str


SHIPPED: tuple[ShippedBag, ...] = (
    ShippedBag('paper', SimSettings(trajectory='paper', seed=0, fps=5.1, vergence='physical'), 320, 240,
               "the papers' stadium loop, 5.0 m in 25.5 s, ~1 frame per step of their 130-step run, with the "
               "rig's vergence step"),
    ShippedBag('walk', SimSettings(trajectory='walk', seed=0, fps=10.0, duration=4.0, vergence='off'), 320, 240,
               'the first 4 s of a wearable rig on a walking person (head bob, sway, wobble)'),
)


def by_name(name: str) -> ShippedBag:
    for b in SHIPPED:
        if b.name == name:
            return b
    raise KeyError(f'no shipped bag {name!r} (have {", ".join(b.name for b in SHIPPED)})')


def generate(spec: ShippedBag, out_dir: Path, progress: bool = False, wheel_odom: WheelOdometry | None = None,
             vergence: str | None = None):
    """Write ``spec`` to ``out_dir`` (must not exist) with its ground truth as TUM; returns the summary.
    ``wheel_odom`` adds simulated wheel odometry (the shipped bags have none); ``vergence`` (a
    ``SimSettings.vergence`` mode) replaces the spec's."""
    from dataclasses import replace

    from fixego_ros.evaluation.tum import write_tum
    from fixego_ros.geometry.rig import default_rig_path, load_rig
    from fixego_ros.sim.bag_writer import write_bag
    from fixego_ros.sim.run import Simulation, resize_rig

    settings = spec.settings if vergence is None else replace(spec.settings, vergence=vergence)
    rig = resize_rig(load_rig(default_rig_path()), spec.width, spec.height)
    sim = Simulation(rig, settings)
    summary = write_bag(out_dir, rig, settings, progress=progress, sim=sim, wheel_odom=wheel_odom)
    write_tum(out_dir / 'ground_truth.tum', [settings.epoch + t for t in sim.stamps], sim.ground_truth())
    return summary


# How close a regenerated bag must be to the shipped one. The simulator is seeded, but numpy and OpenCV pick
# SIMD code paths by CPU (AVX2, AVX-512, ...) whose transcendental functions and interpolation round the last bit
# differently, so the bytes are only identical on the same kind of CPU. What we guarantee everywhere: every
# number within FLOAT_TOL (relative to max(1, |value|)), and an image differing in at most IMAGE_MAX_FRACTION of
# its pixels by at most IMAGE_MAX_LEVELS grey levels (a texel rounded the other way at an edge).
FLOAT_TOL = 1e-9
IMAGE_MAX_LEVELS = 2
IMAGE_MAX_FRACTION = 1e-3


def _differences(x, y, path: str = '') -> list[str]:
    """Where two decoded messages differ beyond the tolerances above (empty = equal)."""
    import numpy as np

    if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
        xa, ya = np.asarray(x), np.asarray(y)
        if xa.shape != ya.shape or xa.dtype != ya.dtype:
            return [f'{path}: shape/type {xa.shape} {xa.dtype} vs {ya.shape} {ya.dtype}']
        if xa.dtype == np.uint8 and path.endswith('data'):
            d = np.abs(xa.astype(np.int16) - ya.astype(np.int16))
            frac = float(np.count_nonzero(d)) / max(d.size, 1)
            if d.size and (int(d.max()) > IMAGE_MAX_LEVELS or frac > IMAGE_MAX_FRACTION):
                return [f'{path}: {frac:.2%} of bytes differ, by up to {int(d.max())}']
            return []
        if np.issubdtype(xa.dtype, np.floating):
            bad = ~np.isclose(xa, ya, rtol=FLOAT_TOL, atol=FLOAT_TOL, equal_nan=True)
            return [f'{path}: {int(bad.sum())} values differ by more than {FLOAT_TOL:g}'] if bad.any() else []
        return [] if np.array_equal(xa, ya) else [f'{path}: differs']
    if isinstance(x, float) or isinstance(y, float):
        ok = isinstance(x, (int, float)) and isinstance(y, (int, float)) and (
            (x != x and y != y) or abs(x - y) <= FLOAT_TOL * max(1.0, abs(x), abs(y)))
        return [] if ok else [f'{path}: {x!r} vs {y!r}']
    if isinstance(x, (list, tuple)):
        if not isinstance(y, (list, tuple)) or len(x) != len(y):
            return [f'{path}: length differs']
        return [d for i, (u, v) in enumerate(zip(x, y, strict=True)) for d in _differences(u, v, f'{path}[{i}]')]
    if isinstance(x, dict):
        if not isinstance(y, dict) or list(x) != list(y):
            return [f'{path}: keys differ']
        return [d for k in x for d in _differences(x[k], y[k], f'{path}.{k}' if path else str(k))]
    if hasattr(x, '__dataclass_fields__'):
        if type(x).__name__ != type(y).__name__:
            return [f'{path}: type differs']
        return [d for name in x.__dataclass_fields__
                for d in _differences(getattr(x, name), getattr(y, name), f'{path}.{name}' if path else name)]
    return [] if x == y else [f'{path}: {x!r} vs {y!r}']


def _tum_differences(a: Path, b: Path) -> list[str]:
    import numpy as np

    ta, tb = np.loadtxt(a, ndmin=2), np.loadtxt(b, ndmin=2)
    if ta.shape != tb.shape:
        return [f'{a.name}: {ta.shape[0]} vs {tb.shape[0]} poses']
    return [] if np.allclose(ta, tb, rtol=FLOAT_TOL, atol=FLOAT_TOL) else [f'{a.name} differs beyond {FLOAT_TOL:g}']


def compare(a: Path, b: Path) -> list[str]:
    """Differences between two bags, message by message, beyond the stated tolerances (empty = the same
    bag up to the CPU's rounding; see FLOAT_TOL and IMAGE_MAX_*). Topics, stamps, order and every integer,
    string and field layout must match exactly."""
    from itertools import zip_longest

    import yaml

    from fixego_ros.bags.reader import Bag
    problems = []
    ba, bb = Bag(a), Bag(b)
    for i, (x, y) in enumerate(zip_longest(ba.messages(), bb.messages())):
        if x is None or y is None:
            problems.append(f'message {i}: only in {a if y is None else b}')
            break
        if (x.topic, x.log_time_ns, x.msgtype) != (y.topic, y.log_time_ns, y.msgtype):
            problems.append(f'message {i}: {x.topic} at {x.log_time_ns} ns vs {y.topic} at {y.log_time_ns} ns')
        elif bytes(x.data) != bytes(y.data):
            diff = _differences(ba.decode(x), bb.decode(y))
            if diff:
                problems.append(f'message {i} ({x.topic} at {x.log_time_ns} ns): {diff[0]}')
        if len(problems) > 5:
            break
    for extra in ('rig.yaml', 'sim.yaml'):     # numbers the simulator measured (vergence steps) round by CPU too
        x, y = (yaml.safe_load((d / extra).read_text()) for d in (a, b))
        problems += [f'{extra}: {d}' for d in _differences(x, y)[:1]]
    problems += _tum_differences(a / 'ground_truth.tum', b / 'ground_truth.tum')
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m fixego_ros.bags.shipped', description=__doc__.split('\n')[0])
    ap.add_argument('--out', type=Path, default=BAGS_DIR, help=f'folder of the bags (default {BAGS_DIR})')
    ap.add_argument('--only', nargs='*', help='names of the bags to (re)generate (default: all)')
    ap.add_argument('--check', action='store_true', help='regenerate into a temporary folder and compare')
    ap.add_argument('--force', action='store_true', help='replace existing bags')
    args = ap.parse_args(argv)
    specs = [by_name(n) for n in args.only] if args.only else list(SHIPPED)
    status = 0
    for spec in specs:
        target = args.out / spec.name
        if args.check:
            with tempfile.TemporaryDirectory() as tmp:
                generate(spec, Path(tmp) / spec.name)
                problems = compare(target, Path(tmp) / spec.name)
            same = 'the same (within the stated tolerances)'
            print(f'{spec.name}: ' + (same if not problems else '; '.join(problems)))
            status |= bool(problems)
            continue
        if target.exists():
            if not args.force:
                print(f'{target} exists (use --force to replace it)', file=sys.stderr)
                return 2
            import shutil
            shutil.rmtree(target)
        s = generate(spec, target, progress=True)
        print(f'{spec.name}: {s.frames} frames, {s.duration_s:.1f} s, {s.bytes / 1e6:.1f} MB -> {target}')
    return status


if __name__ == '__main__':
    sys.exit(main())
