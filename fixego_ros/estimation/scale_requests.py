"""When to ask the rig for a new vergence measurement (ROS-free; ``estimator_node`` publishes the request).

The scale measured by a vergence step holds while the rig keeps its speed and the estimate keeps its shape;
both drift, so its relative std grows with time (``drift_per_s``, a stated model, not a measurement). Once
it passes ``max_rel_std`` the estimator asks for a new step, at most once per ``min_interval_s`` (the left
camera interrupts its own fixation for each). Before any measurement the scale is unobserved: that asks
too. A speed source measures the scale at every step, so with one nothing is asked. A measurement counts from
when the estimator receives it (:func:`newest` of the received one and the back end's): the smoother uses it only
once its frame is in the graph, seconds later when the live smoother is behind, and until then the estimator asked
again. In the demo that made the left head measure the same point a second time at rest, and the 5 s between
steps then cost the first straight its step (docs/results.md "Stop 56").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fixego_ros.estimation.covariance import std_along

Measurement = tuple[float, float]       # (stamp, relative std of the scale)


def vergence_measurement(stamp: float, point: np.ndarray, cov: np.ndarray) -> Measurement:
    """A vergence measurement's (stamp, relative std): its covariance along the ray over its distance."""
    return float(stamp), std_along(point, cov) / max(float(np.linalg.norm(point)), 1e-9)


def newest(*measurements: Measurement | None) -> Measurement | None:
    """The latest of the given measurements (None among them ignored; None when all are)."""
    known = [m for m in measurements if m is not None]
    return max(known, key=lambda m: m[0]) if known else None


@dataclass
class ScaleRequests:
    max_rel_std: float = 0.05
    min_interval_s: float = 5.0
    drift_per_s: float = 0.005
    last_request: float = -math.inf     # stamp of the last request
    count: int = 0

    def rel_std(self, stamp: float, measurement: Measurement | None) -> float:
        """Relative scale std at ``stamp`` from the newest measurement ``(stamp, rel_std)`` (inf: none yet)."""
        if measurement is None:
            return math.inf
        t0, std0 = measurement
        return std0 + self.drift_per_s * max(stamp - t0, 0.0)

    def due(self, stamp: float, measurement: Measurement | None, speed_source: bool) -> bool:
        """Whether to request a vergence step now (and count it as requested)."""
        if speed_source or stamp - self.last_request < self.min_interval_s:
            return False
        if self.rel_std(stamp, measurement) <= self.max_rel_std:
            return False
        self.last_request = stamp
        self.count += 1
        return True
