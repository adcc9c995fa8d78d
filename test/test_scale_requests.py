"""When the estimator asks the rig for a vergence step (estimation/scale_requests.py)."""

import math

import numpy as np
import pytest

from fixego_ros.estimation.scale_requests import ScaleRequests, newest, vergence_measurement


def test_unmeasured_scale_asks_at_most_once_per_interval():
    r = ScaleRequests(max_rel_std=0.05, min_interval_s=5.0, drift_per_s=0.01)
    assert r.rel_std(10.0, None) == math.inf
    assert r.due(10.0, None, speed_source=False)
    assert not r.due(12.0, None, speed_source=False)          # within the interval
    assert r.due(15.0, None, speed_source=False) and r.count == 2


def test_measured_scale_asks_once_its_std_has_grown_past_the_bound():
    r = ScaleRequests(max_rel_std=0.05, min_interval_s=1.0, drift_per_s=0.01)
    m = (100.0, 0.02)                                          # 2 % at t = 100 s, +1 %/s
    assert r.rel_std(102.0, m) == 0.02 + 0.02
    assert not r.due(102.9, m, speed_source=False)             # 4.9 %
    assert r.due(103.5, m, speed_source=False)                 # 5.5 %
    assert r.last_request == 103.5


def test_a_speed_source_never_asks():
    r = ScaleRequests()
    assert not r.due(1e3, None, speed_source=True) and r.count == 0


def test_a_vergence_measurement_counts_from_when_it_is_received():
    """Its relative std is its covariance along the ray over its distance; the newest of the received one and the
    back end's decides (the live smoother uses a measurement seconds later, and meanwhile the estimator asked for
    another: a second step on the same point at rest, stop 56)."""
    point = np.array([0.0, 0.0, 3.0])
    cov = np.diag([1e-4, 1e-4, 0.03 ** 2])
    stamp, rel = vergence_measurement(10.0, point, cov)
    assert stamp == 10.0 and rel == pytest.approx(0.01)
    assert newest(None, None) is None
    assert newest(None, (10.0, 0.01)) == (10.0, 0.01)
    assert newest((12.0, 0.02), (10.0, 0.01)) == (12.0, 0.02)
    r = ScaleRequests(max_rel_std=0.05, min_interval_s=5.0, drift_per_s=0.005)
    assert not r.due(11.0, newest(None, (stamp, rel)), speed_source=False)      # received, not yet used: no ask
    assert r.due(11.0, newest(None, None), speed_source=False)                  # before: it asked again
