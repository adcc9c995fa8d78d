"""Point-level runs with persistent landmarks: the estimator's test bed without images.

Static points cover the walls, floor and ceiling of a room around a simulator trajectory
(:mod:`fixego_ros.sim.trajectories`). Each camera fixates one of them with an ideal servo, re-selects a
point on the other side when its head comes near the pan limit (as the camera nodes do), and tracks
the points whose image lies in the flow window around the image centre for as long as they stay there
(persistent ids; a point that leaves and comes back gets a new id, as a real tracker would give).
Pixels carry Gaussian noise and become rig-frame rays exactly as in the live pipeline. This isolates
the estimator -- scale carried by landmarks, window refinement, scale aids -- from image tracking, and
runs in a fraction of a second per loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.geometry.rig import SIDES, Rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.sim.trajectories import AREA_CENTRE, Trajectory, relative_poses


@dataclass(frozen=True)
class LandmarkSceneConfig:
    fps: float = 5.1
    noise_px: float = 0.3
    density_per_m2: float = 300.0     # points per square metre of wall
    room_half_m: float = 3.5          # half side of the square room around the trajectory's area
    room_height_m: float = 2.8
    window_px: float = 100.0          # flow window (square, centred on the fixation pixel)
    max_tracks: int = 40              # tracks per camera at most
    pan_limit_deg: float = 100.0
    limit_margin_deg: float = 5.0
    reselect_pan_deg: float = 30.0    # a re-selected point is this far from the zero pan on the other side
    initial_pan_deg: float = 30.0     # right camera looks this far right at the start, the left as far left
    seed: int = 0


def room_points(cfg: LandmarkSceneConfig, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) world points on the four walls, floor and ceiling of the room."""
    h, H = cfg.room_half_m, cfg.room_height_m
    cx, cy = AREA_CENTRE
    faces = [  # (origin, u, v) spanning each face
        (np.array([cx - h, cy - h, 0.0]), np.array([2 * h, 0, 0]), np.array([0, 0, H])),
        (np.array([cx - h, cy + h, 0.0]), np.array([2 * h, 0, 0]), np.array([0, 0, H])),
        (np.array([cx - h, cy - h, 0.0]), np.array([0, 2 * h, 0]), np.array([0, 0, H])),
        (np.array([cx + h, cy - h, 0.0]), np.array([0, 2 * h, 0]), np.array([0, 0, H])),
        (np.array([cx - h, cy - h, 0.0]), np.array([2 * h, 0, 0]), np.array([0, 2 * h, 0])),
        (np.array([cx - h, cy - h, H]), np.array([2 * h, 0, 0]), np.array([0, 2 * h, 0])),
    ]
    pts = []
    for o, u, v in faces:
        n = int(cfg.density_per_m2 * np.linalg.norm(u) * np.linalg.norm(v))
        a, b = rng.uniform(size=(2, n, 1))
        pts.append(o + a * u + b * v)
    return np.concatenate(pts)


@dataclass
class LandmarkRun:
    stamps: np.ndarray
    poses: list[Pose]                  # true rig poses, rig frame at the first frame = world
    observations: list[FrameObservation]
    reselections: int
    fixation_points: list[dict[str, np.ndarray]]   # true fixation point of each camera, rig frame at the frame

    def standing(self, k: int, n: int) -> list[FrameObservation]:
        """``n`` frames after frame ``k`` (at its period) with the rig standing where it was at ``k`` while both
        heads took new points as it stopped (the live demo's end): every track and fixation id new in each frame, so
        no landmark seen before places them, and no flow."""
        obs = self.observations[k]
        dt = obs.stamp - self.observations[k - 1].stamp
        frames = []
        for j in range(1, n + 1):
            new = 10 ** 6 * j
            cams = {side: replace(cam, track_ids=cam.track_ids + new, fixation_id=cam.fixation_id + new,
                                  flow_prev=cam.track_rays, flow_curr=cam.track_rays)
                    for side, cam in (('right', obs.right), ('left', obs.left))}
            stamp = obs.stamp + dt * j
            frames.append(replace(obs, stamp=stamp, prev_stamp=stamp - dt, **cams))
        return frames


class LandmarkScene:
    def __init__(self, rig: Rig, cfg: LandmarkSceneConfig | None = None) -> None:
        self.rig = rig
        self.cfg = cfg or LandmarkSceneConfig()
        self.rng = np.random.default_rng(self.cfg.seed)
        self.points = room_points(self.cfg, self.rng)

    def _pixels(self, side: str, X: np.ndarray, pose: Pose, reading: tuple[float, float]) -> np.ndarray:
        cam = self.rig.camera(side)
        d = (pose.inverse().apply(X) - self.rig.center(side)) @ self.rig.cam_to_rig(side, *reading)
        uv = np.full((len(X), 2), np.nan)
        front = d[:, 2] > 0.05
        if np.any(front):
            uv[front] = cam.rays_to_pixels(d[front])
        return uv

    def _pick(self, side: str, pose: Pose, pan_deg: float) -> int:
        """Index of the point nearest the optical axis of a head at ``pan_deg`` (tilt 0) from ``pose``."""
        C = self.rig.cam_to_rig(side, math.radians(pan_deg), 0.0)
        rel = pose.inverse().apply(self.points_rel) - self.rig.center(side)
        return int(np.argmax(rel @ C[:, 2] / np.linalg.norm(rel, axis=1)))

    def run(self, traj: Trajectory, duration: float | None = None) -> LandmarkRun:
        cfg, rig = self.cfg, self.rig
        stamps, world = traj.sample(cfg.fps)
        if duration is not None:
            keep = stamps <= duration + 1e-9
            stamps, world = stamps[keep], [p for p, k in zip(world, keep, strict=True) if k]
        poses = relative_poses(world)
        self.points_rel = world[0].inverse().apply(self.points)
        X = self.points_rel
        half = cfg.window_px / 2.0
        limit = math.radians(cfg.pan_limit_deg - cfg.limit_margin_deg)
        fix = {s: self._pick(s, poses[0], (1 if s == 'right' else -1) * cfg.initial_pan_deg) for s in SIDES}
        fix_id = dict.fromkeys(SIDES, 0)
        tracks: dict[str, dict[int, int]] = {s: {} for s in SIDES}     # point index -> track id
        next_id = dict.fromkeys(SIDES, 0)
        prev: dict[str, tuple[dict[int, np.ndarray], tuple[float, float]] | None] = dict.fromkeys(SIDES)
        out: list[FrameObservation] = []
        fixation_points: list[dict[str, np.ndarray]] = []
        reselections = 0
        for k, (t, pose) in enumerate(zip(stamps, poses, strict=True)):
            cams = {}
            for s in SIDES:
                reading = rig.aim_readings(s, pose.inverse().apply(X[fix[s]]))
                if abs(reading[0]) > limit:
                    side_sign = -1.0 if reading[0] > 0 else 1.0
                    fix[s] = self._pick(s, pose, side_sign * cfg.reselect_pan_deg)
                    fix_id[s] += 1
                    reselections += 1
                    tracks[s] = {}
                    reading = rig.aim_readings(s, pose.inverse().apply(X[fix[s]]))
                cam = rig.camera(s)
                uv = self._pixels(s, X, pose, reading)
                centre = cam.center
                inside = np.all(np.abs(uv - centre) <= half, axis=1)
                inside[fix[s]] = False
                # keep live tracks that are still inside; add new ones up to max_tracks
                live = {i: tid for i, tid in tracks[s].items() if inside[i]}
                free = cfg.max_tracks - len(live)
                if free > 0:
                    cand = np.flatnonzero(inside)
                    cand = cand[~np.isin(cand, list(live))]
                    if len(cand) > free:
                        cand = self.rng.choice(cand, free, replace=False)
                    for i in sorted(cand.tolist()):
                        live[i] = next_id[s]
                        next_id[s] += 1
                tracks[s] = live
                idx = np.array(sorted(live), int)
                noisy = uv[idx] + self.rng.normal(0.0, cfg.noise_px, size=(len(idx), 2))
                rays = rig.pixels_to_rig_rays(s, noisy, *reading) if len(idx) else np.zeros((0, 3))
                fpx = uv[fix[s]] + self.rng.normal(0.0, cfg.noise_px, size=2)
                fray = rig.pixels_to_rig_rays(s, fpx[None], *reading)[0]
                now = {i: r for i, r in zip(idx.tolist(), rays, strict=True)}
                frame = CameraFrame(fray, fix_id[s], rig.cam_to_rig(s, *reading),
                                    track_ids=np.array([live[i] for i in idx.tolist()], np.int64),
                                    track_rays=rays)
                if prev[s] is not None:
                    before = prev[s][0]
                    common = [i for i in idx.tolist() if i in before]
                    if common:
                        frame.flow_prev = np.array([before[i] for i in common])
                        frame.flow_curr = np.array([now[i] for i in common])
                prev[s] = (now, reading)
                cams[s] = frame
            fixation_points.append({s: pose.inverse().apply(X[fix[s]]) for s in SIDES})
            out.append(FrameObservation(float(t), cams['right'], cams['left'],
                                        float(stamps[k - 1]) if k else None, True))
        return LandmarkRun(stamps, poses, out, reselections, fixation_points)
