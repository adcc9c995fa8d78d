"""Offline replay: throughput on a real-size bag and accuracy on the shipped bags.

* Throughput: ``fixego replay``'s pipeline over ``THROUGHPUT_S`` seconds of the paper loop simulated at
  640x480 and 30 Hz (the target is >= 5x real time), with the estimator in-process (``workers=1``)
  and in a second process (``workers=2``), plus the median ms per stage.
* Accuracy: every shipped bag (``bags/``) as ``fixego replay`` replays it (with the bag's own vergence
  measurements when it has them), refined and two-frame ("raw") trajectories: the papers'
  unaligned position error (mean, terminal), evo's ATE after SE(3) and Sim(3) alignment, and the
  estimated/true path length. The replay is deterministic, so repeats only vary in time.

    python -m fixego_ros.bench.replay
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

THROUGHPUT_S = 6.0
_cache: dict[str, Path] = {}
_tmp: tempfile.TemporaryDirectory | None = None


def _big_bag() -> Path:
    """640x480 at 30 Hz, written once per process (the renderer is deterministic)."""
    global _tmp
    if 'big' not in _cache:
        from fixego_ros.geometry.rig import default_rig_path, load_rig
        from fixego_ros.sim.bag_writer import write_bag
        from fixego_ros.sim.run import SimSettings
        _tmp = tempfile.TemporaryDirectory(prefix='fixego-bench-')
        path = Path(_tmp.name) / 'paper640'
        write_bag(path, load_rig(default_rig_path()), SimSettings(trajectory='paper', duration=THROUGHPUT_S),
                  progress=False)
        _cache['big'] = path
    return _cache['big']


def replay_bag(path: Path, workers: int, observe: Callable | None = None):
    """What ``fixego replay BAG`` does with default settings (``observe``: :func:`~fixego_ros.replay.run.replay`'s)."""
    from fixego_ros.bags.reader import Bag
    from fixego_ros.geometry.rig import load_rig
    from fixego_ros.replay.run import ReplaySettings, ReplayTopics, bag_defaults, replay
    rig = load_rig(path / 'rig.yaml')
    bag = Bag(path)      # the bag's own vergence measurements (and fixations), as ``fixego replay`` takes them
    return replay(bag, rig, ReplaySettings.from_getters(rig, **bag_defaults(bag, ReplayTopics())), workers=workers,
                  observe=observe)


def trajectory_figures(out: dict[str, float], key: str, stamps, poses, res) -> None:
    """The papers' unaligned position error (mean, terminal), ATE after SE(3)/Sim(3) and the path-length
    ratio of one estimated trajectory against the replay's ground truth, as ``out[f'{key}.<figure>']``."""
    from fixego_ros.evaluation.metrics import evaluate
    s = evaluate(stamps, poses, res.gt_stamps, res.gt_poses, anchor_first=True).summary
    pe, ape, pl = s['position_error_m'], s['ape_translation_m'], s['path_length_m']
    out[f'{key}.mean_error_cm'] = 100 * pe['mean']
    out[f'{key}.terminal_error_cm'] = 100 * pe['terminal']
    out[f'{key}.ate_se3_cm'] = 100 * (ape['se3'].get('rmse') or float('nan'))
    out[f'{key}.ate_sim3_cm'] = 100 * (ape['sim3'].get('rmse') or float('nan'))
    out[f'{key}.path_length_ratio'] = pl['ratio'] if pl['ratio'] is not None else float('nan')


def run() -> dict[str, float]:
    from fixego_ros.bags.shipped import BAGS_DIR, SHIPPED

    out: dict[str, float] = {}
    big = _big_bag()
    for workers in (1, 2):
        t0 = time.perf_counter()
        res = replay_bag(big, workers)
        wall = time.perf_counter() - t0
        key = f'throughput_640x480_30hz.workers{workers}'
        out[f'{key}.realtime_factor'] = THROUGHPUT_S / wall
        out[f'{key}.ms_per_frame'] = 1e3 * wall / max(res.counts['frames'], 1)
        for stage, ms in res.stage_ms.items():
            out[f'{key}.{stage}_ms_median'] = float(np.median(ms))
            out[f'{key}.{stage}_ms_mean'] = float(np.mean(ms))
    for spec in SHIPPED:
        res = replay_bag(BAGS_DIR / spec.name, 2)
        out[f'{spec.name}.realtime_factor'] = res.realtime_factor
        for label, poses in (('refined', res.poses), ('raw', res.poses_raw)):
            trajectory_figures(out, f'{spec.name}.{label}', res.stamps, poses, res)
    return out


if __name__ == '__main__':
    for k, v in run().items():
        print(f'{k}: {v:.3g}')
