"""Long-trajectory accuracy per flow preset, per refinement mode and with the scale aids (issue 7).

Runs ``fixego replay``'s pipeline over

* the shipped ``paper`` loop and ``walk`` bags (``bags/``),
* a rotation-poor straight run (2 m north, 320x240 at 10 Hz) and the paper loop and walk again, written
  here by the simulator *with* simulated wheel odometry (issue 16's: 20 Hz, its scale 1 % long, noise 2 % of the
  loop's 0.2 m/s) and the vergence measurements of
  ``fixego sim --vergence measurements`` (at start-up and at each new right fixation, triangulated from the
  quantised joint readings; heads undisturbed) so the scale aids can be measured,

for every flow preset (``paper``, ``window``, ``full``) and refinement (``local``: the papers' 3-frame
local BA; ``smoother``: the fixed-lag factor graph (the default); ``constant``: local BA with the
constant-speed prior, nominal 0.5 m/s until the vergence step measures the speed), and reports the papers' unaligned
position error (mean, terminal), ATE after SE(3) and Sim(3) alignment, the estimated/true path length,
and the estimator's median ms per frame; and, per bag, how much of the true motion could show the metric
scale to the rays at all: the angle between each true step's translation and the left camera's lever arm
``(R - I) c_L`` (:mod:`fixego_ros.estimation.observability`; 0 = that step's length is invisible). The
two-frame-only ("raw") trajectory is the same for both refinements and is reported once per preset.
Everything is deterministic, so the results are computed once per process (``make bench`` repeats are
free) and written with a plot of the paper loop to ``bench/accuracy.md`` and ``bench/accuracy_paper.png``.

    python -m fixego_ros.bench.accuracy [--out bench]
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
from pathlib import Path

import numpy as np

from fixego_ros.bench.replay import trajectory_figures
from fixego_ros.sim.wheel_odometry import WheelOdometry

PRESETS = ('paper', 'window', 'full')
REFINEMENTS = ('local', 'smoother', 'constant')
# estimator parameters of each refinement row ('constant' is the local BA with the constant-speed prior)
REFINEMENT_PARAMS = {'local': {'refinement': 'local'}, 'smoother': {'refinement': 'smoother'},
                     'constant': {'refinement': 'local', 'constant_speed': True}}
# issue 16's wheel odometry: 20 Hz, a wheel radius 1 % long (not in its covariance), noise 2 % of the 0.2 m/s
WHEEL_ODOMETRY = WheelOdometry(std_m_s=0.004, rate_hz=20.0, scale_bias=0.01)
# the paper-loop runs drawn in the plot: the default back end with each aid and with none, and the papers' method
PLOTTED = (('paper', 'full', 'local'), ('paper', 'full', 'smoother'), ('paper+vergence', 'full', 'smoother'),
           ('paper+speed', 'full', 'smoother'))
_results: dict[str, float] | None = None
_tracks: dict[str, np.ndarray] = {}
_tmp: tempfile.TemporaryDirectory | None = None


def _aided_bags() -> dict[str, Path]:
    """Straight run, paper loop and walk with simulated wheel odometry and vergence, written once per process."""
    global _tmp
    from fixego_ros.bags.shipped import ShippedBag, by_name, generate
    from fixego_ros.sim.run import SimSettings
    _tmp = tempfile.TemporaryDirectory(prefix='fixego-accuracy-')
    out = {}
    specs = {'straight': ShippedBag('straight', SimSettings(trajectory='straight', seed=0, fps=10.0), 320, 240, ''),
             'paper+aids': by_name('paper'), 'walk+aids': by_name('walk')}
    for name, spec in specs.items():
        path = Path(_tmp.name) / name.replace('+', '_')
        generate(spec, path, wheel_odom=WHEEL_ODOMETRY, vergence='measurements')
        out[name] = path
    return out


def _replay(path: Path, preset: str, refinement: str, aid: str):
    """``aid``: '', 'speed', 'vergence' or 'speed+vergence'."""
    from fixego_ros.bags.reader import Bag
    from fixego_ros.geometry.rig import load_rig
    from fixego_ros.pipeline.odometry import SpeedSettings
    from fixego_ros.pipeline.params import ESTIMATOR_PARAMS, FLOW_PARAMS, params_getter
    from fixego_ros.replay.run import ReplaySettings, replay
    from fixego_ros.sim.bag_writer import VERGENCE_TOPIC, WHEEL_ODOM_TOPIC
    rig = load_rig(path / 'rig.yaml')
    flow = params_getter(FLOW_PARAMS, {'preset': preset})
    est = params_getter(ESTIMATOR_PARAMS, REFINEMENT_PARAMS[refinement])
    settings = ReplaySettings.from_getters(rig, flow=flow, estimator=est,
                                           speed=SpeedSettings(topic=WHEEL_ODOM_TOPIC) if 'speed' in aid else None,
                                           vergence_topic=VERGENCE_TOPIC if 'vergence' in aid else '')
    return replay(Bag(path), rig, settings, workers=1)


LEVER_STEP_DEG = 1.0       # a true step whose lever arm is this far off its translation shows some scale


def lever_arm_stats(rig, gt_poses: list) -> dict[str, float]:
    """Over the true frame-to-frame steps (``gt_poses``: base_link in odom): the share of steps whose lever arm is
    more than ``LEVER_STEP_DEG`` off the translation, and the median angle over the turning steps (deg)."""
    from fixego_ros.estimation.observability import rig_lever_arm_angle
    from fixego_ros.geometry.rotation import base_link_pose_to_rig, rotation_angle
    poses = [base_link_pose_to_rig(p) for p in gt_poses]
    angles, turning = [], []
    for a, b in itertools.pairwise(poses):
        step = a.inverse() @ b
        if np.linalg.norm(step.t) < 1e-6:
            continue
        angles.append(np.degrees(rig_lever_arm_angle(rig, step)))
        turning.append(rotation_angle(step.R) > np.radians(0.5))
    angles, turning = np.array(angles), np.array(turning, bool)
    return {'scale_steps_share': float(np.mean(angles > LEVER_STEP_DEG)) if len(angles) else float('nan'),
            'turning_median_deg': float(np.median(angles[turning])) if turning.any() else float('nan')}


def run() -> dict[str, float]:
    global _results
    if _results is not None:
        return dict(_results)
    from fixego_ros.bags.shipped import BAGS_DIR
    bags: list[tuple[str, Path, str]] = [('paper', BAGS_DIR / 'paper', ''), ('walk', BAGS_DIR / 'walk', '')]
    aided = _aided_bags()
    bags += [('straight', aided['straight'], ''), ('straight+speed', aided['straight'], 'speed'),
             ('paper+speed', aided['paper+aids'], 'speed'),
             ('paper+speed+vergence', aided['paper+aids'], 'speed+vergence')]
    bags += [(f'{name}+vergence', aided[key], 'vergence')
             for name, key in (('paper', 'paper+aids'), ('walk', 'walk+aids'), ('straight', 'straight'))]
    out: dict[str, float] = {}
    for name, path, aid in bags:
        for preset in PRESETS:
            for refinement in REFINEMENTS:
                if 'vergence' in aid and refinement == 'local':
                    continue                       # the local BA does not use the vergence point
                res = _replay(path, preset, refinement, aid)
                key = f'{name}.{preset}.{refinement}'
                bag = name.split('+')[0]
                if f'lever.{bag}.scale_steps_share' not in out:
                    from fixego_ros.geometry.rig import load_rig
                    out.update({f'lever.{bag}.{k}': v
                                for k, v in lever_arm_stats(load_rig(path / 'rig.yaml'), res.gt_poses).items()})
                trajectory_figures(out, key, res.stamps, res.poses, res)
                out[f'{key}.estimate_ms_median'] = float(np.median(res.stage_ms.get('estimate', [np.nan])))
                if refinement == 'local':
                    trajectory_figures(out, f'{name}.{preset}.raw', res.stamps, res.poses_raw, res)
                if (name, preset, refinement) in PLOTTED:
                    _tracks.setdefault('truth', np.array([p.t for p in res.gt_poses]))
                    _tracks[f'{name}, {preset}, {refinement}'] = np.array([p.t for p in res.poses])
    _results = out
    return dict(out)


def table(results: dict[str, float]) -> str:
    """Markdown: one row per bag / preset / refinement."""
    rows = ['| bag | preset | refinement | mean (cm) | terminal (cm) | ATE SE(3) (cm) | ATE Sim(3) (cm) '
            '| path est/true | estimator ms (median) |', '|---|---|---|---:|---:|---:|---:|---:|---:|']
    keys = sorted({k.rsplit('.', 1)[0] for k in results if not k.startswith('lever.')})
    order = {'paper': 0, 'walk': 1, 'straight': 2, 'straight+speed': 3, 'paper+speed': 4, 'paper+speed+vergence': 5,
             'paper+vergence': 6, 'walk+vergence': 7, 'straight+vergence': 8}
    keys.sort(key=lambda k: (order.get(k.split('.')[0], 9), PRESETS.index(k.split('.')[1]),
                             ('raw', *REFINEMENTS).index(k.split('.')[2])))
    for k in keys:
        bag, preset, ref = k.split('.')
        r = {m: results.get(f'{k}.{m}', float('nan')) for m in ('mean_error_cm', 'terminal_error_cm', 'ate_se3_cm',
                                                               'ate_sim3_cm', 'path_length_ratio',
                                                               'estimate_ms_median')}
        ms = '' if ref == 'raw' else f'{r["estimate_ms_median"]:.1f}'
        rows.append(f'| {bag} | {preset} | {ref} | {r["mean_error_cm"]:.1f} | {r["terminal_error_cm"]:.1f} | '
                    f'{r["ate_se3_cm"]:.1f} | {r["ate_sim3_cm"]:.1f} | {r["path_length_ratio"]:.3f} | {ms} |')
    return '\n'.join(rows) + '\n'


def lever_table(results: dict[str, float]) -> str:
    """Markdown: per bag, how much of the true motion could show the metric scale to the rays."""
    rows = [f'| bag | true steps with the lever arm > {LEVER_STEP_DEG:g}° off the translation | '
            'median angle over turning steps |', '|---|---:|---:|']
    for bag in sorted({k.split('.')[1] for k in results if k.startswith('lever.')}):
        median = results[f'lever.{bag}.turning_median_deg']
        rows.append(f'| {bag} | {100 * results[f"lever.{bag}.scale_steps_share"]:.0f} % | '
                    + (f'{median:.2f}° |' if np.isfinite(median) else 'no turns |'))
    return '\n'.join(rows) + '\n'


def plot(path: Path) -> None:
    """Top view of the paper loop: truth and the runs in ``PLOTTED``."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 6))
    for label, xyz in _tracks.items():
        if len(xyz):
            ax.plot(xyz[:, 0], xyz[:, 1], 'k-' if label == 'truth' else '-', lw=2 if label == 'truth' else 1,
                    label=label)
    ax.set_aspect('equal')
    ax.set_xlabel('x (m, odom)')
    ax.set_ylabel('y (m, odom)')
    ax.set_title('paper loop, no alignment')
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(out: Path) -> None:
    """Write ``accuracy.md`` and ``accuracy_paper.png`` into ``out`` (``make bench`` calls this)."""
    res = run()
    out.mkdir(parents=True, exist_ok=True)
    (out / 'accuracy.md').write_text('# Accuracy per preset and refinement (deterministic replays)\n\n'
                                     'Produced by `python -m fixego_ros.bench.accuracy`; see the module docstring.\n\n'
                                     + table(res) + '\nWhere the rays could see the scale at all (true motion; '
                                     '`estimation/observability.py`):\n\n' + lever_table(res))
    plot(out / 'accuracy_paper.png')


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m fixego_ros.bench.accuracy')
    ap.add_argument('--out', default='bench')
    args = ap.parse_args(argv)
    report(Path(args.out))
    print(table(run()))
    print(lever_table(run()))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
