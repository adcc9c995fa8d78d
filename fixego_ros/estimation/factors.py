"""The factors of the metric back end (:mod:`.smoother`), one class per kind of measurement.

Each class holds its noise model and builds GTSAM factors for given keys. GTSAM's own factor types are used
where one fits (projection, between); the others are :class:`gtsam.CustomFactor` with analytic Jacobians
(:class:`ConstantTwist`, :class:`StepDirection` and :class:`ForwardMotion` through it, :class:`ScaleGauge`,
:class:`HeldSpeed`, :class:`Vergence`, :class:`SpeedStep`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gtsam
import numpy as np

from fixego_ros.estimation.keys import camera_key, landmark_key, pose_key, speed_scale_key
from fixego_ros.estimation.status import StepStatus
from fixego_ros.geometry.rotation import Pose, exp_so3, project_to_so3


def to_gtsam(pose: Pose) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(project_to_so3(pose.R)), np.asarray(pose.t, float))


def from_gtsam(pose: gtsam.Pose3) -> Pose:
    """GTSAM's rotations drift off SO(3) by rounding: project them back (SVD) before they leave the graph."""
    return Pose(project_to_so3(pose.rotation().matrix()), np.asarray(pose.translation(), float))


def with_length(step: Pose, length: float) -> Pose:
    """``step`` with its translation ``length`` long: the two-frame solve gives the direction only."""
    n = float(np.linalg.norm(step.t))
    return Pose(step.R, step.t / n * length if n > 1e-9 else step.t)


def constant_twist(a: Pose, t_a: float, b: Pose, t_b: float, stamp: float) -> Pose:
    """The pose at ``stamp`` moving on from ``b`` with the twist ``a`` -> ``b`` (a prediction, and the motion
    between two frames at a stamp between them)."""
    return constant_twists(a, t_a, b, t_b, (stamp,))[0]


def constant_twists(a: Pose, t_a: float, b: Pose, t_b: float, stamps: Sequence[float]) -> list[Pose]:
    """:func:`constant_twist` at each of ``stamps``, the twist taken once (the frames between two smoothed ones)."""
    end = to_gtsam(b)
    step = gtsam.Pose3.Logmap(to_gtsam(a).between(end))
    dt = max(t_b - t_a, 1e-9)
    return [from_gtsam(end.compose(gtsam.Pose3.Expmap(step * ((stamp - t_b) / dt)))) for stamp in stamps]


def _jac(rows: int, cols: int) -> np.ndarray:
    return np.zeros((rows, cols), order='F')


def _relative_translation(values: gtsam.Values, keys: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The translation of pose ``keys[1]`` in the frame of pose ``keys[0]``, and its 3x6 Jacobians in each pose."""
    H1, H2, Ht = _jac(6, 6), _jac(6, 6), _jac(3, 6)
    rel = values.atPose3(keys[0]).between(values.atPose3(keys[1]), H1, H2)
    t = np.asarray(rel.translation(Ht), float)
    return t, Ht @ H1, Ht @ H2


class CameraMount:
    """The camera's optical frame in the rig at one frame, from its pan/tilt readings: a between factor rig pose ->
    camera pose. The small rotation sigma lets the graph absorb the joint readings' noise; where the camera node
    says its readings are less certain (``reading_sigma``: a head turning fast, its angle predicted at the image
    stamp; recorded live runs p50 0.05 deg, p95 0.55 deg), the two add up. Held at the readings alone during a
    swing-back, the rig pose took the readings' error and the landmarks dragged it (docs/results.md "Stop 36")."""

    def __init__(self, rotation_sigma: float, translation_sigma: float = 1e-4) -> None:
        self.rotation_sigma, self.translation_sigma = rotation_sigma, translation_sigma
        self.noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([rotation_sigma] * 3 + [translation_sigma] * 3))

    @staticmethod
    def mount(cam_to_rig: np.ndarray, center: np.ndarray) -> gtsam.Pose3:
        return gtsam.Pose3(gtsam.Rot3(project_to_so3(cam_to_rig)), np.asarray(center, float))

    def factor(self, frame: int, side: str, cam_to_rig: np.ndarray, center: np.ndarray,
               reading_sigma: float = 0.0) -> gtsam.NonlinearFactor:
        noise = self.noise
        if reading_sigma > 0.0:
            rotation = math.hypot(self.rotation_sigma, reading_sigma)
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([rotation] * 3 + [self.translation_sigma] * 3))
        return gtsam.BetweenFactorPose3(pose_key(frame), camera_key(frame, side), self.mount(cam_to_rig, center),
                                        noise)


class Projection:
    """A landmark seen by one camera at one frame: pixel residual (robust, Huber) through that frame's camera pose.
    The rays are undistorted already, so the calibration is the focal lengths alone (principal point at 0)."""

    MIN_DEPTH = 1e-3     # a ray this close to the image plane has no pixel

    def __init__(self, fx: float, fy: float, pixel_sigma: float, huber_k: float) -> None:
        self.fx, self.fy = float(fx), float(fy)
        self.K = gtsam.Cal3_S2(self.fx, self.fy, 0.0, 0.0, 0.0)
        self.noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k),
                                                    gtsam.noiseModel.Isotropic.Sigma(2, pixel_sigma))

    def pixel(self, ray_cam: np.ndarray) -> np.ndarray | None:
        """Pixel (principal point at 0) of a ray in the optical frame, None behind the camera."""
        if ray_cam[2] <= self.MIN_DEPTH:
            return None
        return np.array([self.fx * ray_cam[0] / ray_cam[2], self.fy * ray_cam[1] / ray_cam[2]])

    def factor(self, frame: int, side: str, ray_rig: np.ndarray, cam_to_rig: np.ndarray,
               landmark: int) -> gtsam.NonlinearFactor | None:
        z = self.pixel(cam_to_rig.T @ ray_rig)
        if z is None:
            return None
        return gtsam.GenericProjectionFactorCal3_S2(z, self.noise, camera_key(frame, side), landmark_key(landmark),
                                                    self.K, False, False)


class ConstantTwist:
    """Weak motion prior over three consecutive poses: the body twist (Pose3 log of each step, per second) stays
    the same. It keeps directions the rays do not observe deterministic and bridges frames with nothing seen.

    Its translation part changes meaning when a scale aid has measured the scale (``measured``):

    * before, it is the change of the velocity in m/s (``translation_sigma``). With the steps at the nominal speed
      this holds the speed, which is then a gauge, steady along the path: the unaided paper loop's shape (Sim(3))
      is 16 cm with it and 29-41 cm with the relative form below.
    * after, it is that change over the first step's speed (floored at ``min_speed``): ``speed_sigma``, blind to
      the scale. The absolute form is smallest when every step is short, so it pulled the measured scale down
      wherever the images did not hold it (README "Back end").
    """

    def __init__(self, rotation_sigma: float, translation_sigma: float, speed_sigma: float, min_speed: float) -> None:
        self.rotation_sigma, self.translation_sigma, self.speed_sigma = rotation_sigma, translation_sigma, speed_sigma
        self.min_speed = min_speed

    def factor(self, frames: tuple[int, int, int], dt1: float, dt2: float,
               measured: bool = False, rotation_sigma: float | None = None) -> gtsam.NonlinearFactor:
        """``rotation_sigma``: this factor's, if larger than the class's (the smoother loosens it for a rig that turns
        irregularly)."""
        rotation = self.rotation_sigma if rotation_sigma is None else max(rotation_sigma, self.rotation_sigma)
        noise = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([rotation] * 3 + [self.speed_sigma if measured else self.translation_sigma] * 3))
        keys = [pose_key(f) for f in frames]
        vmin = self.min_speed

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            p0, p1, p2 = (values.atPose3(k) for k in keys)
            A0, A1, B1, B2, J1, J2 = (_jac(6, 6) for _ in range(6))
            l1 = gtsam.Pose3.Logmap(p0.between(p1, A0, A1), J1)
            l2 = gtsam.Pose3.Logmap(p1.between(p2, B1, B2), J2)
            e = l2 / dt2 - l1 / dt1
            speed = float(np.linalg.norm(l1[3:])) / dt1
            m = max(speed, vmin) if measured else 1.0
            if H is not None:
                d1 = [J1 @ A0 / dt1, J1 @ A1 / dt1, np.zeros((6, 6))]      # d(l1 / dt1) / d(p0, p1, p2)
                d2 = [np.zeros((6, 6)), J2 @ B1 / dt2, J2 @ B2 / dt2]      # d(l2 / dt2)
                for j in range(3):
                    de = d2[j] - d1[j]
                    dt = de[3:] / m
                    if measured and speed > vmin:                           # the divisor moves with the first step
                        dt -= np.outer(e[3:], (l1[3:] / dt1) @ d1[j][3:]) / (speed * m ** 2)
                    H[j] = np.vstack([de[:3], dt])
            return np.concatenate([e[:3], e[3:] / m])

        return gtsam.CustomFactor(noise, keys, error)


class TwoFrameStep:
    """The two-frame coplanarity solve keyframe -> frame as a between factor. Its rotation sigmas come from the
    solve's covariance (floored: a solve over few rays claims too much); its translation carries no scale, so it
    is set to ``nominal_speed`` over the interval with a 100 % sigma: the gauge until a scale aid measures it.
    Once one has (``measured``), the length sigma is ``AIDED_LENGTH_SIGMA`` nominal steps, so the gauge no longer
    competes with the measured scale: at 100 % it pulled each step towards the nominal 0.5 m/s wherever no track
    spans three frames, and the paper bag's steps came out 18 % long after the heads' swing-backs (README "Back
    end"). Before any aid it is what sets the scale, so it stays at 100 % until then. A stationary step (no parallax
    at all) holds the frame where it is at ``STATIONARY_LENGTH_SIGMA`` nominal steps whether or not the scale is
    measured: inflated tenfold with the rest, it let a rig that stopped where no landmark placed the frames run on
    at its last speed (docs/results.md "Stop 61"). Only over at least ``STATIONARY_MIN_S``, though: a shorter step
    cannot tell rest from slow motion (at 0.2 m/s a 10-40 ms step moves 2-8 mm, which a 21 deg field of view shows
    mostly as a rotation), and on the demo's last 0.2 m/s stretch such steps (a keyframe 1-2 frames after the last,
    the heads swinging) stood a moving rig: its refined speed fell to 0.1 m/s for 3 s (terminal 32 cm; docs/results.md
    "Stop 63"). A shorter one claims no length beyond a moving step's.
    Cauchy-robust: a wrong solve with an optimistic covariance must not drag the trajectory. (The rotation
    covariance given the translation, tighter where the parallax is small, measured 3.3 / 23 cm on the paper bag
    against 2.5 / 21 cm with this one.)"""

    AIDED_LENGTH_SIGMA = 10.0
    STATIONARY_LENGTH_SIGMA = 0.1
    STATIONARY_MIN_S = 0.1

    @classmethod
    def stands(cls, status: StepStatus, dt: float) -> bool:
        """Whether a solve of this status over ``dt`` seconds says the rig stood (see the class docstring)."""
        return status is StepStatus.STATIONARY and dt >= cls.STATIONARY_MIN_S

    def __init__(self, rotation_floor: float, nominal_speed: float, cauchy_k: float) -> None:
        self.rotation_floor = rotation_floor
        self.nominal_speed = nominal_speed
        self.robust = gtsam.noiseModel.mEstimator.Cauchy.Create(cauchy_k)

    def scaled(self, step: Pose, dt: float) -> Pose:
        return with_length(step, self.nominal_speed * dt)

    def rotation_covariance(self, covariance: np.ndarray) -> np.ndarray:
        return np.diag(np.clip(np.diag(covariance)[:3], self.rotation_floor ** 2, None))

    def factor(self, ref: int, frame: int, step: Pose, covariance: np.ndarray, dt: float,
               measured: bool = False) -> gtsam.NonlinearFactor:
        cov = np.zeros((6, 6))
        cov[:3, :3] = self.rotation_covariance(covariance)
        length_sigma = self.nominal_speed * dt * (self.AIDED_LENGTH_SIGMA if measured else 1.0)
        if not np.any(step.t) and dt >= self.STATIONARY_MIN_S:     # stationary: the rays saw no parallax at all
            length_sigma = self.nominal_speed * dt * self.STATIONARY_LENGTH_SIGMA
        cov[3:, 3:] = np.eye(3) * max(length_sigma, 1e-6) ** 2
        return gtsam.BetweenFactorPose3(pose_key(ref), pose_key(frame), to_gtsam(self.scaled(step, dt)),
                                        gtsam.noiseModel.Robust.Create(self.robust,
                                                                       gtsam.noiseModel.Gaussian.Covariance(cov)))


class StepDirection:
    """The direction of the two-frame step keyframe -> frame: the rays fix it (not its length), so the factor is
    the unit vector of the relative translation against the solved one, 2 components across it, with the
    solve's own angular std (floored). :class:`TwoFrameStep` alone carries it only through an isotropic
    translation sigma, ten nominal steps once a scale aid has measured the scale, which leaves the direction to the
    landmarks (and before an aid its 100 % length sigma leaves the direction +-45 deg). Cauchy-robust like the
    step. Measured (stop 31): walk bag Sim(3) 9.1 -> 3.3 cm, a live-demo dump whose smoother restarted without it
    19 -> 9 cm, a 30 Hz simulated loop 41.9 -> 12.3 cm with it from the first frame instead of from the first
    vergence measurement; but that loop was 3.8 cm with no direction factor at all, and the point-level loop of
    ``test_smoother`` comes out x0.87 long instead of x0.97, and twice the gauge's length unaided. The smoother
    adds it for keyframes only (stop 32): with it on every frame the same 30 Hz loop was 12.3 / 29.5 cm and a
    30 Hz circle 20.6 / 50.0 cm (mean / terminal), keyframes only 5.2 / 10.2 and 1.6 / 2.3.

    The residual divides the graph's relative translation by its length, floored at ``MIN_STEP_FRACTION`` of the
    nominal step over the interval. A rig that starts off, or a frame predicted at rest, puts the step's
    linearisation point at (nearly) zero length, where an unfloored unit vector has a Jacobian of 1 / length: at
    the 1e-6 m floor it was, that is an information of ~1e13 across the direction next to a scale of ~1, and GTSAM
    calls such a system indeterminate (its Cholesky's 2^12 test). On a simulated paper loop whose first step was too
    short to show parallax, the window then anchored the next pose five times and restarted the graph, and the
    estimate stood still for 0.6 s while the rig moved off (11.5 cm mean; 2.0 cm with the floor). Below the floor
    the factor only pulls the step's sideways part towards zero, gently."""

    MIN_SIGMA_RAD = math.radians(0.5)
    MAX_SIGMA_RAD = math.radians(30.0)     # a direction less certain than this is not added
    MIN_STEP_FRACTION = 0.1                # the length floor, as a share of the nominal step over the interval

    def __init__(self, cauchy_k: float, nominal_speed: float) -> None:
        self.robust = gtsam.noiseModel.mEstimator.Cauchy.Create(cauchy_k)
        self.nominal_speed = nominal_speed

    def sigma(self, step: Pose, covariance: np.ndarray) -> float | None:
        """Angular std of the solved direction (rad), floored; None when it is not worth a factor."""
        t = np.asarray(step.t, float)
        n = float(np.linalg.norm(t))
        cov = np.asarray(covariance, float)[3:, 3:]
        if n < 1e-9 or not np.all(np.isfinite(cov)):
            return None
        u = t / n
        P = np.eye(3) - np.outer(u, u)
        spread = float(np.linalg.eigvalsh(P @ (0.5 * (cov + cov.T)) @ P)[-1])
        sigma = max(math.sqrt(max(spread, 0.0)) / n, self.MIN_SIGMA_RAD)
        return sigma if sigma <= self.MAX_SIGMA_RAD else None

    def min_length(self, dt: float) -> float:
        """The length floor of the residual (m) for a step over ``dt`` seconds (at least 1 um)."""
        return max(self.MIN_STEP_FRACTION * self.nominal_speed * dt, 1e-6)

    def factor(self, ref: int, frame: int, step: Pose, covariance: np.ndarray,
               dt: float) -> gtsam.NonlinearFactor | None:
        sigma = self.sigma(step, covariance)
        if sigma is None:
            return None
        return self.along(ref, frame, np.asarray(step.t, float), sigma, dt)

    def along(self, ref: int, frame: int, direction: np.ndarray, sigma: float, dt: float) -> gtsam.NonlinearFactor:
        """The factor for a given ``direction`` (in ``ref``'s rig frame, any length) and angular std ``sigma``."""
        floor = self.min_length(dt)
        u = np.asarray(direction, float) / float(np.linalg.norm(direction))
        basis = np.linalg.svd(u.reshape(1, 3))[2][1:]          # (2, 3): orthonormal, across u
        keys = [pose_key(ref), pose_key(frame)]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            t, T1, T2 = _relative_translation(values, keys)
            length = max(float(np.linalg.norm(t)), floor)
            d = t / length
            if H is not None:
                J = basis @ ((np.eye(3) - np.outer(d, d)) / length)      # d e / d t (2 x 3)
                H[0], H[1] = J @ T1, J @ T2
            return basis @ d

        noise = gtsam.noiseModel.Robust.Create(self.robust, gtsam.noiseModel.Isotropic.Sigma(2, sigma))
        return gtsam.CustomFactor(noise, keys, error)


class ForwardMotion:
    """A motion model: the rig moves along its own forward axis (rig z), as a wheeled robot or a walking person
    carrying it does. Over keyframe -> frame the expected direction is the forward axis of the frame half way
    through the step's rotation (on an arc the chord lies between the two headings), with ``sigma`` radians of
    angular std, Cauchy-robust (a sideways or vertical step costs little once it is well beyond a few sigmas).

    Why (docs/results.md "Stop 55"): both cameras see 21 deg and their axes lie ~34 deg apart in one plane, so a yaw
    of the rig looks to both like a sideways translation and a pitch like a vertical one. After both heads
    re-select their points the landmark map starts anew and this mode ran away (the papers' loop over sixteen seeds:
    one to two failures of 10-60 cm, and 0.005 px of noise on the rays decided which seeds failed). The prior pins
    the mode: 4 -> 10 of 16 seeds within the papers' 3.36 / 4 cm, the worst 13.9 -> 5.7 cm. It is wrong for a rig
    that moves sideways (a head-mounted rig's sway and bob are ~10-16 deg at 1 m/s: the 30 Hz walk bag 2.6 -> 4.1
    cm), so it is a parameter (``smoother_forward_sigma_deg``, 0 = off)."""

    def __init__(self, sigma_rad: float, direction: StepDirection) -> None:
        self.sigma = sigma_rad
        self.direction = direction

    @staticmethod
    def heading(rotation_vector: np.ndarray) -> np.ndarray:
        """The forward axis half way through a step's rotation (in the step's first frame)."""
        return exp_so3(0.5 * np.asarray(rotation_vector, float))[:, 2]

    def factor(self, ref: int, frame: int, rotation_vector: np.ndarray, dt: float) -> gtsam.NonlinearFactor:
        return self.direction.along(ref, frame, self.heading(rotation_vector), self.sigma, dt)


class ScaleGauge:
    """Until a scale aid is used and the landmarks place a frame: the length of keyframe -> frame at the nominal
    speed, in log space (a factor ``exp(sigma)`` either way at one sigma). The two-frame step's linear 100 % sigma
    lets the whole window shrink to rest at a cost of one sigma per step, and the unaided start of the 30 Hz walk bag
    did so under small changes of the method: 76 new landmarks entered at 0.45 s, one pass threw them behind the
    cameras and the path went from 11.5 to 0.5 cm, then stood still for the whole walk (docs/results.md "Stop 55").
    In log space a shrink to 1 % costs (ln 100 / sigma)^2, while the scale stays free within a few times the
    nominal."""

    MIN_FRACTION = 1e-4       # of the nominal step: the length floor of the residual (no log of zero)

    def __init__(self, sigma: float, nominal_speed: float) -> None:
        self.sigma = sigma
        self.nominal_speed = nominal_speed

    def factor(self, ref: int, frame: int, dt: float) -> gtsam.NonlinearFactor:
        nominal = max(self.nominal_speed * dt, 1e-9)
        floor = self.MIN_FRACTION * nominal
        keys = [pose_key(ref), pose_key(frame)]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            t, T1, T2 = _relative_translation(values, keys)
            n = max(float(np.linalg.norm(t)), floor)
            if H is not None:
                J = (t / (n * n)).reshape(1, 3)                 # d ln|t| / d t (1 x 3)
                H[0], H[1] = J @ T1, J @ T2
            return np.array([math.log(n / nominal)])

        return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, self.sigma), keys, error)


class HeldSpeed:
    """The length of the step previous frame -> frame at the speed the landmarks last measured, for a frame they do
    not place. Without it such a frame's length is held only by the relative constant-twist prior, which lets the
    speed decay step by step at little cost (30 % per step at one sigma, and a head's swing-back brings a keyframe
    every frame); in recorded live runs both heads swung back together, no landmark was seen for ~1 s, the speed fell
    to zero and stayed there. The speed comes from frames the landmarks placed, so a gap cannot chain it down. The
    sigma is relative to at least ``min_speed``, so a rig the landmarks saw standing still is free to move off (at the
    nominal 0.5 m/s: 0.15 m/s per second of step; measured against a floor of 0.2 m/s, the 30 Hz loop with 0.05 deg
    noise came out 6.5 -> 5.1 cm and a 30 Hz circle's terminal error 3.7 -> 2.8 cm)."""

    def __init__(self, relative_sigma: float, min_speed: float) -> None:
        self.relative_sigma = relative_sigma
        self.min_speed = min_speed

    def factor(self, ref: int, frame: int, speed: float, dt: float) -> gtsam.NonlinearFactor:
        length = speed * dt
        keys = [pose_key(ref), pose_key(frame)]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            t, T1, T2 = _relative_translation(values, keys)
            n = max(float(np.linalg.norm(t)), 1e-9)
            if H is not None:
                J = (t / n).reshape(1, 3)                       # d |t| / d t (1 x 3)
                H[0], H[1] = J @ T1, J @ T2
            return np.array([n - length])

        sigma = self.relative_sigma * max(speed, self.min_speed) * dt
        return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, max(sigma, 1e-6)), keys, error)


class Vergence:
    """The vergence step's measurement: the right fixation point in the rig frame at one frame, with its 3x3
    covariance, on the fixation landmark. This is where the metric scale enters."""

    def factor(self, frame: int, landmark: int, point_rig: np.ndarray, covariance: np.ndarray
               ) -> gtsam.NonlinearFactor:
        z = np.asarray(point_rig, float).reshape(3)
        keys = [pose_key(frame), landmark_key(landmark)]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            Hp, Hl = _jac(3, 6), _jac(3, 3)
            e = values.atPose3(keys[0]).transformTo(values.atPoint3(keys[1]), Hp, Hl) - z
            if H is not None:
                H[0], H[1] = Hp, Hl
            return e

        cov = 0.5 * (covariance + covariance.T)
        return gtsam.CustomFactor(gtsam.noiseModel.Gaussian.Covariance(cov), keys, error)


class SpeedStep:
    """A speed source (wheel odometry) integrated over keyframe -> frame: the translation in the keyframe's rig
    frame with its covariance, times the source's scale ``k`` (one variable per graph: a wheel radius off by a
    percent is a bias the covariance does not show, and the integrated steps carry it into the path). The rotation
    is left to the cameras. Without another scale source ``k`` stays at its prior (1, :attr:`scale_sigma`); with
    vergence measurements in the same graph the landmarks' metric depths measure it. (The 20 Hz odometry of issue 16,
    1 % bias, replayed with the bag's vergence: every path came out 0.8-1.1 % long with ``k`` held at 1.)"""

    def __init__(self, scale_sigma: float) -> None:
        self.scale_sigma = scale_sigma      # 0: the source's scale is taken as exact

    @property
    def scaled(self) -> bool:
        return self.scale_sigma > 0.0

    def prior(self, graph: int, k: float = 1.0) -> gtsam.NonlinearFactor:
        """The scale's prior: ``k`` with :attr:`scale_sigma`."""
        return gtsam.PriorFactorDouble(speed_scale_key(graph), float(k),
                                       gtsam.noiseModel.Isotropic.Sigma(1, self.scale_sigma))

    def factor(self, ref: int, frame: int, translation: np.ndarray, covariance: np.ndarray,
               graph: int | None = None, scale: float = 1.0) -> gtsam.NonlinearFactor:
        """With the scale variable of ``graph``; ``graph`` None (or no scale sigma): the source's scale held at
        ``scale``."""
        d = np.asarray(translation, float).reshape(3)
        cov = 0.5 * (covariance + covariance.T)
        noise = gtsam.noiseModel.Gaussian.Covariance(cov)
        keys = [pose_key(ref), pose_key(frame)]
        if graph is not None and self.scaled:
            keys.append(speed_scale_key(graph))

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            t, T1, T2 = _relative_translation(values, keys)
            k = values.atDouble(keys[2]) if len(keys) == 3 else scale
            if H is not None:
                H[0], H[1] = T1, T2
                if len(keys) == 3:
                    H[2] = -d.reshape(3, 1)
            return t - k * d

        return gtsam.CustomFactor(noise, keys, error)
