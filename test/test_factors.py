"""The smoother's own factors: analytic Jacobians against central differences, and what each leaves free."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fixego_ros.estimation.factors import ConstantTwist, TwoFrameStep
from fixego_ros.estimation.keys import pose_key
from fixego_ros.geometry.rotation import Pose

TWIST = ConstantTwist(rotation_sigma=0.1, translation_sigma=0.05, speed_sigma=0.3, min_speed=0.05)


def _sigmas(measured: bool) -> np.ndarray:
    return np.array([0.1] * 3 + [0.3 if measured else 0.05] * 3)


def _poses(rng: np.random.Generator, step: float) -> gtsam.Values:
    values = gtsam.Values()
    for k in range(3):
        values.insert(pose_key(k), gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0.0, 0.1, 3)),
                                               rng.normal(0.0, 0.02, 3) + k * np.array([step, 0.0, 0.0])))
    return values


def _scaled(values: gtsam.Values, s: float) -> gtsam.Values:
    out = gtsam.Values()
    for k in range(3):
        p = values.atPose3(pose_key(k))
        out.insert(pose_key(k), gtsam.Pose3(p.rotation(), s * p.translation()))
    return out


def _numeric_jacobian(factor: gtsam.CustomFactor, values: gtsam.Values, sigmas: np.ndarray) -> np.ndarray:
    """Whitened Jacobian by central differences in each pose's tangent space."""
    cols = []
    for k in range(3):
        for d in range(6):
            dv = np.zeros(6)
            dv[d] = 1e-6
            errs = []
            for sign in (1.0, -1.0):
                v = gtsam.Values(values)
                v.update(pose_key(k), values.atPose3(pose_key(k)).retract(sign * dv))
                errs.append(np.asarray(factor.unwhitenedError(v)))
            cols.append((errs[0] - errs[1]) / 2e-6 / sigmas)
    return np.column_stack(cols)


@pytest.mark.parametrize('measured', [False, True])
@pytest.mark.parametrize('step', [0.3, 0.001])          # above and below the speed floor
def test_constant_twist_jacobian_matches_central_differences(step, measured):
    factor = TWIST.factor((0, 1, 2), 0.5, 0.4, measured)
    values = _poses(np.random.default_rng(0), step)
    A, _ = factor.linearize(values).jacobian()
    np.testing.assert_allclose(A, _numeric_jacobian(factor, values, _sigmas(measured)), atol=1e-5)


def test_constant_twist_holds_the_gauge_until_the_scale_is_measured_then_leaves_it_free():
    """Before a scale aid the speed is a gauge and the prior holds it (its error grows with the scale); after, scaling
    every translation leaves the error unchanged, so the prior cannot prefer short steps (the absolute form
    shrank the measured scale wherever the images did not hold it)."""
    values = _poses(np.random.default_rng(1), 0.3)
    gauge, free = TWIST.factor((0, 1, 2), 0.5, 0.4, False), TWIST.factor((0, 1, 2), 0.5, 0.4, True)
    e_gauge, e_free = np.asarray(gauge.unwhitenedError(values)), np.asarray(free.unwhitenedError(values))
    assert np.linalg.norm(e_free[3:]) > 0.05                  # not trivially zero
    for s in (0.5, 3.0):
        np.testing.assert_allclose(free.unwhitenedError(_scaled(values, s)), e_free, atol=1e-9)
        np.testing.assert_allclose(gauge.unwhitenedError(_scaled(values, s))[3:], s * e_gauge[3:], rtol=1e-9)


def test_the_step_length_gauge_relaxes_once_the_scale_is_measured():
    steps = TwoFrameStep(rotation_floor=1e-3, nominal_speed=0.5, cauchy_k=1.0)
    step = Pose(np.eye(3), np.array([1.0, 0.0, 0.0]))
    cov = np.eye(6) * 1e-6

    def length_sigma(measured: bool) -> float:
        sqrt_information = steps.factor(0, 1, step, cov, 0.5, measured).noiseModel().noise().R()   # Robust -> Gaussian
        return 1.0 / abs(float(np.asarray(sqrt_information)[3, 3]))

    assert length_sigma(False) == pytest.approx(0.25)            # nominal 0.5 m/s over 0.5 s, 100 %
    assert length_sigma(True) == pytest.approx(0.25 * TwoFrameStep.AIDED_LENGTH_SIGMA)
