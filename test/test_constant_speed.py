"""Constant-speed prior and the vergence scale anchor (image-free landmark scene)."""

from __future__ import annotations

import numpy as np
import pytest

from fixego_ros.estimation.constant_speed import PRIOR_REL_STD, ConstantSpeed
from fixego_ros.estimation.estimator import Estimator
from fixego_ros.estimation.frames import fixations_of
from fixego_ros.estimation.scale_anchor import ScaleAnchor
from fixego_ros.experiments.landmark_scene import LandmarkScene, LandmarkSceneConfig
from fixego_ros.geometry.rig import make_rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.pipeline.params import ESTIMATOR_PARAMS, estimator_config, params_getter
from fixego_ros.sim.trajectories import make_trajectory

RIG = make_rig(320, 240, 21.0, 0.2)


@pytest.fixture(scope='module')
def straight():
    scene = LandmarkScene(RIG, LandmarkSceneConfig(noise_px=0.3, window_px=300.0, max_tracks=40))
    return scene.run(make_trajectory('straight'), duration=6.0)


def _estimator(**params) -> Estimator:
    return Estimator(RIG, estimator_config(params_getter(ESTIMATOR_PARAMS, {'constant_speed': True, **params}), RIG))


def test_prior_is_the_nominal_speed_until_calibrated():
    c = ConstantSpeed(0.4)
    assert c.prior(0.5) == pytest.approx((0.2, PRIOR_REL_STD * 0.2))
    assert not c.measured
    c.calibrate(0.5, 0.02)
    assert c.measured and c.v == pytest.approx(0.2)
    assert c.prior(1.0)[0] == pytest.approx(0.2)
    for bad in ((0.0, 0.1), (np.nan, 0.1), (1.0, -0.1)):
        with pytest.raises(ValueError):
            c.calibrate(*bad)
    with pytest.raises(ValueError):
        ConstantSpeed(0.0)


def _anchor_on(run, scale: float, frames: int) -> ScaleAnchor:
    """An anchor fed with the true poses, their translations multiplied by ``scale``."""
    a = ScaleAnchor(run.stamps[0], 'right', run.fixation_points[0]['right'], np.eye(3) * 1e-6,
                    RIG.center('right'), 0.3 / RIG.camera('right').fx)
    a.start(Pose.identity(), fixations_of(run.observations[0])['right'][1])
    for obs, pose in zip(run.observations[1:frames], run.poses[1:frames], strict=True):
        f = fixations_of(obs)['right']
        a.add(obs.stamp, Pose(pose.R, pose.t * scale), f[1], f[0])
    return a


def test_anchor_recovers_the_scale_of_a_trajectory(straight):
    assert _anchor_on(straight, 1.0, 3).fit() is None               # too few views
    for scale in (1.0, 2.5):
        fit = _anchor_on(straight, scale, 30).settled()
        assert fit.position_k * scale == pytest.approx(1.0, abs=0.03)
        assert fit.speed_k * scale == pytest.approx(1.0, abs=0.05) and 0 < fit.rel_std < 0.1


def test_anchor_speed_is_the_recent_one(straight):
    """A path drawn at a constant speed while the rig accelerated from rest: the distances are wrong early on,
    the recent metric speed (the slope) is still the true one."""
    stamps = np.array(straight.stamps[:30])
    true_dist = np.array([np.linalg.norm(p.t) for p in straight.poses[:30]])
    v_true = (true_dist[-1] - true_dist[-8]) / (stamps[-1] - stamps[-8])
    a = ScaleAnchor(straight.stamps[0], 'right', straight.fixation_points[0]['right'], np.eye(3) * 1e-6,
                    RIG.center('right'), 0.3 / RIG.camera('right').fx)
    a.start(Pose.identity(), fixations_of(straight.observations[0])['right'][1])
    nominal = 0.5
    for obs, pose, t in zip(straight.observations[1:30], straight.poses[1:30], stamps[1:], strict=True):
        f = fixations_of(obs)['right']
        drawn = pose.t / np.linalg.norm(pose.t) * nominal * (t - stamps[0])
        a.add(obs.stamp, Pose(pose.R, drawn), f[1], f[0])
    fit = a.fit()
    assert fit.speed_k * nominal == pytest.approx(v_true, rel=0.1)
    assert fit.position_k * nominal * (stamps[-1] - stamps[0]) == pytest.approx(true_dist[-1], rel=0.05)


def test_anchor_ends_when_the_camera_reselects(straight):
    a = _anchor_on(straight, 1.0, 8)
    n = len(a.views)
    a.add(9.0, Pose.identity(), a.fixation_id + 1, np.array([0.0, 0.0, 1.0]))
    assert a.ended and len(a.views) == n
    a.add(9.5, Pose.identity(), a.fixation_id, np.array([0.0, 0.0, 1.0]))
    assert len(a.views) == n


def _path(results) -> np.ndarray:
    """Positions, with the earlier ones rewritten by each reported prefix scale (as replay does)."""
    out: list[np.ndarray] = []
    for r in results:
        out = [p * r.prefix_scale for p in out] + [r.pose.t]
    return np.array(out)


def test_steps_keep_the_nominal_speed_and_the_scale_stays_unobserved(straight):
    est = _estimator(speed_nominal=0.5)
    res = [est.update(o) for o in straight.observations]
    assert not res[-1].scale_observed and 'nominal 0.5 m/s' in res[-1].scale_note
    assert all(r.prefix_scale == 1.0 for r in res)
    p = _path(res)
    speed = np.linalg.norm(np.diff(p, axis=0), axis=1) / np.diff(straight.stamps)
    assert np.median(speed) == pytest.approx(0.5, rel=0.15)
    assert np.all(np.isfinite(p))


@pytest.mark.parametrize('late', [False, True])
def test_vergence_point_calibrates_the_speed(straight, late):
    """The vergence point (given before its frame, or ~1 s after it) turns the nominal speed into a metric one
    and rescales the path built so far, once."""
    est = _estimator(speed_nominal=0.5)
    point = straight.fixation_points[0]['right']
    res = []
    for i, obs in enumerate(straight.observations):
        if i == (10 if late else 0):
            est.add_fixation_point(straight.stamps[0], 'right', point, np.eye(3) * 0.01**2)
        res.append(est.update(obs))
    assert res[-1].scale_observed and 'vergence' in res[-1].scale_note
    assert sum(r.prefix_scale != 1.0 for r in res) == 1
    truth = np.array([p.t for p in straight.poses])
    true_len = np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1))
    ratio = np.sum(np.linalg.norm(np.diff(_path(res), axis=0), axis=1)) / true_len
    nominal = _estimator(speed_nominal=0.5)
    nominal_ratio = np.sum(np.linalg.norm(np.diff(_path([nominal.update(o) for o in straight.observations]), axis=0),
                                          axis=1)) / true_len
    # closer to the truth than the nominal speed (x3.5 here); the anchor's own error is in bench.accuracy
    assert abs(ratio - 1.0) < 0.5 * abs(nominal_ratio - 1.0)


def test_vergence_point_too_old_is_ignored(straight):
    est = _estimator()
    for obs in straight.observations[:5]:
        est.update(obs)
    est.add_fixation_point(straight.stamps[0] - 100.0, 'right', np.array([0.0, 0.0, 3.0]), np.eye(3) * 1e-4)
    r = est.update(straight.observations[5])
    assert not r.scale_observed and 'older than the frames kept' in r.scale_note


def test_each_vergence_point_re_measures_the_speed():
    """Every vergence measurement is used: a later one corrects the speed that a first one, 30 % too far, set."""
    scene = LandmarkScene(RIG, LandmarkSceneConfig(noise_px=0.3, window_px=300.0, max_tracks=40))
    straight = scene.run(make_trajectory('straight'), duration=12.0)

    def final_speed(measurements: dict[int, float]) -> float:
        est = _estimator(speed_nominal=0.5)
        res = []
        for i, obs in enumerate(straight.observations):
            if i in measurements:
                point = straight.fixation_points[i]['right'] * measurements[i]     # right camera centre = origin
                est.add_fixation_point(straight.stamps[i], 'right', point, np.eye(3) * 0.01**2)
            res.append(est.update(obs))
        p = _path(res)
        return float(np.linalg.norm(p[-1] - p[-6]) / (straight.stamps[-1] - straight.stamps[-6]))

    truth = np.array([p.t for p in straight.poses])
    v_true = float(np.linalg.norm(truth[-1] - truth[-6]) / (straight.stamps[-1] - straight.stamps[-6]))
    wrong = final_speed({0: 1.3})
    corrected = final_speed({0: 1.3, 25: 1.0})
    assert abs(wrong / v_true - 1.0) > 0.15                       # the first measurement alone leaves it off
    assert abs(corrected / v_true - 1.0) < 0.5 * abs(wrong / v_true - 1.0)


def test_speed_is_the_median_of_the_last_three_measurements():
    """One wild vergence fit (a speed 3x off with a small stated std) does not throw the speed once three are known;
    with one or two the newest counts (a re-measurement replaces the first)."""
    from fixego_ros.estimation.constant_speed import ConstantSpeed

    s = ConstantSpeed(0.5)
    s.calibrate(0.4, 0.05)                 # 0.2 m/s
    assert s.v == pytest.approx(0.2) and s.measured
    s.calibrate(1.1, 0.05)                 # 0.22 m/s: the newest
    assert s.v == pytest.approx(0.22)
    s.calibrate(3.0, 0.05)                 # 0.66 m/s, wild: the median of 0.2, 0.22, 0.66
    assert s.v == pytest.approx(0.22)
    s.calibrate(0.9, 0.05)                 # 0.198: median of 0.22, 0.66, 0.198
    assert s.v == pytest.approx(0.22)
