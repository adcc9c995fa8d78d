"""Live back end: the fixed-lag smoother in a child process, and a pose for every frame at once.

GTSAM holds the GIL for a whole solve (50-120 ms per frame on this machine), so a smoother in a thread would still
stall the node's callbacks, and one in the callback leaves frames without a pose. :class:`LiveSmoother` runs the
:class:`~fixego_ros.estimation.smoother.Smoother` in a child process and answers each frame itself (~2 ms): the
smoother's newest velocity in the rig's frame carried to the frame's stamp, with the rotation the frame's rays
give with that translation. When the smoother has fallen behind by over ``MAX_CARRY_S`` (or too few rays give the
rotation), the rotation of the two-frame coplanarity solve keyframe -> frame (2-11 ms) with the same translation;
before the smoother has answered, that solve alone, its length at the nominal speed, placed on the keyframe. The
smoother's results revise the path as they arrive (the live pose stays continuous; corrections go to the path).
The child takes every keyframe (later flow starts from them, so they must be in its graph), the frame of each
vergence measurement, and another frame once 0.1 s has passed since the last one it took (:class:`_Gate`).

Replay runs the same class with the smoother in the caller's process (``inline``), through the same gate: the
output is deterministic and the replay does what the node does when its child keeps up, without its timing.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import multiprocessing as mp
import os
import signal
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any

import numpy as np

from fixego_ros.estimation.config import EstimatorConfig
from fixego_ros.estimation.coplanarity import RayPairs
from fixego_ros.estimation.covariance import VAR_MAX, checked_measurement
from fixego_ros.estimation.factors import constant_twist, constant_twists, with_length
from fixego_ros.estimation.frames import (
    STAMP_TOLERANCE_S,
    Fixation,
    FrameObservation,
    FrameResult,
    at_stamp,
    fixations_of,
    span_start,
    step_pairs,
)
from fixego_ros.estimation.stage_times import Stage
from fixego_ros.estimation.status import StepStatus
from fixego_ros.estimation.twoframe import (
    MIN_ROTATION_PAIRS,
    Fallback,
    TwoFrameResult,
    TwoFrameSolver,
    kabsch_rotation,
    rotation_given_translation,
    stands_still,
)
from fixego_ros.geometry.rig import SIDES, Rig
from fixego_ros.geometry.rotation import Pose, exp_so3, log_so3
from fixego_ros.interrupt import sigint_ignored

CHILD_NICENESS = 5     # the smoother yields the CPU to the per-frame work (its results may come late, poses not)


def _halfway(rotation: np.ndarray) -> np.ndarray:
    """The rotation half way along ``rotation``'s geodesic from the identity."""
    return exp_so3(0.5 * log_so3(rotation))


class Message(Enum):
    """What the parent sends the smoother process."""

    FRAME = 'frame'
    VELOCITY = 'velocity'
    POINT = 'point'
    CONFIG = 'config'
    RESET = 'reset'
    STOP = 'stop'


@dataclass(frozen=True)
class SmootherState:
    """The smoother's scale bookkeeping, sent with every result (the parent answers the node's queries from it)."""

    scale_observed: bool = False
    scale_note: str = ''
    scale_measurement: tuple[float, float] | None = None
    speed_source_used: bool = False
    frames_skipped: int = 0
    last_error: str = ''
    restarts: int = 0
    repairs: int = 0
    dropped: int = 0
    resections_rejected: int = 0
    speed_scale: float = 1.0
    speed_scale_estimated: bool = False
    vergence_used: int = 0
    update_ms: float = 0.0      # the smoother's own time for the frame this state came with (its process's CPU share
                                # decides how far behind that puts it)
    stage_ms: dict[str, float] = field(default_factory=dict)    # that time by stage (:class:`.stage_times.Stage`)


def _state(smoother: Any, skipped: int, error: str, update_ms: float) -> SmootherState:
    return SmootherState(scale_observed=smoother.scale_observed, scale_note=smoother.scale_note(),
                         scale_measurement=smoother.scale_measurement, speed_source_used=smoother.speed_source_used,
                         frames_skipped=skipped, last_error=error, restarts=smoother.restarts,
                         repairs=smoother.repairs, dropped=smoother.dropped,
                         resections_rejected=smoother.resections_rejected, speed_scale=smoother.speed_scale,
                         speed_scale_estimated=smoother.speed_scale_estimated, vergence_used=smoother.vergence_used,
                         update_ms=update_ms, stage_ms=smoother.stage_ms)


class _Server:
    """What the smoother side does with each message (the child process's loop and :class:`_Inline` share it)."""

    def __init__(self, rig: Rig, config: EstimatorConfig, marginals: bool = True) -> None:
        from fixego_ros.estimation.smoother import Smoother
        self.smoother = Smoother(rig, config, marginals)
        self.skipped, self.error = 0, ''
        self._points: list[float] = []     # stamps of vergence measurements newer than the smoother's last frame

    def skip(self) -> None:
        self.skipped += 1

    def wanted(self, stamp: float, queue: Iterable[tuple[Message, Any]] = ()) -> bool:
        """Whether a vergence measurement at ``stamp`` has come (or waits in ``queue``) and its frame is not in the
        graph yet: that frame goes in, so the measurement needs no carrying to a neighbour (carried at the nominal
        scale before the first one, a point 1.2 deg off its ray was refused and the 30 Hz walk went without a scale
        for 1.6 s, 40 cm mean, with a 0.2 s gap between frames)."""
        points = [p[0] for k, p in queue if k is Message.POINT] + self._points
        return any(abs(s - stamp) <= STAMP_TOLERANCE_S for s in points)

    def handle(self, kind: Message, payload: Any) -> tuple[FrameResult, SmootherState] | None:
        """Apply one message; a frame's reply (result and state), else None."""
        smoother = self.smoother
        if kind is Message.RESET:
            smoother.reset()
            self.skipped, self.error, self._points = 0, '', []
        elif kind is Message.CONFIG:
            smoother.config = payload
        elif kind is Message.VELOCITY or kind is Message.POINT:
            if kind is Message.POINT:
                last = smoother.last_stamp
                self._points = [s for s in (*self._points, float(payload[0])) if last is None or s > last]
            try:
                (smoother.add_velocity if kind is Message.VELOCITY else smoother.add_fixation_point)(*payload)
            except ValueError as e:
                self.error = str(e)
        elif kind is Message.FRAME:
            self._points = [s for s in self._points if s > payload.stamp + STAMP_TOLERANCE_S]
            t = time.perf_counter()
            result = smoother.update(payload)
            update_ms = (time.perf_counter() - t) * 1e3
            return replace(result, twoframe=None, ba=None), _state(smoother, self.skipped, self.error, update_ms)
        return None


def serve(conn: Any, rig: Rig, config: EstimatorConfig) -> None:
    """The child's loop: drain what the parent sent, then handle the oldest message as :class:`_Gate` admits it (a
    non-keyframe is also left out when a later frame is already waiting); when no message has come for
    ``_Gate.FLUSH_S`` the frame it holds goes in (the end of a run). Ends on STOP or when the parent's end closes
    (the parent exited). Ctrl-C is the parent's (the terminal sends it to the whole process group; the parent stops
    us)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError):      # the camera and flow nodes' frames come first on a busy machine
        os.nice(CHILD_NICENESS)
    server = _Server(rig, config)
    gate = _Gate(server)
    queue: deque[tuple[Message, Any]] = deque()
    while True:
        try:
            while conn.poll(0.0 if queue else (_Gate.FLUSH_S if gate.holding else 1.0)):
                queue.append(conn.recv())
        except (EOFError, OSError):
            return
        if queue:
            kind, payload = queue.popleft()
            if kind is Message.STOP:
                return
            admitted = gate.admit(kind, payload, queue)
        else:
            admitted = gate.flush()
        for message in admitted:
            reply = server.handle(*message)
            if reply is not None:
                try:
                    conn.send(reply)
                except (BrokenPipeError, OSError):
                    return


class _Gate:
    """Which frames go into the smoother's graph, one rule for the child and for :class:`_Inline` (so a replay does
    what the node does when its child keeps up): every keyframe (later flow starts from it), the frame of each
    vergence measurement (:meth:`_Server.wanted`), and another frame once ``min_gap_s`` has passed since the last one
    that went in. The newest frame left out is held: it goes in when a measurement for it follows, or when the
    stream pauses (:meth:`flush`), so that a run's last frame is smoothed. The child also leaves out a non-keyframe
    when a later frame already waits (it is behind).

    Until stop 77 the child took the newest frame whenever it was idle (~12 frames per second of a 30 Hz demo,
    against replay's ~10), so the live path was not the one its replay gives, and it was less accurate. Five demo
    runs' recorded observations fed to the back end in a child at 30 Hz (docs/results.md "Stop 77"; mean / terminal
    cm): the old child 2 of 5 within 5 / 5 cm (median 1.26 / 6.81), this gate 4 of 5 (0.75 / 4.59), within 0.2 cm of
    the same replay inline. With every frame in the graph one of them went from 0.55 / 4.59 to 2.83 / 10.48: in
    single updates the window slid 4-7 cm while the right head swung back from its pan limit.

    The gap: of a bag of 10 Hz or less every frame goes into the graph, of a 30 Hz one its keyframes and about every
    third frame. Measured on 30 Hz bags in replay (mean / terminal cm, wall s; docs/results.md "Stop 38"): every frame
    -> the gap, a simulated loop 3.9 / 6.3 in 272 s -> 3.4 / 6.1 in 54 s, a simulated walk 2.9 / 4.0 in 107 s -> 4.0 /
    5.2 in 41 s, a recorded demo 6.9 / 18.2 in 247 s -> 7.1 / 10.6 in 42 s. Keyframes only was faster still (22-35 s)
    but lost the walk's scale in its first second (34 cm mean), as did a gap of 0.2 s. The frame of each vergence
    measurement goes in too: that was why the 0.2 s gap lost the walk's scale (stop 68). With it, 0.2 s keeps the walk
    (4.86 / 9.27 cm against 4.49 / 8.82) and takes a third fewer updates (339 -> 231 on the 30 Hz loop, 80.6 -> 63.0
    ms median each), but the shipped 10 Hz walk without an aid, half its frames then out of the graph, goes from
    Sim(3) 2.39 to 47.18 cm: kept at 0.1 s."""

    MIN_GAP_S = 0.1        # see the class docstring for why not 0.2
    FLUSH_S = 0.2          # the child takes the frame it holds when nothing has come for this long

    def __init__(self, server: _Server) -> None:
        self.server = server
        self.min_gap_s = self.MIN_GAP_S
        self._last = -math.inf                      # the stamp of the last frame that went in
        self._held: FrameObservation | None = None  # the newest frame left out, while no later one has come

    @property
    def holding(self) -> bool:
        return self._held is not None

    def admit(self, kind: Message, payload: Any, queue: Iterable[tuple[Message, Any]] = ()
              ) -> list[tuple[Message, Any]]:
        """The messages to handle now for this one (none, it, or the held frame and then it); ``queue``: what
        waits behind it."""
        if kind is Message.RESET:
            self._last, self._held = -math.inf, None
        admitted: list[tuple[Message, Any]] = []
        if kind is Message.POINT and self._held is not None and self.server.wanted(self._held.stamp, [(kind, payload)]):
            admitted = self.flush()         # the measurement came just after its frame: that frame goes in first
        if kind is Message.FRAME and not payload.keyframe and not self.server.wanted(payload.stamp, queue) \
                and (payload.stamp < self._last + self.min_gap_s - STAMP_TOLERANCE_S
                     or any(k is Message.FRAME for k, _ in queue)):
            self.server.skip()
            self._held = payload
            return admitted
        if kind is Message.FRAME:
            self._last, self._held = payload.stamp, None
        return [*admitted, (kind, payload)]

    def flush(self) -> list[tuple[Message, Any]]:
        """The held frame, now to go in (no longer counted as skipped); none without one."""
        if self._held is None:
            return []
        held, self._held = self._held, None
        self._last = held.stamp
        self.server.skipped -= 1
        return [(Message.FRAME, held)]


class _Inline:
    """The smoother in this process behind the child's pipe interface, deterministic (replay: the node's back end
    without its timing): each frame goes in, or not, as :class:`_Gate` decides when it is sent, and the frame it holds
    when the caller drains (the end of the run)."""

    def __init__(self, rig: Rig, config: EstimatorConfig) -> None:
        self._server = _Server(rig, config, marginals=False)     # replay writes poses, no covariance
        self.gate = _Gate(self._server)
        self._replies: deque[tuple[FrameResult, SmootherState]] = deque()
        self.closed = False

    def send(self, message: tuple[Message, Any]) -> None:
        kind, payload = message
        if kind is Message.STOP:
            self.closed = True
            return
        self._take(self.gate.admit(kind, payload))

    def flush(self) -> None:
        """The end of the caller's frames: the frame the gate holds goes in."""
        self._take(self.gate.flush())

    def _take(self, messages: list[tuple[Message, Any]]) -> None:
        """Hand messages to the smoother and keep its replies."""
        for kind, payload in messages:
            if (reply := self._server.handle(kind, payload)) is not None:
                self._replies.append(reply)

    def poll(self, timeout: float = 0.0) -> bool:
        return bool(self._replies)

    def recv(self) -> tuple[FrameResult, SmootherState]:
        if not self._replies:
            raise EOFError('no reply waiting')
        return self._replies.popleft()

    def close(self) -> None:
        self.closed = True


@dataclass
class _Recent:
    """What the parent keeps of a frame: its pose (fast, then the smoother's), its raw pose and its fixations."""

    stamp: float
    pose: Pose
    raw: Pose              # two-frame steps at the nominal speed (path_raw): the smoother's chain where it solved
                           # the frame, the live step between
    fixation: dict[str, Fixation | None]
    ref: _Recent | None = None      # the frame its flow starts from, and the step from there: a frame the child
    step: Pose | None = None        # skipped moves with its reference when the smoother revises that
    smoothed: bool = False
    solved: Pose | None = None      # its own two-frame step from ``ref`` when that moved it (direction only)


class LiveSmoother:
    """The node's back end (same interface as :class:`~fixego_ros.estimation.smoother.Smoother`); :meth:`close`
    stops the child process (it also ends by itself when the parent exits)."""

    HISTORY_S = 10.0       # frames kept as references (a keyframe can be this old at most) ...
    MAX_HISTORY_S = 60.0   # ... and as long as the smoother may still revise them, up to this (a stalled child)
    SPEED_WINDOW_S = 0.5   # the speed of the fast poses: the smoother's motion over about this long
    JOIN_S = 2.0           # bound on waiting for the child to stop
    ODOM_CONVERGENCE_S = 1.0   # time constant of the continuous pose closing its gap to the newest estimate
    STAND_FRAMES = 3       # frames in a row whose rays show no parallax before the live pose stands (see _standing)
    MAX_CARRY_S = 0.5      # the rotation read with the carried velocity this far past the smoother's newest frame
                           # (then solved: a stale velocity bends it)

    def __init__(self, rig: Rig, config: EstimatorConfig | None = None, inline: bool = False) -> None:
        """``inline``: the smoother in this process, deterministic (replay); else in a child process (the node). Both
        take the frames :class:`_Gate` admits (the child also leaves out a frame when a later one already waits)."""
        self.rig = rig
        self._config = config or EstimatorConfig()
        self.solver = TwoFrameSolver(self._config.solver)
        self._process: Any = None
        if inline:
            self._conn: Any = _Inline(rig, self._config)
        else:
            ctx = mp.get_context('spawn')      # fork would copy the node's DDS threads and locks into the child
            self._conn, child = ctx.Pipe()
            self._process = ctx.Process(target=serve, args=(child, rig, self._config), daemon=True,
                                        name='fixego-smoother')
            with sigint_ignored():
                self._process.start()
            child.close()
        self.smoothed_results = 0
        self.update_ms: deque[float] = deque(maxlen=300)   # the smoother's time per frame it answered (newest last)
        self.stage_ms: dict[str, deque[float]] = {s.value: deque(maxlen=300) for s in Stage}   # ... by stage
        self._local_reset()

    # ------------------------------------------------------------------------------------------- interface
    @property
    def config(self) -> EstimatorConfig:
        return self._config

    @config.setter
    def config(self, config: EstimatorConfig) -> None:
        self._config = config
        self.solver = TwoFrameSolver(config.solver)
        self._send(Message.CONFIG, config)

    @property
    def scale_measurement(self) -> tuple[float, float] | None:
        return self._state.scale_measurement

    @property
    def speed_source_used(self) -> bool:
        return self._state.speed_source_used

    @property
    def scale_observed(self) -> bool:
        return self._state.scale_observed

    @property
    def speed_scale(self) -> float:
        """The speed source's scale as the smoother last estimated or held it (:attr:`Smoother.speed_scale`)."""
        return self._state.speed_scale

    @property
    def speed_scale_estimated(self) -> bool:
        return self._state.speed_scale_estimated

    def scale_note(self) -> str:
        return self._state.scale_note or (f'scale unobserved: steps at the nominal '
                                          f'{self._config.smoother.nominal_speed:g} m/s until the smoother runs')

    @property
    def frames_skipped(self) -> int:
        """Non-keyframes the smoother left out (:class:`_Gate`; they still got a pose here)."""
        return self._state.frames_skipped

    @property
    def behind_s(self) -> float:
        """How far the smoother's newest result lags the newest frame (s of stamps; 0 before either): the frames
        in between have fast poses only, and the path there waits for its revisions."""
        if self._smoothed_stamp is None or not self._recent:
            return 0.0
        return max(0.0, self._recent[-1].stamp - self._smoothed_stamp)

    @property
    def restarts(self) -> int:
        """The smoother's numerical failures (each starts a new graph at the last estimate)."""
        return self._state.restarts

    @property
    def repairs(self) -> int:
        """The smoother's numerical failures repaired in place (a landmark dropped or a pose held)."""
        return self._state.repairs

    @property
    def dropped(self) -> int:
        """Landmarks the smoother dropped because a pass left them behind a camera that sees them."""
        return self._state.dropped

    @property
    def vergence_used(self) -> int:
        """Vergence measurements the smoother has used so far (:attr:`Smoother.vergence_used`)."""
        return self._state.vergence_used

    @property
    def resections_rejected(self) -> int:
        """Frames the smoother placed at the two-frame step's rotation, not at their resection
        (:attr:`Smoother.RESECTION_AGREEMENT_DEG`)."""
        return self._state.resections_rejected

    @property
    def alive(self) -> bool:
        return self._process is None or self._process.is_alive()

    @property
    def last_stamp(self) -> float | None:
        return self._recent[-1].stamp if self._recent else None

    def stage_samples(self, newest: int) -> dict[str, list[float]]:
        """The smoother's ms by stage for its ``newest`` answers (at most the last 300; replay counts its answers by
        :attr:`smoothed_results` around each update)."""
        n = min(max(newest, 0), 300)
        return {stage: list(ms)[len(ms) - min(n, len(ms)):] for stage, ms in self.stage_ms.items()}

    def wait_for_answer(self, timeout_s: float) -> bool:
        """Whether the smoother process has sent something not yet taken, after waiting at most ``timeout_s``; False
        once it is gone or closed (and inline, whose answers come with each frame). It only looks at the pipe, so
        another thread may call it while this one works: the node's waiter does, and the answers are then taken
        between frames (:meth:`drain`) instead of on the next frame's path."""
        if self._process is None or not self._process.is_alive():
            return False
        with contextlib.suppress(EOFError, OSError, ValueError):
            return bool(self._conn.poll(max(0.0, timeout_s)))
        return False

    def add_velocity(self, stamp: float, v_rig: np.ndarray, cov_rig: np.ndarray) -> None:
        """As :meth:`Smoother.add_velocity` (checked here: ValueError on bad values; the child applies it)."""
        v, cov = checked_measurement(stamp, v_rig, cov_rig, 'velocity sample')
        self._send(Message.VELOCITY, (float(stamp), v, cov))

    def add_fixation_point(self, stamp: float, side: str, point_rig: np.ndarray, cov_rig: np.ndarray) -> None:
        """As :meth:`Smoother.add_fixation_point` (checked here; the child applies it)."""
        if side not in SIDES:
            raise ValueError(f'side must be one of {SIDES}, got {side!r}')
        point, cov = checked_measurement(stamp, point_rig, cov_rig, 'fixation point')
        self._send(Message.POINT, (float(stamp), side, point, cov))

    def reset(self) -> None:
        self._send(Message.RESET, None)
        self._local_reset()

    def close(self) -> None:
        """Stop the child (bounded wait, then terminate); a second call does nothing."""
        if self._conn.closed:
            return
        self._send(Message.STOP, None)
        if self._process is None:
            return
        self._process.join(self.JOIN_S)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(self.JOIN_S)
        self._conn.close()

    def drain(self, timeout_s: float) -> tuple[tuple[float, Pose], ...]:
        """Wait (at most ``timeout_s``; 0 = only what has arrived) until the smoother has answered or skipped every
        frame sent to it, and return its revisions not yet handed out by :meth:`update` (the node takes them
        between frames and after the last), in the path as the caller has it: before a stretch of the smoother's that
        the next result carries (``prefix_scale``), so that stretching the path then stretches these too. Inline,
        the frame the gate holds goes in first: the caller drains after its last frame (the child takes it by itself
        once the frames pause)."""
        if isinstance(self._conn, _Inline):
            self._conn.flush()
        end = time.monotonic() + timeout_s
        while self._sent_frames > self._answered + self._state.frames_skipped and time.monotonic() < end:
            if self._conn.poll(min(0.05, max(0.0, end - time.monotonic()))):
                if not self._receive():
                    break
            elif not self.alive:
                break
        self._receive_all()
        revised, k = self._take_revised(), self._prefix_scale
        return revised if k == 1.0 else tuple((s, Pose(p.R, p.t / k)) for s, p in revised)

    # ------------------------------------------------------------------------------------------- frames
    def update(self, obs: FrameObservation) -> FrameResult:
        """A pose for ``obs`` now (two-frame solve from its keyframe, placed on the smoother's estimate of it), and
        the smoother's revisions that arrived since the last call."""
        self._receive_all()
        last = self.last_stamp
        if last is not None and not obs.stamp > last:
            return self._reject(obs, f'stamp {obs.stamp:.6f} not after the last frame {last:.6f}: ignored')
        self._index += 1
        self._send(Message.FRAME, obs)
        self._sent_frames += 1
        ref = at_stamp(self._recent, obs.prev_stamp if obs.prev_stamp is not None else last)
        messages: list[str] = []
        tf, solved = None, None
        if ref is None:
            pose, step, step_raw = self._predict(obs.stamp), Pose.identity(), Pose.identity()
            if last is not None:
                messages.append('flow reference unknown: pose predicted at constant twist')
        else:
            dt = obs.stamp - ref.stamp
            # once the smoother has answered: its motion carried to this stamp, the rotation from the rays (~0.3 ms);
            # before, the two-frame solve (~2 ms warm; the cold starts cost ~16 ms, so a failed warm solve tries the
            # closed-form starts only, and a frame that still fails is predicted; the child solves it fully)
            pairs = step_pairs(self.rig, ref.fixation, obs, self._config.fixation_weight, self._config.joint_weighting)
            rays = kabsch_rotation(pairs.a, pairs.b)         # the rotation-only fit, read by both tests below
            standing = self._standing(pairs, rays)
            tf = None if standing else self._carried(ref, pairs, rays, obs.stamp)
            if tf is not None:
                step = tf.pose
                pose = (ref.pose @ step).normalized()
            else:
                # the prediction only here: a carried frame does without it (0.3 ms of its ~1.5)
                predicted = self._predict(obs.stamp)
                tf = self.solver.solve(pairs, initial=self._warm_start(ref, predicted, dt),
                                       fallback=Fallback.CLOSED_FORM)
                if standing and tf.status is StepStatus.STATIONARY:
                    step = tf.pose          # the rays saw the rig stand, whatever speed the smoother last had
                    pose = (ref.pose @ step).normalized()
                elif tf.status.usable and tf.pose.is_finite() and tf.cheirality >= 0.5:
                    step = (self._dead_reckoned(self._smoothed_span(), tf.pose.R, dt)
                            or with_length(tf.pose, self._speed() * dt))
                    pose = (ref.pose @ step).normalized()
                    length = float(np.linalg.norm(tf.pose.t))
                    if tf.status is not StepStatus.STATIONARY and length > 0.0:     # a direction to start from
                        solved = tf.pose
                        self._heading = ref.pose.R @ tf.pose.t / length
                else:
                    pose = predicted
                    step = ref.pose.inverse() @ pose
                    messages.append(f'two-frame step not usable ({tf.status.value}): pose predicted at constant '
                                    'twist')
            step_raw = with_length(tf.pose if tf.pose.is_finite() else step,
                                    self._config.smoother.nominal_speed * dt)
        raw_base = ref.raw if ref is not None else (self._recent[-1].raw if self._recent else Pose.identity())
        status = StepStatus.INIT if last is None else (tf.status if tf is not None else StepStatus.REJECTED)
        frame = _Recent(obs.stamp, pose, (raw_base @ step_raw).normalized(), fixations_of(obs), ref, step,
                        solved=solved)
        self._recent.append(frame)
        horizon = self._history_start(obs.stamp)
        while self._recent and self._recent[0].stamp < horizon:
            self._recent.popleft().ref = None
        revised = self._take_revised()
        prefix_scale, self._prefix_scale = self._prefix_scale, 1.0
        odom = self._odom_pose(pose, obs.stamp)
        if self._state.last_error:
            messages.append(f'smoother: {self._state.last_error}')
        unknown = np.diag([1e-2] * 3 + [VAR_MAX] * 3)
        cov = self._pose_cov if self._pose_cov is not None else unknown
        return FrameResult(self._index, obs.stamp, status, pose, frame.raw, step, step_raw,
                           tf.covariance if tf is not None else unknown, cov, '; '.join(messages), tf, None,
                           ref.stamp if ref is not None else None, scale_observed=self.scale_observed,
                           scale_note=self.scale_note(), prefix_scale=prefix_scale, revised=revised, odom=odom)

    # ------------------------------------------------------------------------------------------- pieces
    def _local_reset(self) -> None:
        self._recent: deque[_Recent] = deque()
        self._revised: dict[float, Pose] = {}
        self._state = SmootherState()
        self._pose_cov: np.ndarray | None = None
        self._heading: np.ndarray | None = None     # unit, world: the direction of the last solved moving step
        self._still_frames = 0      # frames in a row whose rays showed no parallax
        self._odom: tuple[Pose, Pose, float] | None = None   # the last frame's odom correction, its pose, stamp
        self._index = -1
        self._sent_frames = 0
        self._answered = 0
        self._smoothed_stamp: float | None = None      # the newest frame the smoother answered
        self._prefix_scale = 1.0    # the smoother's stretch of the path so far, reported with the next result

    def _history_start(self, stamp: float) -> float:
        """The oldest stamp kept: ``HISTORY_S`` back, or further while the smoother may still revise those frames
        (its lag behind the newest frame it has answered, or every frame since a reset before its first answer), at
        most ``MAX_HISTORY_S``. A revision only reaches the path through a frame kept here: the demo's child ran
        7-14 s behind on a busy machine, and the path kept fast poses where the smoother had long revised them (up to
        53 cm from the smoother's own estimate; docs/results.md "Stop 59")."""
        start = stamp - self.HISTORY_S
        if self.alive:
            reach = (self._smoothed_stamp - self._config.smoother.lag_s if self._smoothed_stamp is not None
                     else -math.inf)
            start = min(start, reach)
        return max(start, stamp - self.MAX_HISTORY_S)

    def _take_revised(self) -> tuple[tuple[float, Pose], ...]:
        """The revisions not handed out yet, oldest first; from now on the caller has them."""
        revised, self._revised = tuple(sorted(self._revised.items())), {}
        return revised

    def _send(self, kind: Message, payload: Any) -> None:
        with contextlib.suppress(BrokenPipeError, OSError):   # the child is gone: ``alive`` says so, and
            self._conn.send((kind, payload))                  # frames still get their fast poses

    def _receive_all(self) -> None:
        with contextlib.suppress(EOFError, OSError):
            while self._conn.poll(0.0):
                if not self._receive():
                    break

    def _receive(self) -> int:
        """One result from the child: its pose and revisions go into the recent frames (and out as revisions)."""
        try:
            result, state = self._conn.recv()
        except (EOFError, OSError):
            return 0
        self._state = state
        self._answered += 1
        self.smoothed_results += 1
        self.update_ms.append(state.update_ms)
        for stage, ms in state.stage_ms.items():
            self.stage_ms[stage].append(ms)
        if not result.placed:
            return 1
        self._smoothed_stamp = result.stamp
        if result.prefix_scale != 1.0 and math.isfinite(result.prefix_scale):
            self._stretch(result.prefix_scale)
        updates = {round(s, 6): p for s, p in result.revised}
        updates[round(result.stamp, 6)] = result.pose
        moved: set[int] = set()
        for r in self._recent:
            if abs(r.stamp - result.stamp) <= 1e-6 and result.pose_raw.is_finite():
                r.raw = result.pose_raw     # the smoother's two-frame chain: later raw poses go on from it
            p = updates.get(round(r.stamp, 6))
            if p is not None and p.is_finite():
                r.pose, r.smoothed = p, True
                moved.add(id(r))
            elif not r.smoothed and r.ref is not None and r.step is not None and id(r.ref) in moved:
                r.pose = (r.ref.pose @ r.step).normalized()       # skipped by the child: rides on its reference
                moved.add(id(r))
            else:
                continue
            self._revised[r.stamp] = r.pose
        self._between_smoothed(moved)
        if np.all(np.isfinite(result.pose_covariance)):
            self._pose_cov = result.pose_covariance
        return 1

    def _stretch(self, k: float) -> None:
        """The smoother measured the scale and stretched the path before it (:meth:`Smoother._stretch`): every frame
        kept here is stretched too (the revisions that come with it then place the smoother's frames and those riding
        on them), and the caller is told with the next result."""
        for r in self._recent:
            r.pose, r.raw = Pose(r.pose.R, r.pose.t * k), Pose(r.raw.R, r.raw.t * k)
        self._prefix_scale *= k

    def _between_smoothed(self, moved: set[int]) -> None:
        """A frame the child skipped that now lies between two smoothed frames, one of them just ``moved``, goes on the
        geodesic between them at its stamp. Riding on its reference alone, it kept the step the fast pose had taken,
        and each keyframe's revision left a jump at the next one: the path was a sawtooth (a demo run's refined path
        6.9 m for the 5.0 m loop, its live pose 5.2 m)."""
        recent = list(self._recent)
        smoothed = [k for k, r in enumerate(recent) if r.smoothed]
        for a, b in itertools.pairwise(smoothed):
            ra, rb = recent[a], recent[b]
            if b - a < 2 or not (id(ra) in moved or id(rb) in moved):
                continue
            inner = recent[a + 1:b]
            for r, pose in zip(inner, constant_twists(ra.pose, ra.stamp, rb.pose, rb.stamp, [r.stamp for r in inner]),
                               strict=True):
                if pose.is_finite():
                    r.pose = pose
                    self._revised[r.stamp] = pose

    def _speed(self) -> float:
        """m/s: the smoother's motion over its newest ``SPEED_WINDOW_S``; the nominal speed before there is one."""
        span = self._smoothed_span()
        if span is None:
            return self._config.smoother.nominal_speed
        a, b = span
        return float(np.linalg.norm(b.pose.t - a.pose.t)) / (b.stamp - a.stamp)

    def _smoothed_span(self) -> tuple[_Recent, _Recent] | None:
        """The smoother's newest motion: its frame about ``SPEED_WINDOW_S`` before its newest, and the newest (None
        before two smoothed frames apart in time)."""
        smoothed = [r for r in self._recent if r.smoothed]
        if len(smoothed) < 2:
            return None
        a, b = span_start(smoothed, self.SPEED_WINDOW_S) or smoothed[0], smoothed[-1]
        return (a, b) if b.stamp > a.stamp else None

    def _odom_pose(self, pose: Pose, stamp: float) -> Pose:
        """The continuous pose: ``pose`` behind a correction that takes up each revision of the previous frame (so
        the published pose does not jump with it), then shrinks by a share ``dt / ODOM_CONVERGENCE_S`` per frame.
        Each revision of a keyframe, arriving 0.1-0.5 s late, moves the frames placed on it: the live path of a demo
        run was 1.2-1.6 times the loop's (docs/results.md "Stop 45")."""
        correction = Pose.identity()
        if self._odom is not None and len(self._recent) >= 2:
            before, published, t_prev = self._odom       # the correction then, the previous frame's pose then
            correction = (before @ published @ self._recent[-2].pose.inverse()).normalized()
            share = min(1.0, max(0.0, stamp - t_prev) / self.ODOM_CONVERGENCE_S)
            correction = constant_twist(correction, 0.0, Pose.identity(), 1.0, share)    # that share of the way
            if not correction.is_finite():
                correction = Pose.identity()
        self._odom = (correction, pose, stamp)
        return (correction @ pose).normalized()

    def _standing(self, pairs: RayPairs, rays: np.ndarray) -> bool:
        """Whether the rig stands: the rays of this frame and of the ``STAND_FRAMES`` - 1 before it show no parallax
        (:func:`~fixego_ros.estimation.twoframe.stands_still`). Then the live pose stands; until stop 61 it went on
        at the smoother's last velocity, as far as the smoother lagged (a demo whose rig stood 2 s after the loop:
        /fixego/odom moved 28-40 cm over the 2 s). One such frame is not enough: on a 30 Hz bag 13 of 761 moving
        frames show no parallax, each alone, and standing on every one let the demo's live pose lag the rig by up
        to 36 cm. ``rays``: the pairs' Kabsch rotation."""
        still = len(pairs) >= MIN_ROTATION_PAIRS and stands_still(pairs, rays, self.solver.config)
        self._still_frames = self._still_frames + 1 if still else 0
        return self._still_frames >= self.STAND_FRAMES

    def _carried(self, ref: _Recent, pairs: RayPairs, rays: np.ndarray, stamp: float) -> TwoFrameResult | None:
        """The step ref -> frame dead reckoned (:meth:`_dead_reckoned`) with the rotation the rays give with that
        translation (:func:`~fixego_ros.estimation.twoframe.rotation_given_translation` from their Kabsch fit: one
        Gauss-Newton step, ~0.5 ms, against the solve's 2-11 ms on the loaded demo machine). None before the
        smoother has answered, when its newest frame is over ``MAX_CARRY_S`` old, or with too few rays: then the
        two-frame solve gives the rotation. Kabsch alone takes the parallax of near points for rotation (on a 30 Hz
        walk at 1 m/s, dead reckoned with the smoother 2-5 s behind, the live heading drifted 14 deg/s). Measured
        with the smoother answering at once (``fixego sim`` 30 Hz bags, published poses; docs/results.md "Stop
        57"): the loop 3.60 -> 3.02 cm mean, the walk 31.6 -> 16.7 cm. A stale velocity is worse than solving: with
        the answers held back 1.5 s and no ``MAX_CARRY_S``, the walk went 31.6 -> 52.9 cm. ``rays``: the pairs'
        Kabsch rotation."""
        span = self._smoothed_span()
        if span is None or stamp - span[1].stamp > self.MAX_CARRY_S or len(pairs) < MIN_ROTATION_PAIRS:
            return None
        dt = stamp - ref.stamp
        reckoned = self._dead_reckoned(span, rays, dt)        # its translation, to read the rays' rotation with
        if reckoned is None:
            return None
        solver = self.solver.config
        step = self._dead_reckoned(span, rotation_given_translation(pairs, rays, reckoned.t, solver.sigma,
                                                                    solver.loss_scale, iterations=1), dt)
        if step is None:
            return None
        return TwoFrameResult(step, StepStatus.CARRIED, n_constraints=len(pairs),
                              message="the smoother's velocity in the rig frame carried to the stamp, rotation from "
                                      'the rays')

    @staticmethod
    def _dead_reckoned(span: tuple[_Recent, _Recent] | None, rotation: np.ndarray, dt: float) -> Pose | None:
        """The step over ``dt`` with ``rotation``: its translation the smoother's newest velocity in the rig's own
        frame over ``span`` (:meth:`_smoothed_span`, :meth:`_body_velocity`), turned by half the rotation; None
        before the smoother has a motion (``span`` None).

        In the rig's frame the velocity of a rig whose heading follows its path holds through turns, so this holds
        while the smoother lags by seconds. Until stop 49 the smoother's world-frame twist was carried, and past
        ``MAX_CARRY_S`` each 30 Hz step took the direction of its two-frame solve, which scatters by tens of degrees.
        Recorded runs replayed live with the smoother 1.3-1.8 s behind (p50; two CPU-bound processes beside it):
        run 2 live 38.2 and 26.4 cm mean, path x1.65 and x1.56 that way, 18.6 and 15.7 cm, x1.24 and x1.26 dead
        reckoned; run 4 14.6 cm, x1.46, terminal 75 cm against 15.2 cm, x1.12, 33 cm (docs/results.md "Stop 49")."""
        if span is None:
            return None
        step = Pose(rotation, _halfway(rotation) @ LiveSmoother._body_velocity(*span) * dt)
        return step if step.is_finite() else None

    @staticmethod
    def _body_velocity(a: _Recent, b: _Recent) -> np.ndarray:
        """m/s in the rig's frame: the chord a -> b over its time, in the rotation halfway between theirs."""
        mid = a.pose.R @ _halfway(a.pose.R.T @ b.pose.R)
        return mid.T @ (b.pose.t - a.pose.t) / (b.stamp - a.stamp)

    def _warm_start(self, ref: _Recent, predicted: Pose, dt: float) -> Pose:
        """The step ref -> frame to start the two-frame solve from: the prediction's rotation, and the direction of
        the previous frame's own step when it has the same reference, else the rig's last solved heading. The
        prediction's translation alone stands still after a stand or a run of failed frames (the previous ones
        were predicted), and a solve started at zero translation lands behind the cameras: in a demo run 629 of
        ~800 moving frames failed in a cascade and path_raw froze (docs/results.md "Stop 44")."""
        init = ref.pose.inverse() @ predicted
        length = max(self._speed() * dt, 1e-3)
        prev = self._recent[-1] if self._recent else None
        if prev is not None and prev.ref is ref and prev.solved is not None:
            direction = prev.solved.t
        elif self._heading is not None:
            direction = ref.pose.R.T @ self._heading
        else:
            return init
        return Pose(init.R, direction / np.linalg.norm(direction) * length)

    def _predict(self, stamp: float) -> Pose:
        """Constant twist from the last two frames (hold before there are two)."""
        if not self._recent:
            return Pose.identity()
        if len(self._recent) == 1:
            return self._recent[-1].pose
        a, b = self._recent[-2], self._recent[-1]
        return constant_twist(a.pose, a.stamp, b.pose, b.stamp, stamp)

    def _reject(self, obs: FrameObservation, why: str) -> FrameResult:
        last = self._recent[-1] if self._recent else None
        pose = last.pose if last is not None else Pose.identity()
        raw = last.raw if last is not None else Pose.identity()
        return FrameResult.rejected(self._index, obs.stamp, pose, raw, why, scale_observed=self.scale_observed,
                                    scale_note=self.scale_note())
