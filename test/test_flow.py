"""Flow tracking around the fixation point and the stereo front end that turns it into rig-frame rays."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

import fixego_ros.pipeline.frontend as frontend
from fixego_ros.estimation.coplanarity import RayPairs, sampson_residuals
from fixego_ros.geometry.rig import SIDES, default_rig_path, load_rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.pipeline.frontend import (
    BAD_IMAGE,
    BAD_JOINTS,
    MISSING,
    NO_PREVIOUS,
    OK,
    CameraSample,
    KeyframePolicy,
    StereoFrontEnd,
)
from fixego_ros.pipeline.observation import observation_to_rows, rows_to_observation
from fixego_ros.pipeline.sync import StereoSync, SyncParams
from fixego_ros.sim.render import Renderer, project_points
from fixego_ros.sim.run import resize_rig
from fixego_ros.sim.trajectories import AREA_CENTRE, TRIPOD_HEIGHT, attitude
from fixego_ros.sim.world import make_room
from fixego_ros.tracking.fixation import NO_FIXATION_ID
from fixego_ros.tracking.flow import (
    REGISTER_MIN_NCC,
    FlowParams,
    _solve_spd,
    aligned,
    birth_patches,
    detect_corners,
    register,
    track_flow,
    track_points,
    valid_box,
)

# what these tests were written against (the dataclass defaults before they became the node's): the flow window
# around the fixation with up to 150 corners, between consecutive frames
WINDOW = FlowParams(preset='window', max_corners=150)
CONSECUTIVE = KeyframePolicy(max_frames=1)

W, H = 320, 240
SHIFT = (0.37, -0.21)   # px, sub-pixel image motion of the synthetic pair
CENTRE = (150.3, 110.7)


def texture(seed: int, shape: tuple[int, int] = (H, W)) -> np.ndarray:
    """Smoothed random noise: corners everywhere, no repeated structure."""
    img = cv2.GaussianBlur(np.random.default_rng(seed).uniform(0, 255, shape).astype(np.float32), (0, 0), 1.5)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``img`` moved by (dx, dy) px: content at (u, v) appears at (u + dx, v + dy)."""
    M = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


@pytest.fixture(scope='module')
def pair() -> tuple[np.ndarray, np.ndarray]:
    a = texture(0)
    return a, shifted(a, *SHIFT)


def check_counts(tr) -> None:
    c = tr.counts
    assert c.detected == c.lost + c.min_eig + c.outside + c.fb + c.ncc + c.epipolar + c.kept
    assert c.kept == len(tr.prev_px) == len(tr.curr_px)
    assert tr.prev_px.dtype == tr.curr_px.dtype == np.float64
    assert tr.prev_px.shape == tr.curr_px.shape == (c.kept, 2)
    assert np.all(np.isfinite(tr.prev_px)) and np.all(np.isfinite(tr.curr_px))


# ---------------------------------------------------------------------------------------------- params
@pytest.mark.parametrize('kw, field', [
    ({'preset': 'dense'}, 'preset'), ({'window_px': 0}, 'window_px'), ({'window_px': 50.5}, 'window_px'),
    ({'paper_region_px': 200}, 'paper_region_px'), ({'paper_points': 0}, 'paper_points'),
    ({'corner_quality': 0.0}, 'corner_quality'), ({'min_distance_px': -1.0}, 'min_distance_px'),
    ({'lk_win': 1}, 'lk_win'), ({'lk_levels': -1}, 'lk_levels'), ({'min_eig': float('nan')}, 'min_eig'),
    ({'fb_max_px': 0.0}, 'fb_max_px'), ({'border_px': -2}, 'border_px'), ({'ncc_min': 1.5}, 'ncc_min'),
])
def test_params_are_validated_naming_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        FlowParams(**kw)


# ---------------------------------------------------------------------------------------------- track_flow
def test_window_recovers_subpixel_shift_with_many_points_inside_the_window(pair):
    tr = track_flow(*pair, CENTRE, WINDOW)
    check_counts(tr)
    assert tr.counts.kept >= 80 and tr.counts.kept == tr.counts.detected  # clean shift: nothing rejected
    err = np.linalg.norm(tr.curr_px - tr.prev_px - SHIFT, axis=1)
    assert np.median(err) < 0.05 and err.max() < 0.15
    # all inside the 100x100 window centred on the fixation pixel, and filling it
    off = tr.prev_px - CENTRE
    assert np.all(np.abs(off) <= 50.5)
    assert np.all(off.max(axis=0) > 35) and np.all(off.min(axis=0) < -35)
    # points are distinct corners at least min_distance apart
    d = np.linalg.norm(tr.prev_px[:, None] - tr.prev_px[None], axis=2) + 1e3 * np.eye(len(tr))
    assert d.min() >= 6.0 - 1e-9


def test_paper_takes_the_three_strongest_corners_of_the_central_region(pair):
    p = FlowParams(preset='paper')
    tr = track_flow(*pair, CENTRE, p)
    check_counts(tr)
    assert len(tr) == 3
    assert np.all(np.abs(tr.prev_px - CENTRE) <= 15.5)
    assert np.median(np.linalg.norm(tr.curr_px - tr.prev_px - SHIFT, axis=1)) < 0.05
    # the strongest: each has a higher min-eigenvalue score than any other corner of the region
    score = cv2.cornerMinEigenVal(pair[0], 3)
    x0, y0 = int(np.floor(CENTRE[0] - 15 + 0.5)), int(np.floor(CENTRE[1] - 15 + 0.5))
    region = score[y0:y0 + 30, x0:x0 + 30]
    chosen = score[tr.prev_px[:, 1].astype(int), tr.prev_px[:, 0].astype(int)]
    assert chosen.min() >= np.sort(region.ravel())[-60]   # top of 900 candidates (min distance thins them)
    # deterministic
    again = track_flow(*pair, CENTRE, p)
    assert np.array_equal(again.prev_px, tr.prev_px) and np.array_equal(again.curr_px, tr.curr_px)


def test_full_spreads_over_the_image_and_default_centre_is_the_image_centre(pair):
    tr = track_flow(*pair, None, FlowParams(preset='full', max_corners=300))
    check_counts(tr)
    assert len(tr) > 200
    assert np.median(np.linalg.norm(tr.curr_px - tr.prev_px - SHIFT, axis=1)) < 0.05
    lo, hi = tr.prev_px.min(axis=0), tr.prev_px.max(axis=0)
    assert np.all(lo >= 8) and hi[0] <= W - 9 and hi[1] <= H - 9
    assert np.all(hi - lo > 0.85 * np.array([W, H]))
    win = track_flow(*pair, None, WINDOW)
    assert win.center_px == ((W - 1) / 2, (H - 1) / 2)
    assert np.all(np.abs(win.prev_px - win.center_px) <= 50.5)


def test_unrelated_content_is_rejected_and_the_rest_is_kept(pair):
    """Half the window replaced by new texture (an occlusion): no track from there survives."""
    a, b = pair
    b = b.copy()
    b[:, :150] = texture(5)[:, :150]
    tr = track_flow(a, b, CENTRE, WINDOW)
    check_counts(tr)
    full = track_flow(*pair, CENTRE, WINDOW)
    in_new = full.prev_px[:, 0] < 150 - 1
    assert in_new.sum() > 40                                   # the window had many corners there
    assert np.all(tr.prev_px[:, 0] >= 150 - 1)                 # ... none survive
    assert tr.counts.fb + tr.counts.ncc + tr.counts.lost >= in_new.sum()
    far = full.prev_px[full.prev_px[:, 0] > 150 + 12]          # LK window entirely in the unchanged part
    kept = {tuple(p) for p in tr.prev_px}
    assert all(tuple(p) in kept for p in far)
    assert np.median(np.linalg.norm(tr.curr_px - tr.prev_px - SHIFT, axis=1)) < 0.05


def test_forward_backward_alone_rejects_most_unrelated_tracks(pair):
    a, b = pair
    b = b.copy()
    b[:, :150] = texture(5)[:, :150]
    tr = track_flow(a, b, CENTRE, FlowParams(preset='window', max_corners=150, ncc_min=-1.0))   # correlation check off
    assert tr.counts.ncc == 0 and tr.counts.fb > 40
    wrong = np.linalg.norm(tr.curr_px - tr.prev_px - SHIFT, axis=1) > 0.3
    assert wrong.sum() < 0.3 * tr.counts.fb                   # it lets a few through: why ncc_min exists


def test_flat_patches_are_rejected_by_min_eigenvalue(pair):
    a = (pair[0].astype(np.float32) * 0.02 + 128).astype(np.uint8)    # ~5 grey levels of texture
    tr = track_flow(a, shifted(a, *SHIFT), CENTRE, WINDOW)
    check_counts(tr)
    assert tr.counts.detected > 0 and tr.counts.min_eig == tr.counts.detected and len(tr) == 0
    flat = np.full((H, W), 90, np.uint8)
    tr = track_flow(flat, flat, CENTRE, WINDOW)
    assert len(tr) == 0 and 'no corners' in tr.reason


def test_points_leaving_the_image_are_dropped():
    a = texture(1)
    b = shifted(a, 0.0, 12.0)                                  # content moves 12 px down
    tr = track_flow(a, b, (160.0, 200.0), FlowParams(preset='window', max_corners=150, border_px=20))
    check_counts(tr)
    assert tr.counts.outside > 0
    assert np.all(tr.curr_px[:, 1] <= H - 21) and np.all(tr.curr_px >= 20)
    assert np.median(np.abs(tr.curr_px[:, 1] - tr.prev_px[:, 1] - 12.0)) < 0.05


@pytest.mark.parametrize('prev, curr, centre, why', [
    (texture(0), texture(0, (120, 160)), None, 'size changed'),
    (np.zeros((0, 0), np.uint8), np.zeros((0, 0), np.uint8), None, 'empty'),
    (texture(0).astype(np.float32), texture(0).astype(np.float32), None, 'float32'),
    (texture(0), np.dstack([texture(0)] * 3), None, 'not a 2-D'),
    (None, texture(0), None, 'missing'),
    (texture(0), texture(0), (np.nan, 3.0), 'not a finite pixel'),
    (texture(0), texture(0), (3.0,), 'not a finite pixel'),
    (texture(0), texture(0), (-500.0, 100.0), 'outside the image'),
    (texture(0, (10, 10)), texture(0, (10, 10)), None, 'too small'),
])
def test_bad_input_gives_no_points_and_a_reason(prev, curr, centre, why):
    tr = track_flow(prev, curr, centre, WINDOW)
    assert len(tr) == 0 and why in tr.reason
    assert tr.prev_px.shape == tr.curr_px.shape == (0, 2)


# ---------------------------------------------------------------------------------------------- front end
@pytest.fixture(scope='module')
def sim_pair():
    """Two rendered frames of both cameras: a known rig step and a pan/tilt change between them."""
    rig = resize_rig(load_rig(default_rig_path()), W, H)
    renderer = Renderer(make_room(0, 0.006), rig, 'mono8', 1.0, 0)
    P0 = Pose(attitude(0.3), np.array([*AREA_CENTRE, TRIPOD_HEIGHT]))
    step = Pose.from_rvec(np.array([0.004, -0.012, 0.003]), np.array([0.03, -0.01, 0.04]))
    targets = {'right': P0.apply([0.8, 0.1, 3.0]), 'left': P0.apply([-1.0, -0.2, 2.5])}  # world points
    frames = []
    for k, P in enumerate((P0, P0 @ step)):
        frame = {}
        for side in SIDES:
            pan, tilt = rig.aim_readings(side, P.inverse().apply(targets[side]))
            if k == 1:
                pan, tilt = pan + 0.015, tilt - 0.01     # the head moved: ~13 and ~9 px of image motion
            px, _ = project_points(rig, side, P, pan, tilt, targets[side][None])
            frame[side] = CameraSample(renderer.render(side, P, pan, tilt), pan, tilt, tuple(px[0]), 7)
        frames.append(frame)
    fe = StereoFrontEnd(rig, WINDOW, CONSECUTIVE)
    obs = [fe.process(10.0 + k / 30, f) for k, f in enumerate(frames)]
    return rig, step, targets, frames, fe, obs


@pytest.mark.parametrize('side', SIDES)
def test_flow_rays_satisfy_coplanarity_for_the_true_step(sim_pair, side):
    rig, step, _, frames, fe, obs = sim_pair
    cam = obs[1].camera(side)
    assert fe.last[side].status == OK and len(cam.flow_prev) >= 50
    assert np.allclose(np.linalg.norm(cam.flow_prev, axis=1), 1.0)
    f = rig.camera(side).fx
    pairs = RayPairs.build([(cam.flow_prev, cam.flow_curr, rig.center(side), 1.0)])
    res = np.abs(sampson_residuals(step.R, step.t, pairs)) * f      # px; left uses T + (R - I) c_L
    assert np.median(res) < 0.3 and np.percentile(res, 90) < 1.0
    # the same pixels with frame t's pan/tilt at both ends: the head's rotation is left in the flow
    tr, s0 = fe.last_tracks[side], frames[0][side]
    b = rig.pixels_to_rig_rays(side, tr.curr_px, s0.pan, s0.tilt)
    naive = RayPairs.build([(cam.flow_prev, b, rig.center(side), 1.0)])
    res_naive = np.abs(sampson_residuals(step.R, step.t, naive)) * f
    assert np.median(res_naive) > 2.0 and np.median(res_naive) > 20 * np.median(res)
    # and a wrong motion does not fit the compensated flow either (the check has teeth)
    wrong = np.abs(sampson_residuals(step.R, np.array([0.04, 0.0, -0.03]), pairs)) * f
    assert np.median(wrong) > 10 * np.median(res)
    if side == 'left':   # its centre moves by T + (R - I) c_L, not T
        at_origin = RayPairs.build([(cam.flow_prev, cam.flow_curr, np.zeros(3), 1.0)])
        assert np.median(np.abs(sampson_residuals(step.R, step.t, at_origin)) * f) > 5 * np.median(res)


@pytest.mark.parametrize('side', SIDES)
def test_fixation_ray_and_camera_rotation_at_t(sim_pair, side):
    rig, step, targets, frames, fe, obs = sim_pair
    cam, s1 = obs[1].camera(side), frames[1][side]
    P1 = Pose(attitude(0.3), np.array([*AREA_CENTRE, TRIPOD_HEIGHT])) @ step
    truth = P1.inverse().apply(targets[side]) - rig.center(side)
    truth /= np.linalg.norm(truth)
    assert np.degrees(np.arccos(min(1.0, float(cam.fixation_ray @ truth)))) < 1e-4
    assert cam.fixation_id == 7
    assert np.allclose(cam.cam_to_rig, rig.cam_to_rig(side, s1.pan, s1.tilt))
    # the tracks were started in the window around the keyframe's fixation pixel; the region now follows t's
    tr = fe.last_tracks[side]
    assert np.all(np.abs(tr.prev_px - frames[0][side].fixation_px) <= 50.5)
    assert tr.center_px == pytest.approx(frames[1][side].fixation_px)
    assert obs[0].prev_stamp is None and obs[1].prev_stamp == pytest.approx(10.0)
    assert len(obs[0].camera(side).flow_prev) == 0 and fe.last[side].pairs == len(cam.flow_prev)


def synthetic_samples(k: int, **over) -> dict[str, CameraSample | None]:
    """Frame k of a textured scene drifting 0.5 px/frame (no geometry: front-end bookkeeping only)."""
    base = texture(3)
    img = shifted(base, 0.5 * k, 0.0)
    out: dict[str, CameraSample | None] = {s: CameraSample(img, 0.01 * k, -0.02, (160.0, 120.0), 1) for s in SIDES}
    out.update(over)
    return out


@pytest.fixture
def small_rig():
    return resize_rig(load_rig(default_rig_path()), W, H)


@pytest.mark.parametrize('step_s, warps', [(1 / 30, False), (2 / 30, False), (0.1, True), (1 / 5.1, True)])
def test_lk_starts_from_the_affine_prewarp_only_over_long_steps(small_rig, monkeypatch, step_s, warps):
    """At 30 Hz (also across one skipped frame) LK tracks from the previous image as it is: the pre-warp cost a
    quarter of the front end there and changed no accuracy; at 10 Hz and the papers' 5.1 Hz it still runs."""
    calls = []

    def spy(*args, **kwargs):
        calls.append(1)
        return aligned(*args, **kwargs)

    fe = StereoFrontEnd(small_rig, WINDOW, CONSECUTIVE)
    monkeypatch.setattr(frontend, 'aligned', spy)
    for k in range(4):
        fe.process(step_s * k, synthetic_samples(k))
    assert (len(calls) > 0) == warps
    assert fe.last['right'].counts.kept > 20        # tracked either way


def test_missing_camera_and_gaps(small_rig):
    fe = StereoFrontEnd(small_rig, WINDOW, CONSECUTIVE)
    o0 = fe.process(0.0, synthetic_samples(0))
    assert o0.prev_stamp is None
    assert all(fe.last[s].status == NO_PREVIOUS and len(o0.camera(s).flow_prev) == 0 for s in SIDES)
    assert o0.right.fixation_ray is not None
    o1 = fe.process(0.1, synthetic_samples(1, left=None))
    assert o1.prev_stamp == 0.0 and o1.left is None and fe.last['left'].status == MISSING
    assert len(o1.right.flow_prev) > 50 and fe.last['right'].status == OK
    o2 = fe.process(0.2, {'right': synthetic_samples(2)['right']})          # a missing key = missing camera
    assert o2.left is None and len(o2.right.flow_prev) > 50
    o3 = fe.process(0.3, synthetic_samples(3))                                # left back: no flow yet
    assert len(o3.left.flow_prev) == 0 and o3.left.fixation_ray is not None
    assert fe.last['left'].status == NO_PREVIOUS and len(o3.right.flow_prev) > 50
    o4 = fe.process(0.4, synthetic_samples(4))
    assert len(o4.left.flow_prev) > 50 and o4.prev_stamp == 0.3
    assert fe.totals['left.missing'] == 2 and fe.totals['right.ok'] == 4
    assert fe.totals['right.kept'] == sum(len(o.right.flow_prev) for o in (o1, o2, o3, o4))
    fe.reset()
    o5 = fe.process(0.5, synthetic_samples(5))
    assert o5.prev_stamp is None and len(o5.right.flow_prev) == 0


def test_wrong_image_size_bad_joints_and_no_fixation(small_rig):
    fe = StereoFrontEnd(small_rig, WINDOW, CONSECUTIVE)
    fe.process(0.0, synthetic_samples(0))
    small = CameraSample(texture(0, (120, 160)), 0.0, 0.0, (80.0, 60.0), 1)
    o1 = fe.process(0.1, synthetic_samples(1, right=small))
    assert o1.right is None and fe.last['right'].status == BAD_IMAGE and '240x320' in fe.last['right'].detail
    assert len(o1.left.flow_prev) > 50
    o2 = fe.process(0.2, synthetic_samples(2))
    assert len(o2.right.flow_prev) == 0 and fe.last['right'].status == NO_PREVIOUS   # previous was unusable
    bad = CameraSample(synthetic_samples(3)['left'].gray, float('nan'), 0.0, (160.0, 120.0), 1)
    o3 = fe.process(0.3, synthetic_samples(3, left=bad))
    assert o3.left is None and fe.last['left'].status == BAD_JOINTS
    nofix = CameraSample(synthetic_samples(4)['right'].gray, 0.04, -0.02, None, -1)
    o4 = fe.process(0.4, synthetic_samples(4, right=nofix))
    assert o4.right.fixation_ray is None and o4.right.fixation_id == -1 and len(o4.right.flow_prev) > 50
    nan_fix = CameraSample(synthetic_samples(5)['right'].gray, 0.05, -0.02, (np.nan, 1.0), 3)
    o5 = fe.process(0.5, synthetic_samples(5, right=nan_fix))
    assert o5.right.fixation_ray is None and o5.right.fixation_id == -1
    assert fe.last_tracks['right'].center_px == ((W - 1) / 2, (H - 1) / 2)   # no fixation at t: centre
    for o in (o1, o2, o3, o4, o5):
        for cam in (o.right, o.left):
            if cam is not None:
                assert np.all(np.isfinite(cam.flow_prev)) and np.all(np.isfinite(cam.flow_curr))
                assert np.all(np.isfinite(cam.cam_to_rig))
    assert set(fe.stats) >= {'right.status', 'right.kept', 'left.fb', 'left.ncc'}
    assert fe.last_counts['right'].kept == len(o5.right.flow_prev)


def test_a_camera_without_fixation_reaches_the_estimator_input_without_one(small_rig):
    """flow_node's path: the synchroniser completes the frame at once on the left camera's id -1 message, and the
    estimator's input (the observation, and its rows on flow/observation) has the left camera without a fixation
    ray and with fixation id -1, its flow still there; the right camera keeps its fixation."""
    sync = StereoSync(SyncParams(max_wait_s=0.25))
    fe = StereoFrontEnd(small_rig, WINDOW, CONSECUTIVE)
    obs = []
    for k in range(2):
        t = 1.0 + k / 30
        for side, sample in synthetic_samples(k).items():
            sync.add_image(side, t, sample.gray, now=t)
            sync.add_joints(side, t - 0.01, sample.pan, sample.tilt)
            sync.add_joints(side, t + 0.01, sample.pan, sample.tilt)
            if side == 'left' and k == 1:
                sync.add_fixation(side, t, (0.0, 0.0), NO_FIXATION_ID)
            else:
                sync.add_fixation(side, t, sample.fixation_px, sample.fixation_id)
        (frame,) = sync.pop_ready(now=t)                       # no wait: complete at arrival
        obs.append(fe.process(frame.stamp, {s: CameraSample(c.image, c.pan, c.tilt, c.fixation_px, c.fixation_id)
                                            for s, c in frame.cameras.items()}))
    o = obs[1]
    assert o.left.fixation_ray is None and o.left.fixation_id == NO_FIXATION_ID and len(o.left.flow_prev) > 50
    assert o.right.fixation_ray is not None and o.right.fixation_id == 1
    back = rows_to_observation(o.stamp, observation_to_rows(o))
    assert back.left.fixation_ray is None and back.left.fixation_id == NO_FIXATION_ID
    assert back.right.fixation_id == 1 and len(back.left.flow_prev) == len(o.left.flow_prev)
    assert sync.stats.no_fixation == 1 and sync.stats.fixation_timeouts == 0 and sync.stats.stereo_frames == 2


def _zoomed(tex: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """The middle of ``tex`` magnified ``s`` times about the image centre, and the 2x3 map of texture pixels into it."""
    c = np.array([(W - 1) / 2, (H - 1) / 2])
    C = np.array([(tex.shape[1] - 1) / 2, (tex.shape[0] - 1) / 2])
    A = np.column_stack([np.eye(2) * s, c - s * C])
    return cv2.warpAffine(tex, A, (W, H), flags=cv2.INTER_LINEAR), A


def test_tracks_do_not_drift_off_their_points_while_the_scene_comes_closer():
    """20 frames, each 2 % closer (x1.49 in all), tracked frame to frame. LK fits a translation to a window whose
    content grows about the point, and settles off it towards the window's texture, the same way each frame: the
    plain chain ends ~1 px off. From the previous image warped by the points' affine motion it does not add up."""
    tex = texture(3, (3 * H, 3 * W))
    p = FlowParams()
    first, A0 = _zoomed(tex, 1.0)
    start = detect_corners(first, valid_box(first.shape, 40), 60, p)
    on_texture = start - A0[:, 2]
    errors = {}
    for how in ('plain', 'aligned'):
        pts, img, alive, s = start.copy(), first, np.ones(len(start), bool), 1.0
        for _ in range(20):
            s *= 1.02
            nxt, A = _zoomed(tex, s)
            if how == 'plain':
                flow = track_points(img, nxt, pts, p, pts)
            else:
                warped, moved, landed = aligned(img, nxt, pts, p, pts)
                flow = track_points(warped, nxt, moved, p, landed)
            alive &= flow.ok
            pts, img = flow.curr_px, nxt
        assert alive.sum() >= 0.6 * len(start)
        errors[how] = float(np.median(np.linalg.norm(pts - (on_texture * s + A[:, 2]), axis=1)[alive]))
    assert errors['plain'] > 0.5            # the effect is there ...
    assert errors['aligned'] < 0.15         # ... and gone


def test_alignment_needs_enough_points_and_otherwise_changes_nothing(pair):
    a, b = pair
    pts = np.array([[100.0, 100.0], [150.0, 120.0], [200.0, 90.0]])
    warped, moved, landed = aligned(a, b, pts, FlowParams(), pts + 1.0)
    assert warped is a
    np.testing.assert_array_equal(moved, pts)
    np.testing.assert_array_equal(landed, pts + 1.0)


def test_a_birth_patch_registers_where_its_point_is_after_the_scene_came_closer():
    """20 frames each 2 % closer, as above. The 'aligned' chain keeps a little of LK's drift; registering each
    track's birth patch with an affine warp after LK puts it back on its point, and the affine it finds is the
    zoom."""
    tex = texture(3, (3 * H, 3 * W))
    p = FlowParams()
    first, A0 = _zoomed(tex, 1.0)
    start = detect_corners(first, valid_box(first.shape, 40), 60, p)
    on_texture = start - A0[:, 2]
    births = birth_patches(first, start)
    errors, s = {}, 1.0
    for how in ('aligned', 'registered'):
        pts, img, alive, s = start.copy(), first, np.ones(len(start), bool), 1.0
        linear = np.repeat(np.eye(2)[None], len(start), axis=0)
        for _ in range(20):
            s *= 1.02
            nxt, A = _zoomed(tex, s)
            warped, moved, landed = aligned(img, nxt, pts, p, pts)
            flow = track_points(warped, nxt, moved, p, landed)
            alive &= flow.ok
            pts, img = flow.curr_px, nxt
            if how == 'registered':
                pts, linear, ok = register(nxt, pts, births, linear)
                alive &= ok
        assert alive.sum() >= 0.6 * len(start)
        errors[how] = float(np.median(np.linalg.norm(pts - (on_texture * s + A[:, 2]), axis=1)[alive]))
    assert errors['registered'] < 0.03 and errors['aligned'] > 2 * errors['registered']
    np.testing.assert_allclose(np.median(linear[alive], axis=0), np.eye(2) * s, atol=0.01)


def test_the_written_out_solve_of_the_registration_matches_lapack():
    """The birth patches' 6x6 solves avoid LAPACK (it rounds by CPU); they must still solve the systems."""
    rng = np.random.default_rng(4)
    sd = rng.normal(size=(9, 6, 441))
    hess = np.einsum('nip,njp->nij', sd, sd) + np.eye(6)
    np.testing.assert_allclose(_solve_spd(hess, sd), np.linalg.solve(hess, sd), rtol=1e-9, atol=1e-12)
    assert _solve_spd(hess[:0], sd[:0]).shape == (0, 6, 441)


def test_a_patch_that_is_not_one_static_point_does_not_register():
    """A corner made by two surfaces at different depths slides as they part: here the patch's right half moved
    3 px against its left. No affine image of the birth patch matches, and the track is refused (the front end ends
    it); the same points after a plain sub-pixel shift register."""
    a = texture(5)
    pts = np.array([[100.3, 80.6], [200.1, 150.2], [160.7, 120.4]])
    births = birth_patches(a, pts)
    eye = np.repeat(np.eye(2)[None], len(pts), axis=0)
    moved = shifted(a, 0.4, -0.3)
    at, _, ok = register(moved, pts, births, eye)
    assert ok.all()
    np.testing.assert_allclose(at, pts + [0.4, -0.3], atol=0.05)
    parted = a.copy()
    for x, y in pts.astype(int):
        parted[y - 12:y + 13, x:x + 13] = shifted(a, 3.0, 0.0)[y - 12:y + 13, x:x + 13]
    at, _, ok = register(parted, pts, births, eye)
    assert not ok.any()
    np.testing.assert_array_equal(at, pts)          # refused: the input as it was
    assert 0.0 < REGISTER_MIN_NCC < 1.0


def test_the_front_end_ends_tracks_whose_birth_patch_no_longer_registers(small_rig):
    """A textured scene drifting 0.5 px a frame; at frame 3 a band of the right image (rows 120-140) moves 3 px
    against the rest, as the two sides of an occluding edge do. The tracks whose patch straddles the band's edges end,
    counted as ``unregistered``, and no other; the left camera loses none; and the birth patches follow the tracks
    through ends and new detections (those born on the band end when it heals, then none)."""
    fe = StereoFrontEnd(small_rig, WINDOW, CONSECUTIVE)
    for k in range(3):
        fe.process(0.1 * k, synthetic_samples(k))
    before = fe._tracks['right']
    img = synthetic_samples(3)['right'].gray.copy()
    img[120:140] = shifted(texture(3), 1.5 + 3.0, 0.0)[120:140]
    samples = synthetic_samples(3)
    samples['right'] = CameraSample(img, 0.03, -0.02, (160.0, 120.0), 1)
    fe.process(0.3, samples)
    y = before.px[:, 1]
    straddle = ((y > 110) & (y < 130)) | ((y > 130) & (y < 150))
    ended = ~np.isin(before.ids, fe._tracks['right'].ids)
    assert fe.last['right'].counts.unregistered >= 0.5 * straddle.sum() > 0
    assert not (ended & ~straddle).any() and fe.last['left'].counts.unregistered == 0
    unregistered = []
    for k in range(4, 8):
        fe.process(0.1 * k, synthetic_samples(k))
        unregistered.append(fe.last['right'].counts.unregistered + fe.last['left'].counts.unregistered)
        for side in SIDES:
            np.testing.assert_array_equal(fe._births[side].ids, fe._tracks[side].ids)
    assert unregistered[1:] == [0, 0, 0]


def test_a_share_of_the_tracks_is_registered_each_frame_each_about_once_per_period(small_rig):
    """``register_period_s`` 0.3 at 10 frames a second: a third of the tracks per frame, the longest unregistered
    first, so that every live track was registered within the last 0.3 s (an even cost per frame, not a burst)."""
    from dataclasses import replace
    fe = StereoFrontEnd(small_rig, replace(WINDOW, register_period_s=0.3), CONSECUTIVE)
    for k in range(12):
        fe.process(0.1 * k, synthetic_samples(k))
        if k < 4:
            continue
        births, tracks = fe._births['right'], fe._tracks['right']
        np.testing.assert_array_equal(births.ids, tracks.ids)
        followed = births.stamps < 0.1 * k - 1e-9                  # (not born at this frame)
        fresh = np.isclose(births.stamps, 0.1 * k)
        assert abs(int(fresh.sum()) - math.ceil(len(tracks) / 3)) <= fe.last['right'].counts.new + 1
        assert births.stamps.min() > 0.1 * k - 0.3 - 1e-9 and followed.any()
