"""Cramér–Rao bound of the two-frame motion from coplanarity constraints.

With ray noise of angular std sigma, each normalised (Sampson) residual has unit variance per sigma to
first order, so the Fisher information of [rotation vector, T] is ``J^T J / sigma^2`` with J the
residual Jacobian at the true motion and noise-free rays (depths eliminated, as in Gauss–Helmert).
Its inverse bounds the covariance of any unbiased two-frame estimator using the same constraints.
"""

from __future__ import annotations

import numpy as np

from fixego_ros.estimation.coplanarity import RayPairs, numeric_jacobian
from fixego_ros.estimation.covariance import covariance_from_jacobian
from fixego_ros.geometry.rotation import Pose


def two_frame_crb(true_motion: Pose, clean_pairs: RayPairs, sigma: float) -> np.ndarray:
    """6x6 CRB covariance over [rotation vector, T] (rotation perturbation on the left of R)."""
    _, J = numeric_jacobian(true_motion.R, np.concatenate([np.zeros(3), true_motion.t]), clean_pairs,
                            h_rot=1e-8, h_trans=1e-8 * max(1.0, float(np.linalg.norm(true_motion.t))))
    return covariance_from_jacobian(J, sigma**2)


def relative_bounds(true_motion: Pose, crb: np.ndarray) -> tuple[float, float]:
    """RMS bounds of the papers' relative errors: (rotation, translation) = sqrt(trace)/|true|."""
    theta = float(np.linalg.norm(true_motion.rvec()))
    tnorm = float(np.linalg.norm(true_motion.t))
    return (float(np.sqrt(np.trace(crb[:3, :3]))) / max(theta, 1e-12),
            float(np.sqrt(np.trace(crb[3:, 3:]))) / max(tnorm, 1e-12))
