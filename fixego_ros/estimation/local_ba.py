"""Local bundle adjustment of the latest motion over the last n frames (paper eq. 3, DESIGN.md §5).

At frame t, for every earlier frame j of the window, the composed motion ``P_{j,t} = P_{j,t-1} @
P_{t-1,t}`` gives for each camera the essential relation between its fixation rays at j and t; the
cost is the squared geometric distance (pixels) of the fixation point in the image at t from the
epipolar line of the fixation point at j, in the camera's actual frame at t. Only ``P_{t-1,t}`` is
modified. ``paper`` mode minimises that cost alone from the two-frame estimate with Powell (the
papers' local minimiser; few terms against 6 unknowns, so the answer stays near the start);
``joint`` mode adds the two-frame coplanarity residuals and solves the stacked least squares, with the
two-frame solver's Levenberg-Marquardt (:func:`~fixego_ros.estimation.twoframe.levenberg_marquardt`) or,
with ``backend='scipy'``, ``scipy.optimize.least_squares``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, minimize

from fixego_ros.estimation.coplanarity import RayPairs, sampson_residuals, sampson_residuals_jacobian
from fixego_ros.estimation.twoframe import BACKENDS, levenberg_marquardt
from fixego_ros.geometry.rotation import Pose, exp_so3, project_to_so3, skew

MODES = ('paper', 'joint')
MINIMIZERS = ('powell', 'trf')

# left perturbations exp(+-h e_i), for the central-difference Jacobian of the BA terms (forward differences
# are off by ~1% at small baselines: the distances curve on the scale of |T|)
_H_FD = 1e-7
_FD_ROT = np.array([exp_so3(s * _H_FD * np.eye(3)[i]) for s in (1.0, -1.0) for i in range(3)])
_FD_T = np.vstack([np.zeros((6, 3)), _H_FD * np.eye(3), -_H_FD * np.eye(3)])


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
        self.Sv = skew(self.vj)
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

    def distances_batch(self, Rs: np.ndarray, Ts: np.ndarray) -> np.ndarray:
        """:meth:`distances` (M, k) for M motions at once (Rs (M, 3, 3), Ts (M, 3))."""
        Rjt = self.Rp[None] @ Rs[:, None]                                  # (M, k, 3, 3)
        Tjt = np.einsum('kij,mj->mki', self.Rp, Ts) + self.Tp
        B = Tjt[..., None] + Rjt @ self.c3 - self.c3
        n_j = self.Sv @ B                                                  # (M, k, 3, 1)
        n_c = ((Rjt @ self.Ct).swapaxes(-1, -2) @ n_j)[..., 0]
        num = (n_j[..., 0] * (Rjt @ self.y)[..., 0]).sum(axis=-1)
        den = np.hypot(n_c[..., 0] / self.f[:, 0], n_c[..., 1] / self.f[:, 1])
        ok = den > 1e-15
        return np.where(ok, num / np.where(ok, den, 1.0), 0.0)

    def distances_jacobian(self, R: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`distances` (k,) and their central-difference Jacobian (k, 6) over ``[delta, T]`` with the
        rotation perturbed on the left, ``R -> exp(delta) R`` (one batched evaluation of 13 motions)."""
        Rs = np.concatenate([R[None], _FD_ROT @ R, np.repeat(R[None], 6, axis=0)])
        Ts = np.asarray(T, dtype=float) + np.vstack([np.zeros((1, 3)), _FD_T])
        d = self.distances_batch(Rs, Ts)
        plus = np.concatenate([d[1:4], d[7:10]])
        minus = np.concatenate([d[4:7], d[10:13]])
        return d[0], ((plus - minus) / (2.0 * _H_FD)).T

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
                  sigma: float = 1.0 / 1727.0, minimizer: str = 'powell', max_iter: int = 600,
                  backend: str = 'lm', max_nfev: int = 50) -> BAResult:
    """Refine the latest motion from ``start``. Never increases the mode's own cost.

    ``minimizer`` applies to ``paper`` mode: ``powell`` (the papers' derivative-free local search) or
    ``trf`` (Gauss-Newton with damping: with fewer terms than unknowns it takes the smallest change
    that satisfies them). ``joint`` mode always solves its least squares that way. ``backend`` picks the
    least-squares implementation: ``lm`` (the two-frame solver's Levenberg-Marquardt) or ``scipy``
    (``least_squares``, trust-region reflective); ``max_nfev`` bounds its residual evaluations.
    """
    if mode not in MODES:
        raise ValueError(f'BA mode must be one of {MODES}, got {mode!r}')
    if minimizer not in MINIMIZERS:
        raise ValueError(f'BA minimizer must be one of {MINIMIZERS}, got {minimizer!r}')
    if backend not in BACKENDS:
        raise ValueError(f'BA backend must be one of {BACKENDS}, got {backend!r}')
    R0 = start.R
    f_mean = float(np.mean(problem.f)) if len(problem) else 1.0 / sigma
    ba_scale = f_mean * sigma
    joint = mode == 'joint' and pairs is not None and len(pairs) > 0

    def pose_of(x: np.ndarray) -> Pose:
        return Pose(exp_so3(x[:3]) @ R0, x[3:])

    def residuals_of(p: Pose) -> np.ndarray:
        parts = [problem.distances(p.R, p.t) / ba_scale] if len(problem) else []
        if joint:
            parts.append(sampson_residuals(p.R, p.t, pairs) / sigma)
        return np.concatenate(parts) if parts else np.zeros(0)

    def cost_of(p: Pose) -> float:
        if mode == 'paper':
            return float(np.sum(np.square(problem.distances(p.R, p.t))))
        return float(np.sum(np.square(residuals_of(p))))

    def cost(x: np.ndarray) -> float:
        return cost_of(pose_of(x))

    x0 = np.concatenate([np.zeros(3), start.t])
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
                p, msg = (pose_of(sol.x * s) if np.all(np.isfinite(sol.x)) else None), str(sol.message)
            elif backend == 'lm':
                # (paper mode: only the BA terms, the same minimiser as cost())
                p, msg = _least_squares_lm(problem, start, pairs if joint else None, sigma, ba_scale, max_nfev)
            else:
                sol = least_squares(lambda x: residuals_of(pose_of(x)), x0, method='trf', x_scale='jac',
                                    max_nfev=max_nfev)
                p, msg = (pose_of(sol.x) if np.all(np.isfinite(sol.x)) else None), str(sol.message)
        except (ValueError, np.linalg.LinAlgError) as e:
            return BAResult(start, before, before, len(problem), mode, False, f'optimiser error: {e}')
        after = cost_of(p) if p is not None else np.inf
    if not np.isfinite(after) or after > before:
        return BAResult(start, before, before, len(problem), mode, False, 'no improvement; kept start')
    return BAResult(Pose(project_to_so3(p.R), p.t.copy()), before, after, len(problem), mode, after < before, msg)


def _least_squares_lm(problem: BAProblem, start: Pose, pairs: RayPairs | None, sigma: float, ba_scale: float,
                      max_nfev: int) -> tuple[Pose | None, str]:
    """The least-squares modes with :func:`levenberg_marquardt`: the BA terms in units of the ray noise
    (batched central differences), plus the coplanarity residuals when ``pairs`` is given (analytic
    Jacobian). Jacobian scaling as the scipy path: the BA starts next to its answer, at the two-frame
    estimate, so the weak directions the two-frame solve guards against are not an issue here."""
    scaled = pairs.reweighted(1.0 / sigma) if pairs is not None else None

    def fun(R: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, J = problem.distances_jacobian(R, T)
        if scaled is None:
            return r / ba_scale, J / ba_scale
        rs, Js = sampson_residuals_jacobian(R, T, scaled)
        return np.concatenate([r / ba_scale, rs]), np.vstack([J / ba_scale, Js])

    sol = levenberg_marquardt(fun, start.R, start.t, 'jac', tol=1e-8, max_nfev=max_nfev)
    if sol is None or not (np.all(np.isfinite(sol.R)) and np.all(np.isfinite(sol.T))):
        return None, 'no finite solution'
    return Pose(sol.R, sol.T), sol.message
