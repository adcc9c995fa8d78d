"""Persistent point tracks of the stereo front end: ids, predicted LK, epipolar RANSAC, rotation keyframes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fixego_ros.geometry.rig import SIDES, default_rig_path, load_rig
from fixego_ros.geometry.rotation import exp_so3, rot_y
from fixego_ros.pipeline import frontend
from fixego_ros.pipeline.frontend import (
    LK_PREDICTED,
    OK,
    CameraSample,
    KeyframePolicy,
    StereoFrontEnd,
    epipolar_outliers,
)
from fixego_ros.sim.run import resize_rig
from fixego_ros.tracking.flow import FlowParams, track_points

# what these tests were written against (the dataclass defaults before they became the node's)
WINDOW = FlowParams(preset='window', max_corners=150)

W, H = 320, 240


@pytest.fixture(scope='module')
def rig():
    return resize_rig(load_rig(default_rig_path()), W, H)


def texture(seed: int, shape: tuple[int, int] = (H, W)) -> np.ndarray:
    img = cv2.GaussianBlur(np.random.default_rng(seed).uniform(0, 255, shape).astype(np.float32), (0, 0), 1.5)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def view(rig, side: str, scene: np.ndarray, pan: float, tilt: float, R_rig: np.ndarray | None = None) -> np.ndarray:
    """What ``side`` sees at joint readings (pan, tilt) with the rig rotated by ``R_rig`` (rig axes now in the
    rig at the start) of a scene at infinity that it sees as ``scene`` at pan = tilt = 0 before the rotation."""
    cam = rig.camera(side)
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    rays = rig.pixels_to_rig_rays(side, np.column_stack([u.ravel(), v.ravel()]), pan, tilt)
    if R_rig is not None:
        rays = rays @ R_rig.T                                   # into the rig frame at the start
    src = cam.rays_to_pixels(rays @ rig.cam_to_rig(side, 0.0, 0.0)).astype(np.float32)
    return cv2.remap(scene, src[:, 0].reshape(u.shape), src[:, 1].reshape(u.shape), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT)


def samples(rig, pan: float, R_rig: np.ndarray | None = None, fix=(160.0, 120.0)) -> dict[str, CameraSample]:
    return {side: CameraSample(view(rig, side, texture(11 + i), pan, 0.0, R_rig), pan, 0.0, fix, 1)
            for i, side in enumerate(SIDES)}


def check_counts(fe: StereoFrontEnd) -> None:
    for side in SIDES:
        c = fe.last[side].counts
        assert c.detected == c.lost + c.min_eig + c.outside + c.fb + c.ncc + c.epipolar + c.kept
        assert fe.last[side].tracks == c.kept + c.new


# ---------------------------------------------------------------------------------------------- ids
def test_ids_persist_across_frames_and_are_never_reused(rig):
    """A texture drifting with the pan (consistent readings): every track lives on with its id; after
    the camera drops out, a reset and a re-detection, new ids are always larger than any seen before."""
    fe = StereoFrontEnd(rig, WINDOW, KeyframePolicy(max_frames=3))
    o = fe.process(0.0, samples(rig, 0.0))
    first = {s: o.camera(s).track_ids.copy() for s in SIDES}
    assert all(len(v) >= 50 and v.dtype == np.int64 for v in first.values())
    assert all(np.array_equal(v, np.arange(len(v))) for v in first.values())
    seen = {s: set(first[s].tolist()) for s in SIDES}
    for k in range(1, 6):
        o = fe.process(0.2 * k, samples(rig, 0.002 * k))           # ~1.7 px per frame
        check_counts(fe)
        for s in SIDES:
            cam = o.camera(s)
            assert set(first[s].tolist()) <= set(cam.track_ids.tolist())   # nobody died
            assert cam.track_rays.shape == (len(cam.track_ids), 3)
            np.testing.assert_allclose(np.linalg.norm(cam.track_rays, axis=1), 1.0)
            new = set(cam.track_ids.tolist()) - seen[s]
            assert all(i > max(seen[s]) for i in new)
            seen[s] |= new
    # the flow pairs are the tracks at the keyframe and now: the same scene points, so (no rig motion)
    # the same rig-frame rays at both ends
    f = rig.camera('right').fx
    for s in SIDES:
        cam = o.camera(s)
        assert len(cam.flow_prev) >= 50
        ang = np.arccos(np.clip(np.einsum('ij,ij->i', cam.flow_prev, cam.flow_curr), -1, 1)) * f
        assert np.median(ang) < 0.1
    # the left camera drops out (its tracks end), then everything is reset: ids still only grow
    o = fe.process(2.0, {'right': samples(rig, 0.012)['right'], 'left': None})
    assert o.left is None
    fe.reset()
    for k in range(2):
        o = fe.process(3.0 + 0.2 * k, samples(rig, 0.05 + 0.002 * k, fix=(150.0, 110.0)))
        for s in SIDES:
            ids = o.camera(s).track_ids
            born = [i for i in ids.tolist() if i not in seen[s]]
            if k == 0:                                   # after the reset every track is new
                assert len(born) == len(ids) >= 50
            assert not born or min(born) > max(seen[s])
            assert len(np.unique(ids)) == len(ids)
            seen[s] |= set(ids.tolist())
    assert fe.last['right'].status == OK


# ---------------------------------------------------------------------------------------------- predicted LK
def test_predicted_lk_follows_a_60_px_pan_that_plain_lk_loses(rig):
    f = rig.camera('right').fx
    dpan = np.arctan(60.0 / f)                                    # 60 px at the image centre
    s0, s1 = samples(rig, 0.0), samples(rig, dpan)
    fe = StereoFrontEnd(rig, WINDOW, KeyframePolicy(max_frames=1))
    fe.process(0.0, s0)
    tracked = {s: (fe._tracks[s].px.copy(), fe._tracks[s].rays.copy()) for s in SIDES}
    o = fe.process(0.2, s1)
    check_counts(fe)
    for side in SIDES:
        px0, rays0 = tracked[side]
        rep, cam = fe.last[side], o.camera(side)
        assert rep.lk == LK_PREDICTED and not rep.lk_retry
        assert rep.pairs >= 0.9 * len(px0)
        # the rig did not move: each point keeps its rig-frame ray although the image moved ~60 px
        ang = np.arccos(np.clip(np.einsum('ij,ij->i', cam.flow_prev, cam.flow_curr), -1, 1)) * f
        assert np.median(ang) < 0.1 and np.max(ang) < 0.5
        moved = np.linalg.norm(fe.last_tracks[side].curr_px - fe.last_tracks[side].prev_px, axis=1)
        assert np.median(moved) > 55
        # the same points without the prediction: LK from zero motion loses them
        plain = track_points(s0[side].gray, s1[side].gray, px0, WINDOW)
        truth = rig.camera(side).rays_to_pixels(rays0 @ rig.cam_to_rig(side, dpan, 0.0))
        right_place = plain.ok & (np.linalg.norm(plain.curr_px - truth, axis=1) < 1.0)
        assert right_place.sum() < 0.2 * len(px0)
    assert fe.totals['right.lk_predicted'] == 1 and fe.totals['right.lk_zero'] == 0


def test_rig_rotation_is_predicted_at_constant_angular_velocity_and_triggers_keyframes(rig):
    """The rig yaws 2 deg per frame (~30 px) with the heads still: the first step is found from zero motion's
    neighbourhood, later ones from the predicted rotation; a keyframe is taken once the rotation since the
    keyframe exceeds max_rotation_deg (and never with it off, before max_frames)."""
    step = np.radians(2.0)

    def run(max_rotation_deg: float, frames: int) -> tuple[list[bool], StereoFrontEnd, object]:
        fe = StereoFrontEnd(rig, WINDOW, KeyframePolicy(max_frames=20, max_rotation_deg=max_rotation_deg))
        keys = []
        for k in range(frames):
            o = fe.process(0.2 * k, samples(rig, 0.0, rot_y(step * k)))
            check_counts(fe)
            keys.append(bool(o.keyframe))
            if k >= 2:
                assert all(fe.last[s].lk == LK_PREDICTED and not fe.last[s].lk_retry for s in SIDES)
        return keys, fe, o

    keys, _, _ = run(5.0, 8)
    assert keys == [True, False, False, True, False, False, True, False]   # 2, 4 deg fine; 6 deg > 5: keyframe
    keys, fe, o = run(0.0, 4)
    assert keys == [True, False, False, False]
    assert fe.last_rotation_deg == pytest.approx(6.0, abs=0.05)
    # the pairs carry the rig rotation: a = R b with R the 6 deg yaw
    for cam in (o.right, o.left):
        a, b = cam.flow_prev, cam.flow_curr
        err = np.linalg.norm(a - b @ rot_y(step * 3).T, axis=1) * rig.camera('right').fx
        assert len(a) >= 30 and np.median(err) < 0.2


# ---------------------------------------------------------------------------------------------- RANSAC
def _pairs(rig, side: str, n: int, rng, R: np.ndarray, T: np.ndarray, key_pan: float):
    """Rays keyframe -> now of n points 2..8 m in front of ``side`` (pointing at ``key_pan``), and the
    camera's optical frame at the keyframe."""
    C = rig.cam_to_rig(side, key_pan, 0.0)
    c = rig.center(side)
    d = np.column_stack([rng.uniform(-0.06, 0.06, n), rng.uniform(-0.06, 0.06, n), np.ones(n)])
    X = c + (d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(2.0, 8.0, (n, 1))) @ C.T
    a = X - c
    b = (X - T) @ R - c                     # the point in the rig frame at t (rig moved by R, T)
    return a / np.linalg.norm(a, axis=1, keepdims=True), b / np.linalg.norm(b, axis=1, keepdims=True), C


@pytest.mark.parametrize('side', SIDES)
def test_ransac_removes_injected_outliers_and_keeps_inliers(rig, side):
    rng = np.random.default_rng(5)
    f = rig.camera(side).fx
    R, T = exp_so3(np.array([0.01, -0.05, 0.005])), np.array([0.15, 0.02, 0.1])
    a, b, C = _pairs(rig, side, 100, rng, R, T, 0.2)
    Tc = T + (R - np.eye(3)) @ rig.center(side)            # the camera centre's motion
    # 0.2 px of noise on every ray, then 20 % moved 5 px off their epipolar plane
    b = b + rng.normal(0, 0.2 / f, b.shape)
    bad = rng.permutation(100)[:20]
    n = np.cross(a[bad], Tc) @ R                          # epipolar plane normal in the frame at t
    n -= np.einsum('ij,ij->i', n, b[bad])[:, None] * b[bad]
    b[bad] += 5.0 / f * n / np.linalg.norm(n, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    out = epipolar_outliers(a, b, C, f, 1.0)
    assert out is not None
    assert set(np.flatnonzero(out)) >= set(bad.tolist())              # every injected outlier found
    assert out.sum() <= 20 + 3                                        # and nearly every inlier kept
    # no translation: no parallax, E is degenerate, RANSAC does not run
    a0, b0, _ = _pairs(rig, side, 100, rng, R, np.zeros(3) - (R - np.eye(3)) @ rig.center(side), 0.2)
    assert epipolar_outliers(a0, b0, C, f, 1.0) is None
    assert epipolar_outliers(a[:7], b[:7], C, f, 1.0) is None                 # too few pairs


def test_ransac_gets_the_same_numbers_when_the_rays_differ_in_their_last_bits(rig, monkeypatch):
    """The rays come out of BLAS products, whose last bits differ between CPU kernels; a pair at RANSAC's bound then
    flips between inlier and outlier, and the trajectories part on another machine. What OpenCV is given is rounded
    (``frontend.RANSAC_INPUT_STEP``): rays one ulp apart reach it as the same numbers, so it decides the same."""
    seen = []
    real = cv2.findEssentialMat

    def spy(x1, x2, *args, **kwargs):
        seen.append((x1.copy(), x2.copy()))
        return real(x1, x2, *args, **kwargs)

    monkeypatch.setattr(frontend.cv2, 'findEssentialMat', spy)
    rng = np.random.default_rng(11)
    f = rig.camera('right').fx
    a, b, C = _pairs(rig, 'right', 80, rng, exp_so3(np.array([0.0, 0.02, 0.0])), np.array([0.1, 0.0, 0.05]), 0.2)
    b = b + rng.normal(0, 0.5 / f, b.shape)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    up, down = np.nextafter(a, 2.0), np.nextafter(b, -2.0)        # one ulp each way, as another kernel rounds
    assert np.any(up != a) and np.any(down != b)
    outs = [epipolar_outliers(x, y, C, f, 1.0) for x, y in ((a, b), (up, b), (a, down))]
    assert all(o is not None and np.array_equal(o, outs[0]) for o in outs)
    for x1, x2 in seen[1:]:
        assert np.array_equal(x1, seen[0][0]) and np.array_equal(x2, seen[0][1])


def test_front_end_kills_epipolar_outliers(rig):
    """In the front end: tracks whose flow keyframe -> t does not fit the camera's epipolar model end and are
    counted. The images stand still; the keyframe's stored rays are replaced by those a rig 0.3 m away would
    have seen (points 2-6 m deep), a fifth of them moved 5 px off their epipolar plane."""
    fe = StereoFrontEnd(rig, WINDOW, KeyframePolicy(max_frames=5, max_rotation_deg=0.0))
    fe.process(0.0, samples(rig, 0.0))
    fe.process(0.2, samples(rig, 0.0))
    assert fe.last['right'].counts.epipolar == 0 and not fe.last['right'].ransac   # no parallax: skipped
    rng = np.random.default_rng(2)
    f = rig.camera('right').fx
    now = fe.last_tracks['right']
    live = fe._tracks['right']
    n, T = len(live), np.array([0.3, 0.0, 0.0])
    a = live.rays * rng.uniform(2.0, 6.0, (n, 1)) + T          # the points seen from the keyframe's rig
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    bad = rng.permutation(n)[: n // 5]
    off = np.cross(a[bad], T)
    a[bad] += 5.0 / f * off / np.linalg.norm(off, axis=1, keepdims=True)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    fe._key['right'] = type(live)(live.ids, live.px, a)
    o = fe.process(0.4, samples(rig, 0.0))
    check_counts(fe)
    rep = fe.last['right']
    assert now is not None and rep.ransac
    assert len(bad) <= rep.counts.epipolar <= len(bad) + 3
    assert not set(live.ids[bad].tolist()) & set(o.right.track_ids.tolist())   # their tracks ended
    assert rep.pairs == len(o.right.flow_prev) == n - rep.counts.epipolar


# ---------------------------------------------------------------------------------------------- fixation shift
@pytest.mark.parametrize('same_fixation', [True, False])
def test_a_window_jump_the_readings_miss_is_followed_by_the_fixation_points_shift(rig, same_fixation):
    """The heads jump 70 px while the joint readings stay (a servo jerk the readings lag): neither the
    rotation prediction nor zero motion follows, the fixation point's own image motion does (LK_FIXATION). With
    a new fixation point (another id) there is no shift to use and most tracks are lost."""
    from fixego_ros.pipeline.frontend import LK_FIXATION
    f = rig.camera('right').fx
    dpan = np.arctan(70.0 / f)
    fe = StereoFrontEnd(rig, WINDOW, KeyframePolicy(max_frames=1))
    fe.process(0.0, samples(rig, 0.0))
    n0 = {s: len(fe._tracks[s]) for s in SIDES}
    jumped = samples(rig, dpan)
    now = {}
    for side, s in jumped.items():
        ray = rig.pixels_to_rig_rays(side, np.array([[160.0, 120.0]]), 0.0, 0.0)
        fix = rig.camera(side).rays_to_pixels(ray @ rig.cam_to_rig(side, dpan, 0.0))[0]
        now[side] = CameraSample(s.gray, 0.0, 0.0, (float(fix[0]), float(fix[1])), 1 if same_fixation else 2)
    fe.process(0.2, now)
    check_counts(fe)
    kept = {s: fe.last[s].counts.kept for s in SIDES}
    if same_fixation:
        # the right camera goes first and follows by its fixation shift; the rotation it then measures (the
        # readings are stale, so the jump looks like a rig turn) predicts the left camera's points
        assert fe.last['right'].lk == LK_FIXATION and fe.last['right'].lk_retry
        assert fe.last['left'].lk in (LK_PREDICTED, LK_FIXATION)
        assert all(kept[s] >= 0.8 * n0[s] for s in SIDES)
    else:
        assert all(fe.last[s].lk != LK_FIXATION and kept[s] < 0.2 * n0[s] for s in SIDES)


def test_new_corners_are_detected_once_a_twentieth_of_the_target_is_missing_not_for_each_lost_track(rig,
                                                                                                   monkeypatch):
    """A detection costs as much for one corner as for twenty, and a frame usually loses one or two tracks: the
    region is refilled once it lacks 5 % of its target (the target, 150, here: 8), to the full target."""
    import fixego_ros.pipeline.frontend as frontend

    asked: list[int] = []
    detect = frontend.detect_corners

    def counting(gray, box, need, params, exclude=None):
        asked.append(int(need))
        return detect(gray, box, need, params, exclude=exclude)

    monkeypatch.setattr(frontend, 'detect_corners', counting)
    params = FlowParams(preset='full', max_corners=150)
    fe = StereoFrontEnd(rig, params)
    batch = max(1, round(frontend.REPLENISH_FRACTION * params.max_corners))
    assert batch == 8
    fe.process(0.0, samples(rig, 0.0))
    assert asked == [150, 150] and all(len(fe._tracks[s]) == 150 for s in SIDES)
    for k, lose in enumerate((batch - 1, batch), start=1):
        asked.clear()
        for side in SIDES:           # these tracks are lost (as if LK had failed on them)
            keep = np.ones(len(fe._tracks[side]), bool)
            keep[:lose] = False
            fe._tracks[side] = fe._tracks[side].select(keep)
        fe.process(k / 30.0, samples(rig, 0.0))
        if lose < batch:
            assert asked == [] and all(len(fe._tracks[s]) == 150 - lose for s in SIDES)
        else:                        # 7 short from before + 8 now: refilled to the target
            assert asked == [batch - 1 + lose] * 2
            assert all(len(fe._tracks[s]) == 150 for s in SIDES)
