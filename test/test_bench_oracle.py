"""The oracle diagnostic (bench/oracle.py): the simulator's truth against the front end's rays, on one fixed seed."""

from __future__ import annotations

import pytest

from fixego_ros.bench.oracle import run_seed


@pytest.fixture(scope='module')
def seed1() -> dict[str, float]:
    return run_seed(1)


def test_exact_rays_give_the_back_end_its_best_and_the_front_end_is_measured_against_them(seed1):
    # seed 1 of the paper recipe: exact rays 0.97 cm mean, the front end's 3.4 (stop 53)
    assert seed1['exact.mean_error_cm'] < 2.0
    assert seed1['exact.mean_error_cm'] < seed1['front_end.mean_error_cm'] < 10.0
    assert 0.9 < seed1['exact.path_length_ratio'] < 1.1


def test_track_drift_is_reported_by_age_and_stays_small(seed1):
    ages = ['1-1', '2-3', '4-7', '8-15', '16+']
    medians = [seed1[f'drift_px.{a}.median'] for a in ages]
    assert medians[0] < 0.1                       # one frame of LK: a few hundredths of a pixel
    assert medians[-1] < 0.4                      # 16+ frames: 0.2 px since the alignment (0.62 before)
    assert all(seed1[f'drift_px.{a}.p90'] >= m for a, m in zip(ages, medians, strict=True))

