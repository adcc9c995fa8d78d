"""bench.demo_inputs: a recorded demo run's observations turned to the simulator's true head angles."""

from __future__ import annotations

import numpy as np

from fixego_ros.bench.demo_inputs import TrueHeads
from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.geometry.rig import default_rig_path, load_rig, normalize_rays


def test_each_camera_is_turned_to_its_true_angles_and_keeps_its_measurements():
    """Rays recorded through a wrong pan reading (0.6 deg off at the second frame) come out as the camera's own
    measurements through the true angles, the flow's earlier rays through that frame's true angles; a camera
    without true angles is left as recorded and counted."""
    rig = load_rig(default_rig_path())
    rng = np.random.default_rng(1)
    cam_rays = lambda n: normalize_rays(rng.normal(0.0, 0.1, (n, 3)) + np.array([0.0, 0.0, 1.0]))  # noqa: E731
    readings = {1.0: (0.30, 0.05), 2.0: (0.35, 0.05 + np.radians(0.1))}
    truth = {1.0: (0.30, 0.05), 2.0: (0.35 + np.radians(0.6), 0.05)}
    seen_prev, seen_now, tracks = cam_rays(8), cam_rays(8), cam_rays(5)
    hook = TrueHeads(rig, {'right': truth, 'left': {}})

    def frame(stamp: float, prev: float | None) -> FrameObservation:
        C = rig.cam_to_rig('right', *readings[stamp])
        C0 = rig.cam_to_rig('right', *readings[prev]) if prev is not None else C
        right = CameraFrame(C @ np.array([0.0, 0.0, 1.0]), 3, C, seen_prev @ C0.T, seen_now @ C.T,
                            np.arange(5), tracks @ C.T, joint_sigma=np.radians(0.4))
        left = CameraFrame(None, -1, rig.cam_to_rig('left', -0.3, 0.0), joint_sigma=np.radians(0.3))
        return FrameObservation(stamp, right, left, prev_stamp=prev, keyframe=True)

    hook(frame(1.0, None))
    out = hook(frame(2.0, 1.0))
    C_true, C0_true = rig.cam_to_rig('right', *truth[2.0]), rig.cam_to_rig('right', *truth[1.0])
    r = out.right
    np.testing.assert_allclose(r.cam_to_rig, C_true, atol=1e-12)
    np.testing.assert_allclose(r.flow_curr, seen_now @ C_true.T, atol=1e-12)
    np.testing.assert_allclose(r.flow_prev, seen_prev @ C0_true.T, atol=1e-12)
    np.testing.assert_allclose(r.track_rays, tracks @ C_true.T, atol=1e-12)
    np.testing.assert_allclose(r.fixation_ray, C_true @ np.array([0.0, 0.0, 1.0]), atol=1e-12)
    assert r.joint_sigma == 0.0 and r.fixation_id == 3 and list(r.track_ids) == list(range(5))
    # the recorded rays were that far off (the test can tell)
    assert np.degrees(np.arccos(np.clip(np.sum(frame(2.0, 1.0).right.flow_curr * r.flow_curr, 1), -1, 1))).min() > 0.4
    # the left camera had no true angles: as recorded, counted once per frame; and the first frame's flow, which
    # starts at a frame the hook never saw
    assert out.left.joint_sigma == np.radians(0.3)
    assert np.array_equal(out.left.cam_to_rig, rig.cam_to_rig('left', -0.3, 0.0))
    assert hook.missing == 3


def test_the_true_angles_can_keep_the_stated_sigma_be_rounded_to_the_reading_unit_or_be_noisy():
    """The sensitivity variants: TRUE_STATED keeps each camera's stated sigma (TRUE states them exact); QUANTISED
    rounds each axis to its reading unit (off by at most half a unit, and by more than nothing somewhere); NOISY
    adds the asked-for spread, the same draw each time."""
    import math

    from fixego_ros.bench.demo_inputs import AngleSettings, HeadAngles, head_angles, noisy, quantised
    rig = load_rig(default_rig_path())
    rng = np.random.default_rng(2)
    stamps = np.arange(400) / 30.0
    truth = {side: {float(t): (float(a), float(b)) for t, a, b in zip(stamps, rng.uniform(-1, 1, 400),
                                                                          rng.uniform(-0.3, 0.3, 400), strict=True)}
             for side in ('right', 'left')}
    unit = (math.radians(0.1125), math.radians(0.075))
    q = quantised(truth, unit)
    for side in truth:
        err = np.array([np.subtract(q[side][t], truth[side][t]) for t in stamps])
        half = np.array(unit) / 2
        assert np.all(np.abs(err) <= half + 1e-15) and np.all(np.abs(err).max(axis=0) > 0.8 * half)
        steps = np.array([q[side][t] for t in stamps]) / np.array(unit)
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
    sd = math.radians(0.05)
    n1, n2 = noisy(truth, sd, seed=3), noisy(truth, sd, seed=3)
    assert n1 == n2 and n1 != noisy(truth, sd, seed=4)
    err = np.array([np.subtract(n1['right'][t], truth['right'][t]) for t in stamps])
    assert 0.85 * sd < err.std() < 1.15 * sd and abs(err.mean()) < 0.2 * sd

    def obs(stamp: float) -> FrameObservation:
        C = rig.cam_to_rig('right', 0.0, 0.0)
        cam = CameraFrame(C @ np.array([0.0, 0.0, 1.0]), 1, C, joint_sigma=np.radians(0.4))
        return FrameObservation(stamp, cam, None, keyframe=True)

    t0 = float(stamps[0])
    stated = head_angles(HeadAngles.TRUE_STATED, rig, truth, AngleSettings(unit, sd))(obs(t0)).right
    exact = head_angles(HeadAngles.TRUE, rig, truth, AngleSettings(unit, sd))(obs(t0)).right
    assert stated.joint_sigma == np.radians(0.4) and exact.joint_sigma == 0.0
    np.testing.assert_allclose(stated.cam_to_rig, rig.cam_to_rig('right', *truth['right'][t0]), atol=1e-12)
    rounded = head_angles(HeadAngles.QUANTISED, rig, truth, AngleSettings(unit, sd))(obs(t0)).right
    np.testing.assert_allclose(rounded.cam_to_rig, rig.cam_to_rig('right', *q['right'][t0]), atol=1e-12)


def test_a_span_gives_the_angles_to_its_frames_and_cameras_only():
    """``Span``: the true angles replace the recorded ones from START up to END seconds after the run's first image,
    for its cameras only; the other frames and cameras stay as recorded (counted as cameras without true angles). A
    span with no frames, or naming no camera, is refused."""
    import math

    import pytest

    from fixego_ros.bench.demo_inputs import AngleSettings, HeadAngles, Span, head_angles, within
    rig = load_rig(default_rig_path())
    stamps = 100.0 + np.arange(12) / 4.0            # the first image at 100 s, then every 0.25 s
    truth = {side: {float(t): (0.2 + 0.01 * k, 0.05) for k, t in enumerate(stamps)} for side in ('right', 'left')}
    span = Span(1.0, 2.0, ('left',))
    kept = within(truth, span)
    assert kept['right'] == {} and sorted(kept['left']) == [101.0, 101.25, 101.5, 101.75]
    assert within(truth, Span()) == truth

    recorded = {side: rig.cam_to_rig(side, 0.1, 0.0) for side in ('right', 'left')}

    def obs(stamp: float) -> FrameObservation:
        cams = {side: CameraFrame(None, -1, recorded[side], joint_sigma=np.radians(0.2)) for side in recorded}
        return FrameObservation(stamp, cams['right'], cams['left'], keyframe=True)

    hook = head_angles(HeadAngles.TRUE, rig, truth, AngleSettings(span=span))
    out = [hook(obs(float(t))) for t in stamps]
    for t, o in zip(stamps, out, strict=True):
        inside = 1.0 <= t - 100.0 < 2.0
        want = rig.cam_to_rig('left', *truth['left'][float(t)]) if inside else recorded['left']
        np.testing.assert_allclose(o.left.cam_to_rig, want, atol=1e-12)
        assert o.left.joint_sigma == (0.0 if inside else np.radians(0.2))
        np.testing.assert_array_equal(o.right.cam_to_rig, recorded['right'])
    assert hook.missing == 2 * len(stamps) - 4
    for bad in ((2.0, 1.0), (1.0, 1.0), (math.nan, 1.0)):
        with pytest.raises(ValueError, match='start < end'):
            Span(*bad)
    with pytest.raises(ValueError, match='sides'):
        Span(0.0, 1.0, ())
    with pytest.raises(ValueError, match='sides'):
        Span(0.0, 1.0, ('middle',))


def test_the_command_line_refuses_an_empty_span(capsys):
    import pytest

    from fixego_ros.bench.demo_inputs import main
    with pytest.raises(SystemExit) as stop:
        main(['nowhere', '--span', '3', '2'])
    assert stop.value.code == 2 and 'start < end' in capsys.readouterr().err
