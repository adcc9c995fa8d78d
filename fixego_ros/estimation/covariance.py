"""Covariance from a least-squares Jacobian, with weakly observed directions capped, never NaN/inf."""

from __future__ import annotations

import math

import numpy as np

VAR_MAX = 1.0e6  # variance reported for an unobserved direction (m^2 or rad^2)


def covariance_from_jacobian(J: np.ndarray, sigma2: float, var_max: float = VAR_MAX) -> np.ndarray:
    """``sigma2 (J^T J)^-1`` through an eigen-decomposition; null directions get ``var_max``."""
    n = J.shape[1]
    if J.size == 0 or not np.all(np.isfinite(J)) or not np.isfinite(sigma2):
        return np.eye(n) * var_max
    H = J.T @ J
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    floor = max(sigma2, 1e-30) / var_max
    cov = (V * (sigma2 / np.maximum(w, floor))) @ V.T
    return 0.5 * (cov + cov.T)


def residual_variance(r: np.ndarray, n_params: int, prior_sigma: float) -> float:
    """Residual variance ``sum r^2 / (m - n)``; the prior noise variance when there is no redundancy.

    The prior is also a floor: with perfect data the covariance then reflects the expected sensor
    noise rather than collapsing to zero.
    """
    dof = len(r) - n_params
    prior = prior_sigma**2
    if dof <= 0:
        return prior
    return max(float(np.sum(np.square(r)) / dof), prior)


def std_along(point: np.ndarray, cov: np.ndarray) -> float:
    """First-order std of a measured 3-D ``point`` along its own direction from the origin (a vergence measurement:
    along the right camera's fixation ray), from its 3x3 ``cov``."""
    p = np.asarray(point, float)
    u = p / max(float(np.linalg.norm(p)), 1e-9)
    return math.sqrt(max(float(u @ np.asarray(cov, float) @ u), 0.0))


def checked_measurement(stamp: float, value: np.ndarray, cov: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """A 3-vector aid measurement (velocity, fixation point) and its 3x3 covariance, checked as the back ends take
    them: ValueError on a non-finite stamp, value or covariance, or a covariance that is not positive definite."""
    v = np.asarray(value, float).reshape(3)
    c = np.asarray(cov, float).reshape(3, 3)
    if not (np.isfinite(stamp) and np.all(np.isfinite(v)) and np.all(np.isfinite(c))):
        raise ValueError(f'{what} with non-finite stamp, value or covariance')
    if np.any(np.linalg.eigvalsh(0.5 * (c + c.T)) <= 0):
        raise ValueError(f'{what} covariance must be positive definite')
    return v, c
