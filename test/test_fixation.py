"""Fixation tracker, limit re-selection, centring geometry, joint interpolation, and a short ROS-free
closed loop (tracker + servo + emulator)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fixego_ros.bench.servo import SyntheticView, run_closed_loop
from fixego_ros.geometry.rig import CameraModel, PanTiltCalibration, pan_tilt_rotation
from fixego_ros.tracking.fixation import FixationParams, FixationTracker, LimitCheck, SwingStagger
from fixego_ros.tracking.servo import JointHistory, ServoParams, centring_angles, servo_target
from fixego_ros.visca.profiles import PROFILES

CAM = CameraModel(320, 240, 500.0, 500.0, 159.5, 119.5)


def test_select_and_track_subpixel_shifts():
    view = SyntheticView(CAM, seed=2)
    tr = FixationTracker(CAM, FixationParams(search_radius_px=30.0))
    st = tr.update(view.render(0, 0), 0.0)
    assert st.valid and st.reselected and st.reason == 'initial' and st.fixation_id == 0
    assert math.hypot(st.pixel[0] - CAM.cx, st.pixel[1] - CAM.cy) < 30.0
    scene = view.scene_point(st.pixel, 0, 0)
    for k in range(1, 20):
        ox, oy = 1.7 * k, -0.9 * k
        st = tr.update(view.render(0, 0, ox, oy), k / 30)
        assert st.valid and not st.reselected and st.fixation_id == 0 and st.quality > 0.9
        assert np.allclose(st.pixel, view.pixel_of(scene, 0, 0, ox, oy), atol=0.15)
    assert st.age_s == pytest.approx(19 / 30)


def test_no_texture_gives_no_fixation_then_recovers():
    tr = FixationTracker(CAM)
    flat = np.full((CAM.height, CAM.width), 90, np.uint8)
    st = tr.update(flat, 0.0)
    assert not st.valid and st.pixel is None and st.reason == 'no_texture' and st.fixation_id == -1
    st = tr.update(SyntheticView(CAM).render(0, 0), 0.1)
    assert st.valid and st.fixation_id == 0


def test_reselection_reasons_and_ids():
    view = SyntheticView(CAM, seed=4)
    tr = FixationTracker(CAM, FixationParams(search_radius_px=20.0, border_margin_px=30.0))
    tr.update(view.render(0, 0), 0.0)
    # the point walks towards the right border -> 'left_image', new id, new point near the centre
    k, st = 0, None
    for k in range(1, 40):
        st = tr.update(view.render(0, 0, ox=6.0 * k), k * 0.03)
        if st.reselected:
            break
    assert st.reselected and st.reason == 'left_image' and st.fixation_id == 1
    assert abs(st.pixel[0] - CAM.cx) < 25
    # content replaced (occlusion / cut): tracking fails -> 'lost'
    st = tr.update(SyntheticView(CAM, seed=99).render(0, 0), 2.0)
    assert st.reselected and st.reason == 'lost' and st.fixation_id == 2
    # manual request with an offset -> new id near centre + offset
    tr.request_reselect('manual', (-80.0, 40.0))
    st = tr.update(SyntheticView(CAM, seed=99).render(0, 0), 2.1)
    assert st.reason == 'manual' and st.fixation_id == 3
    assert math.hypot(st.pixel[0] - (CAM.cx - 80), st.pixel[1] - (CAM.cy + 40)) < 25
    assert [r.reason for r in tr.reselections] == ['initial', 'left_image', 'lost', 'manual']


def test_a_jump_lucas_kanade_loses_is_found_again_by_the_template_unless_it_has_a_twin():
    """The scene jumps 70 px between two frames (a lagging head at a low frame rate): LK alone loses the point
    (``relocate_radius_px`` 0: a new id), the template search finds it again with its id and LK refines it to a
    tenth of a pixel. When the same patch also appears elsewhere in the search window, nothing is guessed."""
    view = SyntheticView(CAM, seed=5)

    def jump(params: FixationParams, twin: bool = False):
        tr = FixationTracker(CAM, params)
        st0 = tr.update(view.render(0, 0), 0.0)
        scene = view.scene_point(st0.pixel, 0, 0)
        img = view.render(0, 0, ox=70.0)
        px = view.pixel_of(scene, 0, 0, ox=70.0)
        if twin:                                   # a copy of the point's neighbourhood 60 px below it
            u, v, h = round(float(px[0])), round(float(px[1])), 14
            img = img.copy()
            dst = img[v + 60 - h:v + 60 + h + 1, u - h:u + h + 1]
            dst[:] = img[v - h:v + h + 1, u - h:u + h + 1]
        return tr.update(img, 0.2), px

    st, px = jump(FixationParams(relocate_radius_px=0.0))
    assert st.reselected and st.reason == 'lost' and st.fixation_id == 1
    st, px = jump(FixationParams())
    assert st.valid and not st.reselected and st.fixation_id == 0 and st.quality > 0.9
    assert np.allclose(st.pixel, px, atol=0.1)
    st, _ = jump(FixationParams(), twin=True)
    assert st.reselected and st.fixation_id == 1


def test_limit_check_fires_once_per_approach_and_swings_towards_the_middle():
    lc = LimitCheck((-1.0, 1.0), (-0.4, 0.4), margin_rad=0.1, swing_rad=0.6)
    assert lc.check(0.0, 0.0) is None
    assert lc.check(0.95, 0.05) == pytest.approx((0.35, 0.05))    # near +pan: swing 0.6 back, tilt kept
    assert lc.check(0.97, 0.0) is None                           # still near: no second swing
    assert lc.check(0.5, 0.0) is None
    assert lc.check(0.5, -0.35) == pytest.approx((0.5, 0.0))      # near the tilt bottom: to the middle, not past it
    assert lc.check(-0.5, 0.0) is None                           # clear again: re-armed
    assert lc.check(-0.95, 0.0) == pytest.approx((-0.35, 0.0))


def test_a_swing_that_waits_stays_armed():
    lc = LimitCheck((-1.0, 1.0), (-0.4, 0.4), margin_rad=0.1, swing_rad=0.6)
    assert not lc.due(0.5, 0.0)
    assert lc.due(0.95, 0.0) and lc.due(0.97, 0.0)           # asking does not consume the swing
    assert lc.check(0.97, 0.0) == pytest.approx((0.37, 0.0))
    assert not lc.due(0.97, 0.0)                             # fired: not again on this approach


def test_a_swing_waits_while_the_other_camera_has_no_fixation_but_not_longer_than_its_bound():
    dt = 1 / 30
    st = SwingStagger(max_hold_s=0.5)
    assert not st.hold(0.0, dt)                              # the other camera never published: no wait
    st.on_partner(0.0, True)
    assert not st.hold(dt, dt)                               # it fixates: swing at once
    st.on_partner(dt, False)                                 # it swings back (no fixation)
    st.on_partner(0.5 * dt, True)                            # an older message arriving late changes nothing
    waits = [st.hold(k * dt, dt) for k in range(2, 40)]
    assert waits[:16] == [True] * 16 and not any(waits[16:])   # held 0.5 s from the first wait, then swing anyway
    assert st.holds == 1
    st.reset()
    st.on_partner(40 * dt, False)
    assert st.hold(41 * dt, dt) and st.holds == 2            # the next approach waits afresh
    st.on_partner(42 * dt, True)
    assert not st.hold(43 * dt, dt)                          # the other camera fixates again: swing now
    assert not SwingStagger(max_hold_s=0.0, _partner=(0.0, False)).hold(dt, dt)     # 0: never wait


def test_both_heads_due_in_the_same_frame_swing_one_after_the_other():
    """Both reach a limit at the same image stamp, each with the other's last message "fixating": the right swings
    at once; the left waits until the right's message for that frame is in, which says "no fixation"."""
    dt = 1 / 30
    left = SwingStagger(max_hold_s=1.0, wait_for_partner_frame=True)
    right = SwingStagger(max_hold_s=1.0)
    left.on_partner(0.0, True)
    right.on_partner(0.0, True)
    assert not right.hold(dt, dt)                            # the right swings at frame 1 ...
    assert left.hold(dt, dt)                                 # ... the left has not seen the right's frame 1 yet
    left.on_partner(dt, False)
    assert left.hold(2 * dt, dt)                             # now it has: "no fixation", so it goes on waiting
    left.on_partner(3 * dt - 0.4 * dt, True)                 # the right fixates again (its frames 0.4 frame early)
    assert not left.hold(3 * dt, dt)
    assert (left.holds, right.holds) == (1, 0)
    left.reset()
    left.on_partner(10 * dt, True)
    assert left.hold(11 * dt, dt)                            # waits for the right's frame 11 ...
    left.on_partner(11 * dt, True)
    assert not left.hold(11 * dt, dt) and left.holds == 1      # ... which fixates: no wait for a swinging head


@pytest.mark.parametrize('pan,tilt', [(0.95, 0.0), (-0.95, 0.0), (0.0, 0.35), (0.0, -0.35), (0.93, 0.36)])
def test_a_limit_swing_ends_clear_of_every_margin(pan, tilt):
    """Where the head swings to is inside the range with room to follow a point again (the in-image re-selection
    it replaces left the head inside the margin, where it stayed pinned)."""
    lc = LimitCheck((-1.0, 1.0), (-0.4, 0.4), margin_rad=0.1, swing_rad=0.6)
    aim = lc.check(pan, tilt)
    assert aim is not None
    assert -0.9 < aim[0] < 0.9 and -0.3 <= aim[1] <= 0.3
    assert abs(aim[0]) <= abs(pan) and abs(aim[1]) <= abs(tilt)


def test_centring_angles_are_exact():
    rng = np.random.default_rng(0)
    for _ in range(20):
        pan, tilt = rng.uniform(-1.2, 1.2), rng.uniform(-0.4, 0.4)
        goal = rng.uniform(-0.1, 0.1, size=2) + np.array([pan, tilt])
        axis = pan_tilt_rotation(*goal) @ np.array([0.0, 0.0, 1.0])
        ray = pan_tilt_rotation(pan, tilt).T @ axis
        pixel = CAM.rays_to_pixels(ray[None])[0]
        assert np.allclose(centring_angles(CAM, tuple(pixel), pan, tilt), goal, atol=1e-9)
    cal = PanTiltCalibration(pan_sign=-1.0, tilt_sign=1.0, pan_offset=0.1)
    p, t = centring_angles(CAM, (CAM.cx, CAM.cy), 0.3, 0.05, cal)   # centre pixel: stay put
    assert (p, t) == pytest.approx((0.3, 0.05))
    # a point to the right of centre needs more pan (VISCA: + right), below needs less tilt (+ up)
    p, t = centring_angles(CAM, (CAM.cx + 50, CAM.cy + 50), 0.0, 0.0)
    assert p > 0 and t < 0


def test_servo_target_deadband_speed_and_clamp():
    d30 = PROFILES['evi_d30']
    params = ServoParams(gain=1.0, deadband_px=1.0)
    assert servo_target(CAM, d30, (CAM.cx + 0.5, CAM.cy), (0.0, 0.0), params) is None
    tg = servo_target(CAM, d30, (CAM.cx + 50, CAM.cy), (0.0, 0.0), params)
    assert tg.pan == d30.pan_units(math.degrees(math.atan(50 / 500))) and tg.tilt == 0
    assert 1 <= tg.pan_speed <= 0x18 and 1 <= tg.tilt_speed <= 0x14 and tg.pan_speed > 1
    tg = servo_target(CAM, d30, (CAM.cx + 100, CAM.cy), (math.radians(99.0), 0.0), params)
    assert tg.pan == d30.pan_max                           # never beyond the range


def test_joint_history_interpolation():
    h = JointHistory()
    h.add(1.0, 0.0, 0.0)
    h.add(2.0, 1.0, -2.0)
    h.add(1.5, 9.0, 9.0)                                   # out of order: ignored
    assert h.at(1.25) == pytest.approx((0.25, -0.5))
    assert h.at(2.04, max_extrapolation_s=0.05) == (1.0, -2.0)
    assert h.at(2.2, max_extrapolation_s=0.05) is None and h.at(0.5, max_extrapolation_s=0.05) is None


def test_closed_loop_converges_ros_free():
    m = run_closed_loop(duration_s=2.5, baud=115200, settle_s=1.2, drift_px_s=(15.0, -8.0),
                        start_offset_px=(25.0, -15.0))
    assert m['servo_errors'] == 0 and m['reselections'] == 0
    assert m['fixation_err_px_mean'] < 3.0 and m['fixation_err_px_max'] < 6.0
    assert m['joint_interp_err_deg_p95'] < 0.15
    assert m['servo_loop_hz'] > 30


def test_reselect_last_starts_a_new_point_in_the_last_image_that_the_next_frame_follows():
    """Replay: a vergence measurement shows where the head's point is in the image just tracked; the tracker
    starts a new fixation there (new id) and follows it on the next image. Too near the border: no change."""
    view = SyntheticView(CAM, seed=5)
    tr = FixationTracker(CAM, FixationParams(search_radius_px=20.0, border_margin_px=30.0))
    st = tr.update(view.render(0, 0), 0.0)
    other = (st.pixel[0] + 45.0, st.pixel[1] - 20.0)
    scene = view.scene_point(other, 0, 0)
    assert not tr.reselect_last((3.0, 3.0), 'vergence') and tr.fixation_id == st.fixation_id
    assert tr.reselect_last(other, 'vergence')
    assert tr.last.fixation_id == st.fixation_id + 1 and tr.last.reason == 'vergence' and tr.last.stamp == 0.0
    nxt = tr.update(view.render(0, 0, ox=3.0, oy=-2.0), 0.1)
    assert nxt.valid and not nxt.reselected and nxt.fixation_id == st.fixation_id + 1
    assert np.allclose(nxt.pixel, view.pixel_of(scene, 0, 0, 3.0, -2.0), atol=0.3)


def test_the_fixation_point_stays_on_its_scene_point_while_the_scene_comes_closer():
    """14 frames each 2 % closer about a point 40 px off the fixation (x1.32 in all), as a rig walking towards a
    wall sees it. LK alone follows the growing window off the point (the fixation is the longest track of all); the
    template registered with its affine stays on it."""
    import cv2
    rng = np.random.default_rng(4)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (3 * CAM.height, 3 * CAM.width)).astype(np.float32), (0, 0), 1.5)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    about = np.array([CAM.cx + 40.0, CAM.cy - 25.0])         # the zoom's fixed point in the image
    C = np.array([(tex.shape[1] - 1) / 2, (tex.shape[0] - 1) / 2])

    def frame(s: float) -> tuple[np.ndarray, np.ndarray]:
        A = np.column_stack([np.eye(2) * s, about - s * C])
        return cv2.warpAffine(tex, A, (CAM.width, CAM.height), flags=cv2.INTER_LINEAR), A

    tr = FixationTracker(CAM)
    img, A = frame(1.0)
    st = tr.update(img, 0.0)
    on_texture = np.array(st.pixel) - A[:, 2]
    s = 1.0
    for k in range(1, 15):
        s *= 1.02
        img, A = frame(s)
        st = tr.update(img, k / 10)
        assert st.valid and st.fixation_id == 0
    assert math.dist(st.pixel, on_texture * s + A[:, 2]) < 0.05
