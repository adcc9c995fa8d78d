"""Per-step status codes shared by the solver, the local BA, the estimator and the nodes."""

from __future__ import annotations

from enum import StrEnum


class StepStatus(StrEnum):
    """What happened to one frame-to-frame step. ``usable`` ones move the trajectory."""

    INIT = 'init'                  # first frame: pose = identity, nothing solved
    OK = 'ok'                      # solved, well conditioned
    WEAK = 'weak'                  # solved, but some direction (usually scale) is weakly observed
    STATIONARY = 'stationary'      # no parallax at all: rotation only, T = 0
    INSUFFICIENT = 'insufficient'  # fewer constraints than unknowns (6)
    DEGENERATE = 'degenerate'      # input cannot determine a motion (e.g. all rays parallel)
    FAILED = 'failed'              # optimiser failed or produced non-finite values
    REJECTED = 'rejected'          # solved, but rejected (implausible jump or covariance too large)
    PREDICTED = 'predicted'        # step not solved; constant-velocity prediction used instead
    CARRIED = 'carried'            # live pose: the smoother's motion carried to the stamp, rotation from the rays

    @property
    def usable(self) -> bool:
        return self in (StepStatus.OK, StepStatus.WEAK, StepStatus.STATIONARY, StepStatus.CARRIED)
