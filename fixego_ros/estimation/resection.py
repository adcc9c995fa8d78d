"""Pose-only resection: the rig pose that projects known landmarks onto a frame's sightings.

The smoother places each new frame this way before its observations are gated and enter the graph (the landmarks
are held where the window has them). Until stop 67 it was a GTSAM Levenberg-Marquardt over the pose and every
landmark it saw, each landmark pinned by a 1e-6 m prior: a (6 + 3n)-variable problem built factor by factor in
Python to solve a 6-variable one (~110 sightings on the 30 Hz loop: 3.8 ms to build, 3.2 ms to solve, 7 of the
smoother's ~66 ms per update). Here the residuals and their Jacobian are one vectorised expression over all
sightings, minimised by the two-frame solver's 6-DOF Levenberg-Marquardt (:func:`.twoframe.levenberg_marquardt`,
rotation perturbed on the left, Huber weights per pixel coordinate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fixego_ros.estimation.factors import Projection
from fixego_ros.estimation.twoframe import levenberg_marquardt
from fixego_ros.geometry.rotation import Pose, skew


@dataclass(frozen=True)
class Sightings:
    """Known world ``points`` (n, 3) seen at ``pixels`` (n, 2; principal point at 0) by cameras with optical-to-rig
    rotations ``cam_to_rig`` (n, 3, 3), centres ``centers`` (n, 3, rig frame) and focal lengths ``focal`` (n, 2)."""

    points: np.ndarray
    pixels: np.ndarray
    cam_to_rig: np.ndarray
    centers: np.ndarray
    focal: np.ndarray

    def residuals(self, R: np.ndarray, T: np.ndarray, sigma: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel residuals (2n, in units of ``sigma``: one for all, or one per sighting) of the rig pose ``(R, T)``
        (rig -> world) and their Jacobian (2n, 6) over ``[delta, dT]`` with ``R -> exp(delta) R``. A point behind
        its camera gives a constant residual and no gradient (as GTSAM's projection factor does)."""
        n = len(self.points)
        CT = np.transpose(self.cam_to_rig, (0, 2, 1))       # rig -> optical
        d = self.points - T                                 # world offset from the rig origin
        pc = np.einsum('nij,nj->ni', CT, d @ R - self.centers)      # (d @ R: rows R^T (P - t))
        z = pc[:, 2]
        front = z > Projection.MIN_DEPTH          # the smoother's pixels: no pixel this close to the image plane
        zs = np.where(front, z, 1.0)
        fx, fy = self.focal[:, 0], self.focal[:, 1]
        s = np.asarray(sigma, float).reshape(-1, 1)             # (1, 1) or (n, 1)
        r = (self.focal * pc[:, :2] / zs[:, None] - self.pixels) / s
        # d pc / d [delta, dT] = C^T R^T [ [P - t]x | -I ]
        dq = np.concatenate([np.einsum('ji,njk->nik', R, skew(d)), np.broadcast_to(-R.T, (n, 3, 3))], axis=2)
        dpc = np.einsum('nij,njk->nik', CT, dq)
        zero = np.zeros(n)
        dpix = np.stack([np.stack([fx / zs, zero, -fx * pc[:, 0] / zs**2], 1),
                         np.stack([zero, fy / zs, -fy * pc[:, 1] / zs**2], 1)], 1)
        J = np.einsum('nij,njk->nik', dpix, dpc) / s[:, :, None]
        r[~front] = (2.0 * self.focal / s)[~front]
        J[~front] = 0.0
        return r.reshape(-1), J.reshape(-1, 6)


def resect(sightings: Sightings, sigma: float | np.ndarray, huber_k: float, start: Pose, max_nfev: int = 30
           ) -> Pose | None:
    """The rig pose (rig -> world) that best projects the sightings' points onto their pixels: residuals in units
    of ``sigma`` px (one for all, or one per sighting), Huber beyond ``huber_k``, from ``start``. None when the start
    or the end is not finite."""
    found = levenberg_marquardt(lambda R, T: sightings.residuals(R, T, sigma), start.R, start.t, 'jac',
                                loss='huber', f_scale=huber_k, max_nfev=max_nfev)
    if found is None:
        return None
    pose = Pose(found.R, found.T)
    return pose if pose.is_finite() else None
