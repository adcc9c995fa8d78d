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
