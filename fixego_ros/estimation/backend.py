"""Which back end a configuration asks for: one factory for estimator_node, replay and the benchmarks."""

from __future__ import annotations

from fixego_ros.estimation.config import EstimatorConfig
from fixego_ros.estimation.estimator import Estimator
from fixego_ros.estimation.smoother import Smoother
from fixego_ros.geometry.rig import Rig

Backend = Estimator | Smoother


def make_backend(rig: Rig, config: EstimatorConfig) -> Backend:
    """``refinement: smoother`` (the default): the metric fixed-lag smoother; ``local``: the papers' method."""
    return Smoother(rig, config) if config.refinement == 'smoother' else Estimator(rig, config)
