"""Local bundle adjustment of the latest motion over the last n frames (paper eq. 3, DESIGN.md §5).

At frame t, for every earlier frame j of the window, the composed motion ``P_{j,t} = P_{j,t-1} @
P_{t-1,t}`` gives for each camera the essential relation between its fixation rays at j and t; the
cost is the squared geometric distance (pixels) of the fixation point in the image at t from the
epipolar line of the fixation point at j, in the camera's actual frame at t. Only ``P_{t-1,t}`` is
modified. ``paper`` mode minimises that cost alone from the two-frame estimate with Powell (the
papers' local minimiser; few terms against 6 unknowns, so the answer stays near the start);
``joint`` mode adds the two-frame coplanarity residuals and solves the stacked least squares.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, minimize

from fixego_ros.estimation.coplanarity import RayPairs, sampson_residuals
from fixego_ros.geometry.rotation import Pose, exp_so3, project_to_so3, skew

MODES = ('paper', 'joint')
MINIMIZERS = ('powell', 'trf')


@dataclass(frozen=True)
class BATerm:
    """One epipolar term: the fixation ray at an earlier frame j and at t, for one camera."""

    prefix: Pose           # P_{j,t-1}: composed (fixed) motion from j to t-1
    ray_j: np.ndarray      # fixation ray at j (rig frame at j)
    ray_t: np.ndarray      # fixation ray at t (rig frame at t)
    center: np.ndarray     # camera centre in the rig frame
    cam_to_rig_t: np.ndarray  # camera optical frame at t -> rig frame
    fx: float
    fy: float


class BAProblem:
    """Vectorised residuals of a set of :class:`BATerm` as a function of the latest motion."""

    def __init__(self, terms: list[BATerm]) -> None:
        self.terms = terms
        k = len(terms)
        self.Rp = np.array([t.prefix.R for t in terms]).reshape(k, 3, 3)
        self.Tp = np.array([t.prefix.t for t in terms]).reshape(k, 3)
        self.vj = np.array([t.ray_j for t in terms]).reshape(k, 3)
        self.c = np.array([t.center for t in terms]).reshape(k, 3)
        self.Ct = np.array([t.cam_to_rig_t for t in terms]).reshape(k, 3, 3)
        dt = np.einsum('kji,kj->ki', self.Ct, np.array([t.ray_t for t in terms]).reshape(k, 3))
        x = dt / dt[:, 2:3]                                        # fixation at t, normalised image
        self.y = np.einsum('kij,kj->ki', self.Ct, x)[:, :, None]   # the same, rotated into rig frame t
        self.Sv = np.array([skew(v) for v in self.vj]).reshape(k, 3, 3)
        self.f = np.array([[t.fx, t.fy] for t in terms]).reshape(k, 2)
        self.c3 = self.c[:, :, None]

    def __len__(self) -> int:
        return len(self.terms)

    def distances(self, R: np.ndarray, T: np.ndarray) -> np.ndarray:
        """Signed point-to-epipolar-line distances (pixels), one per term."""
        Rjt = self.Rp @ R                                          # P_{j,t} = P_{j,t-1} @ (R, T)
        Tjt = self.Rp @ T + self.Tp
        B = Tjt[:, :, None] + Rjt @ self.c3 - self.c3             # camera baseline j -> t, frame j
        n_j = self.Sv @ B                                          # epipolar plane normal, frame j
        M = Rjt @ self.Ct                                          # camera frame at t -> rig frame j
        n_c = (M.transpose(0, 2, 1) @ n_j)[:, :, 0]                # normal in camera coords at t
        num = (n_j[:, :, 0] * (Rjt @ self.y)[:, :, 0]).sum(axis=1)
        den = np.hypot(n_c[:, 0] / self.f[:, 0], n_c[:, 1] / self.f[:, 1])
        ok = den > 1e-15
        return np.where(ok, num / np.where(ok, den, 1.0), 0.0)

    def cost(self, pose: Pose) -> float:
        """Paper eq. (3): sum of squared distances (px^2)."""
        return float(np.sum(np.square(self.distances(pose.R, pose.t))))


@dataclass
class BAResult:
    pose: Pose
    cost_before: float
    cost_after: float
    n_terms: int
    mode: str
    improved: bool
    message: str = ''


def refine_latest(problem: BAProblem, start: Pose, mode: str = 'paper', pairs: RayPairs | None = None,
                  sigma: float = 1.0 / 1727.0, minimizer: str = 'powell', max_iter: int = 600) -> BAResult:
    """Refine the latest motion from ``start``. Never increases the mode's own cost.

    ``minimizer`` applies to ``paper`` mode: ``powell`` (the papers' derivative-free local search) or
    ``trf`` (Gauss-Newton trust region: with fewer terms than unknowns it takes the smallest change
    that satisfies them). ``joint`` mode always uses ``trf``.
    """
    if mode not in MODES:
        raise ValueError(f'BA mode must be one of {MODES}, got {mode!r}')
    if minimizer not in MINIMIZERS:
        raise ValueError(f'BA minimizer must be one of {MINIMIZERS}, got {minimizer!r}')
    R0 = start.R
    f_mean = float(np.mean(problem.f)) if len(problem) else 1.0 / sigma

    def pose_of(x: np.ndarray) -> Pose:
        return Pose(exp_so3(x[:3]) @ R0, x[3:])

    def residuals(x: np.ndarray) -> np.ndarray:
        p = pose_of(x)
        parts = [problem.distances(p.R, p.t) / (f_mean * sigma)] if len(problem) else []
        if mode == 'joint' and pairs is not None and len(pairs):
            parts.append(sampson_residuals(p.R, p.t, pairs) / sigma)
        return np.concatenate(parts) if parts else np.zeros(0)

    x0 = np.concatenate([np.zeros(3), start.t])
    if mode == 'paper':
        def cost(x: np.ndarray) -> float:
            p = pose_of(x)
            return float(np.sum(np.square(problem.distances(p.R, p.t))))
    else:
        def cost(x: np.ndarray) -> float:
            return float(np.sum(np.square(residuals(x))))

    before = cost(x0)
    if len(problem) == 0 or not np.isfinite(before):
        return BAResult(start, before, before, len(problem), mode, False, 'nothing to adjust')
    with np.errstate(all='ignore'):
        try:
            if mode == 'paper' and minimizer == 'powell':
                # Powell in scaled coordinates: rotation in units of 1 mrad, translation in units of 1% of |T|
                s = np.concatenate([np.full(3, 1e-3), np.full(3, 1e-2 * max(np.linalg.norm(start.t), 1e-3))])
                sol = minimize(lambda z: cost(z * s), x0 / s, method='Powell',
                               options={'xtol': 1e-3, 'ftol': 1e-8, 'maxfev': max_iter})
                x = sol.x * s
                msg = str(sol.message)
            else:
                sol = least_squares(residuals, x0, method='trf', x_scale='jac', max_nfev=50)
                # (paper mode with trf: residuals() holds only the BA terms, same minimiser as cost())
                x, msg = sol.x, str(sol.message)
        except (ValueError, np.linalg.LinAlgError) as e:
            return BAResult(start, before, before, len(problem), mode, False, f'optimiser error: {e}')
    after = cost(x) if np.all(np.isfinite(x)) else np.inf
    if not np.isfinite(after) or after > before:
        return BAResult(start, before, before, len(problem), mode, False, 'no improvement; kept start')
    p = pose_of(x)
    return BAResult(Pose(project_to_so3(p.R), p.t.copy()), before, after, len(problem), mode, after < before, msg)
