"""Analytic Jacobian of the Sampson coplanarity residuals (the LM solver's hot path)."""

from __future__ import annotations

import numpy as np
import pytest

from fixego_ros.estimation.coplanarity import (
    RayPairs,
    numeric_jacobian,
    sampson_residuals,
    sampson_residuals_jacobian,
    sampson_residuals_jacobians,
)
from fixego_ros.geometry.rotation import exp_so3


def random_pairs(rng, n=40, lever=(0.3, -0.05, 0.02)):
    """Two groups: one camera at the rig origin, one on a lever arm; different weights."""
    return RayPairs.build([(rng.normal(size=(n, 3)) + [0, 0, 3], rng.normal(size=(n, 3)) + [0, 0, 3], np.zeros(3), 1.0),
                           (rng.normal(size=(n, 3)) + [0, 0, 3], rng.normal(size=(n, 3)) + [0, 0, 3],
                            np.asarray(lever), 0.5)])


def central_jacobian(R, T, pairs, h=1e-6):
    J = np.zeros((len(pairs), 6))
    for i in range(6):
        dx = np.zeros(6)
        dx[i] = h
        plus = sampson_residuals(exp_so3(dx[:3]) @ R, T + dx[3:], pairs)
        minus = sampson_residuals(exp_so3(-dx[:3]) @ R, T - dx[3:], pairs)
        J[:, i] = (plus - minus) / (2 * h)
    return J


@pytest.mark.parametrize('seed', range(4))
def test_analytic_jacobian_matches_central_differences(seed):
    rng = np.random.default_rng(seed)
    pairs = random_pairs(rng)
    R = exp_so3(rng.normal(size=3) * 0.1)
    T = rng.normal(size=3) * 0.2
    r, J = sampson_residuals_jacobian(R, T, pairs)
    assert np.allclose(r, sampson_residuals(R, T, pairs), rtol=0, atol=1e-14)
    Jc = central_jacobian(R, T, pairs)
    assert np.abs(J - Jc).max() <= 1e-6 * np.abs(Jc).max()
    # the solver's old forward differences at x = 0 are the same derivative, up to their truncation error
    Jf = numeric_jacobian(R, np.concatenate([np.zeros(3), T]), pairs)[1]
    assert np.abs(J - Jf).max() <= 1e-4 * np.abs(J).max()


def test_jacobian_finite_on_degenerate_input():
    rng = np.random.default_rng(0)
    same = np.tile([0.0, 0.0, 1.0], (10, 1))
    cases = [
        (RayPairs.build([(same, same, np.zeros(3), 1.0)]), np.eye(3), np.zeros(3)),        # no baseline at all
        (RayPairs.build([(same, same, np.zeros(3), 1.0)]), np.eye(3), np.array([0, 0, 1.0])),  # along the rays
        (random_pairs(rng), np.eye(3), np.zeros(3)),                                       # T = 0, lever arm only
        (random_pairs(rng, lever=(0, 0, 0)), exp_so3([0.01, 0, 0]), np.zeros(3)),
    ]
    for pairs, R, T in cases:
        r, J = sampson_residuals_jacobian(R, T, pairs)
        assert r.shape == (len(pairs),) and J.shape == (len(pairs), 6)
        assert np.all(np.isfinite(r)) and np.all(np.isfinite(J))
        assert np.allclose(r, sampson_residuals(R, T, pairs), atol=1e-12)


def test_cached_transposes_are_contiguous_copies():
    pairs = random_pairs(np.random.default_rng(1), n=5)
    for name, src in (('aT', pairs.a), ('bT', pairs.b), ('cT', pairs.centers)):
        arr = getattr(pairs, name)
        assert arr.flags.c_contiguous and np.array_equal(arr, src.T)
        assert getattr(pairs, name) is arr                      # computed once
    assert np.array_equal(pairs.aT_cyclic, pairs.a.T[[0, 1, 2, 0, 1]])


def test_batched_jacobians_are_those_of_single_motions_bit_for_bit():
    """The solver refines its starts side by side; a batch must not change a single bit of any of them."""
    rng = np.random.default_rng(3)
    pairs = random_pairs(rng)
    Rs = np.stack([exp_so3(rng.normal(size=3) * 0.1) for _ in range(5)])
    Ts = rng.normal(size=(5, 3)) * 0.2
    Ts[2] = 0.0                                     # one with no baseline of its own (lever arm only)
    r, J = sampson_residuals_jacobians(Rs, Ts, pairs)
    assert r.shape == (5, len(pairs)) and J.shape == (5, len(pairs), 6)
    for k in range(5):
        rk, Jk = sampson_residuals_jacobian(Rs[k], Ts[k], pairs)
        assert np.array_equal(r[k], rk) and np.array_equal(J[k], Jk)
        assert np.allclose(rk, sampson_residuals(Rs[k], Ts[k], pairs), rtol=0, atol=1e-14)
