"""Rotations and rigid motions (SE(3)) used everywhere: one implementation, tested by property tests.

Convention for a motion ``Pose(R, t)``: it maps coordinates in the *later/child* frame into the
*earlier/parent* frame, ``x_parent = R @ x_child + t``. So the rig motion from frame i to i+1 of
DESIGN.md §5 (rig axes at i+1 expressed at i, origin of i+1 expressed at i) is exactly ``Pose(R, T)``,
and motions chain by ``P_{j,t} = P_{j,j+1} @ P_{j+1,j+2} @ ... @ P_{t-1,t}``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

# base_link axes (x fwd, y left, z up) expressed from rig axes (x right, y down, z fwd): v_base = M v_rig
RIG_TO_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: ``skew(a) @ b == np.cross(a, b)``; for ``v`` of shape (..., 3), one per row."""
    v = np.asarray(v, dtype=float)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)


def rot_x(a: float) -> np.ndarray:
    """Rotation about x by ``a`` rad (right-handed)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation about y by ``a`` rad (right-handed)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation about z by ``a`` rad (right-handed)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def exp_so3(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis * angle), Rodrigues' formula (hot path: no scipy)."""
    x, y, z = (float(v) for v in rvec)
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = th2**0.5
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th2
    return np.array([
        [1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
        [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
        [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)],
    ])


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, angle in [0, pi]) of a rotation matrix."""
    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def project_to_so3(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (removes drift after many products)."""
    u, _, vt = np.linalg.svd(R)
    return rotation_from_svd(u, vt)


def rotation_from_svd(u: np.ndarray, vt: np.ndarray) -> np.ndarray:
    """``u @ vt``, the last column of ``u`` flipped when that product is a reflection: the rotation nearest to a
    matrix from its SVD factors (and Kabsch's fit from its cross-covariance's).

    The sign comes from the product's cofactor determinant (exactly +-1 up to rounding for an orthogonal matrix),
    not from LAPACK's LU, and the flip is a negation: the same bits as ``u @ diag(1, 1, sign(det)) @ vt`` at two
    thirds of its cost (every pose that leaves the smoother's graph takes one: ~60,000 calls per captured demo run).
    ``u`` C-contiguous, as that product's left factor was."""
    m = u @ vt
    (a, b, c), (d, e, f), (g, h, i) = m.tolist()
    if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0.0:
        return m
    u = u.copy()
    u[:, 2] = -u[:, 2]
    return u @ vt


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix, w >= 0.

    SciPy's method (``Rotation.from_matrix``: the largest of the trace and the diagonal picks the formula) in plain
    floats, the same bits for a rotation matrix at ~1 us instead of ~30: every pose message and TUM line takes one,
    and each smoother answer revises ~100 path poses (docs/results.md "Stop 46"). Non-finite input goes to SciPy."""
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(R, dtype=float).tolist()
    tr = a + e + i
    if not math.isfinite(tr + b + c + d + f + g + h):
        q = Rotation.from_matrix(R).as_quat()
        return -q if q[3] < 0 else q
    if tr >= a and tr >= e and tr >= i:
        x, y, z, w = h - f, c - g, d - b, 1.0 + tr
    elif a >= e and a >= i:
        x, y, z, w = 1.0 - tr + 2.0 * a, d + b, g + c, h - f
    elif e >= i:
        x, y, z, w = b + d, 1.0 - tr + 2.0 * e, h + f, c - g
    else:
        x, y, z, w = c + g, f + h, 1.0 - tr + 2.0 * i, d - b
    n = math.sqrt(x * x + y * y + z * z + w * w)
    q = np.array([x / n, y / n, z / n, w / n])
    return -q if q[3] < 0 else q


def from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion (x, y, z, w); normalises it, rejects zero or non-finite input."""
    q = np.asarray(q, dtype=float)
    n = np.linalg.norm(q)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or n < 1e-9:
        raise ValueError(f'not a valid quaternion (x, y, z, w): {q.tolist()}')
    return Rotation.from_quat(q / n).as_matrix()


def rotation_angle(R: np.ndarray) -> float:
    """Angle of a rotation matrix in rad."""
    return float(np.linalg.norm(log_so3(R)))


@dataclass(frozen=True)
class Pose:
    """Rigid motion ``x_parent = R x_child + t`` (see module docstring)."""

    R: np.ndarray
    t: np.ndarray

    @staticmethod
    def identity() -> Pose:
        return Pose(np.eye(3), np.zeros(3))

    @staticmethod
    def from_rvec(rvec: np.ndarray, t: np.ndarray) -> Pose:
        return Pose(exp_so3(rvec), np.asarray(t, dtype=float).copy())

    @staticmethod
    def from_matrix(M: np.ndarray) -> Pose:
        return Pose(np.asarray(M[:3, :3], dtype=float).copy(), np.asarray(M[:3, 3], dtype=float).copy())

    def __matmul__(self, other: Pose) -> Pose:
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def inverse(self) -> Pose:
        return Pose(self.R.T, -self.R.T @ self.t)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Map points (3,) or (N, 3) from the child frame into the parent frame."""
        return np.asarray(x) @ self.R.T + self.t

    def rvec(self) -> np.ndarray:
        return log_so3(self.R)

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.t
        return M

    def is_finite(self) -> bool:
        return bool(np.all(np.isfinite(self.R)) and np.all(np.isfinite(self.t)))

    def normalized(self) -> Pose:
        return Pose(project_to_so3(self.R), self.t)


def compose_all(motions: list[Pose]) -> Pose:
    """``motions[0] @ motions[1] @ ...`` (identity for an empty list)."""
    out = Pose.identity()
    for m in motions:
        out = out @ m
    return out


def default_mount() -> Pose:
    """The rig frame in ``base_link`` when the rig file gives no ``rig_in_base_link`` (DESIGN.md §2): same
    origin, x forward = rig z, y left = -rig x, z up = -rig y."""
    return Pose(RIG_TO_BASE.copy(), np.zeros(3))


def rig_pose_to_base_link(pose_rig: Pose, mount: Pose | None = None) -> Pose:
    """Pose of the rig at t in the rig frame at 0 -> pose of base_link in odom (odom = base_link at 0).

    ``mount`` is the rig frame in ``base_link`` (``x_base = mount.R x_rig + mount.t``; the rig file's
    ``rig_in_base_link``); None = the default axes, computed exactly as before mounts existed. With a mount
    the base_link motion is the rig motion seen from base_link: ``mount @ pose_rig @ mount⁻¹``."""
    if mount is None:
        return Pose(RIG_TO_BASE @ pose_rig.R @ RIG_TO_BASE.T, RIG_TO_BASE @ pose_rig.t)
    return mount @ pose_rig @ mount.inverse()


def base_link_pose_to_rig(pose_base: Pose, mount: Pose | None = None) -> Pose:
    """Inverse of :func:`rig_pose_to_base_link` (same ``mount``)."""
    if mount is None:
        return Pose(RIG_TO_BASE.T @ pose_base.R @ RIG_TO_BASE, RIG_TO_BASE.T @ pose_base.t)
    return mount.inverse() @ pose_base @ mount


def base_link_covariance(cov_rig: np.ndarray, pose_rig: Pose, mount: Pose | None = None) -> np.ndarray:
    """First-order 6x6 covariance over [position, rotation] (ROS order, ``odom`` axes) of
    ``rig_pose_to_base_link(pose_rig, mount)``, from the estimator's covariance over [rotation, position] of
    ``pose_rig`` (world-frame rotation perturbation). A mount translation adds the lever arm: the base_link
    origin moves when the rig rotates about its own origin."""
    R_m = RIG_TO_BASE if mount is None else mount.R
    J = np.zeros((6, 6))
    J[:3, 3:] = R_m                   # position rows from the rig position block
    J[3:, :3] = R_m                   # rotation rows from the rig rotation block
    if mount is not None and np.any(mount.t):
        a = pose_rig.R @ mount.R.T @ mount.t
        J[:3, :3] = R_m @ skew(a)     # t_base = R_m t + t_m - R_m R R_m^T t_m, perturbed R -> exp(d)R
    cov = J @ np.asarray(cov_rig, dtype=float) @ J.T
    return 0.5 * (cov + cov.T)


def rotation_error_paper(R_est: np.ndarray, R_true: np.ndarray) -> float:
    """Papers' rotation error ``||theta_hat r_hat - theta r|| / |theta|`` (axis-angle vectors)."""
    true = log_so3(R_true)
    theta = np.linalg.norm(true)
    return float(np.linalg.norm(log_so3(R_est) - true) / max(theta, 1e-12))


def translation_error_paper(t_est: np.ndarray, t_true: np.ndarray) -> float:
    """Papers' translation error ``||T_hat - T|| / ||T||``."""
    return float(np.linalg.norm(np.asarray(t_est) - t_true) / max(np.linalg.norm(t_true), 1e-12))
