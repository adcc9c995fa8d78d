"""Two-frame motion from fixation and flow coplanarity constraints (the papers' "comparison method").

Unknowns: the rig motion ``Pose(R, T)`` from frame t to t+1 (DESIGN.md §5), 6 DOF. Every ray pair
(the fixation point of each camera, and each flow point) gives one normalised coplanarity residual
(:mod:`.coplanarity`). We solve the (optionally robust) least squares with a compact Levenberg-Marquardt
(:func:`levenberg_marquardt`: 6x6 normal equations, analytic Jacobian, fixed variable scaling; the rotation
is updated multiplicatively on the left), or with ``scipy.optimize.least_squares`` (``backend='scipy'``,
trust-region reflective; the same cost, ~10x the per-iteration overhead). Scale is only observable through
the left camera's lever arm, so the covariance is part of the answer, not an afterthought.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from scipy.linalg import lapack
from scipy.optimize import least_squares

from fixego_ros.estimation.coplanarity import (
    RayPairs,
    cheirality,
    numeric_jacobian,
    sampson_residuals,
    sampson_residuals_jacobian,
    sampson_residuals_jacobians,
)
from fixego_ros.estimation.covariance import VAR_MAX, covariance_from_jacobian, residual_variance
from fixego_ros.estimation.status import StepStatus
from fixego_ros.geometry.rotation import Pose, exp_so3, project_to_so3, rotation_angle, rotation_from_svd

LOSSES = ('linear', 'huber', 'soft_l1', 'cauchy', 'arctan')
BACKENDS = ('lm', 'scipy')


class Fallback(Enum):
    """Which cold starts a solve tries: with no warm start, or after a warm one that fails (behind the cameras).
    Per refinement ~2 ms at 150 pairs on this machine (docs/results.md "Stop 45")."""

    COLD = 'cold'                  # every cold start: the closed-form ones and a step along each axis (~16 ms)
    CLOSED_FORM = 'closed_form'    # the 8-point essential matrix's starts only (2-4 refinements: the live pose)
    NONE = 'none'                  # return it as DEGENERATE


@dataclass(frozen=True)
class SolverConfig:
    """Options of the two-frame solve. The defaults are estimator_node's (``pipeline.params``); the two angles
    are its pixel values over the default rig's focal length (config/rig.yaml: 1727 px)."""

    sigma: float = 1.0 / 1727.0        # expected angular noise of one ray (rad) = pixel noise / focal
    loss: str = 'huber'                # scipy's losses: linear, huber, soft_l1, cauchy, arctan
    loss_scale: float = 3.0            # robust loss knee, in multiples of sigma
    max_nfev: int = 30                 # bound on residual evaluations of one refinement
    tol: float = 1e-7                  # relative ftol/xtol of the least-squares solve
    prior_step: float = 0.05           # |T| (m) of the canonical starts when nothing better is known
    min_parallax: float = 0.3 / 1727.0  # rad; median rotation-compensated parallax below this = stationary
    camera_parallax: float = 0.1 / 1727.0   # rad; the same per camera, each with its own rotation (0 = off) ...
    head_sigma: float = math.radians(0.033)  # ... and the heads' rotations this far apart at 3 sqrt(2) sigma
    max_translation_std: float = 0.5   # m; beyond this the step is WEAK (scale unobserved)
    backend: str = 'lm'                # 'lm' (levenberg_marquardt below) or 'scipy' (least_squares, trf)

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f'loss must be one of {LOSSES}, got {self.loss!r}')
        if self.backend not in BACKENDS:
            raise ValueError(f'backend must be one of {BACKENDS}, got {self.backend!r}')


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


MIN_ROTATION_PAIRS = 8           # ray pairs for a Kabsch rotation worth predicting with
MIN_STAND_PAIRS = 2 * MIN_ROTATION_PAIRS     # ray pairs for a "the rig stood" verdict (:func:`stands_still`)
MIN_KNOWN_TRANSLATION_M = 1e-4   # a given step shorter than this leaves its rotation to Kabsch (no parallax to read)


def kabsch_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |a_i - R b_i|^2 (rotation-only fit of ray pairs)."""
    H = b.T @ a
    U, _, Vt = np.linalg.svd(H)
    return rotation_from_svd(np.ascontiguousarray(Vt.T), U.T)


def _median_parallax(a: np.ndarray, b: np.ndarray, R: np.ndarray) -> float:
    """Median rotation-compensated parallax (rad) of ray pairs under the rotation ``R``."""
    return float(np.median(np.linalg.norm(np.cross(a, b @ R.T), axis=1)))


def stands_still(pairs: RayPairs, R: np.ndarray, cfg: SolverConfig) -> bool:
    """Whether a rotation alone explains the pairs: no translation is observed, and the step is taken as the rig
    standing. Either the pairs' median parallax under ``R`` (their joint fit) is below ``cfg.min_parallax``, or, with
    both cameras' rays (``MIN_ROTATION_PAIRS`` each; ``cfg.camera_parallax`` and ``cfg.head_sigma`` > 0), each
    camera's rays fit a rotation of their own (median parallax below ``camera_parallax``) and the two rotations differ
    by less than the heads' independent reading errors allow (3 sqrt(2) ``head_sigma``).

    Why per camera: the two heads' readings are quantised independently (an EVI-D30 unit is 0.114 deg, 3.4 px at
    1727 px), and one rotation cannot take both heads' errors. On a simulated loop that rests 3 s before it moves
    (docs/results.md "Stop 62"), the joint fit left 0.12-1.70 px at rest, so 5 of 27 frames with the heads still
    stood. Per camera it left 0.01-0.09 px. Why the heads' agreement: per camera, a 30 Hz step's parallax mostly fits
    a rotation too (0.15-0.27 px at the 5th percentile), but of another axis in each head. Together the two tests
    stood 27 of 27 of those frames and none of 292 moving ones. The joint test stays: with the readings right, a
    tracker's noise alone (0.05 px a ray) can leave ~0.1 px per camera.

    Fewer than ``MIN_STAND_PAIRS`` pairs never stand: a median over a handful of rays is no evidence of rest. A few
    tracks that survive both heads' swing (six, all near the direction of travel on the papers' loop, seed 2) show
    little parallax while the rig moves on, and the back end held such a frame still over 0.2 s (4 cm of a 0.2 m/s
    walk lost; docs/results.md "Stop 80"). A rig at rest keeps every track, so its steps have many pairs."""
    if len(pairs) < MIN_STAND_PAIRS:
        return False
    if _median_parallax(pairs.a, pairs.b, R) < cfg.min_parallax:
        return True
    if not (cfg.camera_parallax > 0.0 and cfg.head_sigma > 0.0):
        return False
    first = np.all(pairs.centers == pairs.centers[0], axis=1) if len(pairs) else np.zeros(0, bool)
    groups = [first, ~first]        # each row carries its camera's centre (RayPairs.build)
    if (any(int(g.sum()) < MIN_ROTATION_PAIRS for g in groups)
            or not np.all(pairs.centers[~first] == pairs.centers[~first][0])):
        return False                # one camera (or too few rays of one), or more than two centres
    rotations = []
    for g in groups:
        a, b = pairs.a[g], pairs.b[g]
        rotations.append(kabsch_rotation(a, b))
        if not _median_parallax(a, b, rotations[-1]) < cfg.camera_parallax:
            return False
    return rotation_angle(rotations[0].T @ rotations[1]) < 3.0 * math.sqrt(2.0) * cfg.head_sigma


def rotation_given_translation(pairs: RayPairs, R0: np.ndarray, T: np.ndarray, sigma: float, f_scale: float = 3.0,
                               iterations: int = 3, max_turn: float = math.radians(2.0)) -> np.ndarray:
    """The rotation of a step whose translation ``T`` is known (e.g. a velocity carried over the step):
    Gauss-Newton on the pairs' coplanarity residuals over the rotation alone, Huber-weighted at
    ``f_scale`` sigmas, from ``R0`` (the Kabsch fit). Kabsch reads the parallax of near points as rotation; with
    the translation given, the rays' rotation is three unknowns and a few Gauss-Newton steps (~0.1 ms each) fix it.
    Returns ``R0`` when the translation is too short to see (then Kabsch's pure rotation is the answer), and stops
    at the last rotation that lowered the cost, or when a step would turn it more than ``max_turn`` from ``R0``
    (a translation that does not fit the rays)."""
    T = np.asarray(T, float)
    if not (np.all(np.isfinite(T)) and float(np.linalg.norm(T)) > MIN_KNOWN_TRANSLATION_M):
        return R0
    scaled = pairs.reweighted(1.0 / sigma)
    R, R_prev, best = R0, R0, math.inf
    for i in range(iterations + 1):
        with np.errstate(all='ignore'):
            r, J = sampson_residuals_jacobian(R, T, scaled)
            cost, w = huber_cost(r, f_scale)
        if not cost < best:         # worse than the last rotation (or not finite): that one
            return R_prev
        if i == iterations:
            return R
        best, R_prev = cost, R
        Jw = J[:, :3] * w[:, None]
        H, g = Jw.T @ J[:, :3], Jw.T @ r
        s, V = _eigh(H)
        if not (np.all(np.isfinite(s)) and s[0] > NULL_EIGENVALUE_REL * s[-1] > 0.0):
            return R
        delta = -(V @ ((g @ V) / s))
        R_next = exp_so3(delta.tolist()) @ R
        if rotation_angle(R_next @ R0.T) > max_turn:
            return R
        R = R_next
    return R


def essential_start(pairs: RayPairs) -> list[Pose]:
    """Closed-form starts: linear 8-point essential matrix on all rays (lever arm ignored), its four
    (R, t) decompositions filtered by cheirality, each scaled by the 1-D least-squares scale that the
    left camera's lever arm gives (falls back to unit length when that is ill-posed)."""
    if len(pairs) < 8:
        return []
    a, b = pairs.a, pairs.b
    A = np.einsum('ni,nj->nij', a, b).reshape(-1, 9)       # a^T E b = 0
    _, _, Vt = np.linalg.svd(A, full_matrices=False)     # (only V: no N x N U)
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


# --- Levenberg-Marquardt over a rigid motion --------------------------------------------------------

ResidualFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
BatchResidualFn = ResidualFn        # (K, 3, 3), (K, 3) -> (K, m), (K, m, 6)


def huber_cost(r: np.ndarray, f_scale: float) -> tuple[float, np.ndarray]:
    """The Huber cost ``0.5 f_scale^2 sum rho`` of residuals ``r`` and their IRLS weights ``rho'``:
    ``rho' = min(1, f/|r|)`` and ``f^2 rho = r^2 rho' (2 - rho')``."""
    w = f_scale / np.maximum(np.abs(r), f_scale)
    return 0.5 * float((r * w) @ (r * (2.0 - w))), w


def robust_loss(z: np.ndarray, loss: str) -> tuple[np.ndarray, np.ndarray]:
    """``rho(z)`` and ``rho'(z)`` of ``z = (r / f_scale)^2``, as ``scipy.optimize.least_squares`` defines them
    (the cost is ``0.5 f_scale^2 sum rho``)."""
    if loss == 'linear':
        return z, np.ones_like(z)
    if loss == 'huber':
        big = z > 1.0
        sq = np.sqrt(np.where(big, z, 1.0))
        return np.where(big, 2.0 * sq - 1.0, z), np.where(big, 1.0 / sq, 1.0)
    if loss == 'soft_l1':
        t = np.sqrt(1.0 + z)
        return 2.0 * (t - 1.0), 1.0 / t
    if loss == 'cauchy':
        return np.log1p(z), 1.0 / (1.0 + z)
    if loss == 'arctan':
        return np.arctan(z), 1.0 / (1.0 + z * z)
    raise ValueError(f'loss must be one of {LOSSES}, got {loss!r}')


@dataclass
class LMResult:
    """End point of :func:`levenberg_marquardt` with its residuals and Jacobian there."""

    R: np.ndarray
    T: np.ndarray
    r: np.ndarray
    J: np.ndarray
    cost: float          # robust cost, 0.5 f_scale^2 sum rho
    nfev: int
    success: bool        # a tolerance was met (not stopped by max_nfev)
    message: str


def _eigh(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and vectors of a symmetric 6x6: LAPACK directly (half numpy's call overhead);
    NaN when that fails, which the caller treats as unsolvable."""
    s, V, info = lapack.dsyev(H)
    if info != 0:
        return np.full(len(H), np.nan), np.eye(len(H))
    return s, V


# eigenvalues of the normal matrix below this fraction of the largest are rounding (a null direction of J)
NULL_EIGENVALUE_REL = 1e-14


def _trust_region_step(s: list[float], gt: list[float], delta: float,
                       lam: float) -> tuple[list[float], float, bool]:
    """Minimiser of the model ``g.h + h.H.h / 2`` with ``|h| <= delta``, in the eigenbasis of ``H`` (eigenvalues
    ``s``, gradient ``gt`` there): the Gauss-Newton step when it fits, else ``h = -g / (s + lam)`` with ``lam``
    from Newton's method on ``1/|h(lam)| - 1/delta`` (Moré's LM step; scipy's trust-region solver does the
    same on the SVD of J). ``lam`` is the previous multiplier, a warm start. Returns the step (eigenbasis),
    its multiplier and whether it lies on the boundary. Plain floats: six of them are cheaper than numpy."""
    s = [v if v > 0.0 else 0.0 for v in s]
    # Directions with an eigenvalue at rounding level are the null space of J: the gradient J^T r has no real
    # component there, only rounding, which differs between BLAS kernels. Dropping it makes the step the
    # pseudo-inverse (minimum-norm) one, decided by the data rather than by the CPU.
    floor = NULL_EIGENVALUE_REL * s[-1]
    gt = [g if v > floor else 0.0 for g, v in zip(gt, s, strict=True)]
    h = [-g / v if v > floor else 0.0 for g, v in zip(gt, s, strict=True)]
    if sum(v * v for v in h) <= delta * delta:
        return h, 0.0, False
    g2 = [g * g for g in gt]
    upper = math.sqrt(sum(g2)) / delta
    lower = max(0.0, upper - s[-1])
    for _ in range(10):
        if not lower < lam <= upper:
            lam = max(1e-3 * upper, math.sqrt(lower * upper))
        hh = dh = 0.0                                   # |h|^2 and -d|h|^2/dlam / 2
        for gi2, si in zip(g2, s, strict=True):
            q = 1.0 / (si + lam)
            hh += gi2 * q * q
            dh += gi2 * q * q * q
        h_norm = math.sqrt(hh)
        if h_norm > delta:
            lower = lam
        else:
            upper = lam
        if abs(h_norm - delta) < 0.01 * delta:
            break
        lam += (h_norm - delta) / delta * hh / dh
    return [-g / (v + lam) for g, v in zip(gt, s, strict=True)], lam, True


def levenberg_marquardt(fun: ResidualFn, R0: np.ndarray, T0: np.ndarray, x_scale: np.ndarray | str,
                        loss: str = 'linear', f_scale: float = 1.0, tol: float = 1e-7, max_nfev: int = 60,
                        gtol: float = 1e-8) -> LMResult | None:
    """Minimise ``0.5 f_scale^2 sum rho((r / f_scale)^2)`` over a motion ``(R, T)``.

    ``fun(R, T)`` gives the residuals and their Jacobian (m, 6) over ``[delta, dT]`` with the rotation
    perturbed on the left, ``R -> exp(delta) R``; each step updates it that way. Robust losses enter as
    IRLS weights ``rho'`` (same stationary points as scipy's losses). Steps solve the 6x6 normal equations
    with Marquardt damping ``lam`` in scaled coordinates ``x / x_scale``, ``lam`` adapted through a trust
    region on the scaled step (Moré's LM, as scipy's 'trf' without bounds): the radius starts at
    ``|T0 / x_scale|`` and grows or shrinks with how well the model predicted the last step, so with a
    fixed ``x_scale`` steps along a weakly observed direction (the scale) stay bounded however flat the
    cost is there. ``x_scale='jac'`` scales by the inverse column norms of the (weighted) Jacobian, never
    growing, as scipy does (that inflates steps along weakly observed directions: for well posed problems).
    Stops like scipy: relative cost decrease below ``tol`` on a well predicted step, a step below
    ``tol * (tol + |x|)``, the scaled gradient below ``gtol``, or ``max_nfev`` residual evaluations.
    Returns None when the start itself is not finite.
    """

    def one(Rs: np.ndarray, Ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, J = fun(Rs[0], Ts[0])
        return r[None], J[None]

    return levenberg_marquardt_many(one, [(R0, T0, x_scale)], loss, f_scale, tol, max_nfev, gtol)[0]


Start = tuple[np.ndarray, np.ndarray, 'np.ndarray | str']     # R0, T0, x_scale of one refinement


def levenberg_marquardt_many(fun: BatchResidualFn, starts: Sequence[Start], loss: str = 'linear',
                             f_scale: float = 1.0, tol: float = 1e-7, max_nfev: int = 60,
                             gtol: float = 1e-8) -> list[LMResult | None]:
    """:func:`levenberg_marquardt` from several starts side by side: each start takes exactly its own steps,
    and the residuals of those still running are evaluated together, ``fun(Rs, Ts)`` giving (K, m) and
    (K, m, 6). The cold starts of a two-frame solve are ten refinements of the same pairs; one call over all of
    them costs about three over one."""
    if loss not in LOSSES:
        raise ValueError(f'loss must be one of {LOSSES}, got {loss!r}')
    for _, _, x_scale in starts:
        if isinstance(x_scale, str) and x_scale != 'jac':
            raise ValueError(f"x_scale must be an array or 'jac', got {x_scale!r}")
    runs = [_lm_run(R0, T0, x_scale, loss, f_scale, tol, max_nfev, gtol) for R0, T0, x_scale in starts]
    out: list[LMResult | None] = [None] * len(runs)
    with np.errstate(all='ignore'):
        asked = {i: next(run) for i, run in enumerate(runs)}
        while asked:
            running = list(asked)
            r, J = fun(np.stack([asked[i][0] for i in running]), np.stack([asked[i][1] for i in running]))
            for k, i in enumerate(running):
                try:
                    asked[i] = runs[i].send((r[k], J[k]))
                except StopIteration as done:
                    out[i] = done.value
                    del asked[i]
    return out


def _lm_run(R0: np.ndarray, T0: np.ndarray, x_scale: np.ndarray | str, loss: str, f_scale: float, tol: float,
            max_nfev: int, gtol: float) -> Generator[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray],
                                                     LMResult | None]:
    """One refinement of :func:`levenberg_marquardt_many`: yields each motion whose residuals it needs and is
    sent them back (under the caller's ``np.errstate``)."""
    R, T = R0, np.array(T0, dtype=float)
    r, J = yield R, T
    nfev = 1
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return None
    jac_scale = isinstance(x_scale, str)
    f2 = float(f_scale) ** 2

    def robust(r: np.ndarray) -> tuple[float, np.ndarray | None]:
        """Cost and IRLS weights (None: all 1); a non-finite r gives a non-finite cost."""
        if loss == 'linear':
            return 0.5 * float(r @ r), None
        if loss == 'huber':
            return huber_cost(r, f_scale)
        rho, w = robust_loss(r * r * (1.0 / f2), loss)
        return 0.5 * f2 * float(np.sum(rho)), w

    def column_norms(J: np.ndarray, w: np.ndarray | None) -> np.ndarray:
        return np.sqrt(np.einsum('ij,ij->j', J, J) if w is None else (J * J).T @ w)

    rot = np.zeros(3)           # rotation applied so far (first order; for the step test only)
    x_norm = math.sqrt(float(T @ T))
    lam = 0.0
    success, message = False, 'maximum number of residual evaluations reached'
    cost, w = robust(r)
    if jac_scale:
        d_inv = column_norms(J, w)
        d_inv[d_inv == 0] = 1.0
        d = 1.0 / d_inv
    else:
        d = np.asarray(x_scale, dtype=float)
    radius = math.sqrt(float(np.sum((T / d[3:]) ** 2))) or 1.0
    while nfev < max_nfev:
        Jd = J * d
        Jw = Jd if w is None else Jd * w[:, None]
        H = Jw.T @ Jd
        g = Jw.T @ r
        if not math.isfinite(float(H.sum())):
            message = 'non-finite Jacobian'
            break
        if not float(np.abs(g).max()) >= gtol:
            success, message = True, 'gradient below gtol'
            break
        s_arr, V = _eigh(H)
        s, gt = s_arr.tolist(), (g @ V).tolist()
        done = False
        while nfev < max_nfev:
            ht, lam, on_boundary = _trust_region_step(s, gt, radius, lam)
            h_norm = math.sqrt(sum(v * v for v in ht))
            if not math.isfinite(h_norm):
                message, done = 'normal equations not solvable', True
                break
            step = (V @ ht) * d
            R_new, T_new = exp_so3(step[:3].tolist()) @ R, T + step[3:]
            r_new, J_new = yield R_new, T_new
            cost_new, w_new = robust(r_new)
            nfev += 1
            if not math.isfinite(cost_new):
                radius = 0.25 * h_norm
                continue
            reduction = cost - cost_new
            predicted = -sum(gi * hi + 0.5 * si * hi * hi for gi, hi, si in zip(gt, ht, s, strict=True))
            ratio = reduction / predicted if predicted > 0 else (1.0 if reduction == 0 == predicted else 0.0)
            if ratio < 0.25:
                radius = 0.25 * h_norm
            elif ratio > 0.75 and on_boundary:
                radius *= 2.0
            small_step = math.sqrt(float(step @ step)) < tol * (tol + x_norm)
            if reduction > 0:
                cost_old = cost
                R, T, r, J, cost, w = R_new, T_new, r_new, J_new, cost_new, w_new
                rot = rot + step[:3]
                x_norm = math.sqrt(float(rot @ rot + T @ T))
                if jac_scale:
                    d_inv = np.maximum(column_norms(J, w), d_inv)
                    d = 1.0 / d_inv
                if reduction < tol * cost_old and ratio > 0.25:
                    success, message, done = True, 'relative cost decrease below tol', True
                elif small_step:
                    success, message, done = True, 'step below tol', True
                break
            if small_step:
                success, message, done = True, 'step below tol', True
                break
        if done:
            break
    return LMResult(R, T, r, J, cost, nfev, success, message)


@dataclass(frozen=True)
class MotionPrior:
    """Gaussian priors of one step: on T (``t``, isotropic ``sigma_t``) and/or on its length |T|."""

    t: np.ndarray | None = None
    sigma_t: float = 0.0
    length: float | None = None
    sigma_length: float = 0.0

    @staticmethod
    def build(t: np.ndarray | None, sigma_t: float,
              length: tuple[float, float] | None) -> MotionPrior | None:
        """The usable parts (finite, positive sigma) of the given priors, or None when there are none."""
        use_t = t is not None and sigma_t > 0 and bool(np.all(np.isfinite(t)))
        use_len = (length is not None and all(math.isfinite(v) for v in length) and length[0] >= 0
                   and length[1] > 0)
        if not (use_t or use_len):
            return None
        return MotionPrior(np.asarray(t, dtype=float) if use_t else None, float(sigma_t) if use_t else 0.0,
                           float(length[0]) if use_len else None, float(length[1]) if use_len else 0.0)

    def rows(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals and their Jacobian over ``[rotation, T]`` at ``T``."""
        r, J = [], []
        if self.t is not None:
            r.append((T - self.t) / self.sigma_t)
            J.append(np.hstack([np.zeros((3, 3)), np.eye(3) / self.sigma_t]))
        if self.length is not None:
            n = math.sqrt(float(T @ T))
            u = T / n if n > 1e-12 else np.zeros(3)
            r.append(np.array([(n - self.length) / self.sigma_length]))
            J.append(np.concatenate([np.zeros(3), u / self.sigma_length])[None, :])
        return np.concatenate(r), np.vstack(J)


# end pose, converged, message, and the rays' residuals and Jacobian there when the minimiser has them
_Minimum = tuple[Pose, bool, str, tuple[np.ndarray, np.ndarray] | None]


class TwoFrameSolver:
    """Solve one step from stacked ray pairs; never raises on bad data, never returns NaN."""

    def __init__(self, config: SolverConfig | None = None) -> None:
        self.config = config or SolverConfig()

    def solve(self, pairs: RayPairs, initial: Pose | None = None, prior_t: np.ndarray | None = None,
              prior_sigma_t: float = 0.0, prior_length: tuple[float, float] | None = None,
              fallback: Fallback = Fallback.COLD) -> TwoFrameResult:
        """Solve one step. With ``prior_t`` and ``prior_sigma_t`` > 0 a weak Gaussian prior on T (e.g. a
        constant-velocity prediction) keeps directions the rays do not observe (the scale under pure
        translation) where the prediction puts them instead of letting the optimiser wander; with
        ``prior_length = (length, sigma)`` a prior on |T| alone does that for the scale only (the direction
        stays the rays'). The covariance returned is the rays' alone, so those directions still show as
        unobserved. ``fallback``: the cold starts (:class:`Fallback`) tried when there is no warm start, or when
        the warm one lands behind the cameras (the live pose has a time budget and takes the closed-form starts
        only; so does the smoother's cold check of its warm solve)."""
        prior = MotionPrior.build(prior_t, prior_sigma_t, prior_length)
        m = len(pairs)
        done, R_rot = self._unrefined(pairs)
        if done is not None:
            return done
        warm = initial is not None and initial.is_finite()
        best = self._best(pairs, [initial] if warm else self._starts(fallback, pairs, R_rot), prior)
        # a poor warm start gets the cold starts too, unless a prior on T anchors it (real time: the cold starts
        # cost ~10 solves; a prior-anchored bad step is flagged below and predicted by the caller). A prior on
        # the length alone does not: it holds T and -T alike
        if (fallback is not Fallback.NONE and warm
                and (best is None or (best.cheirality < 0.5 and (prior is None or prior.t is None)))):
            best = self._better(self._best(pairs, self._starts(fallback, pairs, R_rot), prior), best)
        return self._finished(best, initial, m)

    def solve_checked(self, pairs: RayPairs, initial: Pose) -> tuple[TwoFrameResult, TwoFrameResult | None]:
        """The warm solve from ``initial`` and, when it is usable (OK or WEAK), its cold check: the same two results as
        ``solve(pairs, initial)`` and ``solve(pairs, fallback=Fallback.CLOSED_FORM)`` (None when the warm one is not
        usable), for less. The warm start and the closed-form starts are refined side by side in one
        :func:`levenberg_marquardt_many` batch, each taking exactly the steps it takes alone, and the pairs' rest test
        runs once. The smoother checks every warm solve this way (:meth:`.smoother.Smoother._two_frame`): alone, the
        warm solve and the check cost 5.2 + 7.1 ms per frame on the 30 Hz loop, batched the refinements 7.8."""
        if not initial.is_finite() or self.config.backend != 'lm':
            warm = self.solve(pairs, initial=initial)      # (scipy refines one start at a time: no batch to share)
            return warm, (self.solve(pairs, fallback=Fallback.CLOSED_FORM)
                          if warm.status in (StepStatus.OK, StepStatus.WEAK) else None)
        done, R_rot = self._unrefined(pairs)
        if done is not None:
            return done, None       # too few pairs, or the rig at rest: no refinement, no check
        closed = self._starts(Fallback.CLOSED_FORM, pairs, R_rot)
        found = self._minimise_lm(pairs, [initial, *closed], None)
        warm = self._best_of(pairs, found[:1])
        if warm is None or warm.cheirality < 0.5:     # as :meth:`solve`: a warm solve behind the cameras gets the
            canonical = [Pose(R_rot, p.t) for p in canonical_starts(self.config.prior_step)]     # cold starts
            warm = self._better(self._best_of(pairs, [*found[1:], *self._minimise_lm(pairs, canonical, None)]), warm)
        warm = self._finished(warm, initial, len(pairs))
        if warm.status not in (StepStatus.OK, StepStatus.WEAK):
            return warm, None
        return warm, self._finished(self._best_of(pairs, found[1:]), None, len(pairs))

    def _unrefined(self, pairs: RayPairs) -> tuple[TwoFrameResult | None, np.ndarray]:
        """The answer that needs no refinement (too few pairs; a rig at rest: a pure rotation explains every pair,
        T unobservable and 0), else None; and the pairs' Kabsch rotation (identity with too few pairs)."""
        cfg, m = self.config, len(pairs)
        if m < 6:
            return TwoFrameResult(Pose.identity(), StepStatus.INSUFFICIENT, n_constraints=m,
                                  message=f'{m} constraints for 6 unknowns'), np.eye(3)
        R_rot = kabsch_rotation(pairs.a, pairs.b)
        if stands_still(pairs, R_rot, cfg):
            return TwoFrameResult(Pose(R_rot, np.zeros(3)), StepStatus.STATIONARY, np.zeros(m),
                                  np.diag([cfg.sigma**2] * 3 + [VAR_MAX] * 3), 0.0, m,
                                  'no parallax: rotation only'), R_rot
        return None, R_rot

    @staticmethod
    def _finished(best: TwoFrameResult | None, initial: Pose | None, m: int) -> TwoFrameResult:
        """A solve's end: FAILED without a finite solution, DEGENERATE when most points lie behind the cameras."""
        if best is None:
            return TwoFrameResult(initial or Pose.identity(), StepStatus.FAILED, n_constraints=m,
                                  message='optimiser produced no finite solution')
        if best.cheirality < 0.5:
            best.status = StepStatus.DEGENERATE
            best.message += f'; only {100 * best.cheirality:.0f}% of points in front of the cameras'
        return best

    def _starts(self, fallback: Fallback, pairs: RayPairs, R_rot: np.ndarray) -> list[Pose]:
        """The cold starts ``fallback`` names (every one for NONE: a solve with no warm start needs some)."""
        closed = essential_start(pairs)
        if fallback is Fallback.CLOSED_FORM:
            return closed
        return closed + [Pose(R_rot, p.t) for p in canonical_starts(self.config.prior_step)]

    @staticmethod
    def _better(a: TwoFrameResult | None, b: TwoFrameResult | None) -> TwoFrameResult | None:
        """Of two solutions of the same pairs: the one in front of the cameras, then the lower cost (``a`` on a
        tie; None only when both are)."""
        if a is None or b is None:
            return a if b is None else b
        return b if (b.cheirality < 0.5, b.cost) < (a.cheirality < 0.5, a.cost) else a

    def _best(self, pairs: RayPairs, starts: list[Pose],
              prior: MotionPrior | None = None) -> TwoFrameResult | None:
        """Refine every start; prefer solutions in front of the cameras, then the lowest cost."""
        return self._best_of(pairs, self._minimise_lm(pairs, starts, prior) if self.config.backend == 'lm'
                             else [self._minimise_scipy(pairs, start, prior) for start in starts])

    def _best_of(self, pairs: RayPairs, found: list[_Minimum | None]) -> TwoFrameResult | None:
        """The best of refined minima, as :meth:`_better` ranks them (each a new result)."""
        best: TwoFrameResult | None = None
        for minimum in found:
            best = self._better(best, self._result(pairs, minimum))
        return best

    def _x_scale(self, start: Pose) -> np.ndarray:
        """Fixed variable scaling (not 'jac': that inflates steps along the weakly observed scale)."""
        return np.concatenate([np.full(3, 1e-2), np.full(3, max(np.linalg.norm(start.t), self.config.prior_step))])

    def _result(self, pairs: RayPairs, found: _Minimum | None) -> TwoFrameResult | None:
        """A refinement's end point with its covariance, status and cheirality (None when it is not finite)."""
        if found is None:
            return None
        cfg = self.config
        pose, success, message, rJ = found
        r, J = rJ if rJ is not None else sampson_residuals_jacobian(pose.R, pose.t, pairs)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
            return None
        sigma2 = residual_variance(r, 6, cfg.sigma)
        cov = covariance_from_jacobian(J, sigma2)
        status = StepStatus.OK
        msg = 'converged' if success else f'stopped: {message}'
        if float(np.sqrt(np.max(np.diag(cov)[3:]))) > cfg.max_translation_std:
            status = StepStatus.WEAK
            msg += '; translation weakly observed'
        return TwoFrameResult(pose, status, r, cov, float(0.5 * np.sum(np.square(r / cfg.sigma))), len(pairs), msg,
                              cheirality(pose.R, pose.t, pairs))

    def _minimise_lm(self, pairs: RayPairs, starts: list[Pose], prior: MotionPrior | None) -> list[_Minimum | None]:
        """:func:`levenberg_marquardt_many` on the rays (and prior rows) from every start at once; each end point
        also carries the rays' residuals and Jacobian there, which the covariance needs."""
        cfg = self.config
        scaled = pairs.reweighted(1.0 / cfg.sigma)      # residuals in units of sigma, with no per-call division

        def fun(Rs: np.ndarray, Ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            r, J = sampson_residuals_jacobians(Rs, Ts, scaled)
            if prior is None:
                return r, J
            rows = [prior.rows(T) for T in Ts]
            return (np.concatenate([r, np.stack([r_p for r_p, _ in rows])], axis=1),
                    np.concatenate([J, np.stack([J_p for _, J_p in rows])], axis=1))

        sols = levenberg_marquardt_many(fun, [(p.R, p.t, self._x_scale(p)) for p in starts], cfg.loss,
                                        cfg.loss_scale, cfg.tol, cfg.max_nfev)
        m = len(pairs)
        out: list[_Minimum | None] = []
        for sol in sols:
            if sol is None or not (np.all(np.isfinite(sol.R)) and np.all(np.isfinite(sol.T))):
                out.append(None)
                continue
            out.append((Pose(project_to_so3(sol.R), sol.T.copy()), sol.success, sol.message,
                        (sol.r[:m] * cfg.sigma, sol.J[:m] * cfg.sigma)))
        return out

    def _minimise_scipy(self, pairs: RayPairs, start: Pose, prior: MotionPrior | None) -> _Minimum | None:
        """The original path: scipy's trust-region reflective over ``x = [rotvec of R R0^T, T]``."""
        cfg = self.config
        x_scale = self._x_scale(start)
        R0 = start.R
        scale = cfg.sigma

        if prior is None:
            def fun(x: np.ndarray) -> np.ndarray:
                return sampson_residuals(exp_so3(x[:3]) @ R0, x[3:], pairs) / scale

            def jac(x: np.ndarray) -> np.ndarray:
                return numeric_jacobian(R0, x, pairs)[1] / scale
        else:
            def fun(x: np.ndarray) -> np.ndarray:
                r = sampson_residuals(exp_so3(x[:3]) @ R0, x[3:], pairs) / scale
                return np.concatenate([r, prior.rows(x[3:])[0]])

            def jac(x: np.ndarray) -> np.ndarray:
                return np.vstack([numeric_jacobian(R0, x, pairs)[1] / scale, prior.rows(x[3:])[1]])

        x0 = np.concatenate([np.zeros(3), start.t])
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
        return Pose(project_to_so3(exp_so3(x[:3]) @ R0), x[3:].copy()), bool(sol.success), str(sol.message), None
