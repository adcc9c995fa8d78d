"""The simulator's truth against what the front end hands the estimator: a diagnostic of where the error comes from.

A seed of the ``paper`` recipe (:mod:`fixego_ros.bench.seeds`) is simulated again for its true rig poses and head
angles, and its bag replayed as ``fixego replay`` does, with each observation looked at before the estimator gets it:

* **drift**: each track's (and fixation's) scene point is ray-cast into the room at its first sighting, through the
  true head angles, and projected at every later frame; the angle to the front end's ray (through the true angles
  too), in pixels, by the number of frames since the track began. Frame-to-frame LK drifted 0.6 px after 16 frames
  (docs/results.md "Stop 53").
* **exact rays**: the estimator gets those projections instead of the front end's rays, and the true head angles
  instead of the readings: what the back end reaches on perfect observations of the same points.
* **exact rays + noise** (``--noise-px``): the same with white noise of that many pixels per axis on every ray (a
  fixed random seed): how the back end degrades on small, unbiased errors (docs/results.md "Stop 55").
* **true angles**: the front end's own rays, but through the true head angles instead of the joint readings (each
  ray turned from the reading's optical frame into the true one): what the readings' quantisation costs. On the
  papers' loop it separates the seeds that miss the goal into those the readings sink (seed 2: 6.11 -> 0.78 cm mean)
  and those whose scale is off by their vergence measurements (seed 20: 5.89 -> 4.45; docs/results.md "Stop 89").

``--span START END`` (seconds after the first frame) hands on the truth only within that span, to find where a
run goes wrong; the drift is measured over the whole run.

    python -m fixego_ros.bench.oracle [--seeds 1,2,3] [--noise-px 0.15] [--span 9 11]
"""

from __future__ import annotations

import argparse
import math
import tempfile
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

import numpy as np

from fixego_ros.bench.jitter import RayJitter
from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.geometry.rig import SIDES, Rig, normalize_rays
from fixego_ros.geometry.rotation import Pose
from fixego_ros.sim.world import World

AGES = ((1, 2), (2, 4), (4, 8), (8, 16), (16, 10**9))     # frames since the track began, [lo, hi)
STAMP_DECIMALS = 4                                        # a bag stamp and a simulated one name the same frame


@dataclass
class Truth:
    """The simulated rig at each frame stamp: rig pose (world) and each head's true (pan, tilt)."""

    rig: Rig
    world: World
    frames: dict[float, tuple[Pose, dict[str, tuple[float, float]]]]

    def at(self, stamp: float) -> tuple[Pose, dict[str, tuple[float, float]]] | None:
        return self.frames.get(round(stamp, STAMP_DECIMALS))


def simulate(seed: int, out: Path) -> Truth:
    """Write the ``paper`` recipe with ``seed`` to ``out`` (as :mod:`.seeds` does) and return its truth. The truth
    comes from a second run of the same seeded simulation: the bag writer keeps no head angles."""
    from fixego_ros.bags.shipped import generate
    from fixego_ros.bench.seeds import paper_spec
    from fixego_ros.geometry.rig import default_rig_path, load_rig
    from fixego_ros.sim.run import Simulation, resize_rig
    spec = paper_spec(seed)
    generate(spec, out)
    rig = resize_rig(load_rig(default_rig_path()), spec.width, spec.height)
    sim = Simulation(rig, spec.settings)
    frames = {round(spec.settings.epoch + f.t, STAMP_DECIMALS): (f.rig_pose, {s: (st.pan, st.tilt) for s, st in
                                                                              f.states.items()})
              for f in sim.frames()}
    return Truth(rig, sim.world, frames)


class Substitute(Enum):
    """What :class:`Oracle` hands the estimator instead of the front end's observation."""

    NOTHING = 'front_end'        # the observation as it is (the drift is measured)
    TRUE_ANGLES = 'true_angles'  # the front end's rays through the true head angles
    EXACT = 'exact'              # the true projections of the tracked points, through the true head angles


@dataclass
class Oracle:
    """``observe`` hook of :func:`~fixego_ros.replay.run.replay`: records each ray's drift and hands on what
    ``substitute`` says, within ``span`` (seconds after the first frame of the truth)."""

    truth: Truth
    substitute: Substitute = Substitute.NOTHING
    span: tuple[float, float] = (-math.inf, math.inf)
    points: dict[tuple, np.ndarray | None] = field(default_factory=dict)   # (side, kind, id) -> world point
    seen: dict[tuple, int] = field(default_factory=dict)                   # ... -> frames seen before
    drift: list[tuple[int, float]] = field(default_factory=list)          # (frames since the first, px)
    readings: dict[tuple[float, str], np.ndarray] = field(default_factory=dict)   # each frame's cam_to_rig

    def __call__(self, obs: FrameObservation) -> FrameObservation:
        if self.truth.at(obs.stamp) is None:
            return obs
        cams = {side: self._camera(side, obs.camera(side), obs.stamp, obs.prev_stamp) for side in SIDES}
        within = self.span[0] <= obs.stamp - min(self.truth.frames) <= self.span[1]
        if self.substitute is Substitute.NOTHING or not within:
            return obs
        return replace(obs, right=cams['right'], left=cams['left'])

    def _seen(self, side: str, stamp: float, cam_to_rig: np.ndarray, rays: np.ndarray) -> np.ndarray:
        """``rays`` (rig frame, through ``cam_to_rig``: the readings) through the true head angles instead."""
        _, angles = self.truth.at(stamp)
        return normalize_rays(rays @ cam_to_rig @ self.truth.rig.cam_to_rig(side, *angles[side]).T)

    def _exact(self, side: str, stamp: float, point: np.ndarray) -> np.ndarray:
        pose, _ = self.truth.at(stamp)
        return normalize_rays(pose.R.T @ (point - pose.t) - self.truth.rig.center(side))

    def _camera(self, side: str, cam: CameraFrame | None, stamp: float, key_stamp: float | None
                ) -> CameraFrame | None:
        _, angles = self.truth.at(stamp)
        if cam is None or side not in angles:
            return cam
        rig = self.truth.rig
        self.readings[(round(stamp, STAMP_DECIMALS), side)] = cam.cam_to_rig
        if self.substitute is Substitute.TRUE_ANGLES:     # no scene points needed: no ray-casting, no drift
            return self._through_true_angles(side, cam, stamp, key_stamp)
        track_rays = np.asarray(cam.track_rays, float).reshape(-1, 3)
        keys = [(side, 'track', int(i)) for i in cam.track_ids]
        rays = list(track_rays)
        fix = cam.fixation_ray
        if fix is not None and np.all(np.isfinite(fix)):
            keys.append((side, 'fixation', int(cam.fixation_id)))
            rays.append(np.asarray(fix, float))
        exact: dict[tuple, np.ndarray] = {}
        if rays:
            for key, seen in zip(keys, self._seen(side, stamp, cam.cam_to_rig, np.array(rays)), strict=True):
                point = self._point(key, side, stamp, seen)
                if point is None:
                    continue
                exact[key] = self._exact(side, stamp, point)
                age = self.seen[key] = self.seen.get(key, -1) + 1
                if age:
                    self.drift.append((age, float(np.linalg.norm(np.cross(exact[key], seen))) * rig.camera(side).fx))
        if self.substitute is Substitute.NOTHING:
            return cam
        tracks = np.array([exact.get(k, r) for k, r in zip(keys, track_rays, strict=False)]).reshape(-1, 3)
        fixation = exact.get((side, 'fixation', int(cam.fixation_id)), fix)
        prev, curr = self._pairs(side, cam, stamp, key_stamp)
        return replace(cam, cam_to_rig=rig.cam_to_rig(side, *angles[side]), track_rays=tracks, fixation_ray=fixation,
                       flow_prev=prev, flow_curr=curr)

    def _through_true_angles(self, side: str, cam: CameraFrame, stamp: float, key_stamp: float | None
                             ) -> CameraFrame:
        """``cam`` with the true head angles and every ray of it turned into them (the flow pairs' keyframe rays
        through that frame's readings and angles); a keyframe without a recorded reading leaves its rays as read."""
        _, angles = self.truth.at(stamp)
        true = self.truth.rig.cam_to_rig(side, *angles[side])
        fix = cam.fixation_ray
        if fix is not None and np.all(np.isfinite(fix)):
            fix = self._seen(side, stamp, cam.cam_to_rig, np.asarray(fix, float)[None])[0]
        prev = np.asarray(cam.flow_prev, float).reshape(-1, 3)
        reading = self.readings.get((round(key_stamp, STAMP_DECIMALS), side)) if key_stamp is not None else None
        if len(prev) and reading is not None and self.truth.at(key_stamp) is not None:
            prev = self._seen(side, key_stamp, reading, prev)
        def turned(rays: np.ndarray) -> np.ndarray:
            return self._seen(side, stamp, cam.cam_to_rig, np.asarray(rays, float).reshape(-1, 3))

        return replace(cam, cam_to_rig=true, track_rays=turned(cam.track_rays), fixation_ray=fix, flow_prev=prev,
                       flow_curr=turned(cam.flow_curr))

    def _pairs(self, side: str, cam: CameraFrame, stamp: float, key_stamp: float | None
               ) -> tuple[np.ndarray, np.ndarray]:
        """The flow pairs keyframe -> now, exact: each pair's point ray-cast at the keyframe, projected at both."""
        a = np.asarray(cam.flow_prev, float).reshape(-1, 3)
        reading = self.readings.get((round(key_stamp, STAMP_DECIMALS), side)) if key_stamp is not None else None
        if not len(a) or reading is None or self.truth.at(key_stamp) is None:
            return np.zeros((0, 3)), np.zeros((0, 3))
        prev, curr = [], []
        for seen in self._seen(side, key_stamp, reading, a):
            point = self._cast(side, key_stamp, seen)
            if point is not None:
                prev.append(self._exact(side, key_stamp, point))
                curr.append(self._exact(side, stamp, point))
        return np.array(prev).reshape(-1, 3), np.array(curr).reshape(-1, 3)

    def _cast(self, side: str, stamp: float, ray_rig: np.ndarray) -> np.ndarray | None:
        """Where ``ray_rig`` (rig frame at ``stamp``, true) from the camera centre meets the room."""
        pose, _ = self.truth.at(stamp)
        origin, direction = pose.apply(self.truth.rig.center(side)), pose.R @ ray_rig
        distance, _ = self.truth.world.raycast(origin, direction)
        return origin + distance * direction if np.isfinite(distance) else None

    def _point(self, key: tuple, side: str, stamp: float, ray_rig: np.ndarray) -> np.ndarray | None:
        if key not in self.points:
            self.points[key] = self._cast(side, stamp, ray_rig)
        return self.points[key]

    def drift_table(self) -> dict[str, float]:
        """Median and p90 drift (px) by :data:`AGES`."""
        out: dict[str, float] = {}
        if not self.drift:
            return out
        age, px = np.array(self.drift).T
        for lo, hi in AGES:
            m = (age >= lo) & (age < hi)
            if m.any():
                name = f'{lo}+' if hi > 10**6 else f'{lo}-{hi - 1}'
                out[f'drift_px.{name}.median'] = float(np.median(px[m]))
                out[f'drift_px.{name}.p90'] = float(np.percentile(px[m], 90))
        return out


def run_seed(seed: int, noise_px: float = 0.0, span: tuple[float, float] = (-math.inf, math.inf)
             ) -> dict[str, float]:
    """Drift of the front end's rays, and the trajectory figures with its rays, with them through the true head
    angles, with exact ones and (``noise_px`` > 0) with exact ones plus that much white noise; the truth handed on
    within ``span`` only."""
    from fixego_ros.bench.replay import replay_bag, trajectory_figures
    out: dict[str, float] = {}
    runs = [(s.value, s, 0.0) for s in Substitute]
    if noise_px > 0:
        runs.append((f'exact_noise_{noise_px:g}px', Substitute.EXACT, noise_px))
    with tempfile.TemporaryDirectory(prefix='fixego-oracle-') as tmp:
        path = Path(tmp) / f'paper_{seed}'
        truth = simulate(seed, path)
        for name, substitute, noise in runs:
            oracle = Oracle(truth, substitute, span)
            jitter = RayJitter(truth.rig, noise)            # noise on what the oracle hands on (none at 0 px)
            res = replay_bag(path, 1, observe=lambda obs, o=oracle, j=jitter: j(o(obs)))
            trajectory_figures(out, name, res.stamps, res.poses, res)
            if substitute is Substitute.NOTHING:
                out.update(oracle.drift_table())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m fixego_ros.bench.oracle', description=__doc__.split('\n')[0])
    ap.add_argument('--seeds', default='1', help='comma-separated seeds of the paper recipe')
    ap.add_argument('--noise-px', type=float, default=0.0,
                    help='also run exact rays with this much white noise (px per axis; 0: not)')
    ap.add_argument('--span', type=float, nargs=2, metavar=('START', 'END'), default=(-math.inf, math.inf),
                    help='hand on the truth only from START to END s after the first frame (default: everywhere)')
    args = ap.parse_args(argv)
    if not (np.isfinite(args.noise_px) and args.noise_px >= 0):
        ap.error('--noise-px must be finite and >= 0')
    if math.isnan(args.span[0]) or math.isnan(args.span[1]) or args.span[0] > args.span[1]:
        ap.error('--span needs START <= END')
    for seed in (int(s) for s in args.seeds.split(',')):
        for k, v in run_seed(seed, args.noise_px, tuple(args.span)).items():
            print(f'seed {seed} {k:36s} {v:8.3f}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
