"""The pose-only resection that places each new frame in the smoother (estimation/resection.py)."""

import gtsam
import numpy as np
import pytest

from fixego_ros.estimation.factors import CameraMount, to_gtsam
from fixego_ros.estimation.resection import Sightings, resect
from fixego_ros.geometry.rotation import Pose, exp_so3, rotation_angle

FOCAL = 400.0
LEFT_CENTER = np.array([-0.2, 0.0, 0.0])


def _scene(rng: np.random.Generator, truth: Pose, noise_px: float, n: int = 60,
           outliers: int = 0) -> Sightings:
    """Two heads 0.2 m apart, each looking about 10 deg outwards at points 2-4 m away in its narrow view."""
    rows = []
    for center, pan in ((np.zeros(3), 0.17), (LEFT_CENTER, -0.17)):
        C = exp_so3(np.array([0.0, pan, 0.0])) @ exp_so3(np.array([rng.normal(0, 0.05), 0.0, 0.0]))
        for _ in range(n // 2):
            ray_cam = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.12, 0.12), 1.0])
            point_rig = center + C @ ray_cam * rng.uniform(2.0, 4.0)
            pixel = FOCAL * ray_cam[:2] + rng.normal(0, noise_px, 2)
            rows.append((truth.apply(point_rig), pixel, C, center))
    for k in range(outliers):
        rows[k] = (rows[k][0], rows[k][1] + rng.uniform(30.0, 60.0, 2), rows[k][2], rows[k][3])
    points, pixels, rotations, centers = (np.array(c) for c in zip(*rows, strict=True))
    return Sightings(points, pixels, rotations, centers, np.full((len(points), 2), FOCAL))


def _truth() -> Pose:
    return Pose(exp_so3(np.array([0.02, 0.4, -0.01])), np.array([0.8, -0.05, 1.3]))


def test_the_jacobian_is_that_of_the_residuals_with_the_rotation_perturbed_on_the_left():
    seen = _scene(np.random.default_rng(1), _truth(), 0.5)
    R, T = exp_so3(np.array([0.01, 0.38, 0.0])), np.array([0.78, -0.04, 1.32])
    r, J = seen.residuals(R, T, 0.7)
    numeric = np.zeros_like(J)
    h = 1e-6
    for k in range(6):
        step = np.zeros(6)
        step[k] = h
        plus = seen.residuals(exp_so3(step[:3]) @ R, T + step[3:], 0.7)[0]
        minus = seen.residuals(exp_so3(-step[:3]) @ R, T - step[3:], 0.7)[0]
        numeric[:, k] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(J, numeric, rtol=1e-5, atol=1e-5)
    assert r.shape == (2 * len(seen.points),)


def test_noise_free_sightings_give_the_pose_back_from_a_start_far_off():
    truth = _truth()
    seen = _scene(np.random.default_rng(2), truth, 0.0)
    start = Pose(exp_so3(np.array([0.03, -0.04, 0.02])) @ truth.R, truth.t + np.array([0.1, -0.05, 0.15]))
    pose = resect(seen, 1.0, 1.345, start)
    assert pose is not None
    assert rotation_angle(pose.R.T @ truth.R) < 1e-7
    np.testing.assert_allclose(pose.t, truth.t, atol=1e-7)


def test_it_agrees_with_gtsams_levenberg_marquardt_over_mounted_projection_factors():
    """The formulation it replaced: GTSAM's projection factors on the rig pose through each camera's mount, the
    points held by tight priors. Without outliers both minimise the same pixel cost (Huber is not reached)."""
    truth = _truth()
    seen = _scene(np.random.default_rng(3), truth, 0.3)
    start = Pose(exp_so3(np.array([0.01, 0.01, 0.0])) @ truth.R, truth.t + np.array([0.03, 0.0, -0.03]))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    K = gtsam.Cal3_S2(FOCAL, FOCAL, 0.0, 0.0, 0.0)
    pixel_noise = gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    values.insert(0, to_gtsam(start))
    for k, (p, z, C, c) in enumerate(zip(seen.points, seen.pixels, seen.cam_to_rig, seen.centers, strict=True)):
        values.insert(k + 1, p)
        graph.add(gtsam.PriorFactorPoint3(k + 1, p, gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
        graph.add(gtsam.GenericProjectionFactorCal3_S2(z, pixel_noise, 0, k + 1, K, False, False,
                                                       CameraMount.mount(C, c)))
    reference = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize().atPose3(0)
    pose = resect(seen, 1.0, 1e6, start)
    assert pose is not None
    assert rotation_angle(pose.R.T @ reference.rotation().matrix()) < 1e-6
    np.testing.assert_allclose(pose.t, reference.translation(), atol=1e-5)


@pytest.mark.parametrize('seed', [4, 5, 6])
def test_gross_outliers_are_held_off_by_the_huber_weights(seed):
    """A tenth of the pixels 30-60 px off: robust, the pose stays within millimetres; by least squares it does
    not (so the test can tell)."""
    truth = _truth()
    seen = _scene(np.random.default_rng(seed), truth, 0.5, outliers=6)
    start = Pose(truth.R, truth.t + np.array([0.02, 0.02, -0.02]))
    robust, plain = resect(seen, 1.0, 1.345, start), resect(seen, 1.0, 1e6, start)
    assert robust is not None and plain is not None
    assert np.linalg.norm(robust.t - truth.t) < 0.01
    assert np.linalg.norm(plain.t - truth.t) > 2 * np.linalg.norm(robust.t - truth.t)


def test_a_point_behind_a_camera_neither_pulls_nor_breaks_the_fit():
    truth = _truth()
    seen = _scene(np.random.default_rng(7), truth, 0.0)
    behind = truth.apply(np.array([0.0, 0.0, -1.0]))       # 1 m behind both heads
    seen = Sightings(np.vstack([seen.points, behind]), np.vstack([seen.pixels, [5.0, 5.0]]),
                     np.concatenate([seen.cam_to_rig, seen.cam_to_rig[:1]]), np.vstack([seen.centers, np.zeros(3)]),
                     np.vstack([seen.focal, [FOCAL, FOCAL]]))
    r, J = seen.residuals(truth.R, truth.t, 1.0)
    assert np.all(r[-2:] == 2.0 * FOCAL) and not J[-2:].any()
    pose = resect(seen, 1.0, 1.345, Pose(truth.R, truth.t + 0.02))
    assert pose is not None and np.linalg.norm(pose.t - truth.t) < 1e-6


def test_a_start_that_is_not_finite_gives_none():
    seen = _scene(np.random.default_rng(8), _truth(), 0.0)
    assert resect(seen, 1.0, 1.345, Pose(np.eye(3), np.array([np.nan, 0.0, 0.0]))) is None


@pytest.mark.parametrize('seed', [8, 9])
def test_a_camera_whose_reading_is_off_counts_as_little_as_its_stated_sigma_says(seed):
    """The left head's pan reading 1 deg off (its angle predicted in a fast turn; the camera node states 1 deg):
    every pixel of that camera is then ~7 px off, so its sightings pull the pose. With one sigma per sighting (the
    left camera's from its stated reading sigma, JointWeighting) the pose follows the right camera; with one sigma
    for all it does not (so the test can tell)."""
    from fixego_ros.estimation.frames import JointWeighting
    truth = _truth()
    seen = _scene(np.random.default_rng(seed), truth, 0.3)
    left = np.all(seen.centers == LEFT_CENTER, axis=1)
    wrong = exp_so3(np.array([0.0, np.radians(1.0), 0.0]))
    rotations = seen.cam_to_rig.copy()
    rotations[left] = np.einsum('ij,njk->nik', wrong, rotations[left])
    off = Sightings(seen.points, seen.pixels, rotations, seen.centers, seen.focal)
    joints = JointWeighting(1.0 / FOCAL, np.radians(0.1))
    sigmas = np.where(left, 1.0 / joints.weight(np.radians(1.0)), 1.0 / joints.weight(np.radians(0.02)))
    assert sigmas[~left].max() == 1.0 and sigmas[left].min() > 5.0
    start = Pose(truth.R, truth.t + np.array([0.02, 0.0, -0.02]))
    weighted, flat = resect(off, sigmas, 1.345, start), resect(off, 1.0, 1.345, start)
    assert weighted is not None and flat is not None
    err = lambda p: (np.degrees(rotation_angle(p.R.T @ truth.R)), np.linalg.norm(p.t - truth.t))  # noqa: E731
    assert err(weighted)[0] < 0.6 * err(flat)[0] and err(weighted)[1] < 0.6 * err(flat)[1], (err(weighted), err(flat))
    # per-sighting sigmas are the residuals' units: one value for all gives the scalar's residuals
    r1, J1 = seen.residuals(truth.R, truth.t, 0.7)
    r2, J2 = seen.residuals(truth.R, truth.t, np.full(len(seen.points), 0.7))
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_array_equal(J1, J2)
