"""Two-frame motion from fixation and flow coplanarity constraints (the papers' "comparison method").

Unknowns: the rig motion ``Pose(R, T)`` from frame t to t+1 (DESIGN.md §5), 6 DOF. Every ray pair
(the fixation point of each camera, and each flow point) gives one normalised coplanarity residual
(:mod:`.coplanarity`). We solve with ``scipy.optimize.least_squares`` (trust-region, optional robust
loss), rotation parameterised as a perturbation of the start. Scale is only observable through the
left camera's lever arm, so the covariance is part of the answer, not an afterthought.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from fixego_ros.estimation.coplanarity import RayPairs, cheirality, numeric_jacobian, sampson_residuals
from fixego_ros.estimation.covariance import VAR_MAX, covariance_from_jacobian, residual_variance
from fixego_ros.estimation.status import StepStatus
from fixego_ros.geometry.rotation import Pose, exp_so3, project_to_so3


@dataclass(frozen=True)
class SolverConfig:
    """Options of the two-frame solve (defaults suit 640x480 at ~1700 px focal length)."""

    sigma: float = 1.0 / 1727.0        # expected angular noise of one ray (rad) = pixel noise / focal
    loss: str = 'linear'               # scipy loss: linear, huber, soft_l1, cauchy, arctan
    loss_scale: float = 3.0            # robust loss knee, in multiples of sigma
    max_nfev: int = 60
    tol: float = 1e-7                  # relative ftol/xtol of the least-squares solve
    prior_step: float = 0.05           # |T| (m) of the canonical starts when nothing better is known
    min_parallax: float = 1e-7         # rad; median rotation-compensated parallax below this = stationary
    max_translation_std: float = 0.5   # m; beyond this the step is WEAK (scale unobserved)


@dataclass
class TwoFrameResult:
    """Motion ``pose`` (t -> t+1), residuals (rad), 6x6 covariance of [rotvec, T], status, message."""

    pose: Pose
    status: StepStatus
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))
    covariance: np.ndarray = field(default_factory=lambda: np.eye(6) * VAR_MAX)
    cost: float = 0.0
    n_constraints: int = 0
    message: str = ''
    cheirality: float = 1.0            # fraction of points triangulated in front of both cameras

    @property
    def translation_std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance)[3:], 0.0, VAR_MAX))


def kabsch_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |a_i - R b_i|^2 (rotation-only fit of ray pairs)."""
    H = b.T @ a
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def essential_start(pairs: RayPairs) -> list[Pose]:
    """Closed-form starts: linear 8-point essential matrix on all rays (lever arm ignored), its four
    (R, t) decompositions filtered by cheirality, each scaled by the 1-D least-squares scale that the
    left camera's lever arm gives (falls back to unit length when that is ill-posed)."""
    if len(pairs) < 8:
        return []
    a, b = pairs.a, pairs.b
    A = np.einsum('ni,nj->nij', a, b).reshape(-1, 9)       # a^T E b = 0
    _, _, Vt = np.linalg.svd(A)
    E = Vt[-1].reshape(3, 3)
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    starts: list[tuple[float, Pose]] = []
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for t in (U[:, 2], -U[:, 2]):
            R = project_to_so3(R)
            starts.append((cheirality(R, t, pairs), Pose(R, t)))
    # Cheirality is fragile with narrow windows and distant points, so keep both signs of the best
    # decompositions; the refinement picks by cost.
    best = max(v for v, _ in starts)
    out = []
    for votes, p in starts:
        if votes < best:
            continue
        t = p.t * _lever_arm_scale(p.R, p.t, pairs)
        out += [Pose(p.R, t), Pose(p.R, -t)]
    return out


def _lever_arm_scale(R: np.ndarray, t_dir: np.ndarray, pairs: RayPairs) -> float:
    """Scale s of ``T = s t_dir`` from rows whose camera centre is off the rig origin (linear in s)."""
    lever = np.linalg.norm(pairs.centers, axis=1) > 0
    if not np.any(lever):
        return 1.0
    a, Rb, c = pairs.a[lever], pairs.b[lever] @ R.T, pairs.centers[lever]
    n = np.cross(a, Rb)
    d = n @ t_dir
    e = np.einsum('ni,ni->n', n, c @ R.T - c)
    den = float(d @ d)
    s = -float(d @ e) / den if den > 1e-18 else 0.0
    return s if np.isfinite(s) and 1e-4 < abs(s) < 1e3 else 1.0


def canonical_starts(step: float) -> list[Pose]:
    """Starts for a rig with no history: standing still in orientation, moving along each axis."""
    out = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            t = np.zeros(3)
            t[axis] = sign * step
            out.append(Pose(np.eye(3), t))
    return out


class TwoFrameSolver:
    """Solve one step from stacked ray pairs; never raises on bad data, never returns NaN."""

    def __init__(self, config: SolverConfig | None = None) -> None:
        self.config = config or SolverConfig()

    def solve(self, pairs: RayPairs, initial: Pose | None = None, prior_t: np.ndarray | None = None,
              prior_sigma_t: float = 0.0) -> TwoFrameResult:
        """Solve one step. With ``prior_t`` and ``prior_sigma_t`` > 0 a weak Gaussian prior on T (e.g. a
        constant-velocity prediction) keeps directions the rays do not observe (the scale under pure
        translation) where the prediction puts them instead of letting the optimiser wander; the
        covariance returned is the rays' alone, so those directions still show as unobserved."""
        prior = (None if prior_t is None or not prior_sigma_t > 0 or not np.all(np.isfinite(prior_t))
                 else (np.asarray(prior_t, dtype=float), float(prior_sigma_t)))
        cfg = self.config
        m = len(pairs)
        if m < 6:
            return TwoFrameResult(Pose.identity(), StepStatus.INSUFFICIENT, n_constraints=m,
                                  message=f'{m} constraints for 6 unknowns')
        # zero flow: a pure rotation explains every pair exactly -> stationary (T unobservable, 0)
        R_rot = kabsch_rotation(pairs.a, pairs.b)
        parallax = np.linalg.norm(np.cross(pairs.a, pairs.b @ R_rot.T), axis=1)
        if float(np.median(parallax)) < cfg.min_parallax:
            return TwoFrameResult(Pose(R_rot, np.zeros(3)), StepStatus.STATIONARY, np.zeros(m),
                                  np.diag([cfg.sigma**2] * 3 + [VAR_MAX] * 3), 0.0, m,
                                  'no parallax: rotation only')
        warm = initial is not None and initial.is_finite()
        best = self._best(pairs, [initial] if warm else self._cold_starts(pairs, R_rot), prior)
        # a poor warm start gets the cold starts too, unless a motion prior anchors it (real time: the cold
        # starts cost ~10 solves; a prior-anchored bad step is flagged below and predicted by the caller)
        if warm and (best is None or (best.cheirality < 0.5 and prior is None)):
            best = self._best(pairs, self._cold_starts(pairs, R_rot) + ([best.pose] if best else []), prior)
        if best is None:
            return TwoFrameResult(initial or Pose.identity(), StepStatus.FAILED, n_constraints=m,
                                  message='optimiser produced no finite solution')
        if best.cheirality < 0.5:
            best.status = StepStatus.DEGENERATE
            best.message += f'; only {100 * best.cheirality:.0f}% of points in front of the cameras'
        return best

    def _cold_starts(self, pairs: RayPairs, R_rot: np.ndarray) -> list[Pose]:
        return essential_start(pairs) + [Pose(R_rot, p.t) for p in canonical_starts(self.config.prior_step)]

    def _best(self, pairs: RayPairs, starts: list[Pose],
              prior: tuple[np.ndarray, float] | None = None) -> TwoFrameResult | None:
        """Refine every start; prefer solutions in front of the cameras, then the lowest cost."""
        best: TwoFrameResult | None = None
        for start in starts:
            res = self._refine(pairs, start, prior)
            if res is None:
                continue
            if best is None or (res.cheirality < 0.5, res.cost) < (best.cheirality < 0.5, best.cost):
                best = res
        return best

    def _refine(self, pairs: RayPairs, start: Pose,
                prior: tuple[np.ndarray, float] | None = None) -> TwoFrameResult | None:
        cfg = self.config
        R0 = start.R
        scale = cfg.sigma

        if prior is None:
            def fun(x: np.ndarray) -> np.ndarray:
                return sampson_residuals(exp_so3(x[:3]) @ R0, x[3:], pairs) / scale

            def jac(x: np.ndarray) -> np.ndarray:
                return numeric_jacobian(R0, x, pairs)[1] / scale
        else:
            t_prior, s_prior = prior
            J_prior = np.hstack([np.zeros((3, 3)), np.eye(3) / s_prior])

            def fun(x: np.ndarray) -> np.ndarray:
                r = sampson_residuals(exp_so3(x[:3]) @ R0, x[3:], pairs) / scale
                return np.concatenate([r, (x[3:] - t_prior) / s_prior])

            def jac(x: np.ndarray) -> np.ndarray:
                return np.vstack([numeric_jacobian(R0, x, pairs)[1] / scale, J_prior])

        x0 = np.concatenate([np.zeros(3), start.t])
        # fixed variable scaling (not 'jac': that inflates steps along the weakly observed scale)
        x_scale = np.concatenate([np.full(3, 1e-2), np.full(3, max(np.linalg.norm(start.t), cfg.prior_step))])
        try:
            with np.errstate(all='ignore'):
                # trf, not MINPACK lm: lm's first step is unbounded and runs off along the weak scale
                sol = least_squares(fun, x0, jac=jac, method='trf', loss=cfg.loss, f_scale=cfg.loss_scale,
                                    max_nfev=cfg.max_nfev, x_scale=x_scale, ftol=cfg.tol, xtol=cfg.tol)
        except (ValueError, np.linalg.LinAlgError):
            return None
        x = sol.x
        if not np.all(np.isfinite(x)):
            return None
        pose = Pose(project_to_so3(exp_so3(x[:3]) @ R0), x[3:].copy())
        r, J = numeric_jacobian(pose.R, np.concatenate([np.zeros(3), pose.t]), pairs)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
            return None
        sigma2 = residual_variance(r, 6, cfg.sigma)
        cov = covariance_from_jacobian(J, sigma2)
        status = StepStatus.OK
        msg = 'converged' if sol.success else f'stopped: {sol.message}'
        if float(np.sqrt(np.max(np.diag(cov)[3:]))) > cfg.max_translation_std:
            status = StepStatus.WEAK
            msg += '; translation weakly observed'
        return TwoFrameResult(pose, status, r, cov, float(0.5 * np.sum(np.square(r / scale))), len(pairs), msg,
                              cheirality(pose.R, pose.t, pairs))
