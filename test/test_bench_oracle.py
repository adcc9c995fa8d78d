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


def test_the_noise_option_perturbs_each_ray_by_the_pixels_asked_and_nothing_without():
    import numpy as np

    from fixego_ros.bench.oracle import Oracle, Truth
    from fixego_ros.geometry.rig import default_rig_path, load_rig, normalize_rays
    rig = load_rig(default_rig_path())
    rays = normalize_rays(np.random.default_rng(3).normal([0.0, 0.0, 1.0], 0.05, (4000, 3)))
    assert np.array_equal(Oracle(Truth(rig, None, {}), True)._noisy('right', rays), rays)
    noisy = Oracle(Truth(rig, None, {}), True, noise_px=0.15)._noisy('right', rays)
    off_px = np.linalg.norm(np.cross(noisy, rays), axis=1) * rig.camera('right').fx
    # two axes of 0.15 px white noise: the offset is Rayleigh, median 0.15 * sqrt(2 ln 2) = 0.177 px
    assert 0.16 < float(np.median(off_px)) < 0.19
    assert np.allclose(np.linalg.norm(noisy, axis=1), 1.0)
