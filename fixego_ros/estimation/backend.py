"""Which back end a configuration asks for: one factory for estimator_node, replay and the benchmarks."""

from __future__ import annotations

from fixego_ros.estimation.config import EstimatorConfig
from fixego_ros.estimation.estimator import Estimator
from fixego_ros.estimation.live_smoother import LiveSmoother
from fixego_ros.estimation.smoother import Smoother
from fixego_ros.geometry.rig import Rig

Backend = Estimator | Smoother | LiveSmoother


def make_backend(rig: Rig, config: EstimatorConfig, live: bool = False) -> Backend:
    """``refinement: smoother`` (the default): the metric fixed-lag smoother, in a child process behind a pose for
    every frame when ``live`` (estimator_node), in this process otherwise (replay: every frame in the graph);
    ``local``: the papers' method."""
    if config.refinement != 'smoother':
        return Estimator(rig, config)
    return LiveSmoother(rig, config) if live else Smoother(rig, config)
