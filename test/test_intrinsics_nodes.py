"""Nodes taking intrinsics from camera_info over real DDS (private domain): flow_node fills them in when they
arrive, estimator_node waits for them at start (bounded), and a camera_info that disagrees with the rig file is
an ERROR on /diagnostics while the rig file is kept."""

from __future__ import annotations

import threading

import pytest
import yaml

pytest.importorskip('rclpy')

import rclpy
from conftest import executor_for, spin_until
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo

from fixego_ros.geometry.rig import CameraModel, RigError, default_rig_path
from fixego_ros.nodes.common import RELIABLE_QOS, SENSOR_QOS

CAM = CameraModel(320, 240, 500.0, 501.0, 159.5, 119.5, (-0.1, 0.01, 0.0, 0.0, 0.0))


def info_msg(cam: CameraModel = CAM) -> CameraInfo:
    m = CameraInfo()
    m.width, m.height, m.distortion_model = cam.width, cam.height, 'plumb_bob'
    m.d = [float(x) for x in cam.dist]
    m.k = [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0]
    return m


def rig_file(tmp_path, cameras: bool) -> str:
    d = yaml.safe_load(default_rig_path().read_text())
    d.pop('right')
    d.pop('left')
    if cameras:
        d['right'] = d['left'] = CAM.to_dict()
    path = tmp_path / 'rig.yaml'
    path.write_text(yaml.safe_dump(d))
    return str(path)


def test_flow_node_takes_missing_intrinsics_from_camera_info(ros_context, tmp_path):
    from fixego_ros.nodes.flow_node import FlowNode
    node = FlowNode(context=ros_context, parameter_overrides=[Parameter('rig_file', value=rig_file(tmp_path, False))])
    peer = rclpy.create_node('info_peer', context=ros_context)
    pubs = {s: peer.create_publisher(CameraInfo, f'/fixego/{s}/camera_info', SENSOR_QOS) for s in ('right', 'left')}
    ex = executor_for(ros_context, node, peer)
    try:
        assert node.rig.missing_intrinsics() == ('right', 'left')
        assert node.intrinsics.status('x').level == DiagnosticStatus.WARN

        def ready():
            for p in pubs.values():
                p.publish(info_msg())
            return node.intrinsics.ready()
        assert spin_until(ex, ready, 10.0)
        assert node.rig.right == CAM and node.rig.left == CAM and node.frontend.rig is node.rig
        st = node.intrinsics.status('x')
        assert st.level == DiagnosticStatus.OK and {v.key: v.value for v in st.values}['left_intrinsics'] == \
            'camera_info'
    finally:
        ex.shutdown()
        peer.destroy_node()
        node.destroy_node()


def test_disagreeing_camera_info_is_an_error_on_diagnostics_and_the_rig_file_is_kept(ros_context, tmp_path):
    from fixego_ros.nodes.flow_node import FlowNode
    node = FlowNode(context=ros_context, parameter_overrides=[
        Parameter('rig_file', value=rig_file(tmp_path, True)), Parameter('diagnostics_period_s', value=0.1)])
    peer = rclpy.create_node('info_peer', context=ros_context)
    pub = peer.create_publisher(CameraInfo, '/fixego/right/camera_info', SENSOR_QOS)
    diags: list[DiagnosticArray] = []
    peer.create_subscription(DiagnosticArray, '/diagnostics', diags.append, RELIABLE_QOS)
    ex = executor_for(ros_context, node, peer)
    other = CameraModel(320, 240, 520.0, 501.0, 159.5, 119.5, CAM.dist)
    try:
        def errored():
            pub.publish(info_msg(other))
            return any(st.level == DiagnosticStatus.ERROR and st.name == 'fixego flow_node: intrinsics'
                       for d in diags for st in d.status)
        assert spin_until(ex, errored, 10.0)
        st = next(st for d in diags for st in d.status if st.level == DiagnosticStatus.ERROR)
        assert 'disagree on K' in st.message and 'fx 500' in st.message and 'fx 520' in st.message
        assert node.rig.right == CAM
    finally:
        ex.shutdown()
        peer.destroy_node()
        node.destroy_node()


def test_estimator_node_waits_for_camera_info_and_gives_up_with_one_line(ros_context, tmp_path):
    from fixego_ros.nodes.estimator_node import EstimatorNode
    peer = rclpy.create_node('info_peer', context=ros_context)
    pubs = {s: peer.create_publisher(CameraInfo, f'/fixego/{s}/camera_info', SENSOR_QOS) for s in ('right', 'left')}
    stop = threading.Event()

    def publish():
        while not stop.wait(0.05):
            for p in pubs.values():
                p.publish(info_msg())
    t = threading.Thread(target=publish, daemon=True)
    t.start()
    try:
        node = EstimatorNode(context=ros_context, parameter_overrides=[
            Parameter('rig_file', value=rig_file(tmp_path, False)), Parameter('camera_info_wait_s', value=20.0)])
        try:
            assert node.rig.right == CAM and node.estimator.rig.left == CAM
            assert node.config.solver.sigma == pytest.approx(1.0 / CAM.fx)       # pixel_sigma / fx
        finally:
            node.destroy_node()
    finally:
        stop.set()
        t.join(timeout=5.0)
        peer.destroy_node()
    with pytest.raises(RigError, match=r'no intrinsics for the right and left camera.*within 0\.3 s'):
        EstimatorNode(context=ros_context, parameter_overrides=[
            Parameter('rig_file', value=rig_file(tmp_path, False)), Parameter('camera_info_wait_s', value=0.3)])
