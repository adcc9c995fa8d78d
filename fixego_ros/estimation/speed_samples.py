"""Samples of an external speed source (wheel odometry), integrated over each step for the back ends."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fixego_ros.geometry.rotation import exp_so3


@dataclass
class SpeedSamples:
    """Velocity samples of an external source (rig frame, m/s) kept for the steps still to come."""

    stamps: list[float] = field(default_factory=list)
    v: list[np.ndarray] = field(default_factory=list)
    cov: list[np.ndarray] = field(default_factory=list)
    max_age_s: float = 0.5

    def add(self, stamp: float, v: np.ndarray, cov: np.ndarray) -> None:
        if self.stamps and stamp <= self.stamps[-1]:
            raise ValueError(f'speed sample at {stamp:.6f} not after the last one ({self.stamps[-1]:.6f})')
        self.stamps.append(float(stamp))
        self.v.append(np.asarray(v, float).reshape(3))
        self.cov.append(np.asarray(cov, float).reshape(3, 3))

    def translation(self, t0: float, t1: float, rotation: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Translation over [t0, t1] in the rig frame at ``t0``, from the samples in it (or the nearest within
        ``max_age_s``), with its covariance (errors taken as fully correlated over the interval: wheel slip is
        not white). ``rotation`` (rotation vector of the rig at ``t1`` in the rig at ``t0``) turns each sample
        from the rig frame at its stamp into the one at ``t0``, at constant angular velocity: on an arc the
        body-frame velocity stays forward while the step's chord turns by half the step's rotation, and a prior
        left in the wrong frame would bend the solved rotation to fit it."""
        if not self.stamps or t1 <= t0:
            return None
        s = np.asarray(self.stamps)
        dt = t1 - t0
        idx = np.flatnonzero((s >= t0 - 1e-9) & (s <= t1 + 1e-9))
        # where each sample lies in the step (its rig frame turned that far); the nearest one outside counts as mid-step
        if len(idx):
            frac = np.clip((s[idx] - t0) / dt, 0.0, 1.0)
        else:
            near = int(np.argmin(np.abs(s - 0.5 * (t0 + t1))))
            if abs(s[near] - 0.5 * (t0 + t1)) > self.max_age_s:
                return None
            idx, frac = np.array([near]), np.array([0.5])
        phi = np.zeros(3) if rotation is None else np.asarray(rotation, float).reshape(3)
        rots = [exp_so3(phi * f) for f in frac]
        v = np.mean([R @ self.v[i] for R, i in zip(rots, idx, strict=True)], axis=0)
        cov = np.mean([R @ self.cov[i] @ R.T for R, i in zip(rots, idx, strict=True)], axis=0)
        return v * dt, cov * dt * dt

    def forget_before(self, t: float) -> None:
        keep = [i for i, s in enumerate(self.stamps) if s >= t - self.max_age_s]
        self.stamps = [self.stamps[i] for i in keep]
        self.v = [self.v[i] for i in keep]
        self.cov = [self.cov[i] for i in keep]
