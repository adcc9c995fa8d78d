"""``fixego sim --vergence physical``: the left head really verges on the right camera's fixation point.

At the first frame and whenever the right camera's fixation id changes, the left camera (after its image of
that frame) takes the right's point as its target and its servo slews there with the head's dynamics
(:class:`~fixego_ros.sim.servo_model.Head`: lag, speed limits, latency) and tracks it like its own point.
During the step the left servo controls at ``control_hz`` ticks (the frames are ticks too; between steps it
commands once per frame as usual). Once both points are within ``settle_deg`` of their optical axes for
``settle_ticks`` ticks, the next frame stamp with a whole window of ``hold_ticks`` ticks either side still
ahead is chosen; the ticks of that window are the measurement (:mod:`~fixego_ros.sim.vergence_measure`;
the right head's angles between its once-per-frame commands come from a copy of its head). Then the left
returns to its own point if it is still valid, otherwise it re-selects one as usual.

This is not the left camera_node's schedule (:class:`~fixego_ros.tracking.vergence.VergenceScheduler`): the node waits
for both fixations to settle before the head leaves and keeps ``vergence_min_interval_s`` between steps, so on the
papers' loop it measures about half as often as this (3.3 against 6.7 measurements per run when the simulator was
given the node's schedule, and 9 of 32 seeds within the papers' accuracy against 19, both with the smoother's 2 s window
of the time; docs/results.md "Stop 76").

Fixation ids (``ground_truth/left/fixation``; one id = one static point, as downstream code assumes): the
left id goes up by one when the step takes the right's point (from the next frame on, the left reports that
point and its pixel, far from the centre while the head slews, as after any re-selection) and again when it
returns (a real camera_node re-selects after the step), also when the point it returns to is the same
world point as before. The step is abandoned (no measurement, head sent back) when the point leaves the left
camera's range or view, or slew + settle + hold exceed ``timeout_s``; a new right fixation during a step
restarts it on the new point. Each step's times are recorded (:class:`StepRecord`): the left is away from
its own point from ``start`` to ``back`` (settled on it again).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fixego_ros.geometry.rig import Rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.sim.servo_model import FixationServo, Head, ServoState
from fixego_ros.sim.vergence_measure import (
    VergenceParams,
    VergenceSource,
    measure,
    off_axis_deg,
    sample,
    tick_period,
    tick_times,
)

NOISE_STREAM = 0x5E8   # second seed word of the measured pixels' noise


@dataclass
class StepRecord:
    """Times (s since the start) of one physical vergence step."""

    right_fixation_id: int
    start: float                      # the left leaves its own point (the command is sent)
    held: float | None = None         # both heads hold the right's point (settled)
    measured_frame: int | None = None
    returning: float | None = None    # the left is sent back
    back: float | None = None         # the left holds its own point again
    outcome: str = 'running'          # 'measured' or why not

    def record(self, epoch: float) -> dict:
        """For ``sim.yaml``: stamps are absolute like the bag's, durations in s."""
        def stamp(t: float | None) -> float | None:
            return None if t is None else float(epoch + t)

        def span(a: float | None, b: float | None) -> float | None:
            return None if a is None or b is None else float(b - a)
        return {'right_fixation_id': int(self.right_fixation_id), 'start_s': stamp(self.start),
                'held_s': stamp(self.held), 'returning_s': stamp(self.returning), 'back_s': stamp(self.back),
                'slew_out_s': span(self.start, self.held), 'slew_back_s': span(self.returning, self.back),
                'away_s': span(self.start, self.back), 'outcome': self.outcome,
                'measured_frame': self.measured_frame}


class VergenceStep(VergenceSource):
    """Drives the left servo through vergence steps (module docstring). Phases: ``idle`` (the servo as usual),
    ``verging`` (slew, settle, hold and measure), ``returning`` (back to its own point)."""

    def __init__(self, rig: Rig, servos: dict[str, FixationServo], pose_at: Callable[[float], Pose],
                 stamps: np.ndarray, params: VergenceParams | None = None, seed: int = 0) -> None:
        super().__init__(params)
        self.rig, self.pose_at = rig, pose_at
        self.left, self.right = servos['left'], servos['right']
        self.stamps = np.asarray(stamps, float)
        self.h = self.p.hold_ticks * tick_period(self.stamps, self.p.control_hz)   # half window, s
        self.rng = np.random.default_rng([int(seed), NOISE_STREAM])
        self.phase = 'idle'
        self.steps: list[StepRecord] = []
        self._settled = 0
        self._window: tuple[int, float] | None = None    # (frame, its time) the measurement will refer to
        self._samples: list[np.ndarray] = []
        self._right_head: Head | None = None             # the right head as of the last frame (commands sent)
        self._t_prev = 0.0

    @property
    def pending_frame(self) -> int | None:
        return self._window[0] if self._window is not None else None

    # -------------------------------------------------------------------- per frame
    def frame(self, k: int, t: float, rig_pose: Pose, right: ServoState) -> ServoState:
        if k == 0:
            state = self.left.start(t, rig_pose)
        elif self.phase == 'idle':
            state = self.left.step(t, rig_pose)
        else:
            state = self._ticks(t, rig_pose)
        if self._new_right_fixation(k, right):
            self._begin(t, rig_pose, right)
        self._right_head = self.right.head.copy()
        self._t_prev = t
        return state

    def finish(self) -> None:
        if self.phase == 'verging':
            self._abandon_measurement(self._t_prev, 'the sequence ended during the step')
        if self.phase != 'idle' and self.steps and self.steps[-1].outcome == 'running':
            self.steps[-1].outcome = 'the sequence ended during the step'
        self._window = None

    # -------------------------------------------------------------------- ticks between frames
    def _ticks(self, t: float, rig_pose: Pose) -> ServoState:
        """Control ticks up to frame time ``t``; the state at ``t`` (observed before any retarget there)."""
        state = None
        for tau in tick_times(self._t_prev, t, self.p.control_hz):
            pose = rig_pose if tau == t else self.pose_at(float(tau))
            self.left.advance(float(tau))
            reselected = False
            if self.phase != 'verging' and not self.left.valid(pose, self.left.point):
                reselected = self.left.reselect(pose)      # its own point lost: chosen anew, as usual
            state = self.left.observe(float(tau), pose, reselected)
            if self.phase == 'verging':
                self._verging(float(tau), pose)
            elif self.phase == 'returning':
                self._returning(float(tau), pose)
            self.left.command(float(tau), pose)
        assert state is not None
        return state

    def _verging(self, tau: float, pose: Pose) -> None:
        step = self.steps[-1]
        point = self.left.point
        if not self.left.valid(pose, point):
            self._abandon(tau, pose, "the right fixation point left the left camera's range or view")
            return
        assert self._right_head is not None
        rpan, rtilt = self._right_head.at(tau)
        settled = max(off_axis_deg(self.rig, 'left', pose, self.left.pan, self.left.tilt, point),
                      off_axis_deg(self.rig, 'right', pose, rpan, rtilt, point)) <= self.p.settle_deg
        if self._window is None:
            self._settled = self._settled + 1 if settled else 0
            if self._settled < self.p.settle_ticks:
                if tau - step.start > self.p.timeout_s:
                    self._abandon(tau, pose, f'the heads did not settle on the point within {self.p.timeout_s:g} s')
                return
            later = np.nonzero(self.stamps - self.h >= tau - 1e-9)[0]
            if len(later) == 0 or self.stamps[later[0]] + self.h > self.stamps[-1] + 1e-9:
                self._abandon(tau, pose, 'the sequence ends before a whole measurement window')
                return
            f = int(later[0])
            self._window, self._samples = (f, float(self.stamps[f])), []
            step.held = step.held if step.held is not None else tau
        f, t_f = self._window
        if tau < t_f - self.h - 1e-9:
            return
        if not settled:       # lost the point inside the window: settle again, then another window
            self._window, self._samples, self._settled = None, [], 0
            return
        self._samples.append(sample(self.rig, self.left.p, pose, point,
                                    {'right': (rpan, rtilt), 'left': (self.left.pan, self.left.tilt)},
                                    self.p.pixel_sigma_px, self.rng))
        if tau >= t_f + self.h - 1e-9:
            m = measure(self.rig, self.left.p, self.p, self._samples, f, t_f,
                        self.pose_at(t_f).inverse().apply(point), step.right_fixation_id)
            if isinstance(m, str):
                self._abandon(tau, pose, m)
                return
            self.measurements.append(m)
            step.outcome, step.measured_frame = 'measured', f
            self._start_return(tau, pose)

    def _returning(self, tau: float, pose: Pose) -> None:
        step = self.steps[-1]
        on = off_axis_deg(self.rig, 'left', pose, self.left.pan, self.left.tilt, self.left.point) <= self.p.settle_deg
        self._settled = self._settled + 1 if on else 0
        if self._settled >= self.p.settle_ticks:
            step.back = tau
            self.phase = 'idle'
        elif step.returning is not None and tau - step.returning > self.p.return_timeout_s:
            self.phase = 'idle'       # (step.back stays None: not back in time)

    # -------------------------------------------------------------------- transitions
    def _begin(self, t: float, rig_pose: Pose, right: ServoState) -> None:
        """The right camera has a new fixation point: verge on it (from the left's state after frame ``t``)."""
        if self.phase == 'verging':
            self._abandon_measurement(t, 'the right camera re-selected during the step')
            if self.steps[-1].outcome == 'running':
                self.steps[-1].outcome = 'the right camera re-selected during the step'
        if not self.left.valid(rig_pose, right.point):
            self._fail(t, right.fixation_id, "the right fixation point is out of the left camera's range or view")
            if self.phase == 'verging':
                self._start_return(t, rig_pose)
            return
        if self.phase != 'verging':
            self.left.resume_point = self.left.point.copy()     # its own point, to return to
        self.left.retarget(right.point)
        self.phase, self._window, self._samples, self._settled = 'verging', None, [], 0
        self.steps.append(StepRecord(int(right.fixation_id), float(t)))
        self.left.command(t, rig_pose)                          # the slew starts now

    def _abandon_measurement(self, t: float, reason: str) -> None:
        self._fail(t, self.steps[-1].right_fixation_id, reason)
        self._window, self._samples = None, []

    def _abandon(self, tau: float, pose: Pose, reason: str) -> None:
        self._abandon_measurement(tau, reason)
        self.steps[-1].outcome = reason
        self._start_return(tau, pose)

    def _start_return(self, tau: float, pose: Pose) -> None:
        own = self.left.resume_point
        self.left.resume_point = None
        if own is not None and self.left.valid(pose, own):
            self.left.retarget(own)          # the same point, a new id (as the live step re-selects)
        elif not self.left.reselect(pose):
            self.left.retarget(own if own is not None else self.left.point)
        self.phase, self._window, self._samples, self._settled = 'returning', None, [], 0
        self.steps[-1].returning = tau
