"""Coplanarity (epipolar) residuals of DESIGN.md §5 in a normalised, angular (Sampson) form.

For a ray pair (a at t, b at t+1, both unit vectors in their own rig frame) seen by a camera whose
centre is ``c`` in the rig frame, the constraint is ``det[a | R b | t_c] = 0`` with
``t_c = T + (R - I) c``. Raw determinants shrink with |T|, so we divide by |t_c| and by the
first-order (Sampson) sensitivity of the determinant to perturbations of both rays in their tangent
planes. The result is, to first order, the angular displacement (rad) a ray must move to satisfy the
constraint: with pixel noise sigma_px it has standard deviation sigma_px / f.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

EPS = 1e-12
_CYCLIC = np.array([0, 1, 2, 0, 1])
_D2_COEF = np.array([2.0, 1.0, 1.0])
_CACHED = ('aT', 'bT', 'cT', 'aT_cyclic')      # RayPairs' cached properties (weights do not enter them)


@dataclass(frozen=True)
class RayPairs:
    """Stacked ray pairs from both cameras: rays at t (``a``), at t+1 (``b``), camera centre per row."""

    a: np.ndarray        # (N, 3) unit rays at t, rig frame at t
    b: np.ndarray        # (N, 3) unit rays at t+1, rig frame at t+1
    centers: np.ndarray  # (N, 3) projection centre of the observing camera in the rig frame
    weights: np.ndarray  # (N,) residual weights (1 = nominal noise)

    def __len__(self) -> int:
        return len(self.a)

    # transposed (3, N) copies, contiguous and cached: the residuals are evaluated many times per solve
    @cached_property
    def aT(self) -> np.ndarray:
        return np.ascontiguousarray(self.a.T)

    @cached_property
    def bT(self) -> np.ndarray:
        return np.ascontiguousarray(self.b.T)

    @cached_property
    def cT(self) -> np.ndarray:
        return np.ascontiguousarray(self.centers.T)

    @cached_property
    def aT_cyclic(self) -> np.ndarray:
        """(5, N) rows a_x, a_y, a_z, a_x, a_y: rows 1:4 and 2:5 are the shifts a cross product takes."""
        return self.aT.take(_CYCLIC, axis=0)

    def reweighted(self, factor: float) -> RayPairs:
        """The same pairs with weights times ``factor`` (e.g. 1/sigma: residuals in units of the noise),
        sharing the cached transposes."""
        out = RayPairs(self.a, self.b, self.centers, self.weights * factor)
        out.__dict__.update({k: v for k, v in self.__dict__.items() if k in _CACHED})
        return out

    @staticmethod
    def build(groups: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]) -> RayPairs:
        """Stack groups ``(a, b, center, weight)``; drops non-finite or zero rows, normalises rays."""
        A, B, C, W = [], [], [], []
        for a, b, c, w in groups:
            a = np.asarray(a, dtype=float).reshape(-1, 3)
            b = np.asarray(b, dtype=float).reshape(-1, 3)
            if len(a) != len(b):
                raise ValueError(f'ray pair arrays differ in length: {len(a)} vs {len(b)}')
            na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
            good = np.isfinite(na) & np.isfinite(nb) & (na > EPS) & (nb > EPS)
            A.append(a[good] / na[good, None])
            B.append(b[good] / nb[good, None])
            C.append(np.broadcast_to(np.asarray(c, dtype=float), (int(good.sum()), 3)))
            W.append(np.full(int(good.sum()), float(w)))
        if not A:
            return RayPairs(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        return RayPairs(np.vstack(A), np.vstack(B), np.vstack(C), np.concatenate(W))


def rotations(rvecs: np.ndarray) -> np.ndarray:
    """Batch of rotation matrices (K, 3, 3) from rotation vectors (K, 3)."""
    return Rotation.from_rotvec(np.asarray(rvecs, dtype=float).reshape(-1, 3)).as_matrix()


def sampson_residuals_batch(Rs: np.ndarray, Ts: np.ndarray, pairs: RayPairs) -> np.ndarray:
    """Normalised coplanarity residuals (K, N) for K motion hypotheses (Rs (K,3,3), Ts (K,3)).

    With unit rays a, b' = R b and t_hat, the determinant is e = a . (b' x t_hat); its gradients in the
    rays' tangent planes have squared norms 1 - (b'.t_hat)^2 - e^2 and 1 - (a.t_hat)^2 - e^2, so the
    Sampson form needs only three dot products (this is the hot path of the solver).
    """
    a, bT, cT = pairs.aT, pairs.bT, pairs.cT                         # (3, N)
    bp = Rs @ bT                                                    # (K, 3, N)
    tc = Ts[:, :, None] + Rs @ cT - cT                              # t_c = T + (R - I) c
    th = tc / np.maximum(np.sqrt((tc * tc).sum(axis=1, keepdims=True)), EPS)
    bx, by, bz = bp[:, 0], bp[:, 1], bp[:, 2]
    tx, ty, tz = th[:, 0], th[:, 1], th[:, 2]
    e = a[0] * (by * tz - bz * ty) + a[1] * (bz * tx - bx * tz) + a[2] * (bx * ty - by * tx)
    bt = bx * tx + by * ty + bz * tz
    at = a[0] * tx + a[1] * ty + a[2] * tz
    denom = np.sqrt(np.maximum(2.0 - bt * bt - at * at - 2.0 * e * e, 1e-18))
    return pairs.weights * e / denom


def sampson_residuals(R: np.ndarray, T: np.ndarray, pairs: RayPairs) -> np.ndarray:
    """Normalised coplanarity residuals (N,) of one motion (R, T)."""
    return sampson_residuals_batch(R[None], np.asarray(T, dtype=float)[None], pairs)[0]


def sampson_residuals_jacobian(R: np.ndarray, T: np.ndarray, pairs: RayPairs) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N,) of one motion and their analytic Jacobian (N, 6) over ``[delta, T]``, where the
    rotation is perturbed on the left, ``R -> exp(delta) R``: at ``x = 0`` the columns of
    :func:`numeric_jacobian` without its truncation error, for under twice the cost of the residuals
    alone (the hot path of the LM solver, hence few whole-array operations).

    With b' = R b, th = t_c / |t_c|, n = a x b', e = th . n and D^2 = 2 - (b'.th)^2 - (a.th)^2 - 2 e^2, the
    residual is w e / D, so dr = w (alpha de + beta (b'.th d(b'.th) + a.th d(a.th))) with
    alpha = 1/D + 2 e^2/D^3 and beta = e/D^3; and d b' = delta x b', d t_c = dT + delta x (R c).
    Vectors are (3, N) or, for cross products, (5, N) with rows x, y, z, x, y (``_CYCLIC``).
    """
    r, J = sampson_residuals_jacobians(R[None], np.asarray(T, dtype=float)[None], pairs)
    return r[0], J[0]


def sampson_residuals_jacobians(Rs: np.ndarray, Ts: np.ndarray, pairs: RayPairs) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sampson_residuals_jacobian` of K motions at once (``Rs`` (K, 3, 3), ``Ts`` (K, 3)): residuals (K, N)
    and Jacobians (K, N, 6), bit for bit those of K single calls. The two-frame solver refines its starts side by
    side: one call over ten motions costs about three over one (150 pairs: 150 against 48 us)."""
    a, ae, c = pairs.aT, pairs.aT_cyclic, pairs.cT
    K, n_rows = len(Rs), a.shape[1]
    R5 = Rs[:, _CYCLIC]
    be = R5 @ pairs.bT                                                 # (K, 5, N): b', cyclic rows
    Rce = R5 @ c                                                       # R c, cyclic rows
    tc = Rce[:, :3] - c
    tc += np.asarray(Ts, dtype=float)[:, :, None]
    u = np.sqrt(np.einsum('kin,kin->kn', tc, tc))
    small = u <= EPS if u.min() <= EPS else None     # no baseline: th = t_c / EPS, as in the residuals
    if small is not None:
        u[small] = EPS
    th = tc / u[:, None]
    te = th[:, _CYCLIC]
    V = np.empty((K, 3, 3, n_rows))                                     # n, b', a
    np.subtract(ae[1:4] * be[:, 2:5], ae[2:5] * be[:, 1:4], out=V[:, 0])
    V[:, 1] = be[:, :3]
    V[:, 2] = a
    S = np.einsum('kjin,kin->kjn', V, th)                               # e, b'.th, a.th
    D2 = 2.0 - _D2_COEF @ (S * S)                                       # 2 - 2e^2 - (b'.th)^2 - (a.th)^2
    clamped = D2 <= 1e-18 if D2.min() <= 1e-18 else None    # D held at its floor: no derivative through it
    if clamped is not None:
        D2[clamped] = 1e-18
    inv_d = 1.0 / np.sqrt(D2)
    e = S[:, 0]
    beta = e * inv_d**3
    if clamped is not None:
        beta[clamped] = 0.0
    C = S * beta[:, None]                                               # beta e, beta b'.th, beta a.th
    C[:, 0] = inv_d + 2.0 * C[:, 0]                                     # alpha
    gt = np.einsum('kjn,kjin->kin', C, V)          # dr/dth = alpha n + beta (b'.th b' + a.th a)
    along = np.einsum('kin,kin->kn', th, gt)
    if small is not None:
        along[small] = 0.0                   # th = t_c / EPS is not a unit vector: nothing to project out
    g = (gt - th * along[:, None]) / u[:, None]                         # dr/dt_c (projected, over |t_c|)
    gb = C[:, 0, None] * (te[:, 1:4] * ae[2:5] - te[:, 2:5] * ae[1:4]) + C[:, 1, None] * th  # dr/db'
    ge, gbe = g[:, _CYCLIC], gb[:, _CYCLIC]
    J = np.empty((K, 6, n_rows))
    J[:, :3] = (be[:, 1:4] * gbe[:, 2:5] - be[:, 2:5] * gbe[:, 1:4]
                + Rce[:, 1:4] * ge[:, 2:5] - Rce[:, 2:5] * ge[:, 1:4])     # b' x g_b + R c x g_{t_c}
    J[:, 3:] = g
    w = pairs.weights
    J *= w
    return w * e * inv_d, J.transpose(0, 2, 1)


def numeric_jacobian(R0: np.ndarray, x: np.ndarray, pairs: RayPairs, h_rot: float = 1e-7,
                     h_trans: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """Residuals and forward-difference Jacobian at ``x = [delta_rotvec, T]`` with ``R = exp(delta) R0``.

    All 7 evaluations run in one vectorised batch, which is what makes the solve fast.
    """
    h = np.array([h_rot] * 3 + [h_trans] * 3)
    X = np.repeat(x[None], 7, axis=0)
    X[1:] += np.diag(h)
    Rs = rotations(X[:, :3]) @ R0
    r = sampson_residuals_batch(Rs, X[:, 3:], pairs)
    return r[0], ((r[1:] - r[0]) / h[:, None]).T


def cheirality(R: np.ndarray, T: np.ndarray, pairs: RayPairs) -> float:
    """Fraction of pairs whose triangulated point lies in front of the camera at both frames.

    The coplanarity residual is blind to the sign of the baseline, so the sign of T comes from here.
    Rows with no parallax (ill-conditioned triangulation) are ignored.
    """
    if len(pairs) == 0:
        return 0.0
    a, c = pairs.a, pairs.centers
    bp = pairs.b @ R.T
    tc = T + c @ R.T - c                      # camera baseline t -> t+1 (rig frame t), per row
    # lam a = tc + mu bp  ->  normal equations of [a, -bp] [lam, mu]^T = tc
    ab = np.einsum('ni,ni->n', a, bp)
    at = np.einsum('ni,ni->n', a, tc)
    bt = np.einsum('ni,ni->n', bp, tc)
    det = 1.0 - ab * ab
    ok = det > 1e-12
    if not np.any(ok):
        return 1.0
    lam = (at - ab * bt)[ok] / det[ok]
    mu = (ab * at - bt)[ok] / det[ok]
    return float(np.mean((lam > 0) & (mu > 0)))
