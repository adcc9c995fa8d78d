"""Where one back-end update's time goes, by stage (issue 19: every millisecond accounted for).

The smoother and its fixed-lag window share one :class:`StageTimes`; the smoother clears it at the start of each
frame's update, and the result reaches ``/diagnostics`` (``smoother_<stage>_ms_p50``), ``fixego replay``'s stage
line and ``bench.replay``. Timing never changes what is computed.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from enum import Enum


class Stage(Enum):
    """The stages of one smoother update, in the order they run."""

    RESECTION = 'resection'         # pose-only fit of the new frame to the landmarks in the graph
    TWO_FRAME = 'two_frame'         # the coplanarity solve keyframe -> frame (warm, and the cold check)
    SIGHTINGS = 'sightings'         # gating the frame's sightings, new landmarks, projection factors
    LINEARISE = 'linearise'         # every factor of the window at the current estimate (each pass)
    ORDER = 'order'                 # COLAMD ordering (each pass)
    ELIMINATE = 'eliminate'         # multifrontal Cholesky (each pass)
    SOLVE = 'solve'                 # back-substitution and retraction (each pass)
    MARGINALISE = 'marginalise'     # variables older than the lag leave the window
    COVARIANCE = 'covariance'       # the newest pose's marginal covariance (at most every 0.5 s)


class StageTimes:
    """Milliseconds per :class:`Stage` since the last :meth:`clear` (a stage entered twice adds up)."""

    def __init__(self) -> None:
        self._ms: dict[Stage, float] = {}

    def clear(self) -> None:
        self._ms = {}

    @contextmanager
    def __call__(self, stage: Stage) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._ms[stage] = self._ms.get(stage, 0.0) + (time.perf_counter() - t0) * 1e3

    def as_dict(self) -> dict[str, float]:
        """Stage name -> ms, every stage listed (0 for one that did not run), in :class:`Stage` order."""
        return {s.value: self._ms.get(s, 0.0) for s in Stage}
