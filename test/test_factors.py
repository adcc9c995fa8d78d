"""The smoother's own factors: analytic Jacobians against central differences, and what each leaves free."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fixego_ros.estimation.factors import (
    ConstantTwist,
    ForwardMotion,
    HeldSpeed,
    ScaleGauge,
    SpeedStep,
    StepDirection,
    TwoFrameStep,
)
from fixego_ros.estimation.keys import pose_key, speed_scale_key
from fixego_ros.geometry.rotation import Pose, exp_so3

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


def _numeric_jacobian(factor: gtsam.CustomFactor, values: gtsam.Values, sigmas: np.ndarray | float,
                      poses: int = 3) -> np.ndarray:
    """Whitened Jacobian by central differences in each pose's tangent space."""
    cols = []
    for k in range(poses):
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


def test_constant_twist_takes_a_looser_rotation_sigma_never_a_tighter_one():
    """The smoother loosens the rotation part for a rig that turns irregularly; a sigma below the configured one is
    not taken (the configured sigma is the floor), and the translation part keeps its own."""
    def sigmas(rotation_sigma):
        factor = TWIST.factor((0, 1, 2), 0.5, 0.4, False, rotation_sigma)
        return 1.0 / np.abs(np.diag(np.asarray(factor.noiseModel().R())))
    np.testing.assert_allclose(sigmas(None), _sigmas(False))
    np.testing.assert_allclose(sigmas(0.01), _sigmas(False))
    np.testing.assert_allclose(sigmas(0.8), [0.8] * 3 + [0.05] * 3)


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


def test_a_stationary_step_holds_the_rig_still():
    """No parallax at all (the solve's translation is zero): a zero step, 10x firmer than the gauge. At 100 % the
    graph let a rig at rest drift at the nominal speed; landmarks then seemed seen from apart and entered without
    their at-rest depth prior (a recorded demo bag: 7.05 -> 6.37 cm; the simulated loop after 7 s at rest lost its
    restart)."""
    steps = TwoFrameStep(rotation_floor=1e-3, nominal_speed=0.5, cauchy_k=1.0)
    cov = np.eye(6) * 1e-6
    for t, sigma in ((np.zeros(3), 0.25 * TwoFrameStep.STATIONARY_LENGTH_SIGMA), (np.array([0.0, 0.0, 1.0]), 0.25)):
        factor = steps.factor(0, 1, Pose(np.eye(3), t), cov, 0.5)
        assert 1.0 / abs(float(np.asarray(factor.noiseModel().noise().R())[3, 3])) == pytest.approx(sigma)
        values = gtsam.Values()
        values.insert(pose_key(0), gtsam.Pose3())
        values.insert(pose_key(1), gtsam.Pose3())
        np.testing.assert_allclose(factor.unwhitenedError(values)[3:], -steps.scaled(Pose(np.eye(3), t), 0.5).t,
                                   atol=1e-12)


def _pair(rng: np.random.Generator, step: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    p0 = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0.0, 0.2, 3)), rng.normal(0.0, 1.0, 3))
    values.insert(pose_key(0), p0)
    values.insert(pose_key(1), p0.compose(gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0.0, 0.05, 3)), step)))
    return values


def test_step_direction_jacobian_matches_central_differences():
    direction = StepDirection(cauchy_k=1.0, nominal_speed=0.5)
    step, cov = Pose(np.eye(3), np.array([0.3, -0.1, 1.0])), np.diag([1e-6] * 3 + [1e-4] * 3)
    factor = direction.factor(0, 1, step, cov, dt=0.2)
    values = _pair(np.random.default_rng(2), np.array([0.5, 0.2, 0.9]))
    J = _numeric_jacobian(factor, values, direction.sigma(step, cov), poses=2)
    A, _ = factor.linearize(values).jacobian()
    weight = np.abs(A).max() / np.abs(J).max()              # the Cauchy kernel's weight at this error
    np.testing.assert_allclose(A, weight * J, atol=1e-5 * np.abs(A).max())


def test_step_direction_holds_the_direction_and_leaves_the_length_free():
    """The rays fix the step's direction, not its length: any length along the solved direction costs nothing, a
    turn away from it costs its angle; a direction the solve barely knows adds no factor."""
    direction = StepDirection(cauchy_k=1.0, nominal_speed=0.5)
    solved = Pose(np.eye(3), np.array([0.0, 0.0, 2.0]))
    cov = np.diag([1e-6] * 3 + [(2.0 * 0.01) ** 2] * 3)         # 0.01 rad across the direction
    factor = direction.factor(0, 1, solved, cov, dt=0.2)
    assert direction.sigma(solved, cov) == pytest.approx(0.01)
    rng = np.random.default_rng(4)
    for length in (0.01, 0.3, 5.0):
        values = _pair(rng, np.array([0.0, 0.0, length]))
        rel = values.atPose3(pose_key(0)).between(values.atPose3(pose_key(1)))
        np.testing.assert_allclose(rel.translation(), [0.0, 0.0, length], atol=1e-9)
        assert np.linalg.norm(factor.unwhitenedError(values)) < 1e-9
    turned = _pair(rng, np.array([np.sin(0.05), 0.0, np.cos(0.05)]))
    assert np.linalg.norm(factor.unwhitenedError(turned)) == pytest.approx(np.sin(0.05), rel=1e-6)
    loose = np.diag([1e-6] * 3 + [4.0] * 3)                       # 1 rad across a 2 m step
    assert direction.sigma(solved, loose) is None and direction.factor(0, 1, solved, loose, dt=0.2) is None


def test_step_direction_stays_gentle_at_a_step_of_no_length():
    """At a (nearly) zero-length step the unit vector's Jacobian would be 1 / length: below a tenth of the nominal
    step it is taken over that floor instead, so a rig predicted at rest does not make the window indeterminate."""
    direction = StepDirection(cauchy_k=1.0, nominal_speed=0.5)
    solved = Pose(np.eye(3), np.array([0.0, 0.0, 2.0]))
    sigma = 0.01
    factor = direction.factor(0, 1, solved, np.diag([1e-6] * 3 + [(2.0 * sigma) ** 2] * 3), dt=0.2)
    floor = direction.min_length(0.2)
    assert floor == pytest.approx(0.01)
    values = _pair(np.random.default_rng(6), np.array([1e-6, 0.0, 0.0]))      # 1 um, across the solved direction
    A, _ = factor.linearize(values).jacobian()
    assert np.abs(A).max() <= 1.01 / (floor * sigma)              # ~1e4: 1 / (1 um * sigma) = 1e8 unfloored
    assert np.linalg.norm(factor.unwhitenedError(values)) == pytest.approx(1e-6 / floor, rel=1e-3)
    above = _pair(np.random.default_rng(6), np.array([0.0, 0.3, 0.3]))         # above the floor: the angle, 45 deg
    assert np.linalg.norm(factor.unwhitenedError(above)) == pytest.approx(np.sin(np.pi / 4), rel=1e-6)


def test_forward_motion_leaves_a_step_along_the_heading_free_and_charges_a_sideways_one():
    """The motion model: along the rig's forward axis (z) any length is free; on an arc the chord, which lies along
    the heading half way through the turn, is free too; a step turned away from it costs its angle."""
    forward = ForwardMotion(np.radians(5.0), StepDirection(cauchy_k=1.0, nominal_speed=0.5))
    rng = np.random.default_rng(8)
    straight = forward.factor(0, 1, np.zeros(3), dt=0.2)
    for length in (0.02, 0.1, 1.0):
        assert np.linalg.norm(straight.unwhitenedError(_pair(rng, np.array([0.0, 0.0, length])))) < 1e-9
    sideways = _pair(rng, 0.1 * np.array([np.sin(0.2), 0.0, np.cos(0.2)]))
    assert np.linalg.norm(straight.unwhitenedError(sideways)) == pytest.approx(np.sin(0.2), rel=1e-6)
    # an arc turning 0.3 rad about the vertical (rig y): the chord points 0.15 rad off the first heading
    turn = np.array([0.0, 0.3, 0.0])
    chord = 0.1 * (exp_so3(turn / 2) @ np.array([0.0, 0.0, 1.0]))
    arc = forward.factor(0, 1, turn, dt=0.2)
    assert np.linalg.norm(arc.unwhitenedError(_pair(rng, chord))) < 1e-9
    assert np.linalg.norm(straight.unwhitenedError(_pair(rng, chord))) == pytest.approx(np.sin(0.15), rel=1e-6)
    assert forward.heading(turn) == pytest.approx(chord / 0.1)


def test_scale_gauge_holds_the_nominal_length_in_log_space():
    """Before a scale aid: the nominal step is free, a factor e either way costs one sigma, and a shrink towards
    rest costs ever more (1 % costs ln 100 sigmas: a linear 100 % prior charged it one), finitely at zero length."""
    gauge = ScaleGauge(sigma=1.4, nominal_speed=0.5)
    factor = gauge.factor(0, 1, dt=0.2)                           # nominal 0.1 m
    rng = np.random.default_rng(9)
    for direction in rng.normal(size=(3, 3)):
        values = _pair(rng, 0.1 * direction / np.linalg.norm(direction))
        assert abs(factor.unwhitenedError(values)[0]) < 1e-9
    assert factor.unwhitenedError(_pair(rng, np.array([0.0, 0.0, 0.1 * np.e])))[0] == pytest.approx(1.0)
    assert factor.unwhitenedError(_pair(rng, np.array([0.0, 0.0, 0.001])))[0] == pytest.approx(-np.log(100.0))
    at_rest = factor.unwhitenedError(_pair(rng, np.zeros(3)))[0]
    assert at_rest == pytest.approx(np.log(ScaleGauge.MIN_FRACTION))
    values = _pair(np.random.default_rng(10), np.array([0.02, -0.01, 0.06]))
    A, _ = factor.linearize(values).jacobian()
    np.testing.assert_allclose(A, _numeric_jacobian(factor, values, 1.4, poses=2), atol=1e-5)


def test_held_speed_jacobian_matches_central_differences():
    held = HeldSpeed(relative_sigma=0.3, min_speed=0.08)
    factor = held.factor(0, 1, speed=0.25, dt=0.2)
    values = _pair(np.random.default_rng(5), np.array([0.02, -0.01, 0.06]))
    J = _numeric_jacobian(factor, values, 0.3 * 0.25 * 0.2, poses=2)
    A, _ = factor.linearize(values).jacobian()
    np.testing.assert_allclose(A, J, atol=1e-5)


def test_held_speed_holds_the_length_in_any_direction():
    """Only the step's length is held (speed x dt, relative sigma, floored at the minimum speed); its direction and
    rotation are left to the other factors."""
    held = HeldSpeed(relative_sigma=0.3, min_speed=0.08)
    factor = held.factor(0, 1, speed=0.25, dt=0.2)               # 5 cm
    rng = np.random.default_rng(6)
    for direction in rng.normal(size=(3, 3)):
        values = _pair(rng, 0.05 * direction / np.linalg.norm(direction))
        assert abs(factor.unwhitenedError(values)[0]) < 1e-9
    assert factor.unwhitenedError(_pair(rng, np.array([0.0, 0.0, 0.08])))[0] == pytest.approx(0.03)
    assert held.factor(0, 1, speed=0.0, dt=0.2).noiseModel().sigmas()[0] == pytest.approx(0.3 * 0.08 * 0.2)


def test_camera_mount_adds_the_readings_sigma_to_its_own():
    from fixego_ros.estimation.factors import CameraMount

    mount = CameraMount(4e-4)
    assert np.allclose(mount.factor(0, 'right', np.eye(3), np.zeros(3)).noiseModel().sigmas()[:3], 4e-4)
    sigmas = mount.factor(0, 'right', np.eye(3), np.zeros(3), reading_sigma=3e-3).noiseModel().sigmas()
    np.testing.assert_allclose(sigmas, [np.hypot(4e-4, 3e-3)] * 3 + [1e-4] * 3)


def test_speed_step_measures_the_step_times_the_sources_scale():
    """The step keyframe -> frame (in the keyframe's frame) is the integrated speed times the source's scale ``k``:
    a wheel radius 2 % long reads 2 % far, and k = 1 / 1.02 explains it. Jacobians (both poses and k) against
    central differences."""
    speed = SpeedStep(scale_sigma=0.05)
    d = np.array([0.01, -0.02, 0.2])
    values = _pair(np.random.default_rng(12), d / 1.02)
    values.insert(speed_scale_key(0), 1.0 / 1.02)
    cov = np.eye(3) * 1e-4
    factor = speed.factor(0, 1, d, cov, graph=0)
    np.testing.assert_allclose(factor.unwhitenedError(values), 0.0, atol=1e-12)
    held = speed.factor(0, 1, d, cov)                                 # no variable: the scale held at 1
    np.testing.assert_allclose(held.unwhitenedError(values), d / 1.02 - d, atol=1e-12)
    assert speed.factor(0, 1, d, cov, scale=1.0 / 1.02).unwhitenedError(values) == pytest.approx(np.zeros(3), abs=1e-12)
    values.update(speed_scale_key(0), 0.97)
    A, _ = factor.linearize(values).jacobian()
    poses = _numeric_jacobian(factor, values, 0.01, poses=2)
    errs = []
    for sign in (1.0, -1.0):
        v = gtsam.Values(values)
        v.update(speed_scale_key(0), 0.97 + sign * 1e-6)
        errs.append(np.asarray(factor.unwhitenedError(v)))
    dk = (errs[0] - errs[1]) / 2e-6 / 0.01
    np.testing.assert_allclose(A, np.column_stack([poses, dk]), atol=1e-5)
    assert SpeedStep(scale_sigma=0.0).factor(0, 1, d, cov, graph=0).keys() == [pose_key(0), pose_key(1)]
