"""``fixego sim --vergence measurements``: vergence measurements without moving the heads (estimator-only tests).

At the first frame and at each new right fixation, the measurement of
:mod:`~fixego_ros.sim.vergence_measure` is made as if both heads were on the right camera's point at that
frame: over the same window of ticks as the ``physical`` step, each head's true angles are the ones that
centre the point, its readings their quantised values and its pixel the centre plus pixel noise. The same
error model as ``physical``, but the servos and images are exactly those of ``off`` (the noise has its own
stream). A point the left camera could not fixate (head range, depth, occlusion) gives no measurement.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fixego_ros.geometry.rig import Rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.sim.servo_model import FixationServo, ServoState, required_readings
from fixego_ros.sim.vergence_measure import VergenceParams, VergenceSource, measure, sample, tick_period

NOISE_STREAM = 0x5E7   # second seed word of the measurement noise (its own stream: images unchanged)


class OnPointVergence(VergenceSource):
    """Measurements at the event frames; the left servo runs as in ``off``."""

    def __init__(self, rig: Rig, servos: dict[str, FixationServo], pose_at: Callable[[float], Pose],
                 stamps: np.ndarray, params: VergenceParams | None = None, seed: int = 0) -> None:
        super().__init__(params)
        self.rig, self.left, self.pose_at = rig, servos['left'], pose_at
        self.dt = tick_period(stamps, self.p.control_hz)
        self.rng = np.random.default_rng([int(seed), NOISE_STREAM])

    def frame(self, k: int, t: float, rig_pose: Pose, right: ServoState) -> ServoState:
        left = self.left.start(t, rig_pose) if k == 0 else self.left.step(t, rig_pose)
        if self._new_right_fixation(k, right):
            if self.left.valid(rig_pose, right.point):
                self._measure(k, t, rig_pose, right)
            else:
                self._fail(t, right.fixation_id, "the right fixation point is out of the left camera's range or view")
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
