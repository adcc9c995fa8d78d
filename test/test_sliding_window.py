"""Sliding-window refinement, scale-observed reporting and the estimator's scale aids (no images)."""

from __future__ import annotations

import numpy as np
import pytest

from fixego_ros.estimation.estimator import Estimator, EstimatorConfig, landmark_observations, papers_config
from fixego_ros.estimation.sliding_window import SlidingWindow, SpeedSamples, WindowConfig
from fixego_ros.experiments.landmark_scene import LandmarkScene, LandmarkSceneConfig
from fixego_ros.geometry.rig import make_rig
from fixego_ros.geometry.rotation import Pose, exp_so3
from fixego_ros.sim.trajectories import make_trajectory

RIG = make_rig(320, 240, 21.0, 0.2)
SIGMA = 0.3 / RIG.camera('right').fx


def _run(name: str, seconds: float, noise_px: float = 0.3, window_px: float = 100.0):
    scene = LandmarkScene(RIG, LandmarkSceneConfig(noise_px=noise_px, window_px=window_px, max_tracks=40))
    return scene.run(make_trajectory(name), duration=seconds)


def _config(**kw) -> EstimatorConfig:
    """The estimator these tests were written against (the dataclass defaults before they became the node's)."""
    return papers_config(sliding=WindowConfig(frames=8, sigma=1.0 / 863.5), **kw)


def _loose() -> None:
    """No step factor: the landmarks alone place the keyframes."""
    return None


def test_window_stays_at_the_truth_on_exact_observations():
    run = _run('paper', 12.0, noise_px=0.0)
    sw = SlidingWindow(WindowConfig(frames=8, sigma=1e-5))
    sw.hold_open = False
    for obs, pose in zip(run.observations, run.poses, strict=True):
        est = sw.add(obs.stamp, pose, *landmark_observations(RIG, obs), _loose())
        assert np.linalg.norm(est.t - pose.t) < 1e-6
    assert sw.stats.landmarks > 20 and sw.stats.observations > 100
    assert sw.stats.variable_frames == 8 and sw.stats.fixed_frames >= 1


def test_new_keyframe_is_placed_against_the_landmarks():
    """A 10 cm / 3 deg wrong guess for the newest keyframe is pulled back by the landmarks already placed."""
    run = _run('paper', 6.0, noise_px=0.0)
    sw = SlidingWindow(WindowConfig(frames=8, sigma=1e-5))
    sw.hold_open = False
    obs = run.observations
    for o, pose in zip(obs[:-1], run.poses[:-1], strict=True):
        sw.add(o.stamp, pose, *landmark_observations(RIG, o), _loose())
    truth = run.poses[-1]
    guess = Pose(truth.R @ exp_so3(np.radians([0.0, 3.0, 0.0])), truth.t + np.array([0.1, 0.0, -0.05]))
    est = sw.add(obs[-1].stamp, guess, *landmark_observations(RIG, obs[-1]), _loose())
    assert np.linalg.norm(est.t - truth.t) < 1e-3


def test_outlier_landmark_is_dropped():
    run = _run('paper', 4.0, noise_px=0.0)
    sw = SlidingWindow(WindowConfig(frames=8, sigma=1e-4))
    sw.hold_open = False
    bad_key = None
    for k, (o, pose) in enumerate(zip(run.observations, run.poses, strict=True)):
        keys, rays, centers = landmark_observations(RIG, o)
        if k >= 10 and bad_key is None:
            bad_key = int(keys[0])
        if bad_key is not None and bad_key in keys.tolist():
            i = keys.tolist().index(bad_key)
            rays = rays.copy()
            rays[i] = (rays[i] + np.array([0.02, 0.0, 0.0]) * (k % 2)) / np.linalg.norm(rays[i] + 0.02 * (k % 2))
        sw.add(o.stamp, pose, keys, rays, centers, _loose())
    assert bad_key in sw.dead or bad_key not in sw.landmarks


def test_scale_is_reported_unobserved_on_a_straight_run():
    run = _run('straight', 6.0)
    est = Estimator(RIG, _config(refinement='sliding'))
    results = [est.update(o) for o in run.observations]
    assert not any(r.scale_observed for r in results)
    assert 'unobserved' in results[-1].scale_note
    # the published covariance says so: position std at least a metre
    assert np.all(np.sqrt(np.diag(results[-1].pose_covariance)[3:]) >= 1.0)


@pytest.mark.parametrize('refinement', ['local', 'sliding'])
def test_turning_alone_does_not_make_the_scale_observed(refinement):
    # a circle with the heading along it: the lever arm lies along every step (estimation/observability.py)
    run = _run('circle', 10.0)
    est = Estimator(RIG, _config(refinement=refinement))
    results = [est.update(o) for o in run.observations]
    assert not any(r.scale_observed for r in results)
    assert 'no scale aid' in results[-1].scale_note and 'constant-curvature' in results[-1].scale_note
    assert np.all(np.sqrt(np.diag(results[-1].pose_covariance)[3:]) >= 1.0)


@pytest.mark.parametrize('refinement', ['local', 'sliding'])
def test_scale_from_rotation_counts_it_observed_after_enough_rotation(refinement):
    run = _run('circle', 10.0)
    est = Estimator(RIG, _config(refinement=refinement, scale_min_rotation_deg=15.0,
                                         scale_from_rotation=True))
    flags = [est.update(o).scale_observed for o in run.observations]
    assert not flags[1] and flags[-1]
    first = flags.index(True)
    true_turn = np.degrees(np.linalg.norm((run.poses[0].inverse() @ run.poses[first]).rvec()))
    assert 8.0 <= true_turn <= 40.0        # reported once the rig has really turned about that much


def test_speed_aid_makes_the_scale_observed_and_fixes_the_path_length():
    run = _run('straight', 8.0)
    rng = np.random.default_rng(3)
    lengths = {}
    for aided in (False, True):
        est = Estimator(RIG, _config(refinement='sliding'))
        res = None
        for k, o in enumerate(run.observations):
            if aided:
                a, b = max(k - 1, 0), min(k + 1, len(run.poses) - 1)
                v = run.poses[k].R.T @ (run.poses[b].t - run.poses[a].t) / (run.stamps[b] - run.stamps[a])
                est.add_velocity(o.stamp - 1e-3, v + rng.normal(0, 0.02, 3), np.eye(3) * 0.02**2)
            res = est.update(o)
        assert res.scale_observed == aided
        lengths[aided] = float(np.linalg.norm(res.pose.t))
    true_length = float(np.linalg.norm(run.poses[-1].t))
    assert abs(lengths[True] / true_length - 1.0) < 0.1


def test_bad_scale_aid_input_is_refused():
    est = Estimator(RIG, _config(refinement='sliding'))
    with pytest.raises(ValueError):
        est.add_velocity(1.0, np.array([np.nan, 0, 0]), np.eye(3))
    with pytest.raises(ValueError):
        est.add_velocity(1.0, np.zeros(3), -np.eye(3))
    est.add_velocity(2.0, np.zeros(3), np.eye(3))
    with pytest.raises(ValueError):
        est.add_velocity(1.5, np.zeros(3), np.eye(3))
    with pytest.raises(ValueError):
        est.add_fixation_point(1.0, 'middle', np.ones(3), np.eye(3))
    with pytest.raises(ValueError):
        est.add_fixation_point(1.0, 'right', np.array([0, 0, np.inf]), np.eye(3))


def test_vergence_point_anchors_the_scale():
    """A start-up vergence distance of the right fixation point makes the scale observed and sets it."""
    run = _run('straight', 6.0)
    lengths = {}
    for aided in (False, True):
        est = Estimator(RIG, _config(refinement='sliding'))
        if aided:
            est.add_fixation_point(run.stamps[0], 'right', run.fixation_points[0]['right'], np.eye(3) * 0.02**2)
        res = [est.update(o) for o in run.observations]
        assert res[-1].scale_observed == aided
        lengths[aided] = float(np.linalg.norm(res[-1].pose.t))
    assert 'vergence' in res[-1].scale_note
    true_length = float(np.linalg.norm(run.poses[-1].t))
    assert abs(lengths[True] / true_length - 1.0) < 0.25


def test_speed_samples_integrate_over_the_step():
    s = SpeedSamples()
    for t in np.arange(0.0, 1.0, 0.1):
        s.add(float(t), np.array([0.0, 0.0, 0.5]), np.eye(3) * 0.01)
    t, cov = s.translation(0.2, 0.6)
    assert np.allclose(t, [0, 0, 0.2]) and np.allclose(cov, np.eye(3) * 0.01 * 0.16)
    assert s.translation(5.0, 6.0) is None


def test_speed_samples_follow_the_rig_round_an_arc():
    """A wheel odometry's body-frame velocity stays forward on an arc while the rig turns: over the step the
    translation is the chord, turned by half the step's rotation from the keyframe's forward axis."""
    s = SpeedSamples()
    for t in np.arange(0.0, 1.001, 0.05):
        s.add(float(t), np.array([0.0, 0.0, 1.0]), np.eye(3) * 1e-4)
    phi = np.array([0.0, np.radians(20.0), 0.0])
    chord = exp_so3(phi / 2) @ np.array([0.0, 0.0, 1.0])

    def angle_deg(t: np.ndarray) -> float:
        return float(np.degrees(np.arccos(np.clip(t @ chord / np.linalg.norm(t), -1.0, 1.0))))

    turned, _ = s.translation(0.0, 1.0, phi)
    unturned, _ = s.translation(0.0, 1.0)
    assert angle_deg(turned) < 0.01 and abs(angle_deg(unturned) - 10.0) < 0.01
    assert abs(np.linalg.norm(turned) - np.sin(phi[1] / 2) / (phi[1] / 2)) < 0.01   # a chord, not the arc length
