"""camera_node in-process (private context/domain) against the VISCA emulator at real 9600-baud timing.

A synthetic publisher renders what the emulated camera sees (the scene shifts as the true pan/tilt
moves, and drifts slowly as if the rig turned). The node must bring its fixation point to the centre
and hold it within a few pixels, track the same scene point, publish joint states that match the true
angles at the image stamps, and re-select (new id) on the ~/reselect service.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from conftest import executor_for, spin_until  # noqa: E402
from geometry_msgs.msg import PointStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image, JointState  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from fixego_ros.bench.servo import SyntheticView  # noqa: E402
from fixego_ros.geometry.rig import CameraModel, Rig  # noqa: E402
from fixego_ros.nodes.camera_node import CameraNode  # noqa: E402
from fixego_ros.nodes.common import RELIABLE_QOS, SENSOR_QOS, array_to_image, sec_to_stamp  # noqa: E402
from fixego_ros.visca.emulator import ViscaEmulator  # noqa: E402

CAM = CameraModel(320, 240, 500.0, 500.0, 159.5, 119.5)


@pytest.fixture
def rig_file(tmp_path):
    path = tmp_path / 'rig.yaml'
    Rig(CAM, CAM).save(path)
    return str(path)


def _mono(node) -> float:
    return node.get_clock().now().nanoseconds * 1e-9


def test_active_node_converges_and_publishes_consistent_joint_states(ros_context, rig_file):
    emu = ViscaEmulator('evi_d30', baud=9600, start_pan_deg=0.0)
    port = emu.start()
    node = CameraNode(context=ros_context, parameter_overrides=[
        Parameter('side', value='right'), Parameter('port', value=port), Parameter('rig_file', value=rig_file),
        Parameter('search_radius_px', value=30.0), Parameter('border_margin_px', value=25.0)])
    peer = rclpy.create_node('peer', context=ros_context)
    ex = executor_for(ros_context, node, peer)
    fixes: list[PointStamped] = []
    joints: list[JointState] = []
    peer.create_subscription(PointStamped, '/fixego/right/fixation', fixes.append, RELIABLE_QOS)
    peer.create_subscription(JointState, '/fixego/right/joint_states', joints.append, RELIABLE_QOS)
    pub = peer.create_publisher(Image,
                                '/fixego/right/image_raw', SENSOR_QOS)
    view = SyntheticView(CAM, seed=3)
    truth: dict[tuple[int, int], tuple[float, float, float, float]] = {}   # stamp -> pan, tilt, ox, oy
    import time
    t0 = time.monotonic()
    state = {'next': t0}

    def publish_frame() -> bool:
        now = time.monotonic()
        if now >= state['next']:
            state['next'] = now + 1 / 30
            el = now - t0
            ox, oy = 30.0 + 12.0 * el, -20.0 - 6.0 * el      # start off-centre, then drift
            pan, tilt = emu.pan_tilt_rad(now)
            stamp = sec_to_stamp(_mono(node))
            truth[(stamp.sec, stamp.nanosec)] = (pan, tilt, ox, oy)
            pub.publish(array_to_image(view.render(pan, tilt, ox, oy), stamp, 'right_optical_frame'))
        return False

    try:
        spin_until(ex, lambda: publish_frame() or time.monotonic() - t0 > 4.0, timeout_s=10.0, step_s=0.005)
        assert fixes and joints, 'node published nothing'
        # --- fixation: one id, same scene point, at the centre after convergence
        ids = {int(f.point.z) for f in fixes}
        assert ids == {0}
        f0 = fixes[0]
        assert f0.header.frame_id == 'right_optical_frame'
        key0 = (f0.header.stamp.sec, f0.header.stamp.nanosec)
        scene = view.scene_point((f0.point.x, f0.point.y), *truth[key0])
        late = [f for f in fixes if f.header.stamp.sec + 1e-9 * f.header.stamp.nanosec
                > fixes[0].header.stamp.sec + 1e-9 * fixes[0].header.stamp.nanosec + 2.0]
        assert len(late) > 20
        errs, track_errs = [], []
        for f in late:
            tr = truth[(f.header.stamp.sec, f.header.stamp.nanosec)]
            true_px = view.pixel_of(scene, *tr)
            track_errs.append(math.hypot(true_px[0] - f.point.x, true_px[1] - f.point.y))
            errs.append(math.hypot(true_px[0] - CAM.cx, true_px[1] - CAM.cy))
        assert max(track_errs) < 1.0, f'tracker drifted off its scene point: {max(track_errs):.2f} px'
        assert np.mean(errs) < 3.0 and max(errs) < 6.0, f'fixation error mean {np.mean(errs):.2f} max {max(errs):.2f}'
        # --- joint states: names, stamps = image stamps, angles = truth at those stamps
        assert joints[0].name == ['right_pan', 'right_tilt']
        jerr = []
        for j in joints:
            key = (j.header.stamp.sec, j.header.stamp.nanosec)
            assert key in truth
            pan, tilt = truth[key][:2]
            jerr.append(max(abs(j.position[0] - pan), abs(j.position[1] - tilt)))
        assert len(joints) > 0.8 * len(truth) - 10
        assert math.degrees(float(np.percentile(jerr, 95))) < 0.2, math.degrees(max(jerr))
        # --- ~/reselect gives a new fixation id
        cli = peer.create_client(Trigger, '/camera_node/reselect')
        assert cli.wait_for_service(timeout_sec=2.0)
        fut = cli.call_async(Trigger.Request())
        assert spin_until(ex, fut.done, timeout_s=3.0) and fut.result().success
        n = len(fixes)
        assert spin_until(ex, lambda: publish_frame() or (len(fixes) > n + 3), timeout_s=3.0, step_s=0.005)
        assert int(fixes[-1].point.z) == 1
        assert node.driver.comm_errors == 0
    finally:
        ex.shutdown(timeout_sec=1.0)
        node.destroy_node()
        peer.destroy_node()
        emu.stop()


def test_passive_node_tracks_without_serial(ros_context, rig_file):
    node = CameraNode(context=ros_context, parameter_overrides=[
        Parameter('side', value='left'), Parameter('port', value=''), Parameter('rig_file', value=rig_file)])
    peer = rclpy.create_node('peer2', context=ros_context)
    ex = executor_for(ros_context, node, peer)
    fixes: list[PointStamped] = []
    joints_seen: list[JointState] = []
    peer.create_subscription(PointStamped, '/fixego/left/fixation', fixes.append, RELIABLE_QOS)
    peer.create_subscription(JointState, '/fixego/left/joint_states', joints_seen.append, RELIABLE_QOS)
    img_pub = peer.create_publisher(Image,
                                    '/fixego/left/image_raw', SENSOR_QOS)
    js_pub = peer.create_publisher(JointState, '/fixego/left/joint_states', RELIABLE_QOS)
    view = SyntheticView(CAM, seed=5)
    flat = np.full((CAM.height, CAM.width), 128, np.uint8)
    try:
        assert node.passive and node.driver is None
        for k in range(15):
            t = 100.0 + k / 30
            js = JointState(name=['left_pan', 'left_tilt'], position=[0.01 * k, 0.0])
            js.header.stamp = sec_to_stamp(t)
            js_pub.publish(js)
            img = flat if k < 3 else view.render(0.0, 0.0, ox=2.0 * k, oy=0.0)
            img_pub.publish(array_to_image(img, sec_to_stamp(t), 'left_optical_frame'))
            spin_until(ex, lambda: False, timeout_s=0.03, step_s=0.005)
        assert spin_until(ex, lambda: len(fixes) >= 10, timeout_s=3.0)
        # flat frames have no fixation: nothing published for them (never NaN)
        assert all(f.header.stamp.sec + 1e-9 * f.header.stamp.nanosec > 100.09 for f in fixes)
        assert all(math.isfinite(f.point.x) and math.isfinite(f.point.y) for f in fixes)
        # the scene drifts +2 px/frame (ox) in the image: the tracked pixel follows it exactly
        xs = [f.point.x for f in fixes]
        assert np.allclose(np.diff(xs), 2.0, atol=0.05)
        assert len(node.history) >= 10 and all(len(j.name) == 2 for j in joints_seen)
        assert len(joints_seen) == 15     # only ours: a passive node publishes no joint states
        cli = peer.create_client(Trigger, '/camera_node/home')
        assert cli.wait_for_service(timeout_sec=2.0)
        fut = cli.call_async(Trigger.Request())
        assert spin_until(ex, fut.done, timeout_s=3.0) and not fut.result().success
    finally:
        ex.shutdown(timeout_sec=1.0)
        node.destroy_node()
        peer.destroy_node()


def test_left_node_vergence_on_start_measures_the_right_fixation_distance(ros_context, tmp_path):
    """Simulated rig (frozen) + both camera nodes over VISCA ptys; the left node's start-up vergence step
    publishes the right fixation point's distance, which the simulator's ray cast confirms."""
    import time

    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from fixego_ros.geometry.rig import default_rig_path, load_rig
    from fixego_ros.nodes.common import LATCHED_QOS
    from fixego_ros.nodes.sim_rig_node import SimRigNode
    from fixego_ros.sim.run import resize_rig

    rig_path = tmp_path / 'rig.yaml'
    resize_rig(load_rig(default_rig_path()), 320, 240).save(rig_path)
    sim = SimRigNode(context=ros_context, parameter_overrides=[
        Parameter('trajectory', value='paper'), Parameter('time_scale', value=0.0), Parameter('fps', value=15.0),
        Parameter('rig_file', value=str(rig_path)), Parameter('exit_at_end', value=False),
        Parameter('pty_file', value=str(tmp_path / 'ptys.json'))])
    common = [Parameter('rig_file', value=str(rig_path)), Parameter('search_radius_px', value=30.0),
              Parameter('border_margin_px', value=25.0)]
    right = CameraNode(context=ros_context, cli_args=['--ros-args', '-r', '__node:=right_camera_node'],
                       parameter_overrides=[Parameter('side', value='right'),
                                            Parameter('port', value=sim.ptys['right']), *common])
    left = CameraNode(context=ros_context, cli_args=['--ros-args', '-r', '__node:=left_camera_node'],
                      parameter_overrides=[Parameter('side', value='left'), Parameter('port', value=sim.ptys['left']),
                                           Parameter('vergence_on_start', value=True),
                                           Parameter('vergence_timeout_s', value=30.0), *common])
    probe = rclpy.create_node('vergence_probe', context=ros_context)
    ex = executor_for(ros_context, sim, right, left, probe)
    got: list[PoseWithCovarianceStamped] = []
    diags: list[DiagnosticArray] = []
    lfix: list[PointStamped] = []
    probe.create_subscription(PoseWithCovarianceStamped, '/fixego/vergence', got.append, LATCHED_QOS)
    probe.create_subscription(DiagnosticArray, '/diagnostics', diags.append, RELIABLE_QOS)
    probe.create_subscription(PointStamped, '/fixego/left/fixation', lfix.append, RELIABLE_QOS)
    t0 = time.monotonic()
    try:
        assert spin_until(ex, lambda: bool(got), timeout_s=40.0, step_s=0.01), \
            f'no /fixego/vergence; left state: {left.vergence_state}'
        t_step = time.monotonic() - t0
        msg = got[0]
        assert msg.header.frame_id == 'rig'
        p = np.array([msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z])
        cov = np.array(msg.pose.covariance).reshape(6, 6)[:3, :3]
        dist = float(np.linalg.norm(p))
        std = float(np.sqrt(p @ cov @ p) / dist)
        # truth: the simulator's ray cast along the published direction from the right camera centre
        pose = sim.trajectory.pose_at(0.0)
        true_dist, _ = sim.renderer.world.raycast(pose.t, pose.R @ (p / dist))
        err = dist - true_dist
        print(f'vergence: true {true_dist:.3f} m, estimated {dist:.3f} m (err {100 * err / true_dist:+.2f} %), '
              f'std {std:.3f} m, {t_step:.1f} s after start')
        assert abs(err) < 0.05 * true_dist
        assert 0.0 < std < 0.1 * true_dist
        assert np.all(np.isfinite(np.array(msg.pose.covariance)))
        # the left node goes back to independent fixation: a new fixation id, and a 'done' status
        assert spin_until(ex, lambda: left.vergence is not None and left.vergence.finished, timeout_s=10.0)
        n = len(lfix)
        assert spin_until(ex, lambda: len(lfix) > n + 3, timeout_s=5.0)
        assert int(lfix[-1].point.z) == max(int(f.point.z) for f in lfix)
        assert left.tracker.reselections[-1].reason == 'vergence_end'
        assert spin_until(ex, lambda: any(s.name.endswith('left: vergence') and s.message.startswith('done')
                                          for d in diags for s in d.status), timeout_s=3.0)
    finally:
        ex.shutdown(timeout_sec=1.0)
        for n in (left, right, probe):
            n.destroy_node()
        sim.close()
        sim.destroy_node()
