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

import numpy as np
from scipy.spatial.transform import Rotation

EPS = 1e-12


@dataclass(frozen=True)
class RayPairs:
    """Stacked ray pairs from both cameras: rays at t (``a``), at t+1 (``b``), camera centre per row."""

    a: np.ndarray        # (N, 3) unit rays at t, rig frame at t
    b: np.ndarray        # (N, 3) unit rays at t+1, rig frame at t+1
    centers: np.ndarray  # (N, 3) projection centre of the observing camera in the rig frame
    weights: np.ndarray  # (N,) residual weights (1 = nominal noise)

    def __len__(self) -> int:
        return len(self.a)

    @property
    def bT(self) -> np.ndarray:
        return self.b.T

    @property
    def cT(self) -> np.ndarray:
        return self.centers.T

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
    a, bT, cT = pairs.a.T, pairs.bT, pairs.cT                        # (3, N)
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
