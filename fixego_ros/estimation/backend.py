"""Which back end a configuration asks for: one factory for estimator_node, replay and the benchmarks."""

from __future__ import annotations

from fixego_ros.estimation.config import EstimatorConfig
from fixego_ros.estimation.estimator import Estimator
from fixego_ros.estimation.live_smoother import LiveSmoother
from fixego_ros.geometry.rig import Rig
from fixego_ros.geometry.rotation import Pose

Backend = Estimator | LiveSmoother


def make_backend(rig: Rig, config: EstimatorConfig, live: bool = False) -> Backend:
    """``refinement: smoother`` (the default): a pose for every frame from its keyframe, and the metric fixed-lag
    smoother over the keyframes revising them; the smoother in a child process when ``live`` (estimator_node: it
    also takes a non-keyframe when idle), in this process otherwise (replay: every keyframe and one other frame per
    0.1 s, deterministic); ``local``: the papers' method."""
    if config.refinement != 'smoother':
        return Estimator(rig, config)
    return LiveSmoother(rig, config, inline=not live)


def answers(backend: Backend) -> int:
    """How many frames the smoother has answered so far (0 for the papers' method)."""
    return backend.smoothed_results if isinstance(backend, LiveSmoother) else 0


def smoother_stage_ms(backend: Backend, since: int) -> dict[str, list[float]]:
    """The smoother's ms by stage (:class:`.stage_times.Stage`) for its answers after the first ``since`` (none for
    the papers' method)."""
    return backend.stage_samples(backend.smoothed_results - since) if isinstance(backend, LiveSmoother) else {}


def final_revisions(backend: Backend) -> tuple[tuple[float, Pose], ...]:
    """The revisions a back end still holds after its last frame (the smoother's answer to that frame)."""
    return backend.drain(0.0) if isinstance(backend, LiveSmoother) else ()
