"""Constant-speed prior: every step gets the same speed, so the trajectory has the right shape at one unknown scale.

The two-frame constraints fix a step's length only through the left camera's lever arm (DESIGN.md §5). On a
real rig that information is below the model error: with VISCA joint readings quantised to 0.11° the cost
of the true motion is 10-1000 times the optimum and nearly flat along the length, so a free solve puts each
length anywhere (on straights it collapses to a spurious near-zero fit, where a tiny rotation steers the
left camera's baseline to fit noise). A walker or a robot keeps its speed from one step to the next, so
holding every step at one speed gives the trajectory's shape; its metric scale is then a single number,
which the start-up vergence step measures (:mod:`.scale_anchor`) or an external speed source replaces.

Until then the speed is ``nominal`` and the scale is reported unobserved. A rig that stands still should be
caught by the two-frame solve's stationary test (no parallax), but the joint-quantisation jitter of the heads
gives each camera ~1 px of apparent parallax, so a still or creeping rig is drawn at this speed (README,
"Constant-speed prior"); one that changes speed a lot on the way is drawn with its average speed.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

# relative std of the step-length prior: the length is a gauge (the rays fit any value about equally), and a
# firm prior keeps each step on the common speed instead of on the spurious near-zero-T fit
PRIOR_REL_STD = 0.1
MEDIAN_OF = 3


@dataclass
class ConstantSpeed:
    """The rig's speed (m/s): ``nominal`` until :meth:`calibrate` measured it."""

    nominal: float = 0.5
    v: float = math.nan
    rel_std: float = math.nan       # of ``v`` once measured
    measured: bool = False
    # the last MEDIAN_OF measured speeds, m/s (older ones never count again)
    history: deque[float] = field(default_factory=lambda: deque(maxlen=MEDIAN_OF))

    def __post_init__(self) -> None:
        if not (math.isfinite(self.nominal) and self.nominal > 0):
            raise ValueError(f'nominal speed must be finite and > 0, got {self.nominal}')
        self.v, self.rel_std, self.measured = self.nominal, math.nan, False

    def prior(self, dt: float) -> tuple[float, float]:
        """Prior (length, std) in m of a step lasting ``dt`` s."""
        return self.v * dt, PRIOR_REL_STD * self.v * dt

    def calibrate(self, k: float, rel_std: float) -> None:
        """A measurement found the speed so far too small by ``k`` (relative std ``rel_std``). From the third
        measurement on the speed is the median of the last :data:`MEDIAN_OF` (one wild fit does not throw it)."""
        if not (math.isfinite(k) and k > 0 and math.isfinite(rel_std) and rel_std >= 0):
            raise ValueError(f'speed calibration needs a finite k > 0 and std >= 0, got {k}, {rel_std}')
        self.history.append(self.v * k)
        recent = list(self.history)
        self.v = sorted(recent)[len(recent) // 2] if len(recent) == MEDIAN_OF else recent[-1]
        self.rel_std = rel_std
        self.measured = True
