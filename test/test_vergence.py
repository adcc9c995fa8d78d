"""Start-up vergence core: triangulation geometry, partner-point search on simulator images, the step's
bounds, and the tracker's select_at."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fixego_ros.geometry.rig import default_rig_path, load_rig, make_rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.sim.render import Renderer, project_points
from fixego_ros.sim.trajectories import attitude, make_trajectory
from fixego_ros.sim.world import World, make_plane, make_room
from fixego_ros.tracking.fixation import FixationTracker
from fixego_ros.tracking.servo import JointHistory
from fixego_ros.tracking.vergence import (
    VergenceParams,
    VergenceStep,
    find_partner_point,
    triangulate_fixation,
    vergence_aims,
)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


# ------------------------------------------------------------------------------------------------ geometry
@pytest.mark.parametrize('X', [[0.0, 0.0, 2.0], [0.3, -0.2, 3.0], [-0.5, 0.1, 4.0], [1.0, 0.4, 2.5]])
def test_triangulation_of_exact_rays_is_exact(X):
    X = np.array(X)
    c = np.array([-0.2, 0.01, 0.005])
    tri = triangulate_fixation(_unit(X), _unit(X - c), c, 1e-3)
    assert tri.ok and tri.reason == ''
    assert np.allclose(tri.point_rig, X, atol=1e-9)
    assert tri.distance_m == pytest.approx(np.linalg.norm(X), abs=1e-9)
    assert tri.gap_m < 1e-9
    assert tri.angle_rad == pytest.approx(math.acos(_unit(X) @ _unit(X - c)), abs=1e-9)


def test_distance_std_scales_as_d_squared_over_baseline():
    sigma = 5e-4
    stds = {}
    for d in (2.0, 4.0):
        for b in (0.2, 0.4):
            X = np.array([0.0, 0.0, d])
            c = np.array([-b, 0.0, 0.0])
            tri = triangulate_fixation(_unit(X), _unit(X - c), c, sigma)
            stds[d, b] = tri.std_m
            # straight ahead of the right camera: both rays' angular noise moves the depth by ~d^2/b each
            assert tri.std_m == pytest.approx(math.sqrt(2) * sigma * d * d / b, rel=0.03)
            assert tri.cov_rig.shape == (3, 3) and np.allclose(tri.cov_rig, tri.cov_rig.T)
    assert stds[4.0, 0.2] / stds[2.0, 0.2] == pytest.approx(4.0, rel=0.02)
    assert stds[2.0, 0.4] / stds[2.0, 0.2] == pytest.approx(0.5, rel=0.02)
    # Monte Carlo agrees with the first-order std
    rng = np.random.default_rng(0)
    X, c = np.array([0.2, 0.0, 3.0]), np.array([-0.2, 0.0, 0.0])
    tri = triangulate_fixation(_unit(X), _unit(X - c), c, sigma)
    ds = []
    for _ in range(2000):
        r = _unit(_unit(X) + sigma * rng.standard_normal(3))
        l = _unit(_unit(X - c) + sigma * rng.standard_normal(3))
        ds.append(triangulate_fixation(r, l, c, sigma).distance_m)
    assert np.std(ds) == pytest.approx(tri.std_m, rel=0.1)


def test_parallel_or_backward_rays_are_rejected_with_a_reason():
    c = np.array([-0.2, 0.0, 0.0])
    far = np.array([0.0, 0.0, 100.0])
    tri = triangulate_fixation(_unit(far), _unit(far - c), c, 1e-3)
    assert not tri.ok and 'parallel' in tri.reason and not np.isfinite(tri.distance_m)
    tri = triangulate_fixation([0.0, 0.0, 1.0], _unit([0.3, 0.0, -1.0]), c, 1e-3)
    assert not tri.ok and tri.reason


# ------------------------------------------------------------------------------------------------ simulator
@pytest.fixture(scope='module')
def room():
    rig = load_rig(default_rig_path())
    return rig, make_room(0, 0.002), Renderer(make_room(0, 0.002), rig, seed=1)


def _fixate_and_search(rig, world, renderer, pose, right_deg):
    """Right head fixates the scene point on its axis; the left head points where the step would aim it."""
    rq = tuple(math.radians(a) for a in right_deg)
    centre = (rig.right.cx, rig.right.cy)
    ray = rig.pixels_to_rig_rays('right', np.array([centre]), *rq)[0]
    with np.errstate(invalid='ignore'):   # planes parallel to the ray
        lam, _ = world.raycast(pose.t, pose.R @ ray)
    X = pose.apply(lam * ray)
    p = VergenceParams()
    lq = vergence_aims(rig, ray, p.min_depth_m, p.max_depth_m, p.patch_half + 4)[0]
    m = find_partner_point(renderer.render('right', pose, *rq), centre, rq, renderer.render('left', pose, *lq), lq,
                           rig, p)
    true_px = project_points(rig, 'left', pose, *lq, X[None])[0][0]
    return m, lam, ray, lq, true_px


@pytest.mark.parametrize('right_deg', [(22.5, 0.0), (0.0, 0.0), (-30.0, 5.0), (60.0, -10.0), (150.0, 3.0),
                                       (200.0, 0.0)])
def test_partner_point_and_distance_on_rendered_images(room, right_deg):
    rig, world, renderer = room
    pose = make_trajectory('paper').pose_at(0.0)
    m, true_d, ray_r, lq, true_px = _fixate_and_search(rig, world, renderer, pose, right_deg)
    assert 2.0 < true_d < 4.0
    assert m.ok, m.reason
    assert np.linalg.norm(np.array(m.pixel) - true_px) < 1.0, (m.pixel, true_px)
    assert m.ncc > 0.9 and m.margin >= 0.1
    ray_l = rig.pixels_to_rig_rays('left', np.array([m.pixel]), *lq)[0]
    tri = triangulate_fixation(ray_r, ray_l, rig.c_L, 0.5 / rig.left.fx)
    assert tri.ok
    assert abs(tri.distance_m - true_d) < 0.03 * true_d
    assert abs(tri.distance_m - true_d) < 4 * tri.std_m + 0.005


def _wall_world(texture: np.ndarray) -> World:
    return World([make_plane([-3.0, 3.0, 2.5], [6.0, 0, 0], [0, 0, -2.5], 0.002, np.random.default_rng(0), 'wall',
                             texture=texture)])


def test_textureless_and_ambiguous_scenes_are_rejected_with_a_reason():
    rig = load_rig(default_rig_path())
    pose = Pose(attitude(0.0), np.array([0.0, 0.0, 1.2]))
    shape = (1251, 3001)
    flat = _wall_world(np.full(shape, 128, np.uint8))
    m, *_ = _fixate_and_search(rig, flat, Renderer(flat, rig, seed=2), pose, (0.0, 0.0))
    assert not m.ok and m.pixel is None and 'textureless' in m.reason
    # vertical stripes, 2 cm period: every period along the (horizontal) epipolar line matches as well
    x = np.arange(shape[1])
    stripes = np.tile((128 + 80 * np.sin(2 * np.pi * x / 10.0)).astype(np.uint8), (shape[0], 1))
    striped = _wall_world(stripes)
    m, *_ = _fixate_and_search(rig, striped, Renderer(striped, rig, seed=2), pose, (0.0, 0.0))
    assert not m.ok and m.pixel is None and 'ambiguous' in m.reason
    # the left camera sees another scene (e.g. the point is occluded): no match
    rq = (0.0, 0.0)
    other = Renderer(make_room(0, 0.002), rig, seed=2).render('left', make_trajectory('paper').pose_at(0.0), 0.3, 0)
    right_img = Renderer(_wall_world(np.random.default_rng(1).integers(0, 255, shape, dtype=np.uint8)), rig,
                         seed=2).render('right', pose, *rq)
    m = find_partner_point(right_img, (rig.right.cx, rig.right.cy), rq, other, (-0.03, 0.0), rig)
    assert not m.ok and ('no match' in m.reason or 'ambiguous' in m.reason)


# ------------------------------------------------------------------------------------------------ step, tracker
def test_step_without_a_right_camera_fails_by_its_timeout():
    rig = make_rig(320, 240)
    hist = JointHistory()
    hist.add(0.0, 0.0, 0.0)
    step = VergenceStep(rig, hist, VergenceParams(timeout_s=1.0))
    img = np.zeros((240, 320), np.uint8)
    for k in range(10):
        act = step.on_left_image(0.1 * k, img, 0.1 * k)
        assert act.kind == 'track' and act.select is None
    assert step.status.startswith('running: waiting')
    step.on_left_image(1.5, img, 1.5)
    assert step.status.startswith('failed: timeout') and 'waiting' in step.status
    assert step.finished and step.result is None   # never moved the head: nothing to return from


def test_tracker_select_at_starts_a_new_fixation_at_the_given_pixel():
    from fixego_ros.bench.servo import SyntheticView
    rig = make_rig(320, 240)
    view = SyntheticView(rig.right, seed=3)
    tr = FixationTracker(rig.right)
    st = tr.update(view.render(0.0, 0.0, 0.0, 0.0), 0.0)
    assert st.fixation_id == 0
    st = tr.select_at(view.render(0.0, 0.0, 0.0, 0.0), (200.3, 100.7), 0.1, 'vergence')
    assert st.reselected and st.fixation_id == 1 and st.pixel == (200.3, 100.7) and st.reason == 'vergence'
    st = tr.update(view.render(0.0, 0.0, 3.0, -2.0), 0.2)     # the scene shifts by (3, -2) px
    assert not st.reselected and st.fixation_id == 1
    assert st.pixel == pytest.approx((203.3, 98.7), abs=0.1)
    st = tr.select_at(view.render(0.0, 0.0, 3.0, -2.0), (2.0, 2.0), 0.3)   # at the border: refused
    assert not st.valid and st.reason == 'outside'
