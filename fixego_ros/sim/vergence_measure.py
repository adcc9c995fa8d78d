"""The simulated vergence measurement, made the way the rig makes it (DESIGN.md §3 ``/fixego/vergence``).

Both heads hold the right camera's fixation point. At each control tick of a short window the rig has, per
camera, the joint readings as VISCA reports them (quantised) and the point's pixel in the image (its small
offset from the centre, with pixel noise). Each tick gives the right fixation ray and the left ray through
the point's pixel, in the rig frame at that tick; :func:`~fixego_ros.tracking.vergence.triangulate_fixation`
(the live step's triangulation) puts the point on the right ray. The window is centred on a frame stamp and
the points are averaged, so the estimate refers to that frame (the point moves smoothly in the rig frame:
the average of a symmetric window is its value at the centre to second order).

Covariance: first order in the eight inputs (pan/tilt reading and pixel u/v of each camera), through the
same triangulation. A reading's error is its quantisation, uniform over one VISCA unit (std unit/√12). Over
the window it averages only as far as the head moves: a head that stands still keeps one error for every
tick, one that sweeps across k units sees k + 1 levels whose errors average out. So the variance of a
reading's window mean is unit²/12 divided by the number of distinct values it took (what the rig itself can
count). The pixel noise is independent per tick and averages over the window.

This module also holds what :class:`~fixego_ros.sim.run.Simulation` asks of a vergence mode
(:class:`VergenceSource`); the modes are :mod:`~fixego_ros.sim.vergence_step` (``physical``) and
:mod:`~fixego_ros.sim.vergence_on_point` (``measurements``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fixego_ros.estimation.covariance import std_along
from fixego_ros.geometry.rig import Rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.sim.render import project_points
from fixego_ros.sim.servo_model import ServoParams, ServoState, quantized, reading_sigmas
from fixego_ros.sim.world import World
from fixego_ros.tracking.vergence import triangulate_fixation

VERGENCE_MODES = ('off', 'physical', 'measurements')
_EPS_ANGLE = 1e-6     # rad, finite-difference step of the readings
_EPS_PIXEL = 1e-3     # px, finite-difference step of the pixels


@dataclass(frozen=True)
class VergenceParams:
    """The step's constants (the live step's counterparts are in :class:`~fixego_ros.tracking.vergence.
    VergenceParams`)."""

    control_hz: float = 30.0      # control ticks per second during a step (at least one per frame)
    settle_deg: float = 2.0       # both points this close to their optical axes ...
    settle_ticks: int = 3         # ... for this many ticks in a row: the heads hold the point
    hold_ticks: int = 2           # the measurement window: ticks within this many of a frame stamp, both sides
    pixel_sigma_px: float = 0.5   # std of a measured fixation pixel, per axis (the tracker's)
    min_angle_deg: float = 0.5    # vergence angle below this: rays too parallel to triangulate
    timeout_s: float = 2.0        # slew + settle + hold; past it the step is abandoned (no measurement)
    return_timeout_s: float = 2.0  # the way back; past it the servo goes on regardless


@dataclass(frozen=True)
class VergenceMeasurement:
    """One vergence measurement: the right fixation point in the rig frame at frame ``frame``'s stamp."""

    frame: int
    t: float                      # s since the start: the frame's time
    point_rig: np.ndarray         # (3,) m
    cov_rig: np.ndarray           # (3, 3) m²
    point_true_rig: np.ndarray    # (3,) the truth at the same time
    angle_rad: float              # vergence angle
    samples: int                  # ticks averaged
    right_fixation_id: int

    @property
    def distance_m(self) -> float:
        """Distance from the right projection centre (the rig origin)."""
        return float(np.linalg.norm(self.point_rig))

    @property
    def distance_true_m(self) -> float:
        return float(np.linalg.norm(self.point_true_rig))

    @property
    def std_m(self) -> float:
        """First-order std of the point along the right fixation ray."""
        return std_along(self.point_rig, self.cov_rig)

    def record(self, epoch: float) -> dict:
        """For ``sim.yaml``."""
        return {'stamp_s': float(epoch + self.t), 'frame': int(self.frame),
                'right_fixation_id': int(self.right_fixation_id),
                'distance_true_m': self.distance_true_m, 'distance_m': self.distance_m,
                'error_m': self.distance_m - self.distance_true_m,
                'position_error_m': float(np.linalg.norm(self.point_rig - self.point_true_rig)),
                'std_m': self.std_m, 'vergence_deg': float(np.degrees(self.angle_rad)), 'samples': int(self.samples)}


# ------------------------------------------------------------------------------------------------ ticks
def tick_times(t0: float, t1: float, hz: float) -> np.ndarray:
    """Control ticks in (t0, t1]: the interval split evenly, at least ``hz`` per second; the last is ``t1``."""
    n = max(1, math.ceil((t1 - t0) * hz - 1e-9))
    out = t0 + (t1 - t0) * np.arange(1, n + 1) / n
    out[-1] = t1
    return out


def tick_period(stamps: np.ndarray, hz: float) -> float:
    """Spacing of the ticks between consecutive frames (frames are evenly spaced)."""
    if len(stamps) < 2:
        return 1.0 / hz
    dt = float(stamps[1] - stamps[0])
    return dt / max(1, math.ceil(dt * hz - 1e-9))


def off_axis_deg(rig: Rig, side: str, rig_pose: Pose, pan: float, tilt: float, point: np.ndarray) -> float:
    """Angle between ``side``'s optical axis (head at true angles pan, tilt) and world ``point``."""
    d = rig.cam_to_rig(side, pan, tilt).T @ (rig_pose.inverse().apply(np.asarray(point, float)) - rig.center(side))
    return float(np.degrees(np.arctan2(np.hypot(d[0], d[1]), d[2])))


def true_distance(world: World, rig_pose: Pose, point_rig: np.ndarray) -> float:
    """The truth a measurement of the right fixation point is checked against: the distance from the right camera
    centre (the rig origin) along the measured direction ``point_rig`` to the first surface of the simulated
    ``world``, the rig at its true ``rig_pose`` (world frame); inf when the ray hits nothing."""
    p = np.asarray(point_rig, dtype=float)
    distance, _ = world.raycast(rig_pose.t, rig_pose.R @ (p / np.linalg.norm(p)))
    return float(distance)


# ------------------------------------------------------------------------------------------------ samples
def sample(rig: Rig, params: ServoParams, rig_pose: Pose, point: np.ndarray, angles: dict[str, tuple[float, float]],
           pixel_sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    """What the rig reads at one tick, as the 8 inputs ``[pan, tilt, u, v]`` of the right then the left camera:
    each head's quantised joint readings at its true ``angles`` and the world ``point``'s pixel with noise."""
    out = []
    for side in ('right', 'left'):
        pan, tilt = angles[side]
        pix, _ = project_points(rig, side, rig_pose, pan, tilt, np.asarray(point, float)[None])
        out += [*quantized(params, pan, tilt), *(pix[0] + rng.normal(0.0, pixel_sigma_px, 2))]
    return np.array(out, dtype=float)


def input_sigmas(params: ServoParams, pixel_sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(std of one quantised reading's error, std of one pixel's noise) over the 8 inputs of :func:`sample`."""
    q = reading_sigmas(params)
    reading = np.array([q[0], q[1], 0.0, 0.0, q[0], q[1], 0.0, 0.0])
    pixel = np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0]) * pixel_sigma_px
    return reading, pixel


def window_variances(params: ServoParams, pixel_sigma_px: float, samples: np.ndarray) -> np.ndarray:
    """Variance of the window mean of each of the 8 inputs (module docstring): quantisation over the number of
    distinct readings, pixel noise over the number of ticks."""
    reading, pixel = input_sigmas(params, pixel_sigma_px)
    units = np.radians(1.0 / np.array([params.pan_units_per_deg, params.tilt_units_per_deg] * 2))
    levels = np.array([len(np.unique(np.round(samples[:, i] / u))) for i, u in zip((0, 1, 4, 5), units,
                                                                                     strict=True)])
    per_level = np.ones(8)
    per_level[[0, 1, 4, 5]] = levels
    return reading ** 2 / per_level + pixel ** 2 / len(samples)


# ------------------------------------------------------------------------------------------------ measure
def _triangulate(rig: Rig, x: np.ndarray, min_angle_rad: float):
    ray_r = rig.pixels_to_rig_rays('right', x[2:4].reshape(1, 2), x[0], x[1])[0]
    ray_l = rig.pixels_to_rig_rays('left', x[6:8].reshape(1, 2), x[4], x[5])[0]
    return triangulate_fixation(ray_r, ray_l, rig.c_L, 1e-4, min_angle_rad)


def measure(rig: Rig, servo: ServoParams, params: VergenceParams, samples: list[np.ndarray], frame: int, t: float,
            point_true_rig: np.ndarray, right_fixation_id: int) -> VergenceMeasurement | str:
    """The measurement of a window of ``samples`` (inputs of :func:`sample`, in tick order, centred on frame
    ``frame`` at time ``t``), or why there is none (the rays' reason)."""
    if not samples:
        return 'no tick in the measurement window'
    min_angle = math.radians(params.min_angle_deg)
    points, angles = [], []
    for x in samples:
        tri = _triangulate(rig, x, min_angle)
        if not tri.ok:
            return tri.reason
        points.append(tri.point_rig)
        angles.append(tri.angle_rad)
    # first order in the inputs, at the middle tick (the window's geometry hardly changes)
    mid = samples[len(samples) // 2]
    J = np.zeros((3, 8))
    for i in range(8):
        h = _EPS_ANGLE if i % 4 < 2 else _EPS_PIXEL
        lo, hi = mid.copy(), mid.copy()
        lo[i] -= h
        hi[i] += h
        a, b = _triangulate(rig, lo, 0.0), _triangulate(rig, hi, 0.0)
        if not (a.ok and b.ok):
            return 'the triangulation is singular at the measured rays'
        J[:, i] = (b.point_rig - a.point_rig) / (2 * h)
    cov = J @ np.diag(window_variances(servo, params.pixel_sigma_px, np.asarray(samples))) @ J.T
    return VergenceMeasurement(frame, float(t), np.mean(points, axis=0), 0.5 * (cov + cov.T),
                               np.asarray(point_true_rig, float), float(np.mean(angles)), len(samples),
                               int(right_fixation_id))


# ------------------------------------------------------------------------------------------------ modes
class VergenceSource:
    """What :class:`~fixego_ros.sim.run.Simulation` asks of a vergence mode: the left camera's state at each
    frame (:meth:`frame`, which also runs the left servo), the measurements made so far (each refers to one
    frame), the earliest frame a measurement under way may still refer to (:attr:`pending_frame`: frames from
    it on are held back until it is done) and :meth:`finish` at the end. A vergence step starts at the first
    frame and whenever the right camera's fixation id changes."""

    def __init__(self, params: VergenceParams | None = None) -> None:
        self.p = params or VergenceParams()
        self.measurements: list[VergenceMeasurement] = []
        self.failures: list[dict] = []     # {'t', 'right_fixation_id', 'reason'}: steps without a measurement
        self._right_id: int | None = None

    @property
    def pending_frame(self) -> int | None:
        return None

    def frame(self, k: int, t: float, rig_pose: Pose, right: ServoState) -> ServoState:
        raise NotImplementedError

    def finish(self) -> None:
        """The sequence has ended (a step under way is recorded as unfinished)."""

    def _new_right_fixation(self, k: int, right: ServoState) -> bool:
        new = k == 0 or right.fixation_id != self._right_id
        self._right_id = right.fixation_id
        return new

    def _fail(self, t: float, right_fixation_id: int, reason: str) -> None:
        self.failures.append({'t': float(t), 'right_fixation_id': int(right_fixation_id), 'reason': reason})
