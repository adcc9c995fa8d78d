"""The fixed-lag window: marginalisation by time, the newest frame's marginal covariance, repairs, and agreement with
GTSAM's own ISAM2 fixed-lag smoother."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

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


def _rotating_chain(seed: int, start_noise: float):
    """Rotating poses tied by noisy steps and position fixes, each new pose started ``start_noise`` (rad, m) off:
    yields (k, graph, values) for k = 0..24."""
    rng = np.random.default_rng(seed)
    step_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.02] * 3 + [0.05] * 3))
    step = gtsam.Pose3(gtsam.Rot3.Rz(0.3) * gtsam.Rot3.Rx(0.1), np.array([1.0, 0.2, 0.0]))
    truth = gtsam.Pose3()
    for k in range(25):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
        else:
            truth = truth.compose(step)
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step.compose(gtsam.Pose3.Expmap(rng.normal(0, 0.05, 6))),
                                               step_noise))
            if k % 3 == 0:
                graph.add(gtsam.GPSFactor(X(k), truth.translation() + rng.normal(0, 0.3, 3),
                                          gtsam.noiseModel.Isotropic.Sigma(3, 0.3)))
        values.insert(X(k), truth.compose(gtsam.Pose3.Expmap(rng.normal(0, start_noise, 6))))
        yield k, graph, values


def test_the_window_agrees_with_gtsams_incremental_fixed_lag_smoother_on_a_nonlinear_chain():
    """Poses leaving the window as the chain goes. ISAM2 never relinearises the variables a marginal holds; the
    window must not either (relinearised, it differed by 2.5 cm here, and on the 30 Hz loop bags the path came out
    3-6 % shorter)."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.0)
    params.relinearizeSkip = 1
    reference, window = gtsam.IncrementalFixedLagSmoother(4.5, params), FixedLagWindow(lag_s=4.5)
    for k, graph, values in _rotating_chain(1, 0.2):
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        stamps.insert((X(k), float(k)))
        reference.update(graph, values, stamps)
        window.update(graph, values, {X(k): float(k)}, newest=(X(k),))
    expected, estimate = reference.calculateEstimate(), window.estimate()
    assert sorted(estimate.keys()) == sorted(expected.keys()) == [X(k) for k in range(20, 25)]
    for k in [X(i) for i in range(20, 25)]:
        np.testing.assert_allclose(estimate.atPose3(k).translation(), expected.atPose3(k).translation(), atol=1e-9)
        np.testing.assert_allclose(estimate.atPose3(k).rotation().matrix(), expected.atPose3(k).rotation().matrix(),
                                   atol=1e-9)


def test_passes_end_when_one_moves_no_pose_beyond_the_tolerance():
    """Another Gauss-Newton pass costs a whole linearisation and elimination of the window: it is made only while
    the last one still moved a pose by more than ``STEP_TOLERANCE``. Started far off, an update takes several; the
    estimate is that of every pass made, within the tolerance."""
    stopping, full = FixedLagWindow(lag_s=4.5), FixedLagWindow(lag_s=4.5)
    full.STEP_TOLERANCE = (0.0, 0.0)
    for window in (stopping, full):
        for k, graph, values in _rotating_chain(2, 0.2):
            window.update(graph, values, {X(k): float(k)}, newest=(X(k),), iterations=5)
    assert full.passes == {6: 25}
    assert 1 not in stopping.passes and sum(stopping.passes.values()) == 25    # one pass moves the new pose
    assert sum(n * c for n, c in stopping.passes.items()) < 6 * 25
    for k in [X(i) for i in range(20, 25)]:
        a, b = stopping.estimate().atPose3(k), full.estimate().atPose3(k)
        np.testing.assert_allclose(a.translation(), b.translation(), atol=2e-3)
        np.testing.assert_allclose(gtsam.Rot3.Logmap(a.rotation().between(b.rotation())), 0.0, atol=1e-3)


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


def _pose_chain(window: FixedLagWindow, n: int) -> None:
    """Poses x0..x(n-1), 1 s apart, 10 cm steps along z, the first held by a prior."""
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 1e-2)
    step = gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.1]))
    for k in range(n):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), noise))
        else:
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, noise))
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.1 * k])))
        window.update(graph, values, {X(k): float(k)}, newest=(X(k),))


def test_a_landmark_nothing_places_is_dropped_and_the_window_goes_on():
    """One view of a point leaves its depth free: the repair drops the point and keeps everything else (it used to
    raise, and the smoother started a new graph without any landmark)."""
    window = FixedLagWindow(lag_s=10.0)
    _pose_chain(window, 3)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(_projection((10.0, 0.0), X(2), L(0)))
    values.insert(L(0), np.array([0.1, 0.0, 5.0]))
    window.update(graph, values, {L(0): 2.0})
    assert window.repairs == ['dropped l0']
    estimate = window.estimate()
    assert not estimate.exists(L(0)) and all(estimate.exists(X(k)) for k in range(3))
    np.testing.assert_allclose(estimate.atPose3(X(2)).translation(), [0.0, 0.0, 0.2], atol=1e-9)
    _pose_chain_continues = gtsam.NonlinearFactorGraph()
    _pose_chain_continues.add(gtsam.BetweenFactorPose3(X(2), X(3), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(
        6, 1e-2)))
    values = gtsam.Values()
    values.insert(X(3), gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.2])))
    window.update(_pose_chain_continues, values, {X(3): 3.0}, newest=(X(3),))
    assert window.estimate().exists(X(3)) and len(window.repairs) == 1


def test_a_landmark_dropped_by_a_repair_while_it_leaves_the_window_is_forgotten_once():
    """A point that nothing places and whose stamp is already past the lag: the repair drops it in the first pass,
    and the marginalisation after that pass must not trip over it (it did: the update raised, and the smoother would
    have started a new graph)."""
    window = FixedLagWindow(lag_s=2.0)
    _pose_chain(window, 6)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(_projection((10.0, 0.0), X(5), L(0)))
    values.insert(L(0), np.array([0.1, 0.0, 5.0]))
    window.update(graph, values, {L(0): 1.0}, newest=(X(5),), iterations=1)
    assert window.repairs == ['dropped l0']
    estimate = window.estimate()
    assert not estimate.exists(L(0)) and sorted(estimate.keys()) == [X(k) for k in range(3, 6)]


def test_a_pose_nothing_holds_is_anchored_where_it_is():
    """Two new poses tied only to each other: the pair is free; the repair holds one where it was placed."""
    window = FixedLagWindow(lag_s=10.0)
    _pose_chain(window, 2)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    step = gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.5]))
    graph.add(gtsam.BetweenFactorPose3(X(5), X(6), step, gtsam.noiseModel.Isotropic.Sigma(6, 1e-2)))
    values.insert(X(5), gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 2.0, 3.0])))
    values.insert(X(6), gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 2.0, 3.4])))
    window.update(graph, values, {X(5): 2.0, X(6): 2.0}, newest=(X(6),))
    assert len(window.repairs) == 1 and window.repairs[0] in ('anchored x5', 'anchored x6')
    estimate = window.estimate()
    gap = estimate.atPose3(X(6)).translation() - estimate.atPose3(X(5)).translation()
    np.testing.assert_allclose(gap, [0.0, 0.0, 0.5], atol=1e-6)
    assert abs(estimate.atPose3(X(5)).translation()[2] - 3.0) < 0.3


def _projection(pixel: tuple[float, float], pose: int, landmark: int) -> gtsam.GenericProjectionFactorCal3_S2:
    K = gtsam.Cal3_S2(500.0, 500.0, 0.0, 0.0, 0.0)
    return gtsam.GenericProjectionFactorCal3_S2(np.array(pixel), gtsam.noiseModel.Isotropic.Sigma(2, 1.0), pose,
                                                landmark, K, False, False)


def _projections_on(window: FixedLagWindow, landmark: int) -> int:
    factors = window.factors()
    found = (factors.at(i) for i in range(factors.size()))
    return sum(1 for f in found if isinstance(f, gtsam.GenericProjectionFactorCal3_S2) and landmark in list(f.keys()))


def test_a_landmark_behind_a_camera_that_sees_it_is_dropped_and_the_one_in_front_kept():
    """Behind a camera a projection factor has no Jacobian: the point would be held by its prior alone and the next
    factorisation can fail. Its views are removed, it leaves at the next update; a point in front stays."""
    window = FixedLagWindow(lag_s=10.0)
    _pose_chain(window, 3)                       # cameras at z = 0, 0.1, 0.2 looking along +z
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    held = gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)
    graph.add(gtsam.PriorFactorPoint3(L(1), np.array([0.0, 0.0, -2.0]), held))      # held behind the cameras
    graph.add(gtsam.PriorFactorPoint3(L(2), np.array([0.5, 0.0, 5.0]), gtsam.noiseModel.Isotropic.Sigma(3, 10.0)))
    for k in (1, 2):
        graph.add(_projection((0.0, 0.0), X(k), L(1)))
        graph.add(_projection((500.0 * 0.5 / (5.0 - 0.1 * k), 0.0), X(k), L(2)))
    values.insert(L(1), np.array([0.0, 0.0, -2.0]))
    values.insert(L(2), np.array([0.5, 0.0, 5.0]))
    window.update(graph, values, {L(1): 2.0, L(2): 2.0}, newest=(X(2),), iterations=1)
    assert window.dropped == [L(1)] and window.repairs == []
    assert _projections_on(window, L(1)) == 0 and _projections_on(window, L(2)) == 2
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.BetweenFactorPose3(X(2), X(3), gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.1])),
                                       gtsam.noiseModel.Isotropic.Sigma(6, 1e-2)))
    values = gtsam.Values()
    values.insert(X(3), gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.3])))
    window.update(graph, values, {X(3): 3.0}, newest=(X(3),))
    estimate = window.estimate()
    assert not estimate.exists(L(1)) and estimate.exists(L(2))
    np.testing.assert_allclose(estimate.atPoint3(L(2)), [0.5, 0.0, 5.0], atol=1e-6)
    np.testing.assert_allclose(estimate.atPose3(X(3)).translation(), [0.0, 0.0, 0.3], atol=1e-6)


def _pulled_chain(window: FixedLagWindow, n: int) -> None:
    """Poses 1 s apart whose steps (10 cm) and position fixes (15 cm a second) disagree: each new fix pulls the poses
    before it, including those that the marginal of the ones gone holds at their frozen linearisation point."""
    step_noise, fix_noise = gtsam.noiseModel.Isotropic.Sigma(6, 1e-2), gtsam.noiseModel.Isotropic.Sigma(6, 0.05)
    step = gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.1]))
    for k in range(n):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        fix = gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.15 * k]))
        graph.add(gtsam.PriorFactorPose3(X(k), fix, fix_noise))
        if k:
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, step_noise))
        values.insert(X(k), fix)
        window.update(graph, values, {X(k): float(k)}, newest=(X(k),), iterations=2)


def test_a_repair_after_marginalising_keeps_the_window_where_it_was():
    """The marginal of the variables gone is a linear factor about the linearisation point of the variables it holds.
    Until stop 64 a repair rebuilt the window in a new ISAM2 that relinearised those: the marginal kept asking for the
    same step from wherever they had moved, and every pass moved the window again (a recorded demo: every pose
    1.1-1.3 m in one repair). A repair must leave the rest of the window where it was."""
    repaired, twin = FixedLagWindow(lag_s=2.5), FixedLagWindow(lag_s=2.5)
    _pulled_chain(repaired, 12)
    _pulled_chain(twin, 12)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(_projection((10.0, 0.0), X(11), L(0)))           # one view: its depth is free
    values.insert(L(0), np.array([0.1, 0.0, 5.0]))
    repaired.update(graph, values, {L(0): 11.0}, iterations=2)
    twin.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {}, iterations=2)
    assert repaired.repairs == ['dropped l0']
    for k in range(9, 12):
        np.testing.assert_allclose(repaired.estimate().atPose3(X(k)).translation(),
                                   twin.estimate().atPose3(X(k)).translation(), atol=1e-6)


def test_the_newest_marginal_is_read_when_the_only_pass_shared_its_clique_with_a_variable_that_left():
    """With no extra pass (``smoother_iterations`` 0) the variables that leave go after the only elimination, and the
    root clique the newest marginal is read from can still hold one of them: its size must come from that pass."""
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    window = FixedLagWindow(lag_s=4.5)
    first, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    first.add(gtsam.PriorFactorPoint3(0, np.zeros(3), noise))
    values.insert(0, np.zeros(3))
    window.update(first, values, {0: 0.0}, newest=(0,))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.BetweenFactorPoint3(0, 1, np.ones(3), noise))
    values.insert(1, np.ones(3))
    window.update(graph, values, {1: 10.0}, newest=(1,))         # 0 (stamp 0) leaves after the pass
    assert list(window.estimate().keys()) == [1]
    np.testing.assert_allclose(window.marginal_covariance(1), 2 * 0.01 * np.eye(3), rtol=1e-9)
