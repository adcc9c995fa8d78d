"""Live demo runs replayed from their estimator inputs, as recorded and with the simulator's true head angles: how
much of a run's error its joint states make (issue 17).

``fixego demo`` writes ``estimator_inputs/`` beside its report: the flow node's observations, the vergence
measurements, and the simulator's true pose and head angles at each image stamp. Each demo folder given is replayed
twice, as ``fixego replay`` replays such a bag (the estimator alone, deterministic):

* **as recorded**: the live observations. The live estimator's child may have left frames out while it was behind;
  replay never is, so this is the run's estimate without the machine's timing;
* **true head angles**: every observation's camera rotations are the ones the true pan/tilt give, and its rays are
  turned with them (a ray is the camera's own measurement turned by the reading; the measurement is kept). The
  readings are then exact (``joint_sigma`` 0).

The difference is what the camera nodes' joint states cost the run. On this stop's recorded runs it was most of a
failed run's terminal error in some (docs/results.md "Stop 82"), and nothing in others.

    python -m fixego_ros.bench.demo_inputs demo_out [more demo folders ...]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.geometry.rig import SIDES, Rig, load_rig

INPUTS = 'estimator_inputs'
STAMP_DECIMALS = 6        # an observation's stamp and a joint state's name the same image


def _key(stamp: float) -> float:
    return round(float(stamp), STAMP_DECIMALS)


class TrueHeads:
    """``replay``'s observe hook: each camera at its true head angles (see the module docstring). ``truth``: per side,
    image stamp -> true (pan, tilt) readings. A camera whose stamp has no true angles, or whose flow starts at a frame
    that had none, keeps what was recorded (counted in :attr:`missing`)."""

    def __init__(self, rig: Rig, truth: dict[str, dict[float, tuple[float, float]]]) -> None:
        self.rig = rig
        self.truth = {side: {_key(t): q for t, q in truth.get(side, {}).items()} for side in SIDES}
        self._turns: dict[tuple[str, float], np.ndarray] = {}     # (side, stamp) -> rotation applied to its rays
        self.missing = 0

    def __call__(self, obs: FrameObservation) -> FrameObservation:
        cams = {side: self._camera(side, obs.camera(side), obs) for side in SIDES}
        return replace(obs, right=cams['right'], left=cams['left'])

    def _camera(self, side: str, cam: CameraFrame | None, obs: FrameObservation) -> CameraFrame | None:
        if cam is None:
            return None
        q = self.truth[side].get(_key(obs.stamp))
        turn = np.eye(3) if q is None else self.rig.cam_to_rig(side, *q) @ np.asarray(cam.cam_to_rig, float).T
        self._turns[(side, _key(obs.stamp))] = turn
        before = self._turns.get((side, _key(obs.prev_stamp))) if obs.prev_stamp is not None else None
        self.missing += (q is None) + (before is None and len(cam.flow_prev) > 0)
        before = np.eye(3) if before is None else before
        ray = None if cam.fixation_ray is None else turn @ np.asarray(cam.fixation_ray, float)
        return replace(cam, cam_to_rig=turn @ cam.cam_to_rig, fixation_ray=ray,
                       flow_prev=np.asarray(cam.flow_prev, float).reshape(-1, 3) @ before.T,
                       flow_curr=np.asarray(cam.flow_curr, float).reshape(-1, 3) @ turn.T,
                       track_rays=np.asarray(cam.track_rays, float).reshape(-1, 3) @ turn.T,
                       joint_sigma=0.0 if q is not None else cam.joint_sigma)


class DemoInputsError(Exception):
    """A demo folder that cannot be replayed this way (the message says why)."""


@dataclass
class RunRow:
    """One demo run: mean / terminal position error (cm, no alignment) live, replayed, with the true head angles."""

    name: str
    live: tuple[float, float] | None
    replayed: tuple[float, float]
    true_heads: tuple[float, float]
    missing: int          # cameras left as recorded for lack of true angles

    def line(self) -> str:
        cell = lambda v: 'n/a' if v is None else f'{v[0]:.2f} / {v[1]:.2f}'  # noqa: E731
        return f'| {self.name} | {cell(self.live)} | {cell(self.replayed)} | {cell(self.true_heads)} |'


def true_angles(bag, topics) -> dict[str, dict[float, tuple[float, float]]]:
    """Per side, stamp -> the simulator's true (pan, tilt) readings from the bag's ground_truth joint states."""
    from fixego_ros.pipeline.messages import pan_tilt, stamp_to_sec
    names = {topics.name(f'ground_truth/{side}/joint_states'): side for side in SIDES}
    if not all(n in bag.topics for n in names):
        raise DemoInputsError(f'{bag.path}: no {" / ".join(names)} (a demo before stop 82 did not record them)')
    out: dict[str, dict[float, tuple[float, float]]] = {side: {} for side in SIDES}
    for m in bag.messages(names):
        side = names[m.topic]
        msg = bag.decode(m)
        out[side][stamp_to_sec(msg.header.stamp)] = pan_tilt(msg, side)
    return out


def _errors(res) -> tuple[float, float]:
    from fixego_ros.evaluation.metrics import evaluate
    pe = evaluate(res.stamps, res.poses, res.gt_stamps, res.gt_poses, anchor_first=True).summary['position_error_m']
    return 100.0 * float(pe['mean']), 100.0 * float(pe['terminal'])


def _live(folder: Path) -> tuple[float, float] | None:
    try:
        pe = json.loads((folder / 'report.json').read_text())['refined']['position_error_m']
        return 100.0 * float(pe['mean']), 100.0 * float(pe['terminal'])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def run_dir(folder: str | Path) -> RunRow:
    """Replay one demo folder's estimator inputs as recorded and with the true head angles."""
    from fixego_ros.bags.reader import Bag, BagError
    from fixego_ros.replay.run import ReplayError, ReplaySettings, ReplayTopics, bag_defaults, replay

    folder = Path(folder)
    try:
        bag = Bag(folder / INPUTS)
        rig = load_rig(folder / INPUTS / 'rig.yaml')
        topics = ReplayTopics()
        settings = ReplaySettings.from_getters(rig, **bag_defaults(bag, topics))
        truth = true_angles(bag, topics)
        recorded = replay(bag, rig, settings, topics)
        oracle = TrueHeads(rig, truth)
        exact = replay(bag, rig, settings, topics, observe=oracle)
    except (BagError, ReplayError, OSError, ValueError) as e:
        raise DemoInputsError(f'{folder}: {" ".join(str(e).split())}') from None
    return RunRow(folder.name, _live(folder), _errors(recorded), _errors(exact), oracle.missing)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m fixego_ros.bench.demo_inputs', description=__doc__.split('\n\n')[0])
    ap.add_argument('folders', nargs='+', type=Path, help='fixego demo output folders (with estimator_inputs/)')
    args = ap.parse_args(argv)
    print('| run | live mean / terminal cm | replayed | true head angles |')
    print('|---|---|---|---|')
    rows = []
    for folder in args.folders:
        try:
            row = run_dir(folder)
        except DemoInputsError as e:
            print(f'python -m fixego_ros.bench.demo_inputs: {e}', file=sys.stderr)
            continue
        rows.append(row)
        print(row.line() + (f' ({row.missing} cameras without true angles)' if row.missing else ''), flush=True)
    if not rows:
        return 1
    for what in ('live', 'replayed', 'true_heads'):
        cells = [getattr(r, what) for r in rows if getattr(r, what) is not None]
        ok = sum(1 for m, t in cells if m <= 5.0 and t <= 5.0)
        medians = [float(np.median([c[k] for c in cells])) if cells else math.nan for k in (0, 1)]
        print(f'{what}: {ok} of {len(cells)} within 5 / 5 cm; median {medians[0]:.2f} / {medians[1]:.2f} cm')
    return 0


if __name__ == '__main__':
    sys.exit(main())
