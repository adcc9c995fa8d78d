"""Two-frame solver, local BA and the incremental estimator on point-level synthetic scenes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fixego_ros.estimation.config import EstimatorConfig, papers_config, papers_solver
from fixego_ros.estimation.coplanarity import RayPairs, sampson_residuals
from fixego_ros.estimation.estimator import Estimator
from fixego_ros.estimation.frames import CameraFrame, FrameObservation, fixations_of, step_pairs
from fixego_ros.estimation.local_ba import BAProblem, BATerm, refine_latest
from fixego_ros.estimation.status import StepStatus
from fixego_ros.estimation.twoframe import MIN_STAND_PAIRS, Fallback, SolverConfig, TwoFrameSolver
from fixego_ros.experiments.point_scene import PRESETS, PointScene, random_motion_sequence
from fixego_ros.geometry.rotation import Pose, exp_so3

CLEAN = replace(PRESETS['dense'], n_flow=20, window_px=100.0, noise_px=0.0)


def scene_and_steps(cfg, seed, n_steps=2):
    rng = np.random.default_rng(seed)
    scene = PointScene(cfg, rng)
    steps = random_motion_sequence(cfg, n_steps, rng)
    poses, noisy, clean = scene.frames(steps)
    return scene, steps, poses, noisy, clean


def pairs_of(scene, obs, k):
    return step_pairs(scene.rig, fixations_of(obs[k - 1]), obs[k])


@pytest.mark.parametrize('offsets', [(0.0, 0.0), (0.05, -0.03)])
@pytest.mark.parametrize('seed', [1, 2, 3])
def test_noise_free_motion_recovered_cold_start(seed, offsets):
    cfg = replace(CLEAN, pan_offset_rad=offsets[0], tilt_offset_rad=offsets[1])
    scene, steps, _, _, clean = scene_and_steps(cfg, seed)
    pairs = pairs_of(scene, clean, 1)
    assert np.linalg.norm(pairs.centers, axis=1).max() > 0        # left camera rows are present
    res = TwoFrameSolver(papers_solver(sigma=1e-4 / scene.rig.right.fx, prior_step=0.25)).solve(pairs)
    assert res.status.usable, res.message
    assert np.linalg.norm(res.pose.rvec() - steps[0].rvec()) <= 1e-6
    assert np.linalg.norm(res.pose.t - steps[0].t) <= 1e-6
    assert np.all(np.isfinite(res.covariance))


def test_noise_free_paper_preset_recovered_through_estimator():
    """Papers' 3 flow points per camera: 8 constraints, still exact without noise (both cameras)."""
    cfg = replace(PRESETS['paper'], noise_px=0.0)
    scene, _, poses, _, clean = scene_and_steps(cfg, 7, n_steps=4)
    est = Estimator(scene.rig, papers_config(solver=papers_solver(sigma=1e-3 / scene.rig.right.fx,
                                                                   prior_step=0.25)))
    for k, obs in enumerate(clean):
        r = est.update(obs)
        assert np.linalg.norm(r.pose.t - poses[k].t) <= 1e-6
        assert np.linalg.norm(r.pose_raw.t - poses[k].t) <= 1e-6


def test_residuals_are_angles_not_shrinkable_by_scale():
    scene, steps, _, noisy, _ = scene_and_steps(replace(CLEAN, noise_px=1.0), 4)
    pairs = pairs_of(scene, noisy, 1)
    r1 = sampson_residuals(steps[0].R, steps[0].t, pairs)
    r_small = sampson_residuals(steps[0].R, steps[0].t * 1e-3, pairs)
    # shrinking T must not drive the (right camera) residuals to zero, unlike raw determinants
    right = np.linalg.norm(pairs.centers, axis=1) == 0
    assert np.allclose(r1[right], r_small[right])
    assert 0.1 < np.std(r1) * scene.rig.right.fx < 3.0                  # ~ pixel noise / f, in radians


def test_covariance_shrinks_as_points_are_added():
    stds = []
    for n in (5, 20, 80):
        # a turning rig close to the scene: every direction observed, so the bound is not capped
        cfg = replace(PRESETS['dense'], n_flow=n, noise_px=0.5, max_yaw_deg=8.0, fixation_depth=3.0)
        scene, steps, _, noisy, _ = scene_and_steps(cfg, 11)
        pairs = pairs_of(scene, noisy, 1)
        res = TwoFrameSolver(papers_solver(sigma=0.5 / scene.rig.right.fx, prior_step=0.25)).solve(
            pairs, initial=steps[0])
        stds.append(np.sqrt(np.trace(res.covariance)))
    assert stds[0] > stds[1] > stds[2]


def test_degenerate_inputs_give_status_not_exception():
    solver = TwoFrameSolver(papers_solver())
    rays = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.0, 0.1, 1.0]])
    few = RayPairs.build([(rays, rays, np.zeros(3), 1.0)])
    assert solver.solve(few).status is StepStatus.INSUFFICIENT
    many = np.random.default_rng(0).normal(size=(30, 3)) + [0, 0, 5]
    zero_flow = RayPairs.build([(many, many, np.zeros(3), 1.0)])
    res = solver.solve(zero_flow)
    assert res.status is StepStatus.STATIONARY and np.allclose(res.pose.t, 0)
    rotated = RayPairs.build([(many, many @ exp_so3([0, 0.01, 0]), np.zeros(3), 1.0)])
    res = solver.solve(rotated)
    # b_i = M^T a_i, so a_i = M b_i: the rotation is M
    assert res.status is StepStatus.STATIONARY and np.allclose(res.pose.R, exp_so3([0, 0.01, 0]), atol=1e-9)
    nan = many.copy()
    nan[::2] = np.nan
    res = solver.solve(RayPairs.build([(nan, many, np.zeros(3), 1.0)]))
    assert res.n_constraints == 15 and res.pose.is_finite()
    parallel = RayPairs.build([(np.tile([0, 0, 1.0], (10, 1)), np.tile([0, 0, 1.0], (10, 1)), np.zeros(3), 1.0)])
    res = solver.solve(parallel)
    assert res.pose.is_finite() and np.all(np.isfinite(res.covariance))


def _two_heads(translation, left_error_rad: float, seed: int = 0) -> RayPairs:
    """Ray pairs of both heads (1727 px cameras 0.2 m apart, looking 30 deg out to each side at points 1.5-4 m
    away) over a rig step ``translation`` without rotation; the left head's reading at the second frame is off by
    ``left_error_rad`` about its vertical, and every ray has 0.02 px of noise."""
    rng = np.random.default_rng(seed)
    groups = []
    for x, yaw, error in ((0.1, 0.5, 0.0), (-0.1, -0.5, left_error_rad)):
        center = np.array([x, 0.0, 0.0])
        view = exp_so3([0.0, yaw, 0.0])
        local = np.c_[rng.uniform(-0.15, 0.15, (60, 2)), np.ones(60)] * rng.uniform(1.5, 4.0, (60, 1))
        points = center + local @ view.T
        a = points - center
        b = (points - np.asarray(translation) - center) @ exp_so3([0.0, error, 0.0])
        noisy = [r / np.linalg.norm(r, axis=1, keepdims=True) + rng.normal(0.0, 0.02 / 1727.0, r.shape) for r in (a, b)]
        groups.append((noisy[0], noisy[1], center, 1.0))
    return RayPairs.build(groups)


def test_a_rig_at_rest_whose_heads_read_differently_stands_still():
    """Stop 62: the heads' readings are quantised independently (an EVI-D30 unit is 2 mrad), so a rig at rest
    whose left head reads 1 mrad off between two frames left parallax under one rotation for both heads (1.7 px,
    against the 0.3 px test), and the step was solved as a motion. Each head's own rotation explains its rays, and
    the two differ by the readings' error: it stands. A 30 Hz step of a rig walking at 0.2 m/s does not."""
    solver = TwoFrameSolver(SolverConfig())
    at_rest = _two_heads(np.zeros(3), 1e-3)
    assert solver.solve(at_rest).status is StepStatus.STATIONARY
    assert TwoFrameSolver(SolverConfig(camera_parallax=0.0)).solve(at_rest).status is not StepStatus.STATIONARY
    assert solver.solve(_two_heads(np.zeros(3), 4e-3)).status is not StepStatus.STATIONARY   # beyond the readings
    for direction in ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]):
        step = 0.2 / 30.0 * np.asarray(direction)
        assert solver.solve(_two_heads(step, 0.0)).status is not StepStatus.STATIONARY


def test_a_handful_of_rays_without_parallax_is_no_evidence_of_rest():
    """Stop 80: six rays that a moving rig's step leaves almost without parallax (points near the direction of
    travel, the only tracks that survived both heads' swing) were taken as the rig standing, and the back end held
    the frame still. Below MIN_STAND_PAIRS pairs the step is solved, not stood; with as many rays it stands."""
    solver = TwoFrameSolver(SolverConfig())
    rng = np.random.default_rng(3)
    ahead = np.c_[rng.uniform(-0.02, 0.02, (MIN_STAND_PAIRS, 2)), np.ones(MIN_STAND_PAIRS)] * 4.0
    step = np.array([0.0, 0.0, 0.04])                  # 0.2 s at 0.2 m/s, straight at the points
    moved = ahead - step

    def pairs(n: int) -> RayPairs:
        return RayPairs.build([(ahead[:n], moved[:n], np.zeros(3), 1.0)])
    few = solver.solve(pairs(MIN_STAND_PAIRS - 1))
    assert few.status is not StepStatus.STATIONARY
    assert solver.solve(pairs(MIN_STAND_PAIRS)).status is StepStatus.STATIONARY     # the same rays, enough of them
    rest = RayPairs.build([(ahead[:6], ahead[:6], np.zeros(3), 1.0)])
    assert solver.solve(rest).status is not StepStatus.STATIONARY       # six rays never stand, not even at rest


def _ba_setup(seed, noise, true_prefix=False):
    cfg = replace(PRESETS['paper'], noise_px=noise)
    scene, steps, _, noisy, _ = scene_and_steps(cfg, seed, n_steps=2)
    est = Estimator(scene.rig, papers_config(window=0, solver=papers_solver(sigma=2 / scene.rig.right.fx)))
    results = [est.update(o) for o in noisy]
    terms = []
    for side in ('right', 'left'):
        K = scene.rig.camera(side)
        ft = noisy[2].camera(side)
        first = steps[0] if true_prefix else results[1].step
        for j, prefix in ((0, first), (1, Pose.identity())):
            terms.append(BATerm(prefix, noisy[j].camera(side).fixation_ray, ft.fixation_ray,
                                scene.rig.center(side), ft.cam_to_rig, K.fx, K.fy))
    return BAProblem(terms), results[2].step, step_pairs(scene.rig, fixations_of(noisy[1]), noisy[2]), steps


@pytest.mark.parametrize('seed', range(6))
@pytest.mark.parametrize('mode, minimizer', [('paper', 'powell'), ('paper', 'trf'), ('joint', 'trf')])
def test_local_ba_never_increases_its_cost(seed, mode, minimizer):
    problem, start, pairs, _ = _ba_setup(seed, 2.0)
    res = refine_latest(problem, start, mode, pairs, 2.0 / 1381.0, minimizer=minimizer)
    assert res.cost_after <= res.cost_before
    assert res.pose.is_finite()
    if mode == 'paper':
        assert res.cost_before == pytest.approx(problem.cost(start))
        assert res.cost_after == pytest.approx(problem.cost(res.pose))


def test_ba_cost_is_zero_at_truth_and_epipolar_distance_in_pixels():
    problem, _, _, steps = _ba_setup(5, 0.0, true_prefix=True)
    assert problem.cost(steps[1]) < 1e-12
    # a 1 mrad yaw error moves the fixation point off the epipolar line by pixels, not by radians
    wrong = Pose(exp_so3([0, 1e-3, 0]) @ steps[1].R, steps[1].t)
    assert 1e-2 < np.sqrt(problem.cost(wrong)) < 1e3


def test_estimator_window_never_spans_reselection_and_memory_is_bounded():
    cfg = replace(PRESETS['paper'], noise_px=0.5)
    scene, _, _, noisy, _ = scene_and_steps(cfg, 3, n_steps=30)
    est = Estimator(scene.rig, papers_config(window=5))
    for k, obs in enumerate(noisy):
        if k >= 10:   # the right camera re-selects its fixation point at frame 10
            obs.right.fixation_id = 1
        est.update(obs)
        if k in (10, 11, 12):
            problem, _ = est._ba_problem(noisy[min(k + 1, len(noisy) - 1)])
        assert len(est._window) <= 5
    # at frame 11 the right camera's window holds only frame 10 (same id), the left one 4 frames
    est2 = Estimator(scene.rig, papers_config(window=5))
    for obs in noisy[:11]:
        est2.update(obs)
    est2._promote()          # what update(noisy[11]) does first: frame 10 becomes the keyframe
    problem, full = est2._ba_problem(noisy[11])
    centers = np.array([t.center[0] for t in problem.terms])
    assert np.sum(centers == 0) == 1 and np.sum(centers != 0) == 4 and full


def test_estimator_flags_bad_steps_and_never_returns_nan():
    cfg = replace(PRESETS['dense'], noise_px=0.2)
    scene, _, _, noisy, _ = scene_and_steps(cfg, 8, n_steps=6)
    est = Estimator(scene.rig, papers_config())
    for obs in noisy[:3]:
        est.update(obs)
    empty = FrameObservation(3.0, None, None)
    r = est.update(empty)
    assert r.status is StepStatus.PREDICTED and r.pose.is_finite()
    bad = CameraFrame(np.array([np.nan, 0, 1]), 0, np.eye(3), np.full((5, 3), np.nan), np.full((5, 3), np.nan))
    r = est.update(FrameObservation(4.0, bad, bad))
    assert not r.status.usable and r.pose.is_finite() and np.all(np.isfinite(r.pose_covariance))
    est.reset()
    assert est.update(noisy[0]).status is StepStatus.INIT


def test_config_validation():
    with pytest.raises(ValueError, match='window'):
        EstimatorConfig(window=2)
    with pytest.raises(ValueError, match='mode'):
        EstimatorConfig(mode='magic')


def test_blind_step_is_bridged_from_the_rates_on_both_sides():
    """Both cameras see nothing across one step (e.g. both re-selected at once) where a turn ends: the step is
    predicted at the turn's rate, then re-estimated from the rates before and after once the next step is
    solved, and the keyframe's corrected pose is reported (the later poses build on it)."""
    cfg = replace(PRESETS['dense'], noise_px=0.0, fixation_depth=4.0, step_length=0.1)
    scene = PointScene(cfg, np.random.default_rng(4))
    turn, t = np.radians(3.0), np.array([0.0, 0.0, 0.1])
    steps = [Pose(exp_so3([0.0, turn, 0.0]), t)] * 4 + [Pose(exp_so3([0.0, turn / 2, 0.0]), t)] + \
        [Pose(np.eye(3), t)] * 4
    poses, _, clean = scene.frames(steps)
    blind = 5
    for k, obs in enumerate(clean):
        for cam in (obs.right, obs.left):
            if k == blind:
                cam.flow_prev, cam.flow_curr = np.zeros((0, 3)), np.zeros((0, 3))
            if k >= blind:
                cam.fixation_id = 1          # re-selected: no fixation pair across the blind step
    est = Estimator(scene.rig, papers_config(window=0))
    results = [est.update(obs) for obs in clean]
    yaw_error = [np.degrees(abs(((poses[k].inverse() @ p).rvec())[1]))
                 for k, p in ((blind, results[blind].pose), (blind, results[blind + 1].corrected[1]))]
    assert results[blind].status is StepStatus.PREDICTED
    assert results[blind + 1].corrected[0] == clean[blind].stamp
    assert yaw_error[0] > 1.0 and yaw_error[1] < 0.1      # predicted: the whole turn rate; bridged: half of it
    later = results[-1].pose
    assert np.degrees(np.linalg.norm((poses[-1].inverse() @ later).rvec())) < 0.1


def test_a_warm_start_behind_the_cameras_falls_back_as_the_caller_asks():
    """A warm solve behind the cameras (the mirror solution) is DEGENERATE with no fallback (a caller that predicts
    instead); the closed-form starts (the live pose's budget) and the full cold starts both recover the motion."""
    scene, steps, _, _, clean = scene_and_steps(CLEAN, 2)
    pairs = pairs_of(scene, clean, 1)
    solver = TwoFrameSolver(papers_solver(sigma=1e-4 / scene.rig.right.fx, prior_step=0.25))
    behind = Pose(steps[0].R, -steps[0].t)          # the mirror solution: the points behind the cameras
    res = solver.solve(pairs, initial=behind, fallback=Fallback.NONE)
    assert res.status is StepStatus.DEGENERATE and res.cheirality < 0.5
    for fallback in (Fallback.CLOSED_FORM, Fallback.COLD):
        res = solver.solve(pairs, initial=behind, fallback=fallback)
        assert res.status.usable and res.cheirality >= 0.5
        assert np.linalg.norm(res.pose.t - steps[0].t) <= 1e-6
