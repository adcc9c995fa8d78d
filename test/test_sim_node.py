"""sim_rig_node: images follow VISCA commands sent to its emulated heads over their ptys."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
serial = pytest.importorskip('serial')

from conftest import executor_for, spin_until  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402


def _nibbles(value: int) -> bytes:
    v = value & 0xFFFF
    return bytes([(v >> 12) & 0xF, (v >> 8) & 0xF, (v >> 4) & 0xF, v & 0xF])


def _absolute_position(pan_units: int, tilt_units: int) -> bytes:
    """VISCA Pan-tiltDrive AbsolutePosition for camera 1 at full speed (raw bytes, independent of our driver)."""
    return bytes([0x81, 0x01, 0x06, 0x02, 0x18, 0x14]) + _nibbles(pan_units) + _nibbles(tilt_units) + b'\xff'


def _read_until_completion(port, timeout_s: float = 5.0) -> list[bytes]:
    """Packets up to the completion ``90 5y FF``; fails on an error reply or timeout."""
    deadline = time.monotonic() + timeout_s
    buf, packets = b'', []
    while time.monotonic() < deadline:
        buf += port.read(port.in_waiting or 1)
        while b'\xff' in buf:
            pkt, buf = buf[:buf.index(b'\xff') + 1], buf[buf.index(b'\xff') + 1:]
            packets.append(pkt)
            assert pkt[1] & 0xF0 != 0x60, f'VISCA error reply {pkt.hex()}'
            if pkt[1] & 0xF0 == 0x50:
                return packets
    raise AssertionError(f'no completion within {timeout_s} s; got {[p.hex() for p in packets]}')


@pytest.mark.parametrize('events', [False, True], ids=['single_threaded', 'events'])
def test_images_follow_visca_commands(ros_context, tmp_path, events):
    """On the Python executor and on the C++ one the node's main() spins it with."""
    from sensor_msgs.msg import CameraInfo, Image, JointState

    from fixego_ros.nodes.common import RELIABLE_QOS, SENSOR_QOS, events_executor, image_to_gray
    from fixego_ros.nodes.sim_rig_node import SimRigNode

    pty_file = tmp_path / 'ptys.json'
    overrides = [Parameter('trajectory', value='straight'), Parameter('time_scale', value=0.0),
                 Parameter('noise_sigma', value=0.0), Parameter('width', value=160),
                 Parameter('height', value=120), Parameter('texel', value=0.006), Parameter('fps', value=20.0),
                 Parameter('pty_file', value=str(pty_file)), Parameter('exit_at_end', value=False),
                 Parameter('pty_link_dir', value=str(tmp_path / 'links' / 'run'))]
    node = SimRigNode(context=ros_context, parameter_overrides=overrides)
    links = {side: tmp_path / 'links' / 'run' / side for side in ('right', 'left')}
    probe = rclpy.create_node('probe', context=ros_context)
    ex = executor_for(ros_context, node, probe, factory=events_executor if events else None)
    images: dict[str, list[Image]] = {'right': [], 'left': []}
    infos: list[CameraInfo] = []
    for side in images:
        probe.create_subscription(Image, f'/fixego/{side}/image_raw',
                                  lambda m, s=side: images[s].append(m), SENSOR_QOS)
    probe.create_subscription(CameraInfo, '/fixego/right/camera_info', infos.append, SENSOR_QOS)
    true_joints: list[JointState] = []
    probe.create_subscription(JointState, '/fixego/ground_truth/right/joint_states', true_joints.append, RELIABLE_QOS)
    try:
        ptys = json.loads(pty_file.read_text())
        assert set(ptys) == {'right', 'left'} and ptys == node.ptys
        assert all(os.path.realpath(links[s]) == os.path.realpath(ptys[s]) for s in ptys)
        assert spin_until(ex, lambda: images['right'] and images['left'] and infos, 10.0)
        assert (images['right'][-1].width, images['right'][-1].height) == (160, 120)
        assert infos[-1].k[0] == pytest.approx(1727.0 / 4)
        pose = node.trajectory.pose_at(0.0)
        emu = node.emulators['right']

        def expected(side: str) -> np.ndarray:
            pan, tilt = node.emulators[side].pan_tilt_rad()
            return node.renderer.render(side, pose, pan, tilt, noise=False)

        before = image_to_gray(images['right'][-1]).astype(int)
        assert np.abs(before - expected('right')).mean() < 0.5  # rendered at the head's start pose (20, 0)
        left_before = image_to_gray(images['left'][-1]).astype(int)

        with serial.Serial(str(links['right']), 9600, timeout=0.05) as port:    # through the pty link
            port.write(_absolute_position(-88, 60))  # pan -10 deg, tilt +5 deg (EVI-D30 units)
            port.flush()
            replies = _read_until_completion(port)
        assert replies[0][1] & 0xF0 == 0x40  # ACK first
        pan_deg, tilt_deg = emu.pan_tilt_deg()
        assert pan_deg == pytest.approx(-10.0, abs=0.2) and tilt_deg == pytest.approx(5.0, abs=0.2)
        t_done = node.get_clock().now().nanoseconds
        n = len(images['right'])

        def fresh():
            return [m for m in images['right'][n:]
                    if m.header.stamp.sec * 10**9 + m.header.stamp.nanosec > t_done]

        assert spin_until(ex, lambda: len(fresh()) >= 1, 5.0)
        after = image_to_gray(fresh()[-1]).astype(int)
        assert np.abs(after - before).mean() > 10  # the view moved with the head
        assert np.abs(after - expected('right')).mean() < 0.5  # exactly what the new angles show
        # the true angles at each image stamp: the start pose before the move, the commanded one after it
        stamps = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in images['right']}
        assert spin_until(ex, lambda: any(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec > t_done
                                          for m in true_joints), 5.0)
        assert all(m.name == ['right_pan', 'right_tilt'] for m in true_joints)
        assert np.degrees(true_joints[0].position) == pytest.approx([node.p['start_pan_deg_right'], 0.0], abs=0.01)
        assert np.degrees(true_joints[-1].position) == pytest.approx([pan_deg, tilt_deg], abs=0.01)
        last_image = max(stamps)
        assert spin_until(ex, lambda: any(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == last_image
                                          for m in true_joints), 5.0)      # one per image, at its stamp
        # the other camera did not move
        assert spin_until(ex, lambda: len(images['left']) > n + 1, 5.0)
        assert np.abs(image_to_gray(images['left'][-1]).astype(int) - left_before).mean() < 0.5
    finally:
        ex.shutdown()
        node.close()
        node.destroy_node()
        probe.destroy_node()
    assert not pty_file.exists()  # removed on close
    assert not any(p.is_symlink() for p in links.values())


def test_node_finishes_at_trajectory_end(ros_context, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped

    from fixego_ros.nodes.common import RELIABLE_QOS
    from fixego_ros.nodes.sim_rig_node import SimRigNode

    overrides = [Parameter('trajectory', value='straight'), Parameter('duration', value=0.6),
                 Parameter('time_scale', value=2.0), Parameter('width', value=80), Parameter('height', value=60),
                 Parameter('texel', value=0.006), Parameter('fps', value=20.0),
                 Parameter('pty_file', value=str(tmp_path / 'p.json'))]
    node = SimRigNode(context=ros_context, parameter_overrides=overrides)
    probe = rclpy.create_node('probe2', context=ros_context)
    ex = executor_for(ros_context, node, probe)
    gts: list[PoseStamped] = []
    diags: list[DiagnosticArray] = []
    probe.create_subscription(PoseStamped, '/fixego/ground_truth/pose', gts.append, RELIABLE_QOS)
    probe.create_subscription(DiagnosticArray, '/diagnostics', diags.append, RELIABLE_QOS)
    try:
        assert spin_until(ex, lambda: node.finished, 5.0)
        assert spin_until(ex, lambda: any(s.message == 'trajectory finished' for d in diags for s in d.status),
                          2.0)
        assert len(gts) >= 3 and gts[0].header.frame_id == 'odom'
        p, q = gts[0].pose.position, gts[0].pose.orientation
        assert (p.x, p.y, p.z, q.x, q.y, q.z) == pytest.approx((0.0,) * 6, abs=1e-12)  # odom = first frame
        assert q.w == pytest.approx(1.0)
        # straight ahead along base_link x, ~1.2 s of trajectory at up to 0.2 m/s
        assert 0.0 < gts[-1].pose.position.x < 0.25 and abs(gts[-1].pose.position.y) < 1e-9
    finally:
        ex.shutdown()
        node.close()
        node.destroy_node()
        probe.destroy_node()
