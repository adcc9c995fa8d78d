"""Frames (issue 18): the rig's mount in base_link (rig file ``rig_in_base_link``), wheel odometry twists in the
robot's base through the mount, and the static/optical transforms the nodes broadcast."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from fixego_ros.geometry.frames import optical_transform, static_transforms
from fixego_ros.geometry.rig import default_rig_path, load_rig, pan_tilt_rotation, rig_from_dict
from fixego_ros.geometry.rotation import (
    RIG_TO_BASE,
    Pose,
    base_link_covariance,
    base_link_pose_to_rig,
    exp_so3,
    log_so3,
    quat_xyzw,
    rig_pose_to_base_link,
    rot_x,
    rot_y,
    rot_z,
)
from fixego_ros.pipeline.odometry import SpeedInput, SpeedSettings, twist_to_rig

# a rig 0.3 m ahead of base_link, 0.1 m to the left and 0.5 m up, pitched 10 deg down and yawed 5 deg left
MOUNT = Pose(rot_z(np.radians(5.0)) @ rot_y(np.radians(10.0)) @ RIG_TO_BASE, np.array([0.3, 0.1, 0.5]))


def rig_with_mount(mount: Pose | None):
    d = yaml.safe_load(default_rig_path().read_text())
    if mount is not None:
        d['rig_in_base_link'] = {'translation': mount.t.tolist(), 'rotation_xyzw': quat_xyzw(mount.R).tolist()}
    return rig_from_dict(d, [])


def base_trajectory(n: int = 40) -> list[Pose]:
    """base_link in odom: forward at 0.5 m/s for 1 s, turning on the spot, then an arc with a bump (roll, z)."""
    out = []
    for k in range(n):
        t = k / 10.0
        yaw = 0.0 if t < 1.0 else 0.8 * (t - 1.0)
        x = min(t, 1.0) * 0.5 + (0.3 * np.sin(0.5 * (t - 2.0)) if t > 2.0 else 0.0)
        y = 0.2 * (t - 2.0) ** 2 if t > 2.0 else 0.0
        out.append(Pose(rot_z(yaw) @ rot_x(0.05 * np.sin(t)), np.array([x, y, 0.02 * np.sin(3 * t)])))
    return out


# ---------------------------------------------------------------------------------------------- mount
def test_default_rig_file_has_no_mount_and_gives_todays_numbers_exactly():
    rig = load_rig(default_rig_path(), [])
    assert rig.mount is None and 'rig_in_base_link' not in rig.to_dict()
    np.testing.assert_array_equal(rig.rig_in_base_link.R, RIG_TO_BASE)
    rng = np.random.default_rng(3)
    for _ in range(20):
        p = Pose(exp_so3(rng.normal(size=3)), rng.normal(size=3))
        got = rig_pose_to_base_link(p, rig.mount)
        # the formula used before mounts existed, bit for bit
        np.testing.assert_array_equal(got.R, RIG_TO_BASE @ p.R @ RIG_TO_BASE.T)
        np.testing.assert_array_equal(got.t, RIG_TO_BASE @ p.t)
        # an explicit default mount gives the same pose (up to rounding)
        explicit = rig_pose_to_base_link(p, rig.rig_in_base_link)
        np.testing.assert_allclose(explicit.R, got.R, atol=1e-15)
        np.testing.assert_allclose(explicit.t, got.t, atol=1e-15)


def test_mount_gives_base_link_trajectory_from_the_rig_motion(tmp_path):
    rig = rig_with_mount(MOUNT)
    rig.save(tmp_path / 'rig.yaml')
    rig = load_rig(tmp_path / 'rig.yaml', [])          # the mount survives a save/load
    np.testing.assert_allclose(rig.mount.t, MOUNT.t)
    np.testing.assert_allclose(rig.mount.R, MOUNT.R, atol=1e-12)
    base = base_trajectory()
    rig_world = [b @ MOUNT for b in base]               # where the rig is when base_link is at b
    rig_rel = [rig_world[0].inverse() @ r for r in rig_world]     # what the estimator reports
    for b, r in zip(base, rig_rel, strict=True):
        want = base[0].inverse() @ b                      # odom = base_link at the first frame
        got = rig_pose_to_base_link(r, rig.mount)
        np.testing.assert_allclose(got.t, want.t, atol=1e-12)
        np.testing.assert_allclose(got.R, want.R, atol=1e-12)
        back = base_link_pose_to_rig(got, rig.mount)
        np.testing.assert_allclose(back.t, r.t, atol=1e-12)
    # turning on the spot (0.64 rad; only the small bump moves base_link) while the rig, 0.3 m ahead, swings
    k = 18
    base_moved = np.linalg.norm(base[k].t - base[10].t)
    assert base_moved < 0.05 and np.linalg.norm(rig_rel[k].t - rig_rel[10].t) > 0.15
    assert np.linalg.norm(rig_pose_to_base_link(rig_rel[k], rig.mount).t
                          - rig_pose_to_base_link(rig_rel[10], rig.mount).t) == pytest.approx(base_moved, abs=1e-12)
    # the default axes would put base_link on the rig's circle: the mount matters
    assert np.linalg.norm(rig_pose_to_base_link(rig_rel[k]).t - rig_pose_to_base_link(rig_rel[10]).t) > 0.15


def test_mount_covariance_adds_the_lever_arm():
    """A rotation uncertainty of the rig moves a base_link 0.3 m behind it: sample the first-order map."""
    rng = np.random.default_rng(1)
    pose = Pose(exp_so3([0.1, -0.3, 0.05]), np.array([0.4, 0.0, 1.0]))
    cov = np.diag([1e-4, 4e-4, 1e-4, 1e-4, 1e-4, 9e-4])          # [rotation, position] of the rig pose
    J = base_link_covariance(cov, pose, MOUNT)
    draws = rng.multivariate_normal(np.zeros(6), cov, 4000)
    mean = rig_pose_to_base_link(pose, MOUNT)
    errs = []
    for d in draws:
        p = rig_pose_to_base_link(Pose(exp_so3(d[:3]) @ pose.R, pose.t + d[3:]), MOUNT)
        errs.append(np.concatenate([p.t - mean.t, log_so3(p.R @ mean.R.T)]))
    np.testing.assert_allclose(np.cov(np.array(errs).T), J, atol=6e-5)
    J0 = base_link_covariance(cov, pose, Pose(MOUNT.R, np.zeros(3)))
    assert np.trace(J[:3, :3]) > np.trace(J0[:3, :3]) + 5e-5     # the lever arm (the sampling checks its size)


def test_mount_too_far_is_an_error():
    d = yaml.safe_load(default_rig_path().read_text())
    d['rig_in_base_link'] = {'translation': [300.0, 0, 0], 'rotation_xyzw': [0, 0, 0, 1]}
    with pytest.raises(ValueError, match=r'rig_in_base_link\.translation'):
        rig_from_dict(d, [])


# ---------------------------------------------------------------------------------------------- wheel odometry
def cov6(lin: float, ang: float) -> list[float]:
    c = np.zeros((6, 6))
    c[:3, :3] = np.eye(3) * lin
    c[3:, 3:] = np.eye(3) * ang
    return c.ravel().tolist()


def test_base_twist_becomes_the_rig_origin_velocity_through_the_mount():
    """The rig velocity from the trajectory itself (finite differences of the rig poses) equals the converted
    base twist, including the lever arm of a turning robot."""
    base = base_trajectory()
    dt = 0.1
    for k in (5, 15, 30):
        b0, b1 = base[k], base[k + 1]
        step_b = b0.inverse() @ b1                         # base_link motion over dt, in base_link at k
        v_base = step_b.t / dt                             # first order (the test motion is smooth)
        w_base = step_b.rvec() / dt
        r0, r1 = b0 @ MOUNT, b1 @ MOUNT
        v_rig_true = (r0.inverse() @ r1).t / dt            # rig origin velocity in the rig frame at k
        v, c = twist_to_rig(v_base, cov6(0.01, 0.0), 0.1, w_base, MOUNT)
        np.testing.assert_allclose(v, v_rig_true, atol=0.03 * max(1.0, np.linalg.norm(v_rig_true)))
        np.testing.assert_allclose(c, MOUNT.R.T @ (np.eye(3) * 0.01) @ MOUNT.R, atol=1e-15)
    # on the spot (k = 15 turns, x constant): the base does not move, the rig does
    step_b = base[15].inverse() @ base[16]
    v, _ = twist_to_rig(step_b.t / dt, cov6(0.01, 0.0), 0.1, step_b.rvec() / dt, MOUNT)
    assert np.linalg.norm(step_b.t / dt) < 0.01 and np.linalg.norm(v) > 0.2
    # exactly: omega x r for a yaw rate
    v, _ = twist_to_rig((0, 0, 0), cov6(0.01, 0.0), 0.1, (0, 0, 1.0), Pose(RIG_TO_BASE, np.array([0.3, 0, 0])))
    np.testing.assert_allclose(RIG_TO_BASE @ v, [0, 0.3, 0], atol=1e-15)


def test_angular_covariance_adds_lever_arm_variance_and_zero_adds_none():
    mount = Pose(RIG_TO_BASE, np.array([0.3, 0.0, 0.0]))
    _, c0 = twist_to_rig((0.5, 0, 0), cov6(0.01, 0.0), 0.1, (0, 0, 0.2), mount)
    _, c1 = twist_to_rig((0.5, 0, 0), cov6(0.01, 0.04), 0.1, (0, 0, 0.2), mount)
    np.testing.assert_allclose(c0, np.eye(3) * 0.01, atol=1e-15)            # zero angular covariance: exact omega
    # yaw-rate variance 0.04 at 0.3 m: base y (= rig -x) gains 0.3² * 0.04, pitch rate moves base z (= rig -y)
    np.testing.assert_allclose(np.diag(c1), [0.01 + 0.09 * 0.04, 0.01 + 0.09 * 0.04, 0.01], atol=1e-12)
    # no mount: the default axes put the rig origin at base_link, the angular part changes nothing
    v, _ = twist_to_rig((0.5, 0, 0), cov6(0.01, 0.04), 0.1, (0, 0, 5.0), None)
    np.testing.assert_allclose(v, [0, 0, 0.5], atol=1e-15)


def test_speed_input_takes_the_base_frame_name_and_rejects_others():
    mount = Pose(RIG_TO_BASE, np.array([0.3, 0.0, 0.0]))
    s = SpeedInput(SpeedSettings(topic='/wheel', base_frame='base_footprint'), mount)
    sample = s.convert(1.0, 'base_footprint', (0.0, 0.0, 0.0), cov6(0.01, 0.0), angular=(0.0, 0.0, 1.0))
    np.testing.assert_allclose(RIG_TO_BASE @ sample.v_rig, [0, 0.3, 0], atol=1e-15)
    assert not s.assumed_frame
    s.convert(2.0, '', (0.1, 0.0, 0.0), cov6(0.01, 0.0))
    assert s.assumed_frame
    with pytest.raises(ValueError, match="expected 'base_footprint'") as e:
        s.convert(3.0, 'base_link', (0.1, 0.0, 0.0), cov6(0.01, 0.0))
    assert e.value.kind == 'frame'


# ---------------------------------------------------------------------------------------------- TF
def test_static_transforms_chain_base_link_to_each_zero_frame():
    d = yaml.safe_load(default_rig_path().read_text())
    d['rig_in_base_link'] = {'translation': MOUNT.t.tolist(), 'rotation_xyzw': quat_xyzw(MOUNT.R).tolist()}
    d['left_in_rig'] = {'translation': [-0.25, 0.01, 0.0], 'rotation_xyzw': quat_xyzw(rot_y(0.1)).tolist()}
    rig = rig_from_dict(d, [])
    tf = {(p, c): pose for p, c, pose in static_transforms(rig, 'base_footprint')}
    assert set(tf) == {('base_footprint', 'rig'), ('rig', 'right_zero'), ('rig', 'left_zero')}
    np.testing.assert_allclose(tf['base_footprint', 'rig'].t, MOUNT.t)
    left = tf['base_footprint', 'rig'] @ tf['rig', 'left_zero']
    np.testing.assert_allclose(left.t, MOUNT.apply([-0.25, 0.01, 0.0]), atol=1e-12)
    np.testing.assert_allclose(tf['rig', 'left_zero'].R, rig.R_L, atol=1e-12)
    np.testing.assert_allclose(tf['rig', 'right_zero'].matrix(), np.eye(4))
    # default mount: the default axes
    tf0 = {(p, c): pose for p, c, pose in static_transforms(load_rig(default_rig_path(), []))}
    np.testing.assert_array_equal(tf0['base_link', 'rig'].R, RIG_TO_BASE)


@pytest.mark.parametrize('side', ['right', 'left'])
def test_optical_transform_follows_pan_tilt_and_the_calibration(side):
    d = yaml.safe_load(default_rig_path().read_text())
    d['pan_tilt'] = {side: {'pan_sign': -1, 'tilt_sign': 1, 'pan_offset': 0.02, 'tilt_offset': -0.01}}
    rig = rig_from_dict(d, [])
    parent, child, pose = optical_transform(rig, side, 0.3, -0.1)
    assert (parent, child) == (f'{side}_zero', f'{side}_optical_frame')
    np.testing.assert_allclose(pose.R, pan_tilt_rotation(-0.3 + 0.02, -0.1 - 0.01), atol=1e-15)
    np.testing.assert_array_equal(pose.t, np.zeros(3))
    # composed with the static rig -> zero transform it is the camera's rotation in the rig frame
    zero = {c: p for _, c, p in static_transforms(rig)}[f'{side}_zero']
    np.testing.assert_allclose((zero @ pose).R, rig.cam_to_rig(side, 0.3, -0.1), atol=1e-12)
    with pytest.raises(ValueError, match='finite'):
        optical_transform(rig, side, float('nan'), 0.0)


def test_a_camera_whose_reading_is_unsure_weighs_less_in_the_step():
    """JointWeighting: a camera whose stated pan/tilt sigma is at most the nominal one counts fully (steady heads,
    every simulated bag), above it its pairs (flow and fixation) are weighted by the rays' noise over the rays' plus
    the reading's; nominal 0 turns it off."""
    import math

    from fixego_ros.estimation.frames import CameraFrame, FrameObservation, JointWeighting, step_pairs
    ray, nominal = 1.0 / 1727.0, math.radians(0.1)
    joints = JointWeighting(ray, nominal)
    assert joints.weight(0.0) == joints.weight(nominal) == 1.0
    sure, unsure = joints.weight(math.radians(0.2)), joints.weight(math.radians(0.5))
    assert 1.0 > sure > unsure > 0.0
    assert unsure == pytest.approx(math.sqrt((ray ** 2 + nominal ** 2) / (ray ** 2 + math.radians(0.5) ** 2)))
    assert JointWeighting(ray, 0.0).weight(math.radians(5.0)) == 1.0
    rig = load_rig(default_rig_path())
    rng = np.random.default_rng(0)
    rays = lambda n: rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 5.0])  # noqa: E731
    cams = {side: CameraFrame(np.array([0.0, 0.0, 1.0]), 7, np.eye(3), rays(5), rays(5), joint_sigma=sigma)
            for side, sigma in (('right', math.radians(0.02)), ('left', math.radians(0.5)))}
    obs = FrameObservation(1.0, cams['right'], cams['left'])
    prev = {side: (np.array([0.0, 0.01, 1.0]), 7) for side in cams}
    pairs = step_pairs(rig, prev, obs, 2.0, joints)
    right = np.all(pairs.centers == rig.center('right'), axis=1)
    # five flow pairs and the fixation pair per camera; the fixation pair at fixation_weight times the camera's
    assert sorted(pairs.weights[right]) == [1.0] * 5 + [2.0]
    assert sorted(pairs.weights[~right]) == pytest.approx([unsure] * 5 + [2.0 * unsure])
    assert np.all(step_pairs(rig, prev, obs, 2.0).weights[~right] >= 1.0)     # the default: no weighting
