"""``fixego sim --vergence measurements``: vergence measurements without moving the heads (estimator-only tests).

At the first frame and at each new right fixation, once the right head has reached its new point (within
``settle_deg`` of its optical axis, as the ``physical`` step waits for; at most ``timeout_s``), the measurement of
:mod:`~fixego_ros.sim.vergence_measure` is made as if both heads were on the right camera's point at that
frame: over the same window of ticks as the ``physical`` step, each head's true angles are the ones that
centre the point, its readings their quantised values and its pixel the centre plus pixel noise. (Measured at the
selection frame instead, a point chosen at the end of a limit swing was 40-90 deg off the right camera's axis in
that frame's images and joints: no front end could match it, and replays used only the first measurement.) The same
error model as ``physical``, but the servos and images are exactly those of ``off`` (the noise has its own
stream). A point the left camera could not fixate (head range, depth, occlusion) gives no measurement.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fixego_ros.geometry.rig import Rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.sim.servo_model import FixationServo, ServoState, required_readings
from fixego_ros.sim.vergence_measure import (
    VergenceParams,
    VergenceSource,
    measure,
    off_axis_deg,
    sample,
    tick_period,
)

NOISE_STREAM = 0x5E7   # second seed word of the measurement noise (its own stream: images unchanged)


class OnPointVergence(VergenceSource):
    """Measurements at the event frames; the left servo runs as in ``off``."""

    def __init__(self, rig: Rig, servos: dict[str, FixationServo], pose_at: Callable[[float], Pose],
                 stamps: np.ndarray, params: VergenceParams | None = None, seed: int = 0) -> None:
        super().__init__(params)
        self.rig, self.left, self.pose_at = rig, servos['left'], pose_at
        self.dt = tick_period(stamps, self.p.control_hz)
        self.rng = np.random.default_rng([int(seed), NOISE_STREAM])
        self._waiting: tuple[int, float] | None = None     # (right fixation id, since) until the head is on it

    def frame(self, k: int, t: float, rig_pose: Pose, right: ServoState) -> ServoState:
        left = self.left.start(t, rig_pose) if k == 0 else self.left.step(t, rig_pose)
        if self._new_right_fixation(k, right):
            if self._waiting is not None:
                self._fail(self._waiting[1], self._waiting[0], 'the right camera selected another point first')
            self._waiting = (right.fixation_id, t)
        if self._waiting is None:
            return left
        started = self._waiting[1]
        if off_axis_deg(self.rig, 'right', rig_pose, right.pan, right.tilt, right.point) <= self.p.settle_deg:
            self._waiting = None
            if self.left.valid(rig_pose, right.point):
                self._measure(k, t, rig_pose, right)
            else:
                self._fail(t, right.fixation_id, "the right fixation point is out of the left camera's range or view")
        elif t - started > self.p.timeout_s:
            self._waiting = None
            self._fail(started, right.fixation_id, f'the right head did not reach its point in {self.p.timeout_s} s')
        return left

    def _measure(self, k: int, t: float, rig_pose: Pose, right: ServoState) -> None:
        samples = []
        for j in range(-self.p.hold_ticks, self.p.hold_ticks + 1):
            pose = rig_pose if j == 0 else self.pose_at(t + j * self.dt)   # (clamped to the trajectory's span)
            angles = {side: required_readings(self.rig, side, pose, right.point) for side in ('right', 'left')}
            samples.append(sample(self.rig, self.left.p, pose, right.point, angles, self.p.pixel_sigma_px, self.rng))
        m = measure(self.rig, self.left.p, self.p, samples, k, t, rig_pose.inverse().apply(right.point),
                    right.fixation_id)
        if isinstance(m, str):
            self._fail(t, right.fixation_id, m)
        else:
            self.measurements.append(m)
