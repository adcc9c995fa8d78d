"""Point-level synthetic scenes for the papers' numerical experiments, tests and benchmarks.

Two cameras fixate their own 3D point each (ideal servo: the fixation point projects exactly to the
principal point before noise). Around each fixation point, flow points are drawn so that their images
at frame t fall inside a square window around the fixation pixel, at depths near the fixation depth.
Observations are pixels with Gaussian noise, turned into rig-frame rays with the known pan/tilt,
exactly as the live pipeline does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.geometry.rig import SIDES, Rig, make_rig
from fixego_ros.geometry.rotation import Pose, rot_y, rot_z


@dataclass(frozen=True)
class SceneConfig:
    """Geometry and noise of one synthetic set-up (lengths in arbitrary units, e.g. baseline = 1)."""

    baseline: float = 1.0
    image_size: int = 512
    hfov_deg: float = 21.0
    fixation_depth: float = 10.0
    fixation_distance: float = 10.0    # distance between the two fixation points
    n_flow: int = 3                    # flow points per camera per step
    window_px: float = 20.0            # side of the square window the flow points are drawn in
    depth_jitter: float = 0.1          # relative depth spread of flow points around the fixation depth
    noise_px: float = 2.0
    step_length: float = 0.25
    max_yaw_deg: float = 1.0
    pan_offset_rad: float = 0.0        # calibration offsets applied to the rig (tests)
    tilt_offset_rad: float = 0.0

    def rig(self) -> Rig:
        rig = make_rig(self.image_size, self.image_size, self.hfov_deg, self.baseline)
        if self.pan_offset_rad or self.tilt_offset_rad:
            from fixego_ros.geometry.rig import PanTiltCalibration
            cal = PanTiltCalibration(1.0, 1.0, self.pan_offset_rad, self.tilt_offset_rad)
            rig = Rig(rig.right, rig.left, rig.R_L, rig.c_L, cal, cal)
        return rig


def random_motion_sequence(cfg: SceneConfig, n_steps: int, rng: np.random.Generator) -> list[Pose]:
    """The papers' motion model: first step a random direction of length ``step_length`` with a yaw in
    ±max_yaw; each next step rotates the translation about the optical (Z) axis by ±max_yaw and adds
    ±max_yaw to the yaw angle (uniform draws)."""
    lim = np.radians(cfg.max_yaw_deg)
    t = rng.normal(size=3)
    t *= cfg.step_length / np.linalg.norm(t)
    yaw = rng.uniform(-lim, lim)
    steps = [Pose(rot_y(yaw), t)]
    for _ in range(n_steps - 1):
        t = rot_z(rng.uniform(-lim, lim)) @ t
        yaw = yaw + rng.uniform(-lim, lim)
        steps.append(Pose(rot_y(yaw), t.copy()))
    return steps


class PointScene:
    """Fixation points in a world frame (= rig frame at frame 0) and the observation generator."""

    def __init__(self, cfg: SceneConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rig = cfg.rig()
        self.rng = rng
        mid = np.array([-cfg.baseline / 2.0, 0.0, cfg.fixation_depth])
        ang = rng.uniform(-np.pi / 6, np.pi / 6)
        u = np.array([np.cos(ang), np.sin(ang) * 0.2, 0.0])
        u /= np.linalg.norm(u)
        self.fixation = {'right': mid + 0.5 * cfg.fixation_distance * u,
                         'left': mid - 0.5 * cfg.fixation_distance * u}

    def readings(self, pose: Pose) -> dict[str, tuple[float, float]]:
        """Joint readings of each camera fixating its point from rig pose ``pose`` (rig -> world)."""
        inv = pose.inverse()
        return {s: self.rig.aim_readings(s, inv.apply(self.fixation[s])) for s in SIDES}

    def flow_points(self, side: str, pose: Pose, pt: tuple[float, float]) -> np.ndarray:
        """World points whose image at ``pose`` lies in the window around the fixation pixel."""
        cfg, cam = self.cfg, self.rig.camera(side)
        uv = cam.center + self.rng.uniform(-cfg.window_px / 2, cfg.window_px / 2, size=(cfg.n_flow, 2))
        rays = self.rig.pixels_to_rig_rays(side, uv, *pt)
        depth_fix = np.linalg.norm(pose.inverse().apply(self.fixation[side]) - self.rig.center(side))
        depths = depth_fix * (1.0 + self.rng.uniform(-cfg.depth_jitter, cfg.depth_jitter, cfg.n_flow))
        return pose.apply(self.rig.center(side) + rays * depths[:, None])

    def observe(self, side: str, X_world: np.ndarray, pose: Pose,
                pt: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """Noisy and noise-free rig-frame rays of world points seen by ``side`` at rig pose ``pose``."""
        cam = self.rig.camera(side)
        C = self.rig.cam_to_rig(side, *pt)
        d = (pose.inverse().apply(np.atleast_2d(X_world)) - self.rig.center(side)) @ C
        uv = cam.rays_to_pixels(d)
        noisy = uv + self.rng.normal(0.0, self.cfg.noise_px, size=(len(d), 2))
        return (self.rig.pixels_to_rig_rays(side, noisy, *pt), self.rig.pixels_to_rig_rays(side, uv, *pt))

    def frames(self, steps: list[Pose]) -> tuple[list[Pose], list[FrameObservation], list[FrameObservation]]:
        """True rig poses (rig at k -> world), noisy observations and the same without noise, for
        frames 0..len(steps)."""
        poses = [Pose.identity()]
        for s in steps:
            poses.append(poses[-1] @ s)
        readings = [self.readings(p) for p in poses]
        fix = [{s: self.observe(s, self.fixation[s], p, r[s]) for s in SIDES}
               for p, r in zip(poses, readings, strict=True)]
        noisy, clean = [], []
        for k, (p, r) in enumerate(zip(poses, readings, strict=True)):
            cams: dict[str, list[CameraFrame]] = {}
            for s in SIDES:
                if k == 0:
                    prev = curr = (np.zeros((0, 3)), np.zeros((0, 3)))
                else:
                    X = self.flow_points(s, poses[k - 1], readings[k - 1][s])
                    prev = self.observe(s, X, poses[k - 1], readings[k - 1][s])
                    curr = self.observe(s, X, p, r[s])
                C = self.rig.cam_to_rig(s, *r[s])
                cams[s] = [CameraFrame(fix[k][s][i][0], 0, C, prev[i], curr[i]) for i in (0, 1)]
            noisy.append(FrameObservation(float(k), cams['right'][0], cams['left'][0]))
            clean.append(FrameObservation(float(k), cams['right'][1], cams['left'][1]))
        return poses, noisy, clean


PRESETS: dict[str, SceneConfig] = {
    # English paper §4.1: baseline 1, 21 deg, 512 px, fixation depth 10 and 10 apart, 3 flow points
    # per camera in a 20x20 px window, 2 px noise, steps of 0.25 with <= 1 deg yaw.
    'paper': SceneConfig(),
    # Many well-tracked points in a wide window with sub-pixel noise (what a KLT front end gives).
    'dense': SceneConfig(n_flow=100, window_px=300.0, noise_px=0.1),
    # Japanese version: baseline 0.2 m, fixation depth 2 m, fixation points 2 m apart, 5 cm steps.
    'jp_2m': SceneConfig(baseline=0.2, fixation_depth=2.0, fixation_distance=2.0, step_length=0.05),
    'jp_10m': SceneConfig(baseline=0.2, fixation_depth=2.0, fixation_distance=10.0, step_length=0.05),
}
