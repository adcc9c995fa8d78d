"""Scale anchor: one fixation point at a metric position (the start-up vergence step) fixes the trajectory's scale.

With the constant-speed prior (:mod:`.constant_speed`) the trajectory is estimated at the right shape but at a
nominal speed until a step length is measured. A fixation point whose position is known in metres (the
vergence step triangulates it from the known baseline) gives that measurement: while the camera keeps
fixating it, its ray at each later frame must point at it from the estimated pose, and only one scale
``k`` of the translation since the anchor frame makes them agree. :meth:`ScaleAnchor.fit` finds ``k``
by one-dimensional least squares over those frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from fixego_ros.geometry.rotation import Pose

# the fit counts once the scale is known this well (relative std) from at least MIN_VIEWS later frames, and
# once the rig has moved (at the fitted scale) enough for the point's direction to change by MIN_PARALLAX_DEG:
# the first steps' lengths and directions are poor (a rig starting from rest breaks the constant speed), and
# their errors are not in the std
MAX_REL_STD = 0.05
MIN_VIEWS = 5
MIN_PARALLAX_DEG = 3.0


@dataclass
class ScaleAnchor:
    """A metric fixation point (rig frame at ``stamp``) and the frames that fixated it since."""

    stamp: float
    side: str                       # the camera that fixates it
    point: np.ndarray               # rig frame at ``stamp``, m
    cov: np.ndarray                 # 3x3, m²
    center: np.ndarray              # the fixating camera's centre in the rig frame
    ray_sigma: float                # rad, noise of one fixation ray
    fixation_id: int | None = None  # the camera's fixation id at ``stamp`` (None: that frame not seen yet)
    base: Pose | None = None        # rig pose at ``stamp`` in the estimate
    views: list[tuple[Pose, np.ndarray]] = field(default_factory=list)   # (pose relative to base, unit ray)
    ended: bool = False             # the camera re-selected its fixation point: no more views

    def start(self, pose: Pose, fixation_id: int) -> None:
        """The anchor frame itself: its estimated pose and the fixation it belongs to."""
        self.base, self.fixation_id = pose, fixation_id

    def add(self, pose: Pose, fixation_id: int | None, ray: np.ndarray | None) -> None:
        """A later frame: a view when the camera still fixates the anchor point, else the anchor ends."""
        if self.base is None or self.ended:
            return
        if fixation_id != self.fixation_id or ray is None:
            self.ended = True
            return
        self.views.append((self.base.inverse() @ pose, np.asarray(ray, float)))

    def parallax_deg(self, k: float) -> float:
        """Angle (deg) the point subtends between the anchor frame and the newest view, at scale ``k``."""
        if not self.views:
            return 0.0
        a = self.point - self.center
        b = self.point - k * self.views[-1][0].t - self.center
        cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
        return math.degrees(math.acos(min(1.0, max(-1.0, cos))))

    def _residuals(self, k: np.ndarray) -> np.ndarray:
        out = []
        for rel, ray in self.views:
            d = rel.R.T @ (self.point - k[0] * rel.t) - self.center
            n = np.linalg.norm(d)
            out.append(np.cross(d / n if n > 0 else d, ray) / self.ray_sigma)
        return np.concatenate(out)

    def fit(self) -> tuple[float, float] | None:
        """(k, std of k): the factor that makes the estimated translation since the anchor metric, or None
        with too few views or when the views do not determine it (no translation, or not finite)."""
        if len(self.views) < MIN_VIEWS:
            return None
        try:
            sol = least_squares(self._residuals, np.array([1.0]), bounds=(1e-3, 1e3), x_scale=1.0, max_nfev=50)
        except (ValueError, np.linalg.LinAlgError):
            return None
        k = float(sol.x[0])
        info = float(sol.jac[:, 0] @ sol.jac[:, 0])
        var_k = 1.0 / info if info > 0 else math.inf
        if not (math.isfinite(k) and math.isfinite(var_k) and var_k > 0):
            return None
        # the point's own distance error scales k one for one
        u = self.point - self.center
        dist = float(np.linalg.norm(u))
        rel_point = math.sqrt(max(float(u @ self.cov @ u), 0.0)) / dist**2 if dist > 0 else math.inf
        std = math.sqrt(var_k + (rel_point * k) ** 2)
        return (k, std) if math.isfinite(std) else None

    def settled(self) -> tuple[float, float] | None:
        """The fit once it is good enough (:data:`MAX_REL_STD`), else None."""
        f = self.fit()
        ok = f is not None and f[1] < MAX_REL_STD * f[0] and self.parallax_deg(f[0]) >= MIN_PARALLAX_DEG
        return f if ok else None
