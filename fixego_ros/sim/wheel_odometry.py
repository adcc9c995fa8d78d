"""Simulated wheel odometry for ``fixego sim`` bags: what a robot's wheel encoders would report.

The true ``base_link`` velocity (:meth:`~fixego_ros.sim.run.Simulation.base_velocities`) scaled by
``1 + scale_bias`` (a wheel radius off by that much: a bias the reported covariance does not show, as on a real
robot), plus seeded Gaussian noise of ``std_m_s`` per axis. One sample per frame at the frame's stamp (``rate_hz``
None: what the bags always had), or at ``rate_hz`` from the start, independent of the frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RATE_MAX_HZ = 1000.0
BIAS_MAX = 0.5
_NOISE_STREAM = 0x0D0   # second seed word of the noise (its own stream: the images are unchanged)


@dataclass(frozen=True)
class WheelOdometry:
    std_m_s: float
    rate_hz: float | None = None
    scale_bias: float = 0.0

    def problems(self) -> list[str]:
        """What is out of range, as ``field must be ..., got value`` (empty when fine)."""
        out = []
        if not (np.isfinite(self.std_m_s) and self.std_m_s >= 0):
            out.append(f'wheel odometry std must be a finite number >= 0 m/s, got {self.std_m_s}')
        if self.rate_hz is not None and not (np.isfinite(self.rate_hz) and 0 < self.rate_hz <= RATE_MAX_HZ):
            out.append(f'wheel odometry rate must be in (0, {RATE_MAX_HZ:g}] Hz, got {self.rate_hz}')
        if not (np.isfinite(self.scale_bias) and abs(self.scale_bias) <= BIAS_MAX):
            out.append(f'wheel odometry scale bias must be in [-{BIAS_MAX:g}, {BIAS_MAX:g}], got {self.scale_bias}')
        return out

    def samples(self, sim, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(times in s since the start, (n, 3) measured velocities in base_link) up to the last frame."""
        if self.rate_hz is None:
            times, v_true = np.asarray(sim.stamps, float), sim.base_velocities()
        else:
            times = np.arange(0.0, float(sim.stamps[-1]) + 1e-9, 1.0 / self.rate_hz)
            v_true = sim.base_velocities(times)
        rng = np.random.default_rng([seed, _NOISE_STREAM])
        v = v_true * (1.0 + self.scale_bias) if self.scale_bias else v_true
        return times, (v + rng.normal(0.0, self.std_m_s, v.shape) if self.std_m_s > 0 else v)

    def record(self, topic: str) -> dict:
        """For sim.yaml: the topic and what was simulated (rate and bias only when set)."""
        out: dict = {'topic': topic, 'std_m_s': float(self.std_m_s)}
        if self.rate_hz is not None:
            out['rate_hz'] = float(self.rate_hz)
        if self.scale_bias:
            out['scale_bias'] = float(self.scale_bias)
        return out
