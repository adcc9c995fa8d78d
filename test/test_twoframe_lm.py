"""The two-frame solver's Levenberg-Marquardt backend ('lm', default) against the scipy backend."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fixego_ros.estimation.coplanarity import RayPairs, sampson_residuals_jacobian, sampson_residuals_jacobians
from fixego_ros.estimation.frames import fixations_of, step_pairs
from fixego_ros.estimation.status import StepStatus
from fixego_ros.estimation.twoframe import (
    BACKENDS,
    LOSSES,
    Fallback,
    MotionPrior,
    SolverConfig,
    TwoFrameSolver,
    levenberg_marquardt,
    levenberg_marquardt_many,
    robust_loss,
)
from fixego_ros.experiments.point_scene import PRESETS, PointScene, random_motion_sequence
from fixego_ros.geometry.rotation import Pose, exp_so3

# baseline 0.2 m, fixation at 2 m, 40 flow points per camera in 300 px: the lever arm observes the scale
SCENE = replace(PRESETS['jp_2m'], n_flow=40, window_px=300.0)


def problem(seed: int, noise_px: float):
    cfg = replace(SCENE, noise_px=noise_px)
    rng = np.random.default_rng(seed)
    scene = PointScene(cfg, rng)
    steps = random_motion_sequence(cfg, 2, rng)
    _, noisy, _ = scene.frames(steps)
    pairs = step_pairs(scene.rig, fixations_of(noisy[0]), noisy[1])
    return steps[0], pairs, max(noise_px, 0.1) / scene.rig.right.fx


def solvers(sigma: float, **kw) -> dict[str, TwoFrameSolver]:
    return {b: TwoFrameSolver(SolverConfig(sigma=sigma, prior_step=0.05, backend=b, **kw)) for b in BACKENDS}


def perturbed(truth: Pose) -> Pose:
    return Pose(exp_so3([1e-3, -1e-3, 5e-4]) @ truth.R, 1.2 * truth.t + 0.005)


def corrupt(pairs: RayPairs, truth: Pose, i: int, angle: float) -> RayPairs:
    """Move ray b[i] by ``angle`` off its true epipolar plane (a gross outlier for the coplanarity residual)."""
    b = pairs.b.copy()
    Rb = truth.R @ b[i]
    n = np.cross(Rb, truth.t + truth.R @ pairs.centers[i] - pairs.centers[i])
    moved = Rb + angle * n / np.linalg.norm(n)
    b[i] = truth.R.T @ (moved / np.linalg.norm(moved))
    return RayPairs(pairs.a, b, pairs.centers, pairs.weights)


def test_default_backend_is_lm_and_config_is_validated():
    assert SolverConfig().backend == 'lm'
    with pytest.raises(ValueError, match='backend'):
        SolverConfig(backend='minpack')
    with pytest.raises(ValueError, match='loss'):
        SolverConfig(loss='l1')


@pytest.mark.parametrize('seed', [0, 4])
def test_backends_agree_noise_free(seed):
    truth, pairs, sigma = problem(seed, 0.0)
    for backend, solver in solvers(sigma, max_nfev=200).items():
        for start in (None, perturbed(truth)):           # cold starts and a warm start
            res = solver.solve(pairs, start)
            assert res.status is StepStatus.OK, (backend, res.message)
            assert np.linalg.norm(res.pose.rvec() - truth.rvec()) < 1e-7, backend
            assert np.linalg.norm(res.pose.t - truth.t) < 1e-6 * np.linalg.norm(truth.t) + 1e-9, backend


@pytest.mark.parametrize('seed', [0, 1, 4, 5])
def test_backends_agree_noisy(seed):
    truth, pairs, sigma = problem(seed, 0.1)
    res = {b: s.solve(pairs, perturbed(truth)) for b, s in solvers(sigma, max_nfev=200).items()}
    lm, sp = res['lm'], res['scipy']
    assert lm.status.usable and sp.status.usable
    assert lm.message.startswith('converged')
    assert lm.cost <= sp.cost * (1 + 1e-6)                            # at least as far down
    assert np.linalg.norm(lm.pose.rvec() - sp.pose.rvec()) < 1e-5      # rad; noise gives ~1e-4 errors
    assert np.linalg.norm(lm.pose.t - sp.pose.t) < 0.02 * np.linalg.norm(sp.pose.t)
    assert np.allclose(np.sqrt(np.diag(lm.covariance)), np.sqrt(np.diag(sp.covariance)), rtol=0.05)


@pytest.mark.parametrize('backend', BACKENDS)
@pytest.mark.parametrize('seed', [0, 2])
def test_robust_losses_reject_an_injected_outlier(seed, backend):
    truth, clean, sigma = problem(seed, 0.0)
    pairs = corrupt(clean, truth, 3, 0.01)                # ~140 sigma off
    err = {}
    for loss in LOSSES:
        solver = TwoFrameSolver(SolverConfig(sigma=sigma, prior_step=0.05, loss=loss, max_nfev=200, backend=backend))
        # a prior pins the scale, so the comparison is about the outlier, not the weakly observed scale
        res = solver.solve(pairs, truth, prior_t=truth.t, prior_sigma_t=0.1 * np.linalg.norm(truth.t))
        err[loss] = np.linalg.norm(res.pose.rvec() - truth.rvec())
    assert err['linear'] > 5e-3
    assert err['huber'] < err['linear'] / 20 and err['soft_l1'] < err['linear'] / 20
    assert err['cauchy'] < err['linear'] / 500 and err['arctan'] < err['linear'] / 1e4


@pytest.mark.parametrize('seed', [0, 1])
def test_prior_rows_fix_the_unobserved_scale(seed):
    truth, pairs, sigma = problem(seed, 0.1)
    # without the lever arm the rays only see the direction of T: the prior alone sets its length
    no_lever = RayPairs(pairs.a, pairs.b, np.zeros_like(pairs.centers), pairs.weights)
    out = {}
    for backend, solver in solvers(sigma, max_nfev=200).items():
        res = solver.solve(no_lever, perturbed(truth), prior_t=2 * truth.t, prior_sigma_t=0.01)
        assert res.status.usable, res.message
        direction = res.pose.t @ truth.t / np.linalg.norm(res.pose.t) / np.linalg.norm(truth.t)
        assert direction > np.cos(np.radians(10.0))
        assert np.linalg.norm(res.pose.t) == pytest.approx(2 * np.linalg.norm(truth.t), rel=0.1)
        # the covariance is the rays' own: the scale still shows as unobserved
        assert res.status is StepStatus.WEAK
        out[backend] = res.pose.t
    assert np.allclose(out['lm'], out['scipy'], atol=1e-4)


@pytest.mark.parametrize('seed', [0, 1])
def test_length_prior_sets_only_the_length(seed):
    """A prior on |T| alone: the length follows it, the direction stays the rays' (both backends agree)."""
    truth, pairs, sigma = problem(seed, 0.1)
    no_lever = RayPairs(pairs.a, pairs.b, np.zeros_like(pairs.centers), pairs.weights)
    length = 3 * float(np.linalg.norm(truth.t))
    out = {}
    for backend, solver in solvers(sigma, max_nfev=200).items():
        res = solver.solve(no_lever, perturbed(truth), prior_length=(length, 0.01 * length))
        assert res.status.usable, res.message
        direction = res.pose.t @ truth.t / np.linalg.norm(res.pose.t) / np.linalg.norm(truth.t)
        assert direction > np.cos(np.radians(10.0))
        assert np.linalg.norm(res.pose.t) == pytest.approx(length, rel=0.05)
        out[backend] = res.pose.t
    assert np.allclose(out['lm'], out['scipy'], atol=1e-4)


def test_motion_prior_rows_have_the_right_jacobian():
    prior = MotionPrior.build(np.array([0.1, 0.0, 0.0]), 0.02, (0.3, 0.05))
    T = np.array([0.2, -0.1, 0.4])
    r, J = prior.rows(T)
    assert r.shape == (4,) and J.shape == (4, 6) and np.all(J[:, :3] == 0)
    h = 1e-7
    numeric = np.stack([(prior.rows(T + h * e)[0] - r) / h for e in np.eye(3)], axis=1)
    assert np.allclose(J[:, 3:], numeric, atol=1e-5)
    assert MotionPrior.build(None, 0.0, (np.nan, 0.1)) is None and MotionPrior.build(None, 0.0, None) is None


@pytest.mark.parametrize('backend', BACKENDS)
def test_never_nan_on_degenerate_input(backend):
    solver = TwoFrameSolver(SolverConfig(backend=backend))
    rng = np.random.default_rng(3)
    same = np.tile([0.0, 0.0, 1.0], (12, 1))
    many = rng.normal(size=(20, 3)) + [0, 0, 5]
    lever = np.array([0.2, 0.0, 0.0])
    cases = {
        'identical rays': RayPairs.build([(same, same, np.zeros(3), 1.0), (same, same, lever, 1.0)]),
        'five pairs': RayPairs.build([(many[:5], many[:5] + 0.01, np.zeros(3), 1.0)]),
        'no pairs': RayPairs.build([]),
        'parallax, no lever arm': RayPairs.build([(many, many + rng.normal(size=many.shape) * 0.01, np.zeros(3), 1.0)]),
        'random rays': RayPairs.build([(many, rng.normal(size=many.shape), np.zeros(3), 1.0),
                                       (many, rng.normal(size=many.shape), lever, 1.0)]),
    }
    starts = [None, Pose.identity(), Pose(exp_so3([0.0, 0.01, 0.0]), np.zeros(3)),
              Pose(np.eye(3), np.array([0.0, 0.0, 1e-12]))]
    for name, pairs in cases.items():
        for start in starts:
            for prior in ((None, 0.0), (np.array([0.0, 0.0, 0.05]), 0.01)):
                res = solver.solve(pairs, start, *prior)
                assert res.pose.is_finite(), (name, start)
                assert np.all(np.isfinite(res.covariance)) and np.all(np.isfinite(res.residuals)), name
                assert np.isfinite(res.cost), name
    assert solver.solve(cases['five pairs']).status is StepStatus.INSUFFICIENT


def test_robust_loss_matches_scipy_definitions():
    z = np.concatenate([np.linspace(0.0, 4.0, 41), [10.0, 1e3]])
    closed = {'linear': z, 'huber': np.where(z <= 1, z, 2 * np.sqrt(z) - 1), 'soft_l1': 2 * (np.sqrt(1 + z) - 1),
              'cauchy': np.log1p(z), 'arctan': np.arctan(z)}
    for loss in LOSSES:
        rho, drho = robust_loss(z, loss)
        assert np.allclose(rho, closed[loss], rtol=1e-12, atol=1e-14), loss
        lo, hi = np.maximum(z - 1e-6, 0), z + 1e-6
        numeric = (robust_loss(hi, loss)[0] - robust_loss(lo, loss)[0]) / (hi - lo)
        smooth = np.abs(z - 1) > 1e-3                    # huber's kink at z = 1
        assert np.allclose(drho[smooth], numeric[smooth], rtol=1e-5), loss
    try:                                                 # scipy's own implementations, where available
        from scipy.optimize._lsq.least_squares import IMPLEMENTED_LOSSES
    except ImportError:
        return
    for loss in LOSSES[1:]:
        ref = np.empty((3, len(z)))
        IMPLEMENTED_LOSSES[loss](z, ref, cost_only=False)
        rho, drho = robust_loss(z, loss)
        assert np.allclose(rho, ref[0]) and np.allclose(drho, ref[1]), loss


@pytest.mark.parametrize('loss', LOSSES)
def test_lm_cost_is_scipys_robust_cost_and_nfev_is_bounded(loss):
    truth, pairs, sigma = problem(1, 0.5)
    scaled = RayPairs(pairs.a, pairs.b, pairs.centers, pairs.weights / sigma)
    calls = []

    def fun(R, T):
        calls.append(1)
        return sampson_residuals_jacobian(R, T, scaled)

    x_scale = np.r_[np.full(3, 1e-2), np.full(3, 0.05)]
    for max_nfev in (1, 3, 20):
        calls.clear()
        sol = levenberg_marquardt(fun, truth.R, truth.t * 1.5, x_scale, loss, 3.0, 1e-7, max_nfev)
        assert len(calls) == sol.nfev <= max_nfev
    z = (sol.r / 3.0) ** 2
    assert sol.cost == pytest.approx(0.5 * 9.0 * np.sum(robust_loss(z, loss)[0]), rel=1e-12)
    r, J = sampson_residuals_jacobian(sol.R, sol.T, scaled)
    assert np.allclose(sol.r, r) and np.allclose(sol.J, J)


def test_lm_survives_non_finite_residuals():
    truth, pairs, sigma = problem(0, 0.1)
    scaled = RayPairs(pairs.a, pairs.b, pairs.centers, pairs.weights / sigma)
    x_scale = np.r_[np.full(3, 1e-2), np.full(3, 0.05)]
    start = perturbed(truth)

    def nan_away(R, T):          # NaN everywhere but close to the start: every long step fails
        r, J = sampson_residuals_jacobian(R, T, scaled)
        return (r, J) if np.linalg.norm(T - start.t) < 1e-3 else (r * np.nan, J)

    sol = levenberg_marquardt(nan_away, start.R, start.t, x_scale, max_nfev=40)
    assert sol is not None and np.all(np.isfinite(sol.T)) and np.all(np.isfinite(sol.R))
    assert np.linalg.norm(sol.T - start.t) < 1e-3
    assert levenberg_marquardt(lambda R, T: (np.full(3, np.nan), np.zeros((3, 6))), np.eye(3), np.zeros(3),
                               x_scale) is None


def test_starts_refined_side_by_side_take_exactly_their_own_steps():
    """``levenberg_marquardt_many`` evaluates the running starts together; each ends where it ends alone (same
    bits, same evaluations), whether it converges early, runs out of evaluations or starts non-finite."""
    truth, pairs, sigma = problem(2, 0.5)
    scaled = RayPairs(pairs.a, pairs.b, pairs.centers, pairs.weights / sigma)
    x_scale = np.r_[np.full(3, 1e-2), np.full(3, 0.05)]
    starts = [(truth.R, truth.t, x_scale), (perturbed(truth).R, perturbed(truth).t, x_scale),
              (np.eye(3), np.array([0.0, 0.0, 0.05]), x_scale), (np.eye(3), np.array([0.05, 0.0, 0.0]), 'jac'),
              (np.eye(3), np.array([np.nan, 0.0, 0.0]), x_scale)]
    batch_sizes = []

    def many(Rs, Ts):
        batch_sizes.append(len(Rs))
        return sampson_residuals_jacobians(Rs, Ts, scaled)

    together = levenberg_marquardt_many(many, starts, 'huber', 3.0, 1e-7, 25)
    assert together[-1] is None and batch_sizes[0] == len(starts) and len(set(batch_sizes)) > 1
    for (R0, T0, xs), sol in zip(starts[:-1], together[:-1], strict=True):
        alone = levenberg_marquardt(lambda R, T: sampson_residuals_jacobian(R, T, scaled), R0, T0, xs, 'huber',
                                    3.0, 1e-7, 25)
        assert sol.nfev == alone.nfev and sol.message == alone.message
        assert np.array_equal(sol.R, alone.R) and np.array_equal(sol.T, alone.T) and sol.cost == alone.cost


def test_rotation_given_the_translation_reads_parallax_that_kabsch_takes_for_rotation():
    """A short step past near points: Kabsch's rotation absorbs their parallax; with the step's translation given,
    the rays' rotation comes out right. A translation too short to see leaves Kabsch's answer, and one that does
    not fit the rays cannot turn the rotation further than ``max_turn``."""
    from fixego_ros.estimation.twoframe import kabsch_rotation, rotation_given_translation
    rng = np.random.default_rng(4)
    R, T = exp_so3([0.0, 0.01, 0.002]), np.array([0.03, 0.0, 0.1])      # 10 cm forward, 3 cm sideways
    points = rng.uniform([-1.0, -0.5, 1.0], [1.0, 0.5, 2.0], size=(80, 3))
    a = points / np.linalg.norm(points, axis=1, keepdims=True)
    in_b = (points - T) @ R                     # the points in the rig frame after the step (x_t = R x_b + T)
    b = in_b / np.linalg.norm(in_b, axis=1, keepdims=True)
    pairs = RayPairs.build([(a, b, np.zeros(3), 1.0)])
    sigma = 1.0 / 1727.0

    def angle(Q):
        return float(np.degrees(np.arccos(np.clip((np.trace(Q @ R.T) - 1.0) / 2.0, -1.0, 1.0))))

    kabsch = kabsch_rotation(pairs.a, pairs.b)
    assert angle(kabsch) > 0.5
    assert angle(rotation_given_translation(pairs, kabsch, T, sigma, iterations=3)) < 1e-3
    assert angle(rotation_given_translation(pairs, kabsch, T, sigma, iterations=1)) < 0.05
    assert np.array_equal(rotation_given_translation(pairs, kabsch, T * 1e-4, sigma), kabsch)
    assert np.array_equal(rotation_given_translation(pairs, kabsch, np.full(3, np.nan), sigma), kabsch)
    wrong = rotation_given_translation(pairs, kabsch, np.array([1.0, 0.0, 0.0]), sigma, max_turn=np.radians(0.2))
    assert np.degrees(np.arccos(np.clip((np.trace(wrong @ kabsch.T) - 1.0) / 2.0, -1.0, 1.0))) <= 0.2 + 1e-9


def _same(a, b) -> bool:
    """Two solve results alike to the bit (pose, status, cost, covariance, cheirality, message)."""
    if a is None or b is None:
        return a is b
    return (a.status is b.status and np.array_equal(a.pose.R, b.pose.R) and np.array_equal(a.pose.t, b.pose.t)
            and a.cost == b.cost and np.array_equal(a.covariance, b.covariance) and a.cheirality == b.cheirality
            and a.message == b.message)


@pytest.mark.parametrize('seed', range(4))
def test_the_batched_cold_check_is_the_two_solves(seed):
    """``solve_checked`` refines the warm start and the closed-form starts in one batch: the smoother's warm solve and
    its cold check come out as the two separate solves, bit for bit, from a good start, from a start behind the
    cameras (the warm solve then takes the cold starts too), for a rig at rest and with too few pairs."""
    truth, pairs, sigma = problem(seed, 0.5)
    solver = TwoFrameSolver(SolverConfig(sigma=sigma, prior_step=0.05))
    behind = Pose(truth.R, -truth.t)
    rest = RayPairs(pairs.a, pairs.a @ truth.R, pairs.centers * 0.0, pairs.weights)    # b = R^T a: rotation only
    few = RayPairs(pairs.a[:5], pairs.b[:5], pairs.centers[:5], pairs.weights[:5])
    for p, start in ((pairs, perturbed(truth)), (pairs, behind), (rest, truth), (few, truth)):
        warm, cold = solver.solve_checked(p, start)
        expected_warm = solver.solve(p, initial=start)
        assert _same(warm, expected_warm)
        usable = expected_warm.status in (StepStatus.OK, StepStatus.WEAK)
        assert _same(cold, solver.solve(p, fallback=Fallback.CLOSED_FORM) if usable else None)
    assert solver.solve_checked(pairs, perturbed(truth))[1] is not None          # the check ran
    assert solver.solve_checked(rest, truth)[0].status is StepStatus.STATIONARY
