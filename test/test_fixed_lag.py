"""The fixed-lag window over ISAM2: marginalisation by time and the newest frame's marginal covariance."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fixego_ros.estimation.fixed_lag import FixedLagWindow


def _chain(n: int, rng: np.random.Generator):
    """A random walk of 3-D points: a prior on the first, noisy steps between the rest (a linear problem, so
    marginalising old points is exact)."""
    prior = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    step = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.2, 0.4]))
    factors = [gtsam.PriorFactorPoint3(0, np.zeros(3), prior)]
    for k in range(1, n):
        factors.append(gtsam.BetweenFactorPoint3(k - 1, k, rng.normal(0.0, 1.0, 3), step))
    return factors


def _run(window: FixedLagWindow, factors, iterations: int = 0) -> None:
    for k, factor in enumerate(factors):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(factor)
        values.insert(k, np.full(3, float(k)))
        window.update(graph, values, {k: float(k)}, newest=(k,), iterations=iterations)


def test_old_variables_leave_the_window_and_the_newest_marginal_is_exact():
    factors = _chain(20, np.random.default_rng(0))
    window = FixedLagWindow(lag_s=4.5)
    _run(window, factors, iterations=1)
    estimate = window.estimate()
    assert sorted(estimate.keys()) == list(range(15, 20))          # stamps 15..19 are within 4.5 s of 19
    full = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for k, factor in enumerate(factors):
        full.add(factor)
        initial.insert(k, np.zeros(3))
    batch = gtsam.LevenbergMarquardtOptimizer(full, initial).optimize()
    np.testing.assert_allclose(estimate.atPoint3(19), batch.atPoint3(19), atol=1e-6)
    np.testing.assert_allclose(window.marginal_covariance(19), gtsam.Marginals(full, batch).marginalCovariance(19),
                               rtol=1e-6, atol=1e-12)


def test_a_key_used_again_stays_in_the_window():
    """A landmark re-observed later is kept by the stamp of its latest use."""
    window = FixedLagWindow(lag_s=2.0)
    prior = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPoint3(100, np.ones(3), prior))
    values.insert(100, np.ones(3))
    window.update(graph, values, {100: 0.0})
    for k in range(1, 6):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.BetweenFactorPoint3(100, k, np.zeros(3), prior))
        values.insert(k, np.ones(3))
        window.update(graph, values, {k: float(k), 100: float(k)}, newest=(k,))
    keys = set(window.estimate().keys())
    assert 100 in keys and 1 not in keys


def test_a_numerical_failure_raises():
    window = FixedLagWindow(lag_s=1.0)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.BetweenFactorPoint3(1, 2, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    values.insert(1, np.zeros(3))
    values.insert(2, np.zeros(3))
    with pytest.raises(RuntimeError):             # nothing fixes the pair's absolute position
        window.update(graph, values, {1: 0.0, 2: 0.0})
