"""Vergence core: triangulation geometry, partner-point search on simulator images, the averaging of frames
(value and honest std), whole steps on rendered images with simulated heads (frozen and moving rig), the step's
bounds and failures, the scheduler's triggers and limits, and the tracker's select_at."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from fixego_ros.geometry.rig import default_rig_path, load_rig, make_rig
from fixego_ros.geometry.rotation import Pose, rot_y
from fixego_ros.sim.render import Renderer, project_points
from fixego_ros.sim.trajectories import attitude, make_trajectory
from fixego_ros.sim.world import World, make_plane, make_room
from fixego_ros.tracking.fixation import NO_FIXATION_ID, FixationTracker
from fixego_ros.tracking.servo import JointHistory, centring_angles
from fixego_ros.tracking.vergence import (
    VergenceParams,
    VergenceSample,
    VergenceSchedule,
    VergenceScheduler,
    VergenceStep,
    average_samples,
    find_partner_point,
    triangulate_fixation,
    vergence_aim_depths,
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
    depth = vergence_aim_depths(rig, ray, p.min_depth_m, p.max_depth_m, p.patch_half + 4)[0]
    lq = rig.aim_readings('left', ray * depth)
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


def test_a_match_that_correlates_too_weakly_is_not_measured(room):
    """Finding the point (best NCC >= ncc_min) is not enough to measure it: a refined match correlating below
    match_ncc_min (live, such steps were 1-26 % off) is refused with its NCC, and taken when the bound allows it."""
    rig, _, renderer = room
    pose = make_trajectory('paper').pose_at(0.0)
    rq = (math.radians(22.5), 0.0)
    centre = (rig.right.cx, rig.right.cy)
    ray = rig.pixels_to_rig_rays('right', np.array([centre]), *rq)[0]
    p = VergenceParams()
    lq = rig.aim_readings('left', ray * vergence_aim_depths(rig, ray, p.min_depth_m, p.max_depth_m,
                                                             p.patch_half + 4)[0])
    left = renderer.render('left', pose, *lq).astype(float)
    noisy = np.clip(left + np.random.default_rng(0).normal(0.0, 10.0, left.shape), 0, 255).astype(np.uint8)
    right = renderer.render('right', pose, *rq)
    m = find_partner_point(right, centre, rq, noisy, lq, rig, p)
    assert not m.ok and m.pixel is None and 'correlates too weakly' in m.reason
    assert p.ncc_min < m.ncc < p.match_ncc_min
    loose = find_partner_point(right, centre, rq, noisy, lq, rig, VergenceParams(match_ncc_min=0.85))
    assert loose.ok and loose.ncc == pytest.approx(m.ncc)
    assert find_partner_point(right, centre, rq, left.astype(np.uint8), lq, rig, p).ok      # the clean image


# ------------------------------------------------------------------------------------------------ averaging
def _samples(X_of_t, c, times, rng, joint_sigma=0.0, moving=True, rate=0.02):
    """Rays at each time towards the (moving, in the rig frame) point X_of_t(t), both with independent joint
    noise of ``joint_sigma`` (rad) per axis."""
    out = []
    for k, t in enumerate(times):
        X = X_of_t(t)
        r = _unit(_unit(X) + joint_sigma * rng.standard_normal(3))
        l = _unit(_unit(X - c) + joint_sigma * rng.standard_normal(3))
        out.append(VergenceSample(t, r, l, (0.001 * k, 0.0, 0.002 * k, 0.0), (0.0, 0.0), (0.0, 0.0), (rate, rate),
                                  (moving, moving)))
    return out


def test_average_follows_a_moving_point_and_reads_it_at_the_reference_frame():
    c = np.array([-0.2, 0.0, 0.0])
    X_of_t = lambda t: np.array([0.3, -0.1, 3.0 - 0.4 * t])          # noqa: E731  the rig approaches at 0.4 m/s
    times = np.arange(12) / 30.0
    avg = average_samples(_samples(X_of_t, c, times, np.random.default_rng(0)), c, 1e-6, 1e-6)
    assert avg.ok and avg.frames == 12 and avg.distinct_readings == 12
    assert avg.t in times
    true = np.linalg.norm(X_of_t(avg.t))
    assert avg.distance_m == pytest.approx(true, abs=2e-5)       # a line through |X(t)|, slightly curved
    assert np.allclose(avg.point_rig, X_of_t(avg.t), atol=2e-5)
    assert avg.rate_mps == pytest.approx(-0.4 * 3.0 / np.linalg.norm(X_of_t(avg.t)), rel=0.05)
    assert avg.cov_rig.shape == (3, 3) and np.allclose(avg.cov_rig, avg.cov_rig.T)


def test_average_std_is_honest_for_independent_and_common_errors():
    """Monte Carlo: independent joint noise shrinks with the frames and the stated std follows it; a common
    pixel error does not shrink, and the stated std does not pretend it does."""
    c = np.array([-0.2, 0.0, 0.0])
    X_of_t = lambda t: np.array([0.2, 0.0, 3.0 + 0.2 * t])             # noqa: E731
    times = np.arange(10) / 30.0
    sigma = math.radians(0.033)
    rng = np.random.default_rng(1)
    errs, stds = [], []
    for _ in range(300):
        avg = average_samples(_samples(X_of_t, c, times, rng, joint_sigma=sigma / math.sqrt(3) * math.sqrt(2)),
                              c, 1e-7, sigma, timing_sigma_s=0.0)
        assert avg.ok
        errs.append(avg.distance_m - np.linalg.norm(X_of_t(avg.t)))
        stds.append(avg.std_m)
    single = triangulate_fixation(X_of_t(0.0), X_of_t(0.0) - c, c, sigma).std_m
    assert np.std(errs) < 0.5 * single                       # averaging helps ...
    assert 0.7 < np.std(errs) / np.median(stds) < 1.5        # ... and the stated std says by how much
    # a head at rest reads exactly: its joint part is zero; a common pixel error is not divided by the frames
    rest = average_samples(_samples(X_of_t, c, times, rng, moving=False, rate=0.0), c, 2e-4, sigma)
    one = triangulate_fixation(X_of_t(rest.t), X_of_t(rest.t) - c, c, 2e-4).std_m
    assert rest.std_m == pytest.approx(one, rel=0.05)


def test_average_std_carries_a_reading_time_error_common_to_the_frames():
    """Monte Carlo: both heads turn at 0.45 rad/s (the demo's arcs) and each head's readings are late by an error
    common to the step's 20 frames (std 1 ms: 0.45 mrad on each of its rays). Averaging cannot reduce it; with
    ``timing_bias_s`` the stated std says how large it is, without it the stated std is a fraction of the error."""
    c = np.array([-0.2, 0.0, 0.0])
    X = np.array([0.4, 0.0, 2.4])
    times = np.arange(20) / 30.0
    rate, tau = 0.45, 1e-3
    rng = np.random.default_rng(3)
    axis = _unit(np.cross(X - c, c))                # turns a ray in the plane of the two rays (the vergence)
    errs, stds = [], {0.0: [], tau: []}
    for _ in range(300):
        late_r, late_l = rate * tau * rng.standard_normal(2)
        samples = [dataclasses.replace(sm, ray_r=_unit(sm.ray_r + late_r * np.cross(axis, sm.ray_r)),
                                       ray_l=_unit(sm.ray_l + late_l * np.cross(axis, sm.ray_l)))
                   for sm in _samples(lambda t: X, c, times, rng, rate=rate)]
        for bias in stds:
            avg = average_samples(samples, c, 1e-7, 1e-7, timing_sigma_s=0.0, timing_bias_s=bias)
            assert avg.ok
            stds[bias].append(avg.std_m)
        errs.append(avg.distance_m - np.linalg.norm(X))
    spread = float(np.std(errs))
    print(f'error std {spread:.4f} m; stated {np.median(stds[tau]):.4f} m with the common part, '
          f'{np.median(stds[0.0]):.6f} m without')
    assert 0.02 * np.linalg.norm(X) > spread > 0.003 * np.linalg.norm(X)     # 0.3-2 %: it matters at 2.4 m
    assert 0.7 < spread / np.median(stds[tau]) < 1.5
    assert np.median(stds[0.0]) < 0.1 * spread


def test_average_rejects_frames_that_disagree_and_parallel_rays():
    c = np.array([-0.2, 0.0, 0.0])
    times = np.arange(10) / 30.0
    rng = np.random.default_rng(2)
    ok = _samples(lambda t: np.array([0.0, 0.0, 3.0]), c, times[:5], rng)
    slipped = _samples(lambda t: np.array([0.0, 0.0, 3.6]), c, times[5:], rng)   # the partner point slipped
    avg = average_samples(ok + slipped, c, 1e-4, 1e-4)
    assert not avg.ok and 'disagree' in avg.reason
    far = _samples(lambda t: np.array([0.0, 0.0, 100.0]), c, times, rng)
    avg = average_samples(far, c, 1e-4, 1e-4)
    assert not avg.ok and 'parallel' in avg.reason
    assert not average_samples([], c, 1e-4, 1e-4).ok


def test_average_rejects_a_measurement_too_weak_for_the_scale():
    """A point seen 4 deg off the baseline's direction at 1.2 m (a right head turned towards the left one) while both
    heads turn at 0.45 rad/s (the demo's arcs): the rays meet at 0.8 deg, and the distance's std is 6-7 % of it. Such
    steps gave the demo's 21-72 % errors (d1: 0.80 deg at 1.25 m, std 8 %; docs/results.md "Stop 85"): with
    ``max_rel_std`` 5 % it fails, saying why; the same step facing the point (std < 1 %) is kept."""
    c = np.array([-0.2, 0.0, 0.0])
    times = np.arange(20) / 30.0
    sigma, pixel = math.radians(0.033), 1.7e-4
    timing = dict(timing_sigma_s=0.005, timing_bias_s=0.001)
    along = 1.2 * np.array([-math.cos(math.radians(4.0)), 0.0, math.sin(math.radians(4.0))])
    samples = _samples(lambda t: along, c, times, np.random.default_rng(5), rate=0.45)
    loose = average_samples(samples, c, pixel, sigma, **timing)
    assert loose.ok and 0.05 * loose.distance_m < loose.std_m < 0.1 * loose.distance_m
    weak = average_samples(samples, c, pixel, sigma, **timing, max_rel_std=0.05)
    assert not weak.ok and 'too weak' in weak.reason and '> 5.0 %' in weak.reason, weak.reason
    facing = _samples(lambda t: np.array([0.0, 0.0, 1.2]), c, times, np.random.default_rng(5), rate=0.45)
    kept = average_samples(facing, c, pixel, sigma, **timing, max_rel_std=0.05)
    assert kept.ok and kept.std_m < 0.01 * kept.distance_m


# ------------------------------------------------------------------------------------------------ whole steps
D30_UNIT = (math.radians(1 / 8.8), math.radians(1 / 12.0))       # VISCA pan, tilt reading quanta


def _quantised(q):
    return tuple(round(a / u) * u for a, u in zip(q, D30_UNIT, strict=True))


def _turning_rig(rate_deg_s: float, until_s: float = math.inf):
    """The paper loop's start pose turning about the vertical at ``rate_deg_s`` until ``until_s`` (pose of t)."""
    pose0 = make_trajectory('paper').pose_at(0.0)
    rate = math.radians(rate_deg_s)
    return lambda t: Pose(pose0.R @ rot_y(rate * min(t, until_s)), pose0.t)


class _SimHeads:
    """Both heads on rendered images: the right one fixates a scene point exactly (quantised readings); the left
    one is driven by the step (aims) or, tracking, by a one-frame servo that centres its fixation; heads turn at
    most 80 deg/s (EVI-D30). Frames at 30 Hz; readings at the frame times."""

    def __init__(self, rig, world, renderer, pose_of_t, right_deg, left_deg):
        self.rig, self.world, self.renderer, self.pose_of_t = rig, world, renderer, pose_of_t
        pose = pose_of_t(0.0)
        rq = tuple(math.radians(a) for a in right_deg)
        ray = rig.pixels_to_rig_rays('right', np.array([[rig.right.cx, rig.right.cy]]), *rq)[0]
        with np.errstate(invalid='ignore'):
            lam, _ = world.raycast(pose.t, pose.R @ ray)
        self.X = pose.apply(lam * ray)              # the right fixation point (world)
        self.left_q = tuple(math.radians(a) for a in left_deg)
        self.tracker = FixationTracker(rig.left)
        self.actions: list[str] = []

    def right(self, t):
        pose = self.pose_of_t(t)
        q = _quantised(self.rig.aim_readings('right', pose.inverse().apply(self.X)))
        px = project_points(self.rig, 'right', pose, *q, self.X[None])[0][0]
        return q, (float(px[0]), float(px[1])), self.renderer.render('right', pose, *q)

    def true_distance(self, t, point_rig):
        pose = self.pose_of_t(t)
        with np.errstate(invalid='ignore'):
            lam, _ = self.world.raycast(pose.t, pose.R @ _unit(point_rig))
        return lam

    def _move(self, target):
        step = math.radians(80.0) / 30.0
        self.left_q = _quantised(tuple(a + float(np.clip(b - a, -step, step))
                                       for a, b in zip(self.left_q, target, strict=True)))

    def run(self, step, frames, right_id=lambda t: 0, right_fixated=lambda t: True):
        for k in range(frames):
            t = k / 30.0
            rq, rpx, rimg = self.right(t)
            step.add_right_joints(t, *rq)
            step.add_right_image(t, rimg)
            step.add_right_fixation(t, rpx, right_id(t))
            step.left_history.add(t, *self.left_q)
            limg = self.renderer.render('left', self.pose_of_t(t), *self.left_q)
            act = step.on_left_image(t, limg, t + 0.001, right_fixated=right_fixated(t))
            self.actions.append(act.kind)
            if act.kind == 'hold':
                self._move(act.aim)
            else:
                if act.reselect:
                    self.tracker.request_reselect('vergence_end')
                st = (self.tracker.select_at(limg, act.select, t, 'vergence') if act.select is not None
                      else self.tracker.update(limg, t))
                step.on_left_fixation(t, st.pixel, st.fixation_id, st.reselected)
                if st.valid:
                    self._move(centring_angles(self.rig.left, st.pixel, *self.left_q))
            step.poll(t + 0.002)
            if step.finished:
                return k
        return frames


@pytest.mark.parametrize('speed', [0.0, 0.2])
def test_a_whole_step_measures_within_one_percent(room, speed):
    """Frozen and moving (0.2 m/s sideways) rig: the step leaves the left's own point, finds and fixates the right
    fixation point, averages 20 settled frames, returns; the distance is within 1 % (and its stated std)."""
    rig, world, renderer = room
    pose0 = make_trajectory('paper').pose_at(0.0)
    pose_of_t = lambda t: Pose(pose0.R, pose0.t + pose0.R @ np.array([speed * t, 0.0, 0.0]))   # noqa: E731
    heads = _SimHeads(rig, world, renderer, pose_of_t, (22.5, 0.0), (-22.5, 0.0))
    hist = JointHistory()
    step = VergenceStep(rig, hist, VergenceParams(prior_depth_m=3.0), left_range=((-1.7, 1.7), (-0.4, 0.4)))
    end = heads.run(step, 150)
    assert step.finished and step.succeeded, step.status
    r = step.result
    true = heads.true_distance(r.stamp, r.point_rig)
    assert 2.0 < true < 4.0
    err = r.distance_m - true
    print(f'speed {speed}: true {true:.3f} m, measured {r.distance_m:.3f} m ({100 * err / true:+.2f} %), std '
          f'{r.std_m:.3f} m, {r.frames} frames ({r.distinct_readings} distinct readings), interrupted '
          f'{step.interrupted_s:.2f} s, away {step.away_s:.2f} s')
    assert abs(err) < 0.01 * true
    assert abs(err) < 3 * r.std_m and r.std_m < 0.02 * true
    n = step.p.frames
    # frozen: both heads stand still, their readings are exact and the pixel part is one correspondence, so the
    # step stops once settle_frames frames stood still; moving: up to ``frames`` frames
    assert step.p.settle_frames <= r.frames < n if speed == 0.0 else n // 2 <= r.frames <= n
    # the head was driven away (hold) and came back; the left's own point is selected again at the end
    assert 'hold' in heads.actions and heads.actions[-1] == 'track'
    kinds = [what for what, _ in step.timeline]
    assert kinds[0] == 'aiming' and 'converging' in kinds and kinds[-1] == 'ended'
    assert 0.0 < step.interrupted_s <= step.away_s < 4.0
    assert end < 150


def test_on_a_turning_rig_the_aim_leads_the_point_and_the_step_measures(room, monkeypatch):
    """The rig turns at 22 deg/s (the papers' loop on its arcs): the right fixation point's direction turns with
    the right head, ~13 deg over the left head's ~0.6 s trip. The aim leads it by the right head's rate over the
    trip, so the partner point is found near the centre (no centring move) and the step measures within 1.5 %.
    Aimed where the point was when the step started (the lead taken out), the search lands ~13 deg off: the
    partner point has to be centred first or is not found."""
    rig, world, renderer = room
    pose_of_t = _turning_rig(22.0)

    def run() -> VergenceStep:
        heads = _SimHeads(rig, world, renderer, pose_of_t, (22.5, 0.0), (-22.5, 0.0))
        step = VergenceStep(rig, JointHistory(), VergenceParams(prior_depth_m=3.0),
                            left_range=((-1.7, 1.7), (-0.4, 0.4)))
        heads.run(step, 150)
        step.true = heads.true_distance(step.result.stamp, step.result.point_rig) if step.succeeded else None
        return step

    led = run()
    kinds = [what for what, _ in led.timeline]
    assert led.succeeded, led.status
    assert 'centring' not in kinds and kinds.count('aim') == 1
    err = led.result.distance_m - led.true
    print(f'turning rig: true {led.true:.3f} m, measured {led.result.distance_m:.3f} m ({100 * err / led.true:+.2f} '
          f'%), std {led.result.std_m:.3f} m, {led.result.frames} frames, timeline {led.timeline}')
    assert abs(err) < 0.015 * led.true and abs(err) < 3 * led.result.std_m

    monkeypatch.setattr(VergenceStep, '_led', lambda self, point, t_seen, t_then: point)
    stale = run()
    kinds = [what for what, _ in stale.timeline]
    assert 'centring' in kinds or not stale.succeeded, stale.timeline


def test_a_step_waits_while_the_heads_turn_faster_than_the_limit(room):
    """The rig turns at 22 deg/s (the papers' arcs) for 1.5 s, then stands. With ``max_rate_deg_s`` 12 the step
    waits with the left on its own point until the turn ends, then measures within 1 %; with the default (60) it
    leaves during the turn. (12 was tried as the default at stop 78: live steps then kept within 1.4 % of the truth,
    but the demo runs lost the first arc's measurement and met 5 / 5 cm in 7 of 15 against 9 of 15; docs/results.md
    "Stop 78".)"""
    rig, world, renderer = room
    until = 1.5
    left_at = {}
    for max_rate in (12.0, VergenceParams().max_rate_deg_s):
        heads = _SimHeads(rig, world, renderer, _turning_rig(22.0, until), (22.5, 0.0), (-22.5, 0.0))
        step = VergenceStep(rig, JointHistory(), VergenceParams(prior_depth_m=3.0, max_rate_deg_s=max_rate),
                            left_range=((-1.7, 1.7), (-0.4, 0.4)))
        heads.run(step, 150)
        assert step.succeeded, step.status
        left_at[max_rate] = heads.actions.index('hold') / 30.0        # the first frame the step drives the head
        true = heads.true_distance(step.result.stamp, step.result.point_rig)
        err = step.result.distance_m - true
        print(f'max_rate_deg_s {max_rate:g}: left at {left_at[max_rate]:.2f} s, true {true:.3f} m, measured '
              f'{step.result.distance_m:.3f} m ({100 * err / true:+.2f} %), std {step.result.std_m:.3f} m')
        assert abs(err) < 0.01 * true and abs(err) < 3 * step.result.std_m
    assert left_at[12.0] >= until and left_at[VergenceParams().max_rate_deg_s] < until, left_at


def test_a_first_aim_led_past_the_bound_fails_before_the_head_moves(room):
    """The rig turns at 22 deg/s away from the right fixation point: the plan's aims fit a 1.6 s bound (51 deg, 1.51 s
    there and back), but the first one, led for where the point will be when the head arrives, does not. The step
    fails without driving the head: nothing interrupted, no return, and the scheduler is told the own point was not
    left."""
    rig, world, renderer = room
    heads = _SimHeads(rig, world, renderer, _turning_rig(-22.0), (22.5, 0.0), (-22.5, 0.0))
    step = VergenceStep(rig, JointHistory(), VergenceParams(prior_depth_m=3.0, max_interruption_s=1.6),
                        left_range=((-1.7, 1.7), (-0.4, 0.4)))
    heads.run(step, 150)
    assert step.finished and not step.succeeded and 'once led for the turning rig' in step.reason, step.reason
    assert 'max_interruption_s 1.6 s' in step.reason
    assert 'hold' not in heads.actions and step.interrupted_s == 0.0 and step.t_left is None


def test_the_return_is_cut_short_when_the_right_camera_has_no_fixation(room):
    """The right camera loses its fixation (a swing back from its pan limit) while the left head returns from a
    measurement: the left selects its own point at once, where the head is, instead of leaving both cameras without
    a fixation for the rest of the trip (~0.7 s; the end of the demo loop: 8-13 frames with neither fixated, placed
    by the motion model through the rig's final stop). The measurement stands; the interruption is the trip out."""
    rig, world, renderer = room
    pose0 = make_trajectory('paper').pose_at(0.0)
    results = {}
    for cut in (False, True):
        heads = _SimHeads(rig, world, renderer, lambda t: pose0, (22.5, 0.0), (-22.5, 0.0))
        step = VergenceStep(rig, JointHistory(), VergenceParams(prior_depth_m=3.0),
                            left_range=((-1.7, 1.7), (-0.4, 0.4)))
        heads.run(step, 150, right_fixated=lambda t, s=step, c=cut: not (c and s.phase == 'returning'))
        results[cut] = (step, heads)
    (full, _), (cut, heads) = results[False], results[True]
    kinds = [what for what, _ in cut.timeline]
    print(f'interrupted {full.interrupted_s:.2f} s with the whole return, {cut.interrupted_s:.2f} s cut: '
          f'{cut.timeline}')
    # (the renderer's noise differs between the two runs: the same distance to its noise)
    assert full.succeeded and cut.succeeded and cut.result.distance_m == pytest.approx(full.result.distance_m, 1e-3)
    assert 'return cut short' in kinds and 'return cut short' not in [w for w, _ in full.timeline]
    assert kinds[kinds.index('returning') + 1] == 'return cut short' and kinds[-1] == 'ended'
    assert cut.finished and cut.interrupted_s < full.interrupted_s - 0.4
    assert heads.actions[-1] == 'track' and heads.tracker.last.valid and heads.tracker.last.reselected  # own point


def test_a_move_past_the_interruption_bound_is_not_made(room, monkeypatch):
    """A rig turning at 10 deg/s with the aim's lead taken out (the test above): the partner point is found ~6 deg
    off the centre and needs a centring move. With a bound that admits the 49 deg trip there and back (predicted
    1.46 s) but not the centring move on top, the step gives up at the search and the head returns: the left
    fixation is interrupted about the trip alone, within the bound. The default bound makes the centring move and
    measures (its return is shorter than predicted: the rig turned the heads' directions closer meanwhile)."""
    rig, world, renderer = room
    pose_of_t = _turning_rig(10.0)
    monkeypatch.setattr(VergenceStep, '_led', lambda self, point, t_seen, t_then: point)
    steps = {}
    for bound in (1.5, VergenceParams().max_interruption_s):
        heads = _SimHeads(rig, world, renderer, pose_of_t, (22.5, 0.0), (-22.5, 0.0))
        step = VergenceStep(rig, JointHistory(), VergenceParams(prior_depth_m=3.0, max_interruption_s=bound),
                            left_range=((-1.7, 1.7), (-0.4, 0.4)))
        heads.run(step, 150)
        steps[bound] = step
        print(f'bound {bound} s: interrupted {step.interrupted_s:.2f} s, {step.status}, timeline {step.timeline}')
    tight, default = steps.values()
    kinds = [what for what, _ in tight.timeline]
    assert not tight.succeeded and 'max_interruption_s 1.5 s' in tight.reason and 'centring' not in kinds
    assert tight.finished and 0.8 < tight.interrupted_s <= 1.5
    assert 'centring' in [what for what, _ in default.timeline]


def test_frames_whose_rays_turned_too_parallel_are_left_out_not_the_step(room):
    """The rig turns at 30 deg/s and the heads, looking 66 deg aside, turn with it towards the baseline's line: the
    rays of the later frames meet at under 0.5 deg. Those frames are left out and the step measures with the
    earlier ones (before, one such frame failed the whole step). What they measure is weak (std ~9 % at 0.5 deg):
    measured here with ``max_rel_std`` 0.2; the default 5 % fails the step as too weak to measure the scale."""
    rig, world, renderer = room
    for max_rel_std in (0.2, VergenceParams().max_rel_std):
        heads = _SimHeads(rig, world, renderer, _turning_rig(30.0), (-66.0, 0.0), (-60.0, 0.0))
        step = VergenceStep(rig, JointHistory(), VergenceParams(prior_depth_m=3.0, max_rel_std=max_rel_std),
                            left_range=((-1.7, 1.7), (-0.4, 0.4)))
        heads.run(step, 150)
        if max_rel_std == 0.2:
            assert step.succeeded, step.status
            r = step.result
            assert 'nearly parallel' in step._note and step.p.settle_frames <= r.frames < step.p.frames
            true = heads.true_distance(r.stamp, r.point_rig)
            assert abs(r.distance_m - true) < 3 * r.std_m and 0.05 * true < r.std_m < 0.1 * true
        else:
            assert not step.succeeded and 'too weak to measure the distance' in step.status, step.status


def test_the_measurement_takes_the_left_angles_from_the_callers_estimate(room):
    """``left_joints`` (camera_node: the servo's commanded motion replayed between readings) gives the left angles of
    the averaged frames, not the straight line between readings: an estimate 0.05 deg further left moves the
    distance as the geometry says (the rays converge later: the point comes out further)."""
    rig, world, renderer = room
    pose0 = make_trajectory('paper').pose_at(0.0)
    distances = {}
    for offset_deg in (0.0, 0.05):
        heads = _SimHeads(rig, world, renderer, lambda t: pose0, (22.5, 0.0), (-22.5, 0.0))
        hist = JointHistory()
        asked = []
        offset = math.radians(offset_deg)

        def left_joints(t, hist=hist, offset=offset, asked=asked):
            asked.append(t)
            q = hist.at(t, max_extrapolation_s=0.0)
            return None if q is None else (q[0] - offset, q[1])

        step = VergenceStep(rig, hist, VergenceParams(prior_depth_m=3.0), left_range=((-1.7, 1.7), (-0.4, 0.4)),
                            left_joints=left_joints)
        heads.run(step, 150)
        assert step.succeeded, step.status
        assert {round(t, 6) for t in asked} >= {round(s, 6) for s in step._sample_cache}
        distances[offset_deg] = step.result.distance_m
    # d(distance)/d(angle) = d^2 / (baseline sin) at ~3.7 m and 0.2 m: ~0.05 deg -> ~6 cm
    grew = distances[0.05] - distances[0.0]
    assert 0.03 < grew < 0.12, distances


def test_a_right_reselection_while_averaging_uses_the_frames_before_it_or_fails(room):
    rig, world, renderer = room
    pose0 = make_trajectory('paper').pose_at(0.0)
    results = {}
    pose_of_t = lambda t: Pose(pose0.R, pose0.t + pose0.R @ np.array([0.2 * t, 0.0, 0.0]))   # noqa: E731
    for cut in (8, 0):        # frames of the partner point gathered (after settling) before the right re-selects
        heads = _SimHeads(rig, world, renderer, pose_of_t, (22.5, 0.0), (-22.5, 0.0))
        step = VergenceStep(rig, JointHistory(), VergenceParams(prior_depth_m=3.0, frames=30, settle_frames=3))
        state = {'t_cut': None}

        def right_id(t, step=step, state=state, cut=cut):
            if step.phase != 'converging':
                return 0 if state['t_cut'] is None or t < state['t_cut'] else 1
            if state['t_cut'] is None and len(step._samples(list(step.left_frames))) >= cut:
                state['t_cut'] = t
            return 0 if state['t_cut'] is None or t < state['t_cut'] else 1

        heads.run(step, 200, right_id)
        results[cut] = step
    long, short = results[8], results[0]
    assert long.succeeded and any(what == 'cut short' for what, _ in long.timeline)
    assert 8 <= long.result.frames < 30
    assert not short.succeeded and 're-selected' in short.reason and short.finished


@pytest.mark.parametrize(('right_pan', 'pan_max', 'bound_s', 'why'),
                         [(22.5, 0.2, 1.8, "beyond the left head's range"), (22.5, 1.7, 1.2, 'too long a trip'),
                          (85.0, 1.7, 10.0, 'nearly along the baseline')])
def test_a_point_out_of_range_or_too_far_fails_before_the_head_leaves(room, right_pan, pan_max, bound_s, why):
    """The right point is 49 deg from where the left head looks: beyond a head limited to pan 11 deg, or too far
    for 1.2 s there and back at 80 deg/s (predicted 1.46 s); or the right head looks 5 deg off the baseline's line
    (vergence ~0.3 deg, where an arc turns the heads): refused without moving the head (no interruption)."""
    rig, world, renderer = room
    pose0 = make_trajectory('paper').pose_at(0.0)
    heads = _SimHeads(rig, world, renderer, lambda t: pose0, (right_pan, 0.0), (-22.5, 0.0))
    step = VergenceStep(rig, JointHistory(), VergenceParams(max_interruption_s=bound_s),
                        left_range=((-1.7, pan_max), (-0.4, 0.4)))
    heads.run(step, 30)
    assert step.finished and not step.succeeded and why in step.reason
    assert 'hold' not in heads.actions and step.interrupted_s == 0.0 and step.away_s == 0.0


def test_step_without_a_right_camera_fails_by_its_wait_timeout():
    rig = make_rig(320, 240)
    hist = JointHistory()
    hist.add(0.0, 0.0, 0.0)
    step = VergenceStep(rig, hist, VergenceParams(wait_timeout_s=1.0))
    img = np.zeros((240, 320), np.uint8)
    for k in range(10):
        act = step.on_left_image(0.1 * k, img, 0.1 * k)
        assert act.kind == 'track' and act.select is None
    assert step.status.startswith('running: waiting')
    step.on_left_image(1.5, img, 1.5)
    assert step.status.startswith('failed: both fixations not settled within 1 s')
    assert step.finished and step.result is None and step.away_s == 0.0   # never moved the head


def test_step_timeouts_fire_from_poll_without_images():
    """A head that never arrives: the aim, then the step, then the return are each bounded, images or not."""
    rig = make_rig(320, 240)
    step = VergenceStep(rig, JointHistory(), VergenceParams(timeout_s=1.0, aim_timeout_s=0.5))
    step.t_start, step.phase, step.t_left, step.home = 0.0, 'aiming', 0.0, (0.0, 0.0)
    step._aim = (0.5, 0.0)
    step.poll(0.4)
    assert step.phase == 'aiming'
    step.poll(1.2)
    assert step.phase == 'returning' and 'timeout after 1 s in phase aiming' in step.reason
    step.poll(1.5)
    assert not step.finished
    step.poll(1.8)
    assert step.finished and step.needs_reselect and step.away_s == pytest.approx(1.8)


# ------------------------------------------------------------------------------------------------ scheduler
def test_scheduler_start_up_right_fixation_request_and_period_triggers():
    s = VergenceScheduler(VergenceSchedule(period_s=30.0, min_interval_s=5.0, retry_s=2.0), now=100.0)
    assert s.due(100.0) == 'start'
    s.started('start', 100.0)
    assert s.due(100.5) is None
    s.finished(True, 102.0)
    assert s.due(102.0) is None and s.pending is None
    assert not s.on_right_fixation(7, 103.0)           # the first id seen is no change
    assert not s.on_right_fixation(7, 103.5)
    assert s.on_right_fixation(8, 104.0)                # a new right point: due once the min interval is over
    assert s.due(106.9) is None and s.due(107.0) == 'right_fixation'
    s.started('right_fixation', 107.0)
    s.finished(True, 109.0)
    assert s.trigger('request', 110.0) and s.due(113.9) is None and s.due(114.0) == 'request'
    s.started('request', 114.0)
    s.finished(True, 116.0)
    assert s.due(143.9) is None and s.due(144.0) == 'period'          # 30 s after the last start
    assert s.attempts == 3 and s.successes == 3 and s.failures == 0
    assert s.triggers['start'] == 1 and s.triggers['right_fixation'] == 1 and s.triggers['request'] == 1


def test_scheduler_and_step_ignore_the_right_cameras_no_fixation_messages():
    """The right node's id -1 ("no valid fixation at this stamp", e.g. it lost its point for a frame) is not a new
    right fixation point: 7, -1, 7 triggers nothing; 7, -1, 8 triggers once (8 is new against 7, not against -1).
    A running step does not take it for a right pixel either (it would read as the right re-selecting)."""
    s = VergenceScheduler(VergenceSchedule(min_interval_s=0.0), now=0.0)
    s.started(s.due(0.0), 0.0)
    s.finished(True, 1.0)
    assert not s.on_right_fixation(7, 2.0)
    assert not s.on_right_fixation(NO_FIXATION_ID, 2.1) and s.right_id == 7
    assert not s.on_right_fixation(7, 2.2)
    assert s.due(2.3) is None and s.triggers['right_fixation'] == 0
    assert not s.on_right_fixation(NO_FIXATION_ID, 2.4)
    assert s.on_right_fixation(8, 2.5) and s.due(2.5) == 'right_fixation' and s.triggers['right_fixation'] == 1
    step = VergenceStep(make_rig(320, 240), JointHistory())
    step.add_right_fixation(1.0, (160.0, 120.0), 8)
    step.add_right_fixation(1.1, (0.0, 0.0), NO_FIXATION_ID)
    assert [f[2] for f in step.right_fix] == [8]


def test_scheduler_ignores_and_counts_triggers_while_a_step_runs_and_coalesces_waiting_ones():
    s = VergenceScheduler(VergenceSchedule(min_interval_s=5.0), now=0.0)
    s.started(s.due(0.0), 0.0)
    s.on_right_fixation(0, 0.1)
    assert not s.on_right_fixation(1, 0.5) and not s.trigger('period', 0.6)
    assert s.ignored == 2 and s.pending is None
    s.finished(True, 2.0)
    assert s.due(10.0) is None                      # the ignored ones are not run later
    assert s.trigger('request', 3.0) and s.on_right_fixation(2, 4.0)
    assert s.due(7.0) == 'request'                  # two waiting triggers: one step
    s.started('request', 7.0)
    assert s.pending is None and s.due(30.0) is None


def test_a_request_during_a_step_waits_for_the_next_one():
    """fixego demo resets the estimator, then asks for a measurement at rest: the start-up step still running
    then must not swallow the request (stop 31: two of three demo runs started the rig without a scale)."""
    s = VergenceScheduler(VergenceSchedule(min_interval_s=5.0), now=0.0)
    s.started(s.due(0.0), 0.0)
    assert s.trigger('request', 0.5) and s.ignored == 0
    s.finished(True, 2.0)
    assert s.due(6.9) is None and s.due(7.0) == 'request'       # after the min interval


def test_a_request_answered_by_the_running_steps_measurement_is_dropped():
    """The estimator asks before it has received the start-up measurement: the step running then measures after the
    request came, which answers it (at stop 55 the left head measured the same point a second time at rest). A
    measurement stamped before the request, a failed step or one without a stamp leaves it pending."""
    s = VergenceScheduler(VergenceSchedule(min_interval_s=5.0), now=0.0)
    s.started(s.due(0.0), 0.0)
    s.trigger('request', 0.5)
    s.finished(True, 2.0, measured_at=1.2)
    assert s.pending is None and s.answered == 1 and s.due(7.0) is None
    for ok, measured_at in ((True, 0.4), (False, 1.2), (True, None)):
        s = VergenceScheduler(VergenceSchedule(min_interval_s=5.0), now=0.0)
        s.started(s.due(0.0), 0.0)
        s.trigger('request', 0.5)
        s.finished(ok, 2.0, measured_at=measured_at)
        assert s.answered == 0 and s.due(7.0) in ('request', 'retry')


def test_scheduler_min_interval_counts_from_steps_that_left_the_own_point():
    s = VergenceScheduler(VergenceSchedule(min_interval_s=5.0, retry_s=30.0), now=0.0)
    s.started(s.due(0.0), 0.0)
    s.finished(True, 2.0)                                     # left its own point: the min interval runs from here
    s.trigger('request', 3.0)
    s.started(s.due(7.0), 7.0)
    s.finished(False, 17.0, left_own_point=False)             # waited in vain (the rig turned): interrupted nothing
    assert s.trigger('request', 17.5) and s.due(17.5) == 'request'      # no min interval after it
    s.started('request', 17.5)
    s.finished(False, 19.0, left_own_point=True)              # failed after leaving: the min interval applies
    assert s.trigger('request', 19.5) and s.due(23.9) is None and s.due(24.0) == 'request'


def test_scheduler_retries_a_failure_with_back_off_or_at_the_next_trigger():
    s = VergenceScheduler(VergenceSchedule(min_interval_s=1.0, retry_s=2.0, retry_max_s=5.0), now=0.0)
    s.started(s.due(0.0), 0.0)
    s.finished(False, 1.0)
    assert s.due(2.9) is None and s.due(3.0) == 'retry'          # back-off 2 s
    s.started('retry', 3.0)
    s.finished(False, 4.0)
    assert s.due(7.9) is None and s.due(8.0) == 'retry'          # doubled: 4 s
    s.started('retry', 8.0)
    s.finished(False, 9.0)
    assert s.due(13.9) is None and s.due(14.0) == 'retry'        # capped at 5 s
    assert s.trigger('request', 10.0) and s.due(10.0) == 'request'   # a trigger comes first (min interval 1 s)
    s.started('request', 10.0)
    s.finished(True, 11.0)
    assert s.failures_in_a_row == 0 and s.due(100.0) is None and s.t_retry is None
    assert (s.attempts, s.successes, s.failures) == (4, 1, 3) and s.triggers['retry'] == 2


# ------------------------------------------------------------------------------------------------ tracker
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
