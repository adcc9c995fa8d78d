"""Benchmark of the estimation core: one two-frame solve and one local-BA step (median, p99).

Targets (issue): medians <= 2 ms (two-frame) and <= 3 ms (local BA) on a 2-core machine. Run with
``python -m fixego_ros.bench.core``. Timings are taken over a sequence of steps after a warm start, as in
the live estimator (each solve starts from the previous step).
"""

from __future__ import annotations

import time

import numpy as np

from fixego_ros.estimation.config import papers_config, papers_solver
from fixego_ros.estimation.estimator import Estimator
from fixego_ros.estimation.frames import step_pairs
from fixego_ros.estimation.local_ba import refine_latest
from fixego_ros.experiments.point_scene import PRESETS, PointScene, random_motion_sequence


def _time_preset(name: str, n_steps: int, seed: int = 0) -> dict[str, float]:
    cfg = PRESETS[name]
    rng = np.random.default_rng(seed)
    scene = PointScene(cfg, rng)
    steps = random_motion_sequence(cfg, n_steps, rng)
    _, obs, _ = scene.frames(steps)
    sigma = cfg.noise_px / scene.rig.right.fx
    est = Estimator(scene.rig, papers_config(window=3, solver=papers_solver(sigma=sigma, prior_step=cfg.step_length),
                                             max_step_translation=4 * cfg.step_length))
    tf, ba = [], {'paper_powell': [], 'paper_trf': [], 'joint': []}
    for k, o in enumerate(obs):
        if k < 2:
            est.update(o)
            continue
        pairs = step_pairs(scene.rig, est._window[-1].fixation, o)
        t0 = time.perf_counter()
        res = est.solver.solve(pairs, initial=est._latest.motion_raw if est._latest else None)
        tf.append(time.perf_counter() - t0)
        problem, _ = est._ba_problem(o)
        for key, (mode, mini) in {'paper_powell': ('paper', 'powell'), 'paper_trf': ('paper', 'trf'),
                                  'joint': ('joint', 'trf')}.items():
            t0 = time.perf_counter()
            refine_latest(problem, res.pose, mode, pairs, sigma, minimizer=mini)
            ba[key].append(time.perf_counter() - t0)
        est.update(o)
    out = {f'{name}.two_frame_ms.median': 1e3 * float(np.median(tf)),
           f'{name}.two_frame_ms.p99': 1e3 * float(np.percentile(tf, 99))}
    for key, v in ba.items():
        out[f'{name}.local_ba_{key}_ms.median'] = 1e3 * float(np.median(v))
        out[f'{name}.local_ba_{key}_ms.p99'] = 1e3 * float(np.percentile(v, 99))
    return out


def run(n_steps: int = 60) -> dict[str, float]:
    out: dict[str, float] = {}
    for name in ('paper', 'dense'):
        out.update(_time_preset(name, n_steps))
    for k, v in out.items():
        print(f'{k:45s} {v:8.2f}')
    return out


if __name__ == '__main__':
    run()
