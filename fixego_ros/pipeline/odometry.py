"""External speed aid: a nav_msgs/Odometry twist (e.g. wheel odometry) as a rig-frame velocity sample.

ROS-free (messages are read by attribute, so rclpy messages and rosbags' decoded ones both work). REP-105
puts an Odometry twist in its child frame; the only child frame accepted is the robot's base
(``base_frame``, default ``base_link``: x forward, y left, z up), or an empty one, taken to mean it. The
twist becomes the velocity of the rig origin in the rig frame (x right, y down, z forward) through the
rig's mount (``rig_in_base_link``: rotation ``R``, rig origin ``r`` in the base frame):
``v_rig = Rᵀ (v_base + ω × r)``. The covariance is ``Rᵀ (C_v + [r]× C_ω [r]×ᵀ) R`` (linear and angular
blocks taken as independent; the cross blocks are ignored). ``ω`` is the twist's angular part as given:
a source that does not measure it (all zeros) contributes no lever-arm velocity, and an all-zero angular
covariance adds no variance (ω taken as exact), so with a mount offset from the base origin a robot that
turns must report ω. Without a mount (the default axes, origin at the rig origin) ``r = 0``: only the
linear part counts.

A sample is rejected whole, with an :class:`OdometryError` whose ``kind`` names the check, when its
stamp is not finite, goes backwards (or repeats), is older than ``max_age_s`` relative to the newest
frame, when the velocity is not finite, when the covariance is not 36 finite numbers, has a negative
variance or is not positive semi-definite, or when the child frame is another frame. An all-zero linear
covariance means "unknown" in ROS: it becomes ``default_std``² on each axis. Nothing non-finite is ever
passed on.

Vergence (:func:`vergence_from_msg`): the right camera's fixation point measured by a vergence step (the left
camera_node, or ``fixego sim``) as a geometry_msgs/PoseWithCovarianceStamped in the
rig frame; the position and its 3x3 covariance block go to ``Estimator.add_fixation_point``, the
orientation is not used. estimator_node and ``fixego replay`` share this one conversion.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from fixego_ros.geometry.rotation import RIG_TO_BASE, Pose, skew
from fixego_ros.pipeline.messages import stamp_to_sec

ODOMETRY_TYPE = 'nav_msgs/msg/Odometry'
VERGENCE_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
VERGENCE_FRAMES = ('rig', '')   # the vergence point is in the rig frame ('' taken to mean it)
MIN_STD = 1e-4   # m/s: variances are floored at MIN_STD² so the estimator can always invert the covariance

# estimator_node parameters of the speed aid (name -> (default, description)); fixego replay uses the defaults
SPEED_PARAMS: dict[str, tuple[object, str]] = {
    'speed_topic': ('', "nav_msgs/Odometry of an external speed source (e.g. wheel odometry; twist in base_frame) "
                        "used as a scale aid; '' = off"),
    'speed_default_std': (0.1, 'm/s; std of each velocity axis when the Odometry twist covariance is all zeros '
                               '(unknown)'),
    'speed_max_age_s': (0.2, 's; a speed sample older than this relative to the newest frame is not used '
                             '(dropped and counted)'),
}


class OdometryError(ValueError):
    """An Odometry sample we cannot use; ``kind`` says which check failed: stamp, order, stale, frame,
    velocity, covariance."""

    def __init__(self, message: str, kind: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class VelocitySample:
    """Velocity of the rig origin in the rig frame at ``stamp`` (m/s) and its 3x3 covariance ((m/s)²)."""

    stamp: float
    v_rig: np.ndarray
    cov_rig: np.ndarray


def covariance_block(cov6: np.ndarray, what: str) -> np.ndarray:
    """The leading 3x3 block (linear velocity, or position) of a row-major 6x6 ROS covariance;
    :class:`OdometryError` (kind ``covariance``) when it is not 36 numbers or the block is not finite."""
    if cov6.size != 36:
        raise OdometryError(f'{what} has {cov6.size} entries, expected 36 (6x6 row-major)', 'covariance')
    c = cov6.reshape(6, 6)[:3, :3].copy()
    if not np.all(np.isfinite(c)):
        raise OdometryError(f'{what} not finite', 'covariance')
    return c


def psd_eigen(c: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(symmetrised c, eigenvalues ascending, eigenvectors); :class:`OdometryError` (kind ``covariance``) when
    c is not positive semi-definite beyond round-off."""
    c = 0.5 * (c + c.T)
    w, V = np.linalg.eigh(c)
    if w[0] < -1e-9 * max(1.0, w[-1]):
        raise OdometryError(f'{what} not positive semi-definite (eigenvalues {w.tolist()})', 'covariance')
    return c, w, V


def _vector3(v: Any, what: str) -> np.ndarray:
    if hasattr(v, 'x'):
        v = (v.x, v.y, v.z)
    try:
        out = np.asarray(v, dtype=float).reshape(3)
    except (TypeError, ValueError) as e:
        raise OdometryError(f'{what} not numeric: {e}', 'velocity') from None
    if not np.all(np.isfinite(out)):
        raise OdometryError(f'non-finite {what} {out.tolist()}', 'velocity')
    return out


def _psd_floor(c: np.ndarray, what: str) -> np.ndarray:
    if np.any(np.diag(c) < 0):
        raise OdometryError(f'negative {what} variance {np.diag(c).tolist()}', 'covariance')
    c, w, V = psd_eigen(c, f'twist covariance ({what})')
    return (V * np.maximum(w, MIN_STD ** 2)) @ V.T if w[0] < MIN_STD ** 2 else c


def twist_to_rig(linear: Any, covariance: Any, default_std: float, angular: Any = None,
                 mount: Pose | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(v_rig, cov_rig) of a base-frame twist (x, y, z or a Vector3 each) and its row-major 6x6 covariance:
    the velocity of the rig origin in the rig frame (see the module docstring; ``mount`` None = the default
    axes, rig origin at the base origin). :class:`OdometryError` (kind ``velocity`` / ``covariance``) when
    they are unusable."""
    v_base = _vector3(linear, 'linear velocity')
    w_base = np.zeros(3) if angular is None else _vector3(angular, 'angular velocity')
    try:
        cov6 = np.asarray(covariance, dtype=float)
    except (TypeError, ValueError) as e:
        raise OdometryError(f'twist covariance not numeric: {e}', 'covariance') from None
    c = covariance_block(cov6, 'twist covariance')
    if not math.isfinite(default_std) or default_std <= 0:
        raise ValueError(f'speed_default_std must be a positive number of m/s, got {default_std}')
    c = np.eye(3) * default_std ** 2 if not np.any(c) else _psd_floor(c, 'velocity')   # zeros: "unknown"
    if mount is None:
        v_rig = RIG_TO_BASE.T @ v_base
        cov_rig = RIG_TO_BASE.T @ c @ RIG_TO_BASE
        return v_rig, 0.5 * (cov_rig + cov_rig.T)
    R, r = mount.R, mount.t
    v_origin = v_base + np.cross(w_base, r)          # velocity of the rig origin, base axes
    c_w = cov6.reshape(6, 6)[3:, 3:]
    if not np.all(np.isfinite(c_w)):
        raise OdometryError('twist covariance (angular) not finite', 'covariance')
    if np.any(c_w) and np.any(r):
        S = skew(r)                                   # w x r = -[r]x w
        c = c + S @ _psd_floor(c_w, 'angular') @ S.T
    cov_rig = R.T @ c @ R
    return R.T @ v_origin, 0.5 * (cov_rig + cov_rig.T)


@dataclass(frozen=True)
class SpeedSettings:
    """The speed aid's parameters (:data:`SPEED_PARAMS`); ``topic`` '' = off."""

    topic: str = str(SPEED_PARAMS['speed_topic'][0])
    default_std: float = float(SPEED_PARAMS['speed_default_std'][0])
    max_age_s: float = float(SPEED_PARAMS['speed_max_age_s'][0])
    base_frame: str = 'base_link'

    def __post_init__(self) -> None:
        if not (math.isfinite(self.default_std) and self.default_std > 0):
            raise ValueError(f'speed_default_std must be a positive number of m/s, got {self.default_std}')
        if not self.max_age_s > 0:
            raise ValueError(f'speed_max_age_s must be > 0 s, got {self.max_age_s}')

    @classmethod
    def from_getter(cls, g: Callable[[str], object], base_frame: str = 'base_link') -> SpeedSettings:
        return cls(str(g('speed_topic')), float(g('speed_default_std')), float(g('speed_max_age_s')), base_frame)


class SpeedInput:
    """Turns a stream of Odometry messages into :class:`VelocitySample` s, in stamp order.

    ``frame_stamp`` (the newest frame the estimator has) drops samples older than ``max_age_s`` relative to
    it. ``assumed_frame`` is set when a sample had no child frame and was taken as ``base_frame``.
    """

    def __init__(self, settings: SpeedSettings = SpeedSettings(), mount: Pose | None = None) -> None:
        self.settings = settings
        self.mount = mount            # the rig frame in the base frame (Rig.mount; None = default axes)
        self.base_frame, self.default_std, self.max_age_s = (settings.base_frame, settings.default_std,
                                                             settings.max_age_s)
        self.last_stamp: float | None = None
        self.assumed_frame = False

    def reset(self) -> None:
        self.last_stamp = None

    def convert(self, stamp: float, child_frame_id: str, linear: Any, covariance: Any,
                frame_stamp: float | None = None, angular: Any = None) -> VelocitySample:
        if not math.isfinite(stamp):
            raise OdometryError(f'non-finite stamp {stamp}', 'stamp')
        if child_frame_id and child_frame_id != self.base_frame:
            raise OdometryError(f"twist in frame '{child_frame_id}', expected '{self.base_frame}' (REP-105: the "
                                'twist is in child_frame_id; set base_frame to the frame the rig file\'s '
                                'rig_in_base_link is given in)', 'frame')
        if self.last_stamp is not None and stamp <= self.last_stamp:
            raise OdometryError(f'stamp {stamp:.6f} s not after the previous sample ({self.last_stamp:.6f} s)',
                                'order')
        if frame_stamp is not None and stamp < frame_stamp - self.max_age_s:
            raise OdometryError(f'sample at {stamp:.3f} s is {frame_stamp - stamp:.3f} s older than the newest '
                                f'frame (speed_max_age_s {self.max_age_s:g})', 'stale')
        v, cov = twist_to_rig(linear, covariance, self.default_std, angular, self.mount)
        self.last_stamp = stamp
        if not child_frame_id:
            self.assumed_frame = True
        return VelocitySample(float(stamp), v, cov)

    def from_msg(self, msg: Any, frame_stamp: float | None = None) -> VelocitySample:
        """Sample of a nav_msgs/Odometry message (rclpy or rosbags)."""
        return self.convert(stamp_to_sec(msg.header.stamp), str(msg.child_frame_id), msg.twist.twist.linear,
                            msg.twist.covariance, frame_stamp, msg.twist.twist.angular)


def vergence_from_msg(msg: Any) -> tuple[float, np.ndarray, np.ndarray]:
    """(stamp s, point (3,) m, covariance 3x3 m²) of a vergence PoseWithCovarianceStamped (rclpy or rosbags):
    the position block of the 6x6 pose covariance. ValueError, saying why, for a message the estimator must
    not get (it would anchor the scale on it): another frame, a non-finite value, a covariance that is not
    36 numbers or not positive semi-definite. A zero stamp is accepted (it still names a frame)."""
    frame_id = str(msg.header.frame_id)
    if frame_id not in VERGENCE_FRAMES:
        raise ValueError(f"vergence point in frame '{frame_id}', expected 'rig'")
    stamp = stamp_to_sec(msg.header.stamp)
    p = msg.pose.pose.position
    try:
        point = np.array([p.x, p.y, p.z], dtype=float)
        cov6 = np.asarray(msg.pose.covariance, dtype=float)
    except (TypeError, ValueError) as e:
        raise ValueError(f'vergence message not numeric: {e}') from None
    if not math.isfinite(stamp):
        raise ValueError(f'vergence message with non-finite stamp {stamp}')
    if not np.all(np.isfinite(point)):
        raise ValueError(f'vergence point not finite: {point.tolist()}')
    cov = covariance_block(cov6, 'vergence point covariance')
    psd_eigen(cov, 'vergence point covariance')
    return stamp, point, cov
