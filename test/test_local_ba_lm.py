"""Local BA least-squares modes on the shared Levenberg-Marquardt core ('lm', default) against scipy."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fixego_ros.estimation.config import papers_config, papers_solver
from fixego_ros.estimation.estimator import Estimator
from fixego_ros.estimation.frames import fixations_of, step_pairs
from fixego_ros.estimation.local_ba import BAProblem, BATerm, refine_latest
from fixego_ros.experiments.point_scene import PRESETS, PointScene, random_motion_sequence
from fixego_ros.geometry.rotation import Pose, exp_so3, rotation_angle


def ba_setup(seed: int, noise: float, preset: str = 'paper'):
    """BA terms of the third frame over a 3-frame window (prefix from the estimator), its two-frame step,
    the step's ray pairs, the true steps and sigma."""
    cfg = replace(PRESETS[preset], noise_px=noise)
    rng = np.random.default_rng(seed)
    scene = PointScene(cfg, rng)
    steps = random_motion_sequence(cfg, 2, rng)
    _, noisy, _ = scene.frames(steps)
    sigma = max(noise, 0.1) / scene.rig.right.fx
    est = Estimator(scene.rig, papers_config(window=0, solver=papers_solver(sigma=sigma, prior_step=cfg.step_length)))
    results = [est.update(o) for o in noisy]
    terms = []
    for side in ('right', 'left'):
        K = scene.rig.camera(side)
        ft = noisy[2].camera(side)
        for j, prefix in ((0, results[1].step), (1, Pose.identity())):
            terms.append(BATerm(prefix, noisy[j].camera(side).fixation_ray, ft.fixation_ray,
                                scene.rig.center(side), ft.cam_to_rig, K.fx, K.fy))
    pairs = step_pairs(scene.rig, fixations_of(noisy[1]), noisy[2])
    return BAProblem(terms), results[2].step, pairs, steps, sigma


def test_batched_distances_and_jacobian():
    problem, start, _, _, _ = ba_setup(2, 2.0)
    rng = np.random.default_rng(0)
    Rs = np.array([exp_so3(rng.normal(size=3) * 0.01) @ start.R for _ in range(4)])
    Ts = start.t + rng.normal(size=(4, 3)) * 0.01
    batch = problem.distances_batch(Rs, Ts)
    for k in range(4):
        assert np.array_equal(batch[k], problem.distances(Rs[k], Ts[k]))
    d, J = problem.distances_jacobian(start.R, start.t)
    assert np.array_equal(d, problem.distances(start.R, start.t))
    h = 1e-7                      # the distances curve on the scale of |T| (~1e-3 here)
    Jc = np.zeros_like(J)
    for i in range(6):
        dx = np.zeros(6)
        dx[i] = h
        Jc[:, i] = (problem.distances(exp_so3(dx[:3]) @ start.R, start.t + dx[3:])
                    - problem.distances(exp_so3(-dx[:3]) @ start.R, start.t - dx[3:])) / (2 * h)
    assert np.abs(J - Jc).max() <= 1e-5 * np.abs(Jc).max()


@pytest.mark.parametrize('seed', range(5))
@pytest.mark.parametrize('preset, noise', [('paper', 2.0), ('dense', 0.1)])
def test_joint_mode_lm_agrees_with_scipy(seed, preset, noise):
    problem, start, pairs, _, sigma = ba_setup(seed, noise, preset)
    out = {b: refine_latest(problem, start, 'joint', pairs, sigma, backend=b, max_nfev=200) for b in ('scipy', 'lm')}
    lm, sp = out['lm'], out['scipy']
    assert lm.cost_before == sp.cost_before
    for res in out.values():
        assert res.pose.is_finite() and res.cost_after <= res.cost_before
    assert lm.cost_after <= sp.cost_after * (1 + 1e-3) + 1e-9
    if sp.improved and lm.improved:
        assert rotation_angle(lm.pose.R.T @ sp.pose.R) < 1e-3 and np.linalg.norm(lm.pose.t - sp.pose.t) < 0.05


@pytest.mark.parametrize('seed', range(4))
def test_paper_mode_least_squares_on_lm(seed):
    problem, start, pairs, _, sigma = ba_setup(seed, 2.0)
    res = refine_latest(problem, start, 'paper', pairs, sigma, minimizer='trf')         # backend 'lm' by default
    assert res.pose.is_finite() and res.cost_after <= res.cost_before
    assert res.cost_before == pytest.approx(problem.cost(start))
    assert res.cost_after == pytest.approx(problem.cost(res.pose))
    # few terms against 6 unknowns: a damped Gauss-Newton satisfies them with a small change of the start
    assert res.cost_after <= 1e-6 * max(res.cost_before, 1.0)
    assert rotation_angle(res.pose.R.T @ start.R) < 0.05


def test_powell_is_untouched_by_the_backend():
    problem, start, pairs, _, sigma = ba_setup(3, 2.0)
    a = refine_latest(problem, start, 'paper', pairs, sigma, backend='lm')
    b = refine_latest(problem, start, 'paper', pairs, sigma, backend='scipy')
    assert np.array_equal(a.pose.R, b.pose.R) and np.array_equal(a.pose.t, b.pose.t) and a.cost_after == b.cost_after


def test_backend_validated_and_degenerate_inputs_finite():
    problem, start, pairs, _, sigma = ba_setup(1, 2.0)
    with pytest.raises(ValueError, match='backend'):
        refine_latest(problem, start, 'joint', pairs, sigma, backend='ceres')
    assert not refine_latest(BAProblem([]), start, 'joint', pairs, sigma).improved
    for s in (Pose(start.R, np.zeros(3)), Pose.identity()):
        for mode, minimizer in (('joint', 'powell'), ('paper', 'trf')):
            res = refine_latest(problem, s, mode, pairs, sigma, minimizer=minimizer)
            assert res.pose.is_finite() and np.isfinite(res.cost_after) and res.cost_after <= res.cost_before
