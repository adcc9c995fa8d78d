"""White noise on rays: how much a replay's result depends on the last bits of its input.

The seed benchmark (:mod:`.seeds`) replays each bag again with every ray the front end hands on perturbed by a
hundredth of a pixel (:class:`RayJitter`), far below the front end's own error (0.05-0.2 px), and the oracle
(:mod:`.oracle`) adds larger noise to exact rays. At stop 55 a 0.005 px perturbation moved one seed of the papers'
loop from 11.2 to 57.6 cm mean (docs/results.md "Stop 55"): one replay per seed does not say how a change of the
method fares, several draws do.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.geometry.rig import SIDES, Rig, normalize_rays


def jittered(rays: np.ndarray, sigma_rad: float, rng: np.random.Generator) -> np.ndarray:
    """Unit rays (N, 3) with white noise of ``sigma_rad`` per axis (renormalised); as they are for a zero sigma or
    no rays."""
    rays = np.asarray(rays, float).reshape(-1, 3)
    if sigma_rad <= 0 or not len(rays):
        return rays
    return normalize_rays(rays + rng.normal(0.0, sigma_rad, rays.shape))


@dataclass
class RayJitter:
    """``observe`` hook of :func:`~fixego_ros.replay.run.replay`: every ray of each camera (tracks, fixation, flow
    pairs) with ``px`` pixels of white noise per axis at that camera's focal length; seeded, so a draw repeats."""

    rig: Rig
    px: float
    seed: int = 0
    rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.px) and self.px >= 0):
            raise ValueError(f'px must be finite and >= 0, got {self.px!r}')
        self.rng = np.random.default_rng(self.seed)

    def __call__(self, obs: FrameObservation) -> FrameObservation:
        cams = {side: self._camera(side, obs.camera(side)) for side in SIDES}
        return replace(obs, right=cams['right'], left=cams['left'])

    def _camera(self, side: str, cam: CameraFrame | None) -> CameraFrame | None:
        if cam is None or self.px <= 0:
            return cam
        sigma = self.px / self.rig.camera(side).fx
        fixation = cam.fixation_ray
        if fixation is not None and np.all(np.isfinite(fixation)):
            fixation = jittered(fixation, sigma, self.rng)[0]
        return replace(cam, fixation_ray=fixation, track_rays=jittered(cam.track_rays, sigma, self.rng),
                       flow_prev=jittered(cam.flow_prev, sigma, self.rng),
                       flow_curr=jittered(cam.flow_curr, sigma, self.rng))
