"""The offline pipeline behind ``fixego replay`` (ROS-free, single-threaded, deterministic).

Reads an image-level bag (DESIGN.md §3) in recording order and runs what the live nodes run, in one
process: the fixations, the stamp synchroniser with the bag's clock, the stereo flow front end and the
estimator, with the parameters of the nodes (:mod:`fixego_ros.pipeline.params`). Same bag and settings give
the same output, byte for byte.

Fixations (:class:`FixationSource`): a bag recorded on the rig (``fixego record``) has the camera nodes'
``<side>/fixation`` messages, the points the heads really fixated, and those are used as the live ``flow_node``
uses them (``RECORDED``). A bag with only images and joint states (another simulator, DESIGN.md §3) gets a
passive :class:`~fixego_ros.tracking.fixation.FixationTracker` per camera (``TRACKED``: the recorded heads moved
on their own; it finds the point each keeps near the centre). Re-tracking a rig's bag does not give the run
back: that tracker carries its point across the head's limit swings by template search, so after a swing it
follows another point than the head, 40-90 px off the centre, and the vergence steps measured a point it does
not follow.

Inputs (:class:`ReplayInput`): a bag of the estimator's own inputs, ``flow_node``'s ``<ns>/flow/observation``
messages (what ``fixego demo`` writes beside its report, or ``fixego record`` of that topic on a rig), replays the
estimator alone (``OBSERVATIONS``): each observation goes to the back end as the live node got it, with the bag's
vergence measurements and speed samples, so a live run's estimate can be reproduced and re-run with other estimator
parameters without the images. Such a bag has no images; one with images replays from the images (``IMAGES``).

With ``workers=2`` the estimator runs in a second process fed through a queue (front end and
estimator overlap on two cores); the estimator sees the same observations in the same order, so
the output is identical to ``workers=1``.

Bad data degrades and is reported, never silently: undecodable messages, images of the wrong
encoding or size, non-finite joint states and stamps that go backwards are skipped and counted
(:attr:`ReplayResult.counts`); a cut recording is replayed up to the cut (:attr:`ReplayResult.notes`).
What makes a replay impossible raises :class:`ReplayError` with a one-line reason.

A corrupt bag (:mod:`fixego_ros.bags.reader`: a CRC, the compression or the framing of a record fails) is
replayed up to its first damaged record, like a cut one, and :attr:`ReplayResult.corrupt` says so: the frames
before the damage come from records that passed their checks, so they are kept ("loses nothing"), but the
result is flagged, and ``fixego replay`` exits with 2 after writing it.

Scale aid (off by default, :attr:`ReplaySettings.speed`): nav_msgs/Odometry messages on the speed topic
are converted (:mod:`fixego_ros.pipeline.odometry`) and fed to the back end's ``add_velocity`` in bag order,
through the same queue as the frames (so ``workers=2`` sees the same interleaving); they do not drive the
synchroniser's clock. Unusable ones are skipped and noted once per cause.

Vergence measurements (:attr:`ReplaySettings.vergence_topic`; ``fixego replay`` uses the bag's ``vergence`` topic when
it has one): geometry_msgs/PoseWithCovarianceStamped messages, any number (the left camera_node's repeated
vergence step, or ``fixego sim``), are converted with
:func:`~fixego_ros.pipeline.odometry.vergence_from_msg` and given to the back end's ``add_fixation_point`` as the
right camera's fixation point, through the same queue and without driving the clock, like speed samples.
A message that cannot be converted or that the estimator refuses is skipped and noted.
"""

from __future__ import annotations

import contextlib
import enum
import math
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fixego_ros.bags.reader import Bag, DecodeError
from fixego_ros.estimation.backend import Backend, answers, final_revisions, make_backend, smoother_stage_ms
from fixego_ros.estimation.config import EstimatorConfig
from fixego_ros.estimation.frames import STAMP_TOLERANCE_S, FrameObservation
from fixego_ros.geometry.rig import SIDES, Rig
from fixego_ros.geometry.rotation import Pose, rig_pose_to_base_link
from fixego_ros.interrupt import sigint_ignored
from fixego_ros.pipeline.camera_info import CAMERA_INFO_TYPE, IntrinsicsFromInfo
from fixego_ros.pipeline.frontend import CameraSample, KeyframePolicy, StereoFrontEnd
from fixego_ros.pipeline.messages import (
    CloudError,
    ImageError,
    cloud_to_table,
    fixation_from_msg,
    gray_for_camera,
    joint_sigma,
    msg_to_pose,
    pan_tilt,
    stamp_to_sec,
)
from fixego_ros.pipeline.observation import ROW_DTYPE, ObservationError, rows_to_observation
from fixego_ros.pipeline.odometry import (
    ODOMETRY_TYPE,
    VERGENCE_TYPE,
    OdometryError,
    SpeedInput,
    SpeedSettings,
    VelocitySample,
    vergence_from_msg,
)
from fixego_ros.pipeline.params import (
    ESTIMATOR_PARAMS,
    FIXATION_PARAMS,
    FLOW_PARAMS,
    Getter,
    estimator_config,
    fixation_params,
    flow_params,
    keyframe_policy,
    params_getter,
    sync_params,
)
from fixego_ros.pipeline.sync import StereoSync, SyncedFrame, SyncParams
from fixego_ros.threads import portable_opencv
from fixego_ros.tracking.fixation import NO_FIXATION_ID, FixationParams, FixationTracker
from fixego_ros.tracking.flow import FlowParams

IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')
JOINTS_TYPE = 'sensor_msgs/msg/JointState'
POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
FIXATION_TYPE = 'geometry_msgs/msg/PointStamped'
OBSERVATION_TYPE = 'sensor_msgs/msg/PointCloud2'


class ReplayInput(enum.Enum):
    """What a replay starts from (see the module docstring)."""

    IMAGES = 'images'                # images and joint states: fixations, synchroniser, flow front end, estimator
    OBSERVATIONS = 'observations'    # flow_node's <ns>/flow/observation messages: the estimator alone


class FixationSource(enum.Enum):
    """Where a replay's fixations come from (see the module docstring)."""

    RECORDED = 'recorded'    # the bag's <side>/fixation messages (camera_node's, as the live flow_node takes them)
    TRACKED = 'tracked'      # a passive tracker per camera on the images (bags without fixation messages)


class ReplayError(Exception):
    """The bag cannot be replayed (missing topics, wrong types); the message says what to do."""


@dataclass(frozen=True)
class ReplayTopics:
    """Where the inputs are in the bag: the contract's names under ``namespace`` unless remapped."""

    namespace: str = '/fixego'
    remap: tuple[tuple[str, str], ...] = ()     # (contract topic, bag topic)

    def name(self, suffix: str) -> str:
        default = f'{self.namespace.rstrip("/")}/{suffix}'
        return dict(self.remap).get(default, default)

    def routes(self, fixations: FixationSource = FixationSource.TRACKED,
               inputs: ReplayInput = ReplayInput.IMAGES) -> dict[str, tuple[str, str]]:
        """bag topic -> (kind, side)."""
        if inputs is ReplayInput.OBSERVATIONS:
            return {self.name('flow/observation'): ('observation', ''),
                    self.name('ground_truth/pose'): ('ground_truth', '')}
        out = {self.name(f'{side}/image_raw'): ('image', side) for side in SIDES}
        out.update({self.name(f'{side}/joint_states'): ('joints', side) for side in SIDES})
        if fixations is FixationSource.RECORDED:
            out.update({self.name(f'{side}/fixation'): ('fixation', side) for side in SIDES})
        out[self.name('ground_truth/pose')] = ('ground_truth', '')
        return out


@dataclass(frozen=True)
class ReplaySettings:
    fixation: FixationParams
    flow: FlowParams
    keyframes: KeyframePolicy
    sync: SyncParams
    estimator: EstimatorConfig
    speed: SpeedSettings = field(default_factory=SpeedSettings)      # scale aid; topic '' = off
    vergence_topic: str = ''                                          # vergence measurements; '' = off
    fixations: FixationSource = FixationSource.TRACKED
    inputs: ReplayInput = ReplayInput.IMAGES

    @classmethod
    def from_getters(cls, rig: Rig, camera: Getter | None = None, flow: Getter | None = None,
                     estimator: Getter | None = None, speed: SpeedSettings | None = None,
                     vergence_topic: str = '', fixations: FixationSource = FixationSource.TRACKED,
                     inputs: ReplayInput = ReplayInput.IMAGES) -> ReplaySettings:
        """The nodes' parameters (defaults of :mod:`~fixego_ros.pipeline.params` unless a getter is given)."""
        camera = camera or params_getter(FIXATION_PARAMS)
        flow = flow or params_getter(FLOW_PARAMS)
        estimator = estimator or params_getter(ESTIMATOR_PARAMS)
        return cls(fixation_params(camera), flow_params(flow), keyframe_policy(flow), sync_params(flow),
                   estimator_config(estimator, rig), speed or SpeedSettings(), vergence_topic, fixations, inputs)


@dataclass
class ReplayResult:
    stamps: list[float] = field(default_factory=list)       # frames that got a pose
    poses: list[Pose] = field(default_factory=list)         # refined, base_link in odom
    poses_raw: list[Pose] = field(default_factory=list)     # two-frame only
    gt_stamps: list[float] = field(default_factory=list)
    gt_poses: list[Pose] = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)         # what was read, skipped and why
    steps: Counter = field(default_factory=Counter)          # estimator step statuses
    notes: list[str] = field(default_factory=list)           # degradations, in the order they happened
    corrupt: str = ''        # '' or the bag's corruption line (also in notes): what precedes it was replayed
    stage_ms: dict[str, list[float]] = field(default_factory=dict)
    wall_s: float = 0.0
    bag_duration_s: float = 0.0

    @property
    def realtime_factor(self) -> float:
        return self.bag_duration_s / self.wall_s if self.wall_s > 0 else math.inf

    def note(self, key: str, text: str) -> None:
        """Record a degradation once per ``key`` (the counts say how often it happened)."""
        if key not in self.counts:
            self.notes.append(text)
        self.counts[key] += 1


@dataclass
class _Estimate:
    """What the pipeline keeps of one estimator update (small: it crosses a process boundary)."""

    stamp: float
    placed: bool
    status: str
    message: str
    pose: Pose
    pose_raw: Pose
    ms: float
    prefix_scale: float = 1.0       # the scale was measured here: earlier positions are multiplied by it
    corrected: tuple[float, Pose, Pose] | None = None   # a blind step re-estimated: (stamp, pose, pose_raw)
    revised: tuple[tuple[float, Pose], ...] = ()        # the smoother's newer poses of earlier frames
    smoother_ms: dict[str, list[float]] = field(default_factory=dict)  # its answers' ms by stage, during this update


@dataclass
class _FixationPoint:
    """A vergence measurement on its way to the back end's ``add_fixation_point`` (crosses the process boundary)."""

    stamp: float
    side: str
    point: np.ndarray
    cov: np.ndarray


@dataclass
class _Refused:
    """The estimator refused a fixation point (ValueError): reported by the pipeline, not fatal."""

    stamp: float
    message: str


def _add_point(estimator: Backend, p: _FixationPoint) -> _Refused | None:
    try:
        estimator.add_fixation_point(p.stamp, p.side, p.point, p.cov)
    except ValueError as e:
        return _Refused(p.stamp, str(e))
    return None


def _update(estimator: Backend, stamp: float, obs) -> _Estimate:
    t0 = time.perf_counter()
    before = answers(estimator)
    r = estimator.update(obs)
    mount = estimator.rig.mount
    corrected = None
    if r.corrected is not None:
        c_stamp, c_pose, c_raw = r.corrected
        corrected = (c_stamp, rig_pose_to_base_link(c_pose, mount), rig_pose_to_base_link(c_raw, mount))
    revised = tuple((s, rig_pose_to_base_link(p, mount)) for s, p in r.revised)
    return _Estimate(stamp, r.placed, r.status.value, r.message, rig_pose_to_base_link(r.pose, mount),
                     rig_pose_to_base_link(r.pose_raw, mount), (time.perf_counter() - t0) * 1e3, r.prefix_scale,
                     corrected, revised, smoother_stage_ms(estimator, before))


@dataclass
class _Tail:
    """The revisions the back end still held after the last frame (base_link poses by stamp)."""

    revised: tuple[tuple[float, Pose], ...]


def _tail(estimator: Backend) -> _Tail:
    mount = estimator.rig.mount
    return _Tail(tuple((s, rig_pose_to_base_link(p, mount)) for s, p in final_revisions(estimator)))


@dataclass
class _Failed:
    """The estimator process failed (an exception in the estimator): the one line the parent reports."""

    message: str


def _estimator_worker(factory: Callable[[Rig, EstimatorConfig], Backend], rig: Rig, config: EstimatorConfig,
                      inbox, outbox) -> None:
    """Second process: estimate observations (and take velocity samples and fixation points) from the ``inbox``
    connection in order until None, results (and refused points) to ``outbox``. ``factory`` is the parent's
    :func:`make_backend` (a test may put a spy there), so both processes run the same back end.

    The parent owns this process: Ctrl-C is ignored here (the terminal sends it to the whole process group; the
    parent ends us), and we exit on our own when the parent is gone (killed without cleaning up: its ends of the
    pipes close), so no orphan waits for ever. An exception is sent to the parent as :class:`_Failed`, not
    printed."""
    import multiprocessing as mp
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = mp.parent_process()
    try:
        estimator = factory(rig, config)
        batch: list[_Estimate | _Refused] = []
        while True:
            if not inbox.poll(1.0):
                if parent is not None and not parent.is_alive():
                    return
                continue
            item = inbox.recv()
            if item is None:
                break
            if isinstance(item, VelocitySample):
                estimator.add_velocity(item.stamp, item.v_rig, item.cov_rig)
                continue
            if isinstance(item, _FixationPoint):
                if (refused := _add_point(estimator, item)) is not None:
                    batch.append(refused)
                continue
            batch.append(_update(estimator, *item))
            if len(batch) >= 16:
                outbox.send(batch)
                batch = []
        batch.append(_tail(estimator))
        outbox.send(batch)
        outbox.send(None)
    except (EOFError, BrokenPipeError, ConnectionResetError):     # the parent's ends closed: it has gone or
        return                                                       # given up on us
    except Exception as e:  # reported by the parent in one line; the worker must not print a traceback
        with contextlib.suppress(OSError):
            outbox.send(_Failed(' '.join(f'{type(e).__name__}: {e}'.split())))


class _InProcess:
    def __init__(self, rig: Rig, config: EstimatorConfig) -> None:
        self.estimator = make_backend(rig, config)
        self.done: list[_Estimate] = []
        self.refused: list[_Refused] = []     # fixation points the estimator did not take
        self.tail = _Tail(())

    def submit(self, stamp: float, obs) -> None:
        self.done.append(_update(self.estimator, stamp, obs))

    def submit_velocity(self, s: VelocitySample) -> None:
        self.estimator.add_velocity(s.stamp, s.v_rig, s.cov_rig)

    def submit_fixation_point(self, stamp: float, side: str, point: np.ndarray, cov: np.ndarray) -> None:
        if (refused := _add_point(self.estimator, _FixationPoint(stamp, side, point, cov))) is not None:
            self.refused.append(refused)

    def finish(self) -> list[_Estimate]:
        self.tail = _tail(self.estimator)
        return self.done

    def abort(self) -> None:
        pass


class _Subprocess:
    """The estimator in its own process, fed through two one-way pipes. Every wait is bounded: a worker that
    dies, fails or stalls raises :class:`ReplayError`; :meth:`abort` (any error, Ctrl-C) ends it.

    Pipes rather than ``multiprocessing.Queue``: a queue's named semaphores go through Python's resource tracker,
    which now and then reported one of them as leaked at exit (after replay's last line). The main thread never
    writes to the pipe itself: a sender thread does, so the main thread never blocks on a worker that is busy or
    waiting for its results to be read."""

    def __init__(self, rig: Rig, config: EstimatorConfig, timeout_s: float = 120.0) -> None:
        import multiprocessing as mp
        ctx = mp.get_context('spawn')      # no fork: the parent holds OpenCV's thread pool
        child_in, self._to_child = ctx.Pipe(duplex=False)
        self._from_child, child_out = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_estimator_worker, args=(make_backend, rig, config, child_in, child_out),
                                daemon=True, name='fixego-replay-estimator')
        with sigint_ignored():            # inherited through exec: a Ctrl-C while the child boots is the parent's
            self.proc.start()
        child_in.close()
        child_out.close()
        self._outgoing: queue.SimpleQueue = queue.SimpleQueue()
        self._sender = threading.Thread(target=self._send_in_order, daemon=True, name='fixego-replay-sender')
        self._sender.start()
        self.timeout_s = timeout_s
        self.done: list[_Estimate] = []
        self.refused: list[_Refused] = []     # known once finished
        self.tail = _Tail(())                 # likewise

    def _send_in_order(self) -> None:
        """The sender thread: everything queued, in order, up to and including the end (None)."""
        while True:
            item = self._outgoing.get()
            try:
                self._to_child.send(item)
            except OSError:     # the worker is gone or we aborted (our end closed): finish() or abort() says so
                return
            if item is None:
                return

    def submit(self, stamp: float, obs) -> None:
        self._outgoing.put((stamp, obs))

    def submit_velocity(self, s: VelocitySample) -> None:
        self._outgoing.put(s)

    def submit_fixation_point(self, stamp: float, side: str, point: np.ndarray, cov: np.ndarray) -> None:
        self._outgoing.put(_FixationPoint(stamp, side, point, cov))

    def finish(self) -> list[_Estimate]:
        """All results, in order; the worker has exited when this returns."""
        self._outgoing.put(None)
        quiet_since = time.monotonic()
        while True:
            if not self._from_child.poll(0.5):
                if not self.proc.is_alive() and not self._from_child.poll(0.0):
                    raise ReplayError(f'the estimator process ended unexpectedly (exit code {self.proc.exitcode})')
                if time.monotonic() - quiet_since > self.timeout_s:
                    raise ReplayError(f'the estimator process gave no result for {self.timeout_s:.0f} s')
                continue
            try:
                batch = self._from_child.recv()
            except EOFError:
                self.proc.join(timeout=2.0)
                raise ReplayError(f'the estimator process ended unexpectedly (exit code {self.proc.exitcode})'
                                  ) from None
            if batch is None:
                break
            if isinstance(batch, _Failed):
                raise ReplayError(f'the estimator failed: {batch.message}')
            quiet_since = time.monotonic()
            self.done.extend(e for e in batch if isinstance(e, _Estimate))
            self.refused.extend(e for e in batch if isinstance(e, _Refused))
            self.tail = next((e for e in batch if isinstance(e, _Tail)), self.tail)
        self.proc.join(timeout=5.0)
        self.abort()                       # no-op when it has exited, as it should have
        return self.done

    def abort(self) -> None:
        """End the worker (bounded: terminate, then kill) and close our ends; the sender thread then ends too
        (its write fails), and being a daemon it never holds up the exit."""
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(timeout=2.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(timeout=2.0)
        self._outgoing.put(None)           # a sender still waiting for work stops at once
        self._sender.join(timeout=2.0)
        self._to_child.close()
        self._from_child.close()


class _Timer:
    def __init__(self, result: ReplayResult) -> None:
        self.result = result

    def __call__(self, stage: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.result.stage_ms.setdefault(stage, []).append((t1 - t0) * 1e3)
        return t1


def _revise(res: ReplayResult, index_of: dict[float, int], revised: tuple[tuple[float, Pose], ...]) -> None:
    """The smoother revised earlier frames: the path takes its newer estimates."""
    for stamp, pose in revised:
        k = index_of.get(stamp)
        if k is not None and pose.is_finite():
            res.poses[k] = pose


def vergence_topic_in(bag: Bag, topics: ReplayTopics) -> str:
    """The contract's vergence topic (``<namespace>/vergence``) when the bag lists it with the right type, else ''."""
    name = topics.name('vergence')
    t = bag.topics.get(name)
    return name if t is not None and t.msgtype == VERGENCE_TYPE else ''


def bag_defaults(bag: Bag, topics: ReplayTopics) -> dict[str, Any]:
    """What ``fixego replay`` takes from the bag unless told otherwise (the :class:`ReplaySettings` fields
    ``vergence_topic``, ``fixations`` and ``inputs``): its vergence measurements, its recorded fixations and its
    images, when it has them (its observations when it has those and no images). The benchmarks use the same, so
    they measure what a user's replay does."""
    return {'vergence_topic': vergence_topic_in(bag, topics), 'fixations': fixations_in(bag, topics),
            'inputs': inputs_in(bag, topics)}


def inputs_in(bag: Bag, topics: ReplayTopics) -> ReplayInput:
    """OBSERVATIONS when the bag lists ``<ns>/flow/observation`` (PointCloud2) and neither camera's images, else
    IMAGES (a bag recorded with images replays through the front end, which is what produced its observations)."""
    images = [topics.name(f'{side}/image_raw') for side in SIDES]
    t = bag.topics.get(topics.name('flow/observation'))
    has_obs = t is not None and t.msgtype == OBSERVATION_TYPE
    return ReplayInput.OBSERVATIONS if has_obs and not any(n in bag.topics for n in images) else ReplayInput.IMAGES


def fixations_in(bag: Bag, topics: ReplayTopics) -> FixationSource:
    """RECORDED when the bag lists both cameras' ``<side>/fixation`` with the right type, else TRACKED."""
    names = [topics.name(f'{side}/fixation') for side in SIDES]
    ok = all(n in bag.topics and bag.topics[n].msgtype == FIXATION_TYPE for n in names)
    return FixationSource.RECORDED if ok else FixationSource.TRACKED


def check_topics(bag: Bag, topics: ReplayTopics, speed_topic: str = '', vergence_topic: str = '',
                 fixations: FixationSource = FixationSource.TRACKED, inputs: ReplayInput = ReplayInput.IMAGES
                 ) -> None:
    """Fail early when the bag lists its topics and a required one is missing or of the wrong type."""
    if not bag.topics:
        return          # a cut file without summary or metadata: topics are only known while reading
    listed = ', '.join(sorted(bag.topics)) or 'none'
    for what, name, msgtype in (('speed', speed_topic, ODOMETRY_TYPE), ('vergence', vergence_topic, VERGENCE_TYPE)):
        if not name:
            continue
        t = bag.topics.get(name)
        if t is None:
            raise ReplayError(f'{bag.path}: no {what} topic {name} (topics in the bag: {listed})')
        if t.msgtype != msgtype:
            raise ReplayError(f'{bag.path}: {what} topic {name} is {t.msgtype or "of unknown type"}, '
                              f'expected {msgtype}')
    required = [('image_raw', IMAGE_TYPES), ('joint_states', (JOINTS_TYPE,))]
    if fixations is FixationSource.RECORDED:
        required.append(('fixation', (FIXATION_TYPE,)))
    suffixes = [(f'{side}/{name}', types) for side in SIDES for name, types in required]
    if inputs is ReplayInput.OBSERVATIONS:
        suffixes = [('flow/observation', (OBSERVATION_TYPE,))]
    for suffix, types in suffixes:
        name = topics.name(suffix)
        t = bag.topics.get(name)
        if t is None:
            raise ReplayError(f'{bag.path}: no topic {name} (topics in the bag: {listed}); '
                              f'use --namespace or --remap {name}:=TOPIC')
        if t.msgtype not in types:
            raise ReplayError(f'{bag.path}: {name} is {t.msgtype or "of unknown type"}, expected '
                              f'{" or ".join(types)}')


def intrinsics_from_bag(bag: Bag, rig: Rig, topics: ReplayTopics = ReplayTopics()) -> tuple[Rig, list[str]]:
    """The rig with the intrinsics it lacks taken from the first ``<ns>/<side>/camera_info`` of the bag, and the
    problems found (a CameraInfo that disagrees with the rig file, which wins, or cannot be used). ReplayError
    when a camera still has no intrinsics. Reads only up to the first CameraInfo of each camera."""
    wanted = {topics.name(f'{side}/camera_info'): side for side in SIDES}
    wanted = {t: s for t, s in wanted.items() if t in bag.topics and bag.topics[t].msgtype == CAMERA_INFO_TYPE}
    fill = IntrinsicsFromInfo(rig)
    if wanted:
        for m in bag.messages(wanted):
            side = wanted[m.topic]
            if side in fill.seen:
                continue
            try:
                fill.on_info(side, bag.decode(m))
            except DecodeError as e:
                fill.seen.add(side)
                fill.errors[side] = f'{m.topic}: {e}'
            if fill.seen >= set(wanted.values()):
                break
    missing = fill.rig.missing_intrinsics()
    if missing:
        why = '; '.join(fill.errors[s] for s in missing if s in fill.errors)
        raise ReplayError(f'no intrinsics for the {" and ".join(missing)} camera: the rig file gives none and the '
                          f'bag has no usable {" / ".join(topics.name(f"{s}/camera_info") for s in missing)}'
                          + (f' ({why})' if why else '') + ' (add them to the rig file, or '
                          f'{missing[0]}: {{calibration: FILE.yaml}})')
    return fill.rig, [fill.errors[s] for s in SIDES if s in fill.errors]


def replay(bag: Bag, rig: Rig, settings: ReplaySettings, topics: ReplayTopics = ReplayTopics(),
           progress: Callable[[int], None] | None = None, workers: int = 1,
           observe: Callable[[FrameObservation], FrameObservation] | None = None) -> ReplayResult:
    """Run the pipeline over ``bag``; ``progress(images_done)`` is called as it goes. ``workers=2`` runs
    the estimator in a second process (same output, faster on two cores). ``observe`` sees each front-end
    observation and returns what the estimator gets (diagnostics: :mod:`fixego_ros.bench.oracle`). OpenCV runs
    its portable code paths from here on (:func:`~fixego_ros.threads.portable_opencv`: the same trajectory on any
    CPU)."""
    portable_opencv()
    speed_topic = settings.speed.topic
    observed = settings.inputs is ReplayInput.OBSERVATIONS
    tracked = not observed and settings.fixations is FixationSource.TRACKED    # a passive tracker per camera
    check_topics(bag, topics, speed_topic, settings.vergence_topic, settings.fixations, settings.inputs)
    routes = topics.routes(settings.fixations, settings.inputs)
    if speed_topic:
        routes[speed_topic] = ('speed', '')
    if settings.vergence_topic:
        routes[settings.vergence_topic] = ('vergence', '')
    speed = SpeedInput(settings.speed, rig.mount)
    last_frame: float | None = None      # stamp of the newest frame given to the estimator
    res = ReplayResult()
    clock = _Timer(res)
    trackers = {side: FixationTracker(rig.camera(side), settings.fixation) for side in SIDES} if tracked else {}
    gate_px = settings.estimator.smoother.gate_px
    sync = StereoSync(settings.sync)
    frontend = StereoFrontEnd(rig, settings.flow, settings.keyframes)
    estimator = (_Subprocess if workers > 1 else _InProcess)(rig, settings.estimator)
    last_image = dict.fromkeys(SIDES, -math.inf)
    last_fixation_id: dict[str, int | None] = dict.fromkeys(SIDES)     # recorded fixations: re-selections counted
    now = -math.inf
    wall0 = time.perf_counter()

    verged: list[tuple[float, np.ndarray]] = []     # vergence points whose frame has not been processed yet

    def follow_the_head(frame: SyncedFrame) -> None:
        """A vergence measurement names the point the right head fixates at its stamp. When the passive tracker
        follows another one (it carries its point across the head's swings by template search), it selects anew
        where the measured point projects in the frame's image (or near there on the next image when it is past
        that one), so that the next frame's fixation is the measured point (``Smoother`` carries the measurement to
        it). Measured on a 30 Hz simulated loop: 6 of 7 measurements lay 86-223 px off the replay's fixation and
        were ignored; with this, all 7 were used."""
        right = frame.cameras.get('right')
        due = [v for v in verged if v[0] <= frame.stamp + STAMP_TOLERANCE_S]
        verged[:] = [v for v in verged if v[0] > frame.stamp + STAMP_TOLERANCE_S]
        for v_stamp, point in due:
            if right is None or abs(v_stamp - frame.stamp) > STAMP_TOLERANCE_S:
                continue             # its frame came without the right camera, or went by before the message
            px = rig.rig_points_to_pixels('right', point, right.pan, right.tilt)[0]
            fix = right.fixation_px
            if not np.all(np.isfinite(px)) or (fix is not None and math.dist(fix, px) <= gate_px):
                continue
            tracker, cam = trackers['right'], rig.camera('right')
            if tracker.last is not None and abs(tracker.last.stamp - frame.stamp) <= STAMP_TOLERANCE_S:
                if not tracker.reselect_last((float(px[0]), float(px[1])), 'vergence'):
                    continue         # too close to the border for a template
            else:                    # the tracker is past that image: near there on the next one
                tracker.request_reselect('vergence', (float(px[0] - cam.cx), float(px[1] - cam.cy)))
            res.counts['vergence_reselections'] += 1

    def process(frame: SyncedFrame) -> None:
        nonlocal last_frame
        t0 = time.perf_counter()
        if verged and tracked:
            follow_the_head(frame)
        samples = {side: None if c is None else CameraSample(c.image, c.pan, c.tilt, c.fixation_px, c.fixation_id,
                                                       c.joint_sigma)
                   for side, c in frame.cameras.items()}
        obs = frontend.process(frame.stamp, samples)
        clock('flow', t0)
        estimator.submit(frame.stamp, obs if observe is None else observe(obs))
        last_frame = frame.stamp
        res.counts['frames'] += 1

    try:
        for m in bag.messages(routes):
            kind, side = routes[m.topic]
            t0 = time.perf_counter()
            try:
                msg = bag.decode(m)
            except DecodeError as e:
                res.note(f'undecodable:{m.topic}', f'{e}: skipped')
                continue
            stamp = stamp_to_sec(msg.header.stamp)
            if kind == 'speed':          # does not drive the synchroniser's clock
                try:
                    sample = speed.from_msg(msg, last_frame)
                except OdometryError as e:
                    res.note(f'bad_speed:{e.kind}', f'speed sample on {m.topic} unusable ({e}): such samples '
                                                    'are skipped')
                    continue
                if speed.assumed_frame and 'speed_frame_assumed' not in res.counts:
                    res.note('speed_frame_assumed', f'{m.topic}: empty child_frame_id, twist taken as '
                                                    f'{settings.speed.base_frame}')
                estimator.submit_velocity(sample)
                res.counts['speed_samples'] += 1
                continue
            if kind == 'vergence':       # a one-off measurement: does not drive the clock either
                try:
                    v_stamp, point, cov = vergence_from_msg(msg)
                except ValueError as e:
                    res.note('bad_vergence', f'vergence measurement on {m.topic} unusable ({e}): skipped')
                    continue
                estimator.submit_fixation_point(v_stamp, 'right', point, cov)
                res.counts['vergence'] += 1
                if tracked:
                    verged.append((v_stamp, point))
                continue
            if kind == 'observation':    # flow_node's output: the estimator's input as the live node got it
                try:
                    obs = rows_to_observation(stamp, cloud_to_table(msg, ROW_DTYPE))
                except (CloudError, ObservationError) as e:
                    res.note('bad_observation', f'observation at {stamp:.3f} s unusable ({e}): such messages are '
                                                'skipped')
                    continue
                if last_frame is not None and stamp <= last_frame:
                    res.note('observation_out_of_order', f'observation stamps go backwards at {stamp:.3f} s: such '
                                                         'observations are skipped')
                    continue
                estimator.submit(stamp, obs if observe is None else observe(obs))
                last_frame = stamp
                res.counts['frames'] += 1
                if progress is not None:
                    progress(res.counts['frames'])
                continue
            if kind == 'image':
                res.counts['images'] += 1
                if stamp <= last_image[side]:
                    res.note(f'image_out_of_order:{side}', f'{side} image stamps go backwards at {stamp:.3f} s: '
                                                            f'such images are skipped')
                    continue
                try:
                    gray = gray_for_camera(msg, rig.camera(side))
                except ImageError as e:
                    res.counts[f'bad_image:{side}'] += 1
                    res.note(f'bad_image:{side}:{e.kind}', f'{side} image unusable ({e}): such images are skipped')
                    continue
                last_image[side] = stamp
                t0 = clock('decode', t0)
                sync.add_image(side, stamp, gray, max(now, stamp))
                if tracked:              # recorded: the bag's fixation message completes the camera's part
                    fix = trackers[side].update(gray, stamp)
                    clock('fixation', t0)
                    # as camera_node: a fixation or an explicit "none" for every image (the frame need not wait)
                    sync.add_fixation(side, stamp, fix.pixel, fix.fixation_id if fix.valid else NO_FIXATION_ID)
                    if not fix.valid:
                        res.counts[f'no_fixation:{side}'] += 1
                if progress is not None:
                    progress(res.counts['images'])
            elif kind == 'fixation':
                try:
                    pixel, fid = fixation_from_msg(msg)
                except ValueError as e:
                    res.note(f'bad_fixation:{side}', f'{side} fixation unusable ({e}): such messages are skipped')
                    continue
                if not sync.add_fixation(side, stamp, pixel, fid):
                    res.note(f'fixation_rejected:{side}', f'{side} fixation at {stamp:.3f} s late or out of order: '
                                                           'such messages are skipped')
                    continue
                if pixel is None:
                    res.counts[f'no_fixation:{side}'] += 1
                elif fid != last_fixation_id[side]:
                    res.counts[f'reselections:{side}'] += last_fixation_id[side] is not None
                    last_fixation_id[side] = fid
            elif kind == 'joints':
                try:
                    pan, tilt = pan_tilt(msg, side)
                except ValueError as e:
                    res.note(f'bad_joints:{side}', f'{e}: skipped')
                    continue
                if not sync.add_joints(side, stamp, pan, tilt, joint_sigma(msg, side)):
                    res.note(f'joints_rejected:{side}', f'{side} joint state at {stamp:.3f} s non-finite or out of '
                                                         f'order: such readings are skipped')
                    continue
            else:
                try:
                    res.gt_poses.append(msg_to_pose(msg.pose))
                    res.gt_stamps.append(stamp)
                except ValueError as e:
                    res.note('bad_ground_truth', f'ground truth pose unusable ({e}): skipped')
                continue
            now = max(now, stamp)
            for frame in sync.pop_ready(now):
                process(frame)
        for frame in sync.pop_ready(now, flush=True):
            process(frame)
        estimates = estimator.finish()
    except BaseException:
        estimator.abort()
        raise
    for r in estimator.refused:     # known only now with workers=2: reported the same way for both
        res.counts['vergence'] -= 1
        res.note('bad_vergence', f'vergence measurement at {r.stamp:.3f} s refused by the estimator ({r.message}): '
                                 'skipped')
    index_of: dict[float, int] = {}
    for e in estimates:
        res.stage_ms.setdefault('estimate', []).append(e.ms)
        for stage, ms in e.smoother_ms.items():
            res.stage_ms.setdefault(f'smoother_{stage}', []).extend(ms)
        if not e.placed:
            res.note('frames_not_placed', f'frame at {e.stamp:.3f} s not placed: {e.message}')
            continue
        res.steps[e.status] += 1
        if e.prefix_scale != 1.0:
            # the path so far was built at a nominal speed and a scale aid has measured the real one (the smoother:
            # the part that had left its window before the aid): the written trajectory is the back end's best, so
            # it gets the metric scale
            res.note('prefix_rescaled', f'scale measured by {e.stamp:.3f} s: the {len(res.poses)} poses before it '
                                        f'rescaled by {e.prefix_scale:.3f}')
            res.poses = [Pose(p.R, p.t * e.prefix_scale) for p in res.poses]
            res.poses_raw = [Pose(p.R, p.t * e.prefix_scale) for p in res.poses_raw]
        if e.corrected is not None and res.stamps and abs(res.stamps[-1] - e.corrected[0]) <= 1e-6 \
                and e.corrected[1].is_finite() and e.corrected[2].is_finite():
            res.poses[-1], res.poses_raw[-1] = e.corrected[1], e.corrected[2]   # a blind step bridged late
            res.counts['blind_steps_bridged'] += 1
        if not (e.pose.is_finite() and e.pose_raw.is_finite()):
            res.note('non_finite_pose', f'frame at {e.stamp:.3f} s: non-finite pose left out')
            continue
        _revise(res, index_of, e.revised)
        index_of[e.stamp] = len(res.stamps)
        res.stamps.append(e.stamp)
        res.poses.append(e.pose)
        res.poses_raw.append(e.pose_raw)
    _revise(res, index_of, estimator.tail.revised)     # the smoother's answer to the last frames

    res.wall_s = time.perf_counter() - wall0
    res.notes = bag.report.lines() + res.notes
    res.corrupt = bag.report.corrupt_line()
    damaged = f' ({res.corrupt})' if res.corrupt else ''
    s = sync.stats
    res.counts.update({'sync_frames': s.frames, 'stereo_frames': s.stereo_frames,
                       'single_camera_frames': s.single_camera_frames, 'late_images': s.late_images,
                       'frames_without_joints': s.no_joints})
    if tracked:
        for side in SIDES:
            res.counts[f'reselections:{side}'] = len(trackers[side].reselections)
    if observed and res.counts['frames'] == 0:
        raise ReplayError(f'{bag.path}: no observation on {topics.name("flow/observation")} could be '
                          f'read{damaged}')
    if not observed and res.counts['images'] == 0:
        raise ReplayError(f'{bag.path}: no image on {topics.name("right/image_raw")} or '
                          f'{topics.name("left/image_raw")} could be read{damaged}')
    if not res.stamps:
        raise ReplayError(f'{bag.path}: no frame could be estimated ({"; ".join(res.notes) or "no stereo frame"})')
    res.bag_duration_s = res.stamps[-1] - res.stamps[0]
    gt_sorted = np.all(np.diff(res.gt_stamps) > 0) if len(res.gt_stamps) > 1 else True
    if not gt_sorted:
        order = np.argsort(res.gt_stamps, kind='stable')
        res.gt_stamps = [res.gt_stamps[i] for i in order]
        res.gt_poses = [res.gt_poses[i] for i in order]
        res.notes.append('ground truth stamps were out of order: sorted')
    return res
