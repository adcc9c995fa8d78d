"""The nodes' TF: estimator_node's publish_tf choice (auto | true | false) and static rig transforms, camera_node's
optical frame from the joint readings. tf2_ros is not installable from wheels, so a stand-in module records what
the nodes send (the nodes import tf2_ros only when they make a broadcaster)."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
import yaml

pytest.importorskip('rclpy')

from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from fixego_ros.geometry.frames import optical_transform
from fixego_ros.geometry.rig import default_rig_path
from fixego_ros.geometry.rotation import RIG_TO_BASE, Pose, from_quat_xyzw, quat_xyzw, rot_y
from fixego_ros.nodes.common import sec_to_stamp
from fixego_ros.pipeline.params import ESTIMATOR_NODE_PARAMS, ParamsError

MOUNT = Pose(rot_y(0.2) @ RIG_TO_BASE, np.array([0.3, 0.0, 0.4]))


class _Recorder:
    def __init__(self, node) -> None:
        self.sent: list = []
        self.node = node
        SENT.append(self)

    def sendTransform(self, tf) -> None:
        self.sent.extend(tf if isinstance(tf, list) else [tf])


class _Static(_Recorder):
    pass


SENT: list[_Recorder] = []


@pytest.fixture
def fake_tf2(monkeypatch):
    mod = types.ModuleType('tf2_ros')
    mod.TransformBroadcaster = _Recorder
    mod.StaticTransformBroadcaster = _Static
    monkeypatch.setitem(sys.modules, 'tf2_ros', mod)
    SENT.clear()
    yield SENT
    SENT.clear()


@pytest.fixture
def rig_file(tmp_path):
    d = yaml.safe_load(default_rig_path().read_text())
    d['rig_in_base_link'] = {'translation': MOUNT.t.tolist(), 'rotation_xyzw': quat_xyzw(MOUNT.R).tolist()}
    path = tmp_path / 'rig.yaml'
    path.write_text(yaml.safe_dump(d))
    return str(path)


def _pose(tf) -> Pose:
    t, q = tf.transform.translation, tf.transform.rotation
    return Pose(from_quat_xyzw(np.array([q.x, q.y, q.z, q.w])), np.array([t.x, t.y, t.z]))


def test_publish_tf_is_a_choice_and_takes_a_bool():
    spec = ESTIMATOR_NODE_PARAMS['publish_tf']
    assert spec.default == 'auto' and spec.check(False) == 'false' and spec.check(True) == 'true'
    with pytest.raises(ParamsError, match='publish_tf'):
        spec.check('sometimes')


@pytest.mark.parametrize('publish_tf, speed_topic, on', [
    (None, '', True), (None, '/wheel/odom', False), (False, '', False), ('true', '/wheel/odom', True),
    (True, '', True)])
def test_estimator_publish_tf_auto_true_false(ros_context, fake_tf2, rig_file, publish_tf, speed_topic, on):
    from fixego_ros.nodes.estimator_node import EstimatorNode
    overrides = [Parameter('rig_file', value=rig_file), Parameter('speed_topic', value=speed_topic)]
    if publish_tf is not None:                       # a bool as `-p publish_tf:=false` gives it
        overrides.append(Parameter('publish_tf', value=publish_tf))
    node = EstimatorNode(context=ros_context, parameter_overrides=overrides)
    try:
        assert (node.tf is not None) == on
        assert [type(b) for b in fake_tf2].count(_Recorder) == int(on)
    finally:
        node.destroy_node()


def test_estimator_frames_and_static_transforms(ros_context, fake_tf2, rig_file):
    from fixego_ros.nodes.estimator_node import EstimatorNode
    node = EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter('rig_file', value=rig_file), Parameter('odom_frame', value='world_odom'),
        Parameter('base_frame', value='base_footprint')])
    try:
        (static,) = [b for b in fake_tf2 if isinstance(b, _Static)]
        frames = {(t.header.frame_id, t.child_frame_id): _pose(t) for t in static.sent}
        assert set(frames) == {('base_footprint', 'rig'), ('rig', 'right_zero'), ('rig', 'left_zero')}
        np.testing.assert_allclose(frames['base_footprint', 'rig'].t, MOUNT.t)
        np.testing.assert_allclose(frames['base_footprint', 'rig'].R, MOUNT.R, atol=1e-9)
        np.testing.assert_allclose(frames['rig', 'left_zero'].t, node.rig.c_L)
        stamp = sec_to_stamp(12.5)
        node._send_tf(stamp, Pose(np.eye(3), np.array([1.0, 2.0, 3.0])))
        tf = node.tf.sent[-1]
        assert (tf.header.frame_id, tf.child_frame_id) == ('world_odom', 'base_footprint')
        assert tf.header.stamp == stamp and tf.transform.translation.y == 2.0
        ps = node._stamped(stamp, Pose.identity())
        assert ps.header.frame_id == 'world_odom'
        assert node.speed.base_frame == 'base_footprint'
    finally:
        node.destroy_node()
    SENT.clear()
    node = EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter('rig_file', value=rig_file), Parameter('publish_static_tf', value=False)])
    try:
        assert not any(isinstance(b, _Static) for b in fake_tf2)
    finally:
        node.destroy_node()


def test_without_tf2_ros_nothing_is_broadcast(ros_context, rig_file, monkeypatch):
    monkeypatch.setitem(sys.modules, 'tf2_ros', None)        # import fails as on a wheels-only install
    from fixego_ros.nodes.estimator_node import EstimatorNode
    node = EstimatorNode(context=ros_context, parameter_overrides=[Parameter('rig_file', value=rig_file)])
    try:
        assert node.tf is None
    finally:
        node.destroy_node()


def test_passive_camera_node_broadcasts_its_optical_frame_from_the_joint_readings(ros_context, fake_tf2, rig_file):
    from fixego_ros.nodes.camera_node import CameraNode
    node = CameraNode(context=ros_context, parameter_overrides=[Parameter('side', value='left'),
                                                                Parameter('rig_file', value=rig_file)])
    try:
        js = JointState()
        js.header.stamp = sec_to_stamp(3.0)
        js.name = ['left_pan', 'left_tilt']
        js.position = [0.25, -0.05]
        node._on_joint_state(js)
        js.position = [float('nan'), 0.0]
        node._on_joint_state(js)                              # ignored: nothing sent
        (tf,) = node.tf.sent
        assert (tf.header.frame_id, tf.child_frame_id) == ('left_zero', 'left_optical_frame')
        assert tf.header.stamp == sec_to_stamp(3.0)
        want = optical_transform(node.rig, 'left', 0.25, -0.05)[2]
        np.testing.assert_allclose(_pose(tf).R, want.R, atol=1e-9)
    finally:
        node.destroy_node()
