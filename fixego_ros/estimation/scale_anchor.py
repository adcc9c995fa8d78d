"""Scale anchor: one fixation point at a metric position (the start-up vergence step) fixes the trajectory's scale.

With the constant-speed prior (:mod:`.constant_speed`) the trajectory is estimated at the right shape but at a
nominal speed until a step length is measured. A fixation point whose position is known in metres (the
vergence step triangulates it from the known baseline) gives that measurement: while the camera keeps
fixating it, its ray at each later frame must point at it from the estimated pose, and only one scale
``k_j`` of the estimated translation since the anchor frame makes them agree: the metric distance
travelled to frame j is ``k_j |t_j|``. A rig that starts from rest is slower at first than the constant
speed draws it, so the speed is the slope of those distances over the recent frames (not their ratio to
the start), and the path so far is scaled by the newest ``k_j`` (:meth:`ScaleAnchor.fit`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from fixego_ros.geometry.rotation import Pose

# the fit counts once the speed is known this well (relative std) from at least MIN_VIEWS later frames, and
# once the rig has moved (at the fitted scale) enough for the point's direction to change by MIN_PARALLAX_DEG
MAX_REL_STD = 0.1
MIN_VIEWS = 6
MIN_PARALLAX_DEG = 3.0
# the speed is the slope over the newest RECENT_FRACTION of the views (at least MIN_VIEWS // 2 of them)
RECENT_FRACTION = 0.5


@dataclass(frozen=True)
class AnchorFit:
    """What the anchor measured: factors that make the estimate metric."""

    position_k: float      # the path so far (its newest position is ``position_k`` times the estimated one)
    speed_k: float         # the speed (the recent metric speed is ``speed_k`` times the estimated one)
    rel_std: float         # of ``speed_k``


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
    # per view: stamp, estimated distance from the anchor frame |t_j|, its metric factor k_j and std
    views: list[tuple[float, float, float, float]] = field(default_factory=list)
    ended: bool = False             # the camera re-selected its fixation point: no more views
    newest: Pose | None = None      # the newest view's pose relative to the anchor frame
    rel_point: float = field(init=False)   # relative std of the point's distance: it scales every k_j one for one

    def __post_init__(self) -> None:
        u = self.point - self.center
        dist = float(np.linalg.norm(u))
        self.rel_point = math.sqrt(max(float(u @ self.cov @ u), 0.0)) / dist**2 if dist > 0 else math.inf

    def start(self, pose: Pose, fixation_id: int) -> None:
        """The anchor frame itself: its estimated pose and the fixation it belongs to."""
        self.base, self.fixation_id = pose, fixation_id

    def add(self, stamp: float, pose: Pose, fixation_id: int | None, ray: np.ndarray | None) -> None:
        """A later frame: a view when the camera still fixates the anchor point, else the anchor ends."""
        if self.base is None or self.ended:
            return
        if fixation_id != self.fixation_id or ray is None:
            self.ended = True
            return
        rel = self.base.inverse() @ pose
        dist = float(np.linalg.norm(rel.t))
        k = self._view_k(rel, np.asarray(ray, float)) if dist > 0 else None
        if k is not None:
            self.views.append((stamp, dist, *k))
            self.newest = rel

    def _view_k(self, rel: Pose, ray: np.ndarray) -> tuple[float, float] | None:
        """(k, std): the scale of ``rel.t`` that makes the view's ray point at the anchor point."""
        def residuals(k: np.ndarray) -> np.ndarray:
            d = rel.R.T @ (self.point - k[0] * rel.t) - self.center
            n = np.linalg.norm(d)
            return np.cross(d / n if n > 0 else d, ray) / self.ray_sigma

        try:
            sol = least_squares(residuals, np.array([1.0]), bounds=(1e-3, 1e3), x_scale=1.0, max_nfev=30)
        except (ValueError, np.linalg.LinAlgError):
            return None
        k = float(sol.x[0])
        info = float(sol.jac[:, 0] @ sol.jac[:, 0])
        if not (math.isfinite(k) and info > 0):
            return None
        std = math.sqrt(1.0 / info + (self.rel_point * k) ** 2)
        return (k, std) if math.isfinite(std) else None

    def parallax_deg(self, k: float) -> float:
        """Angle (deg) the point subtends between the anchor frame and the newest view, at scale ``k``."""
        if self.newest is None:
            return 0.0
        a = self.point - self.center
        b = self.point - k * self.newest.t - self.center
        cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
        return math.degrees(math.acos(min(1.0, max(-1.0, cos))))

    def fit(self) -> AnchorFit | None:
        """The factors, or None with too few views or when the recent distances do not give a speed."""
        if len(self.views) < MIN_VIEWS:
            return None
        v = np.array(self.views)
        recent = v[-max(MIN_VIEWS // 2, math.ceil(RECENT_FRACTION * len(v))):]
        t = recent[:, 0] - recent[0, 0]
        metric = recent[:, 1] * recent[:, 2]                       # k_j |t_j|
        w = 1.0 / np.maximum(recent[:, 1] * recent[:, 3], 1e-9)    # 1 / std of k_j |t_j|
        try:
            (slope_m, _), cov = np.polyfit(t, metric, 1, w=w, cov='unscaled')
            slope_e = np.polyfit(t, recent[:, 1], 1)[0]
        except (ValueError, np.linalg.LinAlgError):
            return None
        if not (slope_e > 0 and slope_m > 0 and np.all(np.isfinite(cov))):
            return None
        speed_k = float(slope_m / slope_e)
        rel_std = math.sqrt(max(float(cov[0, 0]), 0.0)) / float(slope_m)
        return AnchorFit(float(v[-1, 2]), speed_k, rel_std) if math.isfinite(rel_std) else None

    def settled(self) -> AnchorFit | None:
        """The fit once it is good enough (:data:`MAX_REL_STD`, :data:`MIN_PARALLAX_DEG`), else None."""
        f = self.fit()
        ok = f is not None and f.rel_std < MAX_REL_STD and self.parallax_deg(f.position_k) >= MIN_PARALLAX_DEG
        return f if ok else None
