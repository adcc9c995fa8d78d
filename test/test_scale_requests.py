"""When the estimator asks the rig for a vergence step (estimation/scale_requests.py)."""

import math

from fixego_ros.estimation.scale_requests import ScaleRequests


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
