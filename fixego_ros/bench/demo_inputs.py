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

``--angles`` adds other head angles (:class:`HeadAngles`), each a column, to measure how much angle error the
estimator tolerates: the true angles with the sigma the camera nodes stated (the weighting of the live run, the
values exact), rounded to the head's reading unit (``--profile``), or with Gaussian noise (``--noise-deg`` per axis
and frame, seeded). Stop 85 measured them (docs/results.md "Stop 85").

``--span START END`` (seconds after the run's first image) and ``--sides`` give those angles to the frames of that
span and those cameras only, the rest as recorded: which frames' angles decide a run. Halving the span finds them in
a dozen replays; stop 86 found a failed run's 25 cm in 0.18 s of one camera (docs/results.md "Stop 86").

    python -m fixego_ros.bench.demo_inputs demo_out [more demo folders ...] [--angles true true-stated quantised noisy]
        [--span 22.7 23.0 --sides left]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

import numpy as np

from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.geometry.rig import SIDES, Rig, load_rig
from fixego_ros.tracking.joint_prediction import PredictionParams

INPUTS = 'estimator_inputs'
STAMP_DECIMALS = 6        # an observation's stamp and a joint state's name the same image


def _key(stamp: float) -> float:
    return round(float(stamp), STAMP_DECIMALS)


Angles = dict[str, dict[float, tuple[float, float]]]     # per side, image stamp -> (pan, tilt) readings (rad)


class HeadAngles(Enum):
    """The head angles a replay gives each camera instead of the recorded ones (its rays turned with them)."""

    TRUE = 'true'                   # the simulator's, stated exact (joint_sigma 0)
    TRUE_STATED = 'true-stated'     # the simulator's, with the sigma the camera node stated (the live weighting)
    QUANTISED = 'quantised'         # the simulator's rounded to the head's reading unit, the stated sigma
    NOISY = 'noisy'                 # the simulator's plus Gaussian noise per axis and frame, the stated sigma


def quantised(truth: Angles, unit_rad: tuple[float, float]) -> Angles:
    """``truth`` rounded to the reading unit (pan, tilt), as the head's position inquiry reports it."""
    qp, qt = unit_rad
    return {side: {t: (round(p / qp) * qp, round(q / qt) * qt) for t, (p, q) in v.items()} for side, v in truth.items()}


def noisy(truth: Angles, sigma_rad: float, seed: int = 0) -> Angles:
    """``truth`` plus independent Gaussian noise of ``sigma_rad`` on each axis of each stamp (seeded, in stamp order:
    the same draw for the same folder)."""
    rng = np.random.default_rng(seed)
    out: Angles = {}
    for side in sorted(truth):
        stamps = sorted(truth[side])
        e = sigma_rad * rng.standard_normal((len(stamps), 2))
        out[side] = {t: (truth[side][t][0] + a, truth[side][t][1] + b) for t, (a, b) in zip(stamps, e, strict=True)}
    return out


@dataclass(frozen=True)
class Span:
    """The frames and cameras a replay gives other head angles (the rest keep the recorded ones): image stamps from
    ``start_s`` up to ``end_s`` seconds after the run's first image, of the cameras in ``sides``."""

    start_s: float = -math.inf
    end_s: float = math.inf
    sides: tuple[str, ...] = SIDES

    def __post_init__(self) -> None:
        if math.isnan(self.start_s) or math.isnan(self.end_s) or not self.start_s < self.end_s:
            raise ValueError(f'a span needs start < end, got {self.start_s} .. {self.end_s}')
        if not self.sides or set(self.sides) - set(SIDES):
            raise ValueError(f'a span\'s sides are some of {SIDES}, got {self.sides}')


def within(truth: Angles, span: Span) -> Angles:
    """``truth`` for the stamps and sides of ``span`` only (:class:`TrueHeads` leaves the other cameras as
    recorded). The run's first image is the earliest stamp of either side."""
    first = min((t for v in truth.values() for t in v), default=0.0)
    return {side: ({t: q for t, q in v.items() if span.start_s <= t - first < span.end_s}
                   if side in span.sides else {}) for side, v in truth.items()}


class TrueHeads:
    """``replay``'s observe hook: each camera at its true head angles (see the module docstring). ``truth``: per side,
    image stamp -> true (pan, tilt) readings. A camera whose stamp has no true angles, or whose flow starts at a frame
    that had none, keeps what was recorded (counted in :attr:`missing`). The angles given are stated exact
    (``joint_sigma`` 0) unless ``keep_sigma``: then each camera keeps the sigma its camera node stated."""

    def __init__(self, rig: Rig, truth: Angles, keep_sigma: bool = False) -> None:
        self.rig = rig
        self.keep_sigma = keep_sigma
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
                       joint_sigma=0.0 if q is not None and not self.keep_sigma else cam.joint_sigma)


class DemoInputsError(Exception):
    """A demo folder that cannot be replayed this way (the message says why)."""


@dataclass
class RunRow:
    """One demo run: mean / terminal position error (cm, no alignment) live, replayed, and replayed with each of the
    head angles asked for."""

    name: str
    live: tuple[float, float] | None
    replayed: tuple[float, float]
    angles: dict[HeadAngles, tuple[float, float]] = field(default_factory=dict)
    missing: int = 0          # cameras left as recorded (no true angles, or outside the span; first variant)

    def line(self) -> str:
        cell = lambda v: 'n/a' if v is None else f'{v[0]:.2f} / {v[1]:.2f}'  # noqa: E731
        return '| ' + ' | '.join([self.name, cell(self.live), cell(self.replayed),
                                  *(cell(v) for v in self.angles.values())]) + ' |'


def true_angles(bag, topics) -> Angles:
    """Per side, stamp -> the simulator's true (pan, tilt) readings from the bag's ground_truth joint states."""
    from fixego_ros.pipeline.messages import pan_tilt, stamp_to_sec
    names = {topics.name(f'ground_truth/{side}/joint_states'): side for side in SIDES}
    if not all(n in bag.topics for n in names):
        raise DemoInputsError(f'{bag.path}: no {" / ".join(names)} (a demo before stop 82 did not record them)')
    out: Angles = {side: {} for side in SIDES}
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


@dataclass(frozen=True)
class AngleSettings:
    """What the :class:`HeadAngles` other than TRUE need: the head's reading unit (rad, pan and tilt) and the noise."""

    unit_rad: tuple[float, float] = PredictionParams().quantum_rad      # an EVI-D30's (pan, tilt)
    noise_rad: float = math.radians(0.05)
    seed: int = 0
    span: Span = Span()     # where they replace the recorded angles (everywhere by default)


def head_angles(which: HeadAngles, rig: Rig, truth: Angles, settings: AngleSettings) -> TrueHeads:
    """The observe hook that gives the cameras of ``settings.span`` ``which`` angles."""
    if which is HeadAngles.QUANTISED:
        truth = quantised(truth, settings.unit_rad)
    elif which is HeadAngles.NOISY:
        truth = noisy(truth, settings.noise_rad, settings.seed)
    return TrueHeads(rig, within(truth, settings.span), keep_sigma=which is not HeadAngles.TRUE)


def run_dir(folder: str | Path, angles: tuple[HeadAngles, ...] = (HeadAngles.TRUE,),
            settings: AngleSettings | None = None) -> RunRow:
    """Replay one demo folder's estimator inputs as recorded and with each of ``angles``."""
    from fixego_ros.bags.reader import Bag, BagError
    from fixego_ros.replay.run import ReplayError, ReplaySettings, ReplayTopics, bag_defaults, replay

    folder = Path(folder)
    settings = settings or AngleSettings()
    try:
        bag = Bag(folder / INPUTS)
        rig = load_rig(folder / INPUTS / 'rig.yaml')
        topics = ReplayTopics()
        replay_settings = ReplaySettings.from_getters(rig, **bag_defaults(bag, topics))
        truth = true_angles(bag, topics)
        row = RunRow(folder.name, _live(folder), _errors(replay(bag, rig, replay_settings, topics)))
        for i, which in enumerate(angles):
            hook = head_angles(which, rig, truth, settings)
            row.angles[which] = _errors(replay(bag, rig, replay_settings, topics, observe=hook))
            if i == 0:
                row.missing = hook.missing
    except (BagError, ReplayError, OSError, ValueError) as e:
        raise DemoInputsError(f'{folder}: {" ".join(str(e).split())}') from None
    return row


def _summary(what: str, cells: list[tuple[float, float]]) -> str:
    ok = sum(1 for m, t in cells if m <= 5.0 and t <= 5.0)
    medians = [float(np.median([c[k] for c in cells])) if cells else math.nan for k in (0, 1)]
    return f'{what}: {ok} of {len(cells)} within 5 / 5 cm; median {medians[0]:.2f} / {medians[1]:.2f} cm'


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m fixego_ros.bench.demo_inputs', description=__doc__.split('\n\n')[0])
    ap.add_argument('folders', nargs='+', type=Path, help='fixego demo output folders (with estimator_inputs/)')
    ap.add_argument('--angles', nargs='+', choices=[a.value for a in HeadAngles], default=[HeadAngles.TRUE.value],
                    help='head angles to replay with besides the recorded ones, a column each (default: true)')
    ap.add_argument('--noise-deg', type=float, default=0.05, help='noisy: Gaussian noise per axis and frame (deg)')
    ap.add_argument('--profile', default='evi_d30', help="quantised: the camera profile whose reading unit to use")
    ap.add_argument('--span', nargs=2, type=float, metavar=('START', 'END'),
                    help="those angles only for images START..END s after the run's first (the rest as recorded)")
    ap.add_argument('--sides', nargs='+', choices=SIDES, default=list(SIDES), help='... and only for these cameras')
    args = ap.parse_args(argv)
    from fixego_ros.visca.profiles import get_profile
    try:
        profile = get_profile(args.profile)
    except (ValueError, OSError) as e:
        ap.error(str(e))
    if not (math.isfinite(args.noise_deg) and args.noise_deg >= 0.0):
        ap.error(f'--noise-deg must be finite and >= 0, got {args.noise_deg}')
    angles = tuple(dict.fromkeys(HeadAngles(a) for a in args.angles))
    unit = (math.radians(1.0 / profile.pan_units_per_deg), math.radians(1.0 / profile.tilt_units_per_deg))
    try:
        span = Span(*(args.span or ()), sides=tuple(s for s in SIDES if s in args.sides))
    except ValueError as e:
        ap.error(str(e))
    settings = AngleSettings(unit, math.radians(args.noise_deg), span=span)
    partial = span != Span()
    print('| run | live mean / terminal cm | replayed | ' + ' | '.join(a.value for a in angles) + ' |')
    print('|---|---|---|' + '---|' * len(angles))
    rows = []
    for folder in args.folders:
        try:
            row = run_dir(folder, angles, settings)
        except DemoInputsError as e:
            print(f'python -m fixego_ros.bench.demo_inputs: {e}', file=sys.stderr)
            continue
        rows.append(row)
        note = ('outside the span or without true angles' if partial else 'without true angles')
        print(row.line() + (f' ({row.missing} cameras {note})' if row.missing else ''), flush=True)
    if not rows:
        return 1
    print(_summary('live', [r.live for r in rows if r.live is not None]))
    print(_summary('replayed', [r.replayed for r in rows]))
    for a in angles:
        print(_summary(a.value, [r.angles[a] for r in rows]))
    return 0


if __name__ == '__main__':
    sys.exit(main())
