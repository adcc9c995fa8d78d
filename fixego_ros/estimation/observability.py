"""Whether one step's metric length is observable from the two cameras' rays (DESIGN.md §5).

The coplanarity residuals see only the *directions* of the camera baselines ``T`` (right camera, at the
rig origin) and ``T_L = T + D`` with the lever arm ``D = (R - I) c_L``. Scaling ``T`` by ``k`` keeps both
directions -- and so every residual -- unchanged exactly when ``D`` is parallel to ``T`` (or zero). That
is not only the straight line (``D = 0``): for a rig moving on a planar arc with its heading along the
path (a cart, a tripod steered along a curve: *Ackermann* motion) and the cameras side by side, the chord
``T`` and ``D`` both point at half the turned angle, so the lever arm carries no scale on any step of a
straight-and-arc loop like the papers'. Only motion off that pattern -- heading turned against the path,
curvature changing within a step, the head swaying -- tilts ``D`` away from ``T``; the sine of that angle is
what a step can say about its length. :func:`lever_arm_angle` measures it (:func:`rig_lever_arm_angle` for a
rig's step); :func:`length_invariant` is the exact statement, used by the tests.
"""

from __future__ import annotations

import math

import numpy as np

from fixego_ros.estimation.coplanarity import RayPairs, sampson_residuals
from fixego_ros.geometry.rig import Rig
from fixego_ros.geometry.rotation import Pose


def lever_arm(R: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``D = (R - I) c``: how far a camera at ``c`` (rig frame) moves beyond the rig origin's ``T``."""
    c = np.asarray(c, dtype=float)
    return np.asarray(R, dtype=float) @ c - c


def lever_arm_angle(R: np.ndarray, T: np.ndarray, c: np.ndarray, min_norm: float = 1e-9) -> float:
    """Angle (rad, in [0, pi/2]) between the step's translation ``T`` and the lever arm ``(R - I) c``; 0 when
    the lever arm is too short to tell (no rotation) or ``T`` is zero. 0 means the step's length is not
    observable from the rays; the relative length precision of a step is about ``sigma_dir / sin(angle) *
    |T| / |D|`` for a translation-direction precision ``sigma_dir``."""
    D = lever_arm(R, c)
    T = np.asarray(T, dtype=float)
    nd, nt = float(np.linalg.norm(D)), float(np.linalg.norm(T))
    if not (math.isfinite(nd) and math.isfinite(nt)) or nd < min_norm or nt < min_norm:
        return 0.0
    s = float(np.linalg.norm(np.cross(D / nd, T / nt)))
    return math.asin(min(1.0, s))


def rig_lever_arm_angle(rig: Rig, step: Pose) -> float:
    """:func:`lever_arm_angle` of one rig step (rig frame at t): the right camera's baseline against the left
    camera's extra lever arm ``(R - I)(c_L - c_R)``, for any placement of the two cameras in the rig."""
    c_r, c_l = rig.center('right'), rig.center('left')
    return lever_arm_angle(step.R, step.t + lever_arm(step.R, c_r), c_l - c_r)


def length_invariant(R: np.ndarray, T: np.ndarray, pairs: RayPairs, k: float = 2.0, atol: float = 1e-12) -> bool:
    """True when every coplanarity residual of ``(R, k T)`` has the size of that of ``(R, T)``, so the cost is
    the same: the rays cannot tell the step's length (scale) at this motion. (Sizes, not values: a ``k`` small
    enough to reverse the left camera's baseline flips the sign of its residuals and nothing else.)"""
    r1 = sampson_residuals(R, T, pairs)
    r2 = sampson_residuals(R, k * np.asarray(T, dtype=float), pairs)
    return bool(np.allclose(np.abs(r1), np.abs(r2), rtol=0.0, atol=atol))
