"""The ray jitter behind the seed benchmark's draws (bench/jitter.py): every ray perturbed by the pixels asked,
nothing else touched, and a draw repeats."""

from __future__ import annotations

import numpy as np
import pytest

from fixego_ros.bench.jitter import RayJitter
from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.geometry.rig import default_rig_path, load_rig, normalize_rays


@pytest.fixture
def rig():
    return load_rig(default_rig_path())


def _obs(n: int = 2000) -> FrameObservation:
    rng = np.random.default_rng(5)
    rays = lambda: normalize_rays(rng.normal([0.0, 0.0, 1.0], 0.05, (n, 3)))  # noqa: E731
    right = CameraFrame(rays()[0], 3, np.eye(3), rays(), rays(), np.arange(n), rays())
    return FrameObservation(1.0, right, None, 0.9, True)


def test_every_ray_moves_by_the_pixels_asked_and_the_rest_stays(rig):
    obs = _obs()
    out = RayJitter(rig, 0.01, seed=1)(obs)
    assert out.left is None and out.stamp == obs.stamp and out.prev_stamp == obs.prev_stamp
    a, b = obs.right, out.right
    assert b.fixation_id == 3 and np.array_equal(b.track_ids, a.track_ids)
    assert np.array_equal(b.cam_to_rig, a.cam_to_rig)
    for name in ('track_rays', 'flow_prev', 'flow_curr'):
        before, after = getattr(a, name), getattr(b, name)
        off_px = np.linalg.norm(np.cross(before, after), axis=1) * rig.camera('right').fx
        # two axes of 0.01 px white noise: Rayleigh, median 0.01 * sqrt(2 ln 2) = 0.0118 px
        assert 0.011 < float(np.median(off_px)) < 0.0126, name
        assert np.allclose(np.linalg.norm(after, axis=1), 1.0)
    assert 0 < np.linalg.norm(np.cross(a.fixation_ray, b.fixation_ray)) * rig.camera('right').fx < 0.1


def test_a_draw_repeats_another_differs_and_zero_changes_nothing(rig):
    obs = _obs(50)
    one, again, other = (RayJitter(rig, 0.01, seed=s)(obs) for s in (1, 1, 2))
    assert np.array_equal(one.right.track_rays, again.right.track_rays)
    assert not np.array_equal(one.right.track_rays, other.right.track_rays)
    assert np.array_equal(RayJitter(rig, 0.0)(obs).right.track_rays, obs.right.track_rays)
    with pytest.raises(ValueError):
        RayJitter(rig, -0.01)
