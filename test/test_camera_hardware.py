"""camera_node and the hardware it cannot see: the camera model behind the port, and a head mounted inverted.

Model check (in-process node, private context, the VISCA emulator on a pty): on connect the node asks
CAM_VersionInq; a match is logged once; another model is one error line naming expected and found and an ERROR
on /diagnostics (fatal with ``require_model_match``); no answer is a warning and the node carries on; a
re-connect asks again.

Inversion: a head whose device angles run against the kinematics (``pan_sign = tilt_sign = -1`` in the rig
file, e.g. mounted upside down with the camera's image flip on) must still be servoed onto its fixation point,
and its joint states stay device angles.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from conftest import DriftingView, executor_for, spin_until  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from fixego_ros.geometry.rig import CameraModel, PanTiltCalibration, Rig, pan_tilt_rotation  # noqa: E402
from fixego_ros.nodes.camera_node import CameraNode  # noqa: E402
from fixego_ros.nodes.common import RELIABLE_QOS  # noqa: E402
from fixego_ros.pipeline.params import ParamsError  # noqa: E402
from fixego_ros.tracking.servo import FixationServo, ServoParams, centring_angles  # noqa: E402
from fixego_ros.visca.emulator import ViscaEmulator  # noqa: E402
from fixego_ros.visca.profiles import PROFILES  # noqa: E402

CAM = CameraModel(320, 240, 500.0, 500.0, 159.5, 119.5)
D70 = (0x0020, 0x040E, 0x0100, 2)
INVERTED = PanTiltCalibration(pan_sign=-1.0, tilt_sign=-1.0)


@pytest.fixture
def rig_file(tmp_path):
    path = tmp_path / 'rig.yaml'
    Rig(CAM, CAM).save(path)
    return str(path)


class _Log:
    """Stands in for the node's logger from its constructor on: keeps (level, text), passes everything on."""

    def __init__(self, logger) -> None:
        self._logger, self.lines = logger, []

    # one method per level: rclpy's logger tells call sites apart by their frame and line
    def info(self, text, *args, **kwargs):
        self.lines.append(('info', str(text)))
        return self._logger.info(text, *args, **kwargs)

    def warning(self, text, *args, **kwargs):
        self.lines.append(('warning', str(text)))
        return self._logger.warning(text, *args, **kwargs)

    def error(self, text, *args, **kwargs):
        self.lines.append(('error', str(text)))
        return self._logger.error(text, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._logger, name)

    def about_model(self) -> list[tuple[str, str]]:
        return [(lv, t) for lv, t in self.lines if 'CAM_VersionInq' in t or 'camera model' in t
                or 'matches profile' in t or 'answers model' in t]


@pytest.fixture
def node_log(monkeypatch):
    log = _Log(rclpy.logging.get_logger('camera_node'))
    monkeypatch.setattr(CameraNode, 'get_logger', lambda self: log)
    return log


def _node(ctx, port, rig_file, **params) -> CameraNode:
    values = {'side': 'right', 'port': port, 'baud': 115200, 'rig_file': rig_file, 'diagnostics_period_s': 0.1,
              **params}
    return CameraNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])


def _model_status(diags: list[DiagnosticArray]) -> DiagnosticStatus | None:
    for d in reversed(diags):
        for st in d.status:
            if st.name == 'fixego camera_node right: camera model':
                return st
    return None


def _values(st: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in st.values}


def test_mismatch_is_one_error_line_and_an_error_status_and_a_reconnect_checks_again(ros_context, rig_file,
                                                                                    node_log):
    with ViscaEmulator('evi_d30', baud=115200) as emu:
        emu.faults.version_override = D70            # an EVI-D70 answering behind the evi_d30 profile
        node = _node(ros_context, emu.link_path, rig_file)
        probe = rclpy.create_node('probe', context=ros_context)
        diags: list[DiagnosticArray] = []
        probe.create_subscription(DiagnosticArray, '/diagnostics', diags.append, RELIABLE_QOS)
        ex = executor_for(ros_context, node, probe)
        try:
            assert node.model_check.outcome == 'mismatch'
            lines = node_log.about_model()
            assert len(lines) == 1 and lines[0][0] == 'error', lines
            assert 'expects model 0x0402' in lines[0][1] and 'answers model 0x040e (EVI-D70/P)' in lines[0][1]
            assert spin_until(ex, lambda: _model_status(diags) is not None, timeout_s=5.0)
            st = _model_status(diags)
            assert st.level == DiagnosticStatus.ERROR and 'mismatch' in st.message
            assert _values(st)['camera_model'] == '0x040e' and _values(st)['expected_models'] == '0x0402'
            # the node carries on: the servo loop reads the head
            n = len(node.history)
            assert spin_until(ex, lambda: len(node.history) > n + 5, timeout_s=5.0)
            # the camera is swapped for the right model while unplugged: asked again on reconnect, logged once
            emu.faults.version_override = None
            emu.faults.disconnect(0.3)
            assert spin_until(ex, lambda: node.model_check.outcome == 'match', timeout_s=10.0)
            assert node.driver.stats['reconnects'] >= 1
            assert spin_until(ex, lambda: _model_status(diags).level == DiagnosticStatus.OK, timeout_s=5.0)
            lines = node_log.about_model()
            assert len(lines) == 2 and lines[1][0] == 'info' and 'matches profile evi_d30' in lines[1][1], lines
        finally:
            ex.shutdown(timeout_sec=1.0)
            node.destroy_node()
            probe.destroy_node()


def test_a_matching_camera_is_logged_once(ros_context, rig_file, node_log):
    with ViscaEmulator('evi_d30', baud=115200) as emu:
        node = _node(ros_context, emu.link_path, rig_file)
        ex = executor_for(ros_context, node)
        try:
            assert node.model_check.outcome == 'match'
            emu.faults.disconnect(0.2)                   # the same camera again after a reconnect: not repeated
            assert spin_until(ex, lambda: node.driver.stats['reconnects'] >= 1
                              and node._model_checked == node.driver.stats['reconnects'], timeout_s=10.0)
            lines = node_log.about_model()
            assert len(lines) == 1 and lines[0][0] == 'info' and 'model 0x0402' in lines[0][1], lines
        finally:
            ex.shutdown(timeout_sec=1.0)
            node.destroy_node()


def test_require_model_match_makes_a_mismatch_fatal(ros_context, rig_file, node_log):
    with ViscaEmulator('evi_d30', baud=115200) as emu:
        emu.faults.version_override = D70
        with pytest.raises(ParamsError, match=r'require_model_match is true.*expects model 0x0402.*0x040e'):
            _node(ros_context, emu.link_path, rig_file, require_model_match=True)
        # the default does not stop it
        node = _node(ros_context, emu.link_path, rig_file, require_model_match=False)
        node.destroy_node()


@pytest.mark.parametrize('fault', ['silent', 'syntax_error'])
def test_no_answer_to_the_version_inquiry_warns_and_carries_on(ros_context, rig_file, node_log, fault):
    with ViscaEmulator('evi_d30', baud=115200) as emu:
        emu.faults.version_reply = fault             # old firmware
        t0 = time.monotonic()
        node = _node(ros_context, emu.link_path, rig_file, require_model_match=True, serial_timeout_s=0.2)
        assert time.monotonic() - t0 < 5.0
        probe = rclpy.create_node('probe', context=ros_context)
        diags: list[DiagnosticArray] = []
        probe.create_subscription(DiagnosticArray, '/diagnostics', diags.append, RELIABLE_QOS)
        ex = executor_for(ros_context, node, probe)
        try:
            assert spin_until(ex, lambda: node._model_checked == 0, timeout_s=5.0)     # silence: asked 3 times
            assert node.model_check.outcome == 'no_answer'
            assert node._model_tries == (0, 1 if fault == 'syntax_error' else 3)     # a refusal is final at once
            lines = node_log.about_model()
            assert len(lines) == 1 and lines[0][0] == 'warning' and 'CAM_VersionInq' in lines[0][1], lines
            assert spin_until(ex, lambda: getattr(_model_status(diags), 'level', None) == DiagnosticStatus.WARN,
                              timeout_s=5.0)
            n = len(node.history)
            assert spin_until(ex, lambda: len(node.history) > n + 5, timeout_s=5.0)
        finally:
            ex.shutdown(timeout_sec=1.0)
            node.destroy_node()
            probe.destroy_node()


# ------------------------------------------------------------------------------ an inverted head
def _closed_loop(world: PanTiltCalibration, servo_cal: PanTiltCalibration | None, steps: int = 12) -> list[float]:
    """Pixel error (px) per command of a servo on a head whose device angles map to the kinematics by ``world``;
    the head reaches each target before the next image."""
    profile = PROFILES['evi_d30']
    servo = FixationServo(CAM, profile, ServoParams(feedforward=False), servo_cal)
    d = pan_tilt_rotation(0.25, -0.12) @ np.array([0.0, 0.0, 1.0])     # the fixated scene point's direction
    joints = world.reading(0.2, -0.08)                                   # near it, in device angles
    errors = []
    for k in range(steps):
        ray = pan_tilt_rotation(*world.kinematic(*joints)).T @ d
        pixel = CAM.rays_to_pixels(ray.reshape(1, 3))[0]
        errors.append(float(math.hypot(pixel[0] - CAM.cx, pixel[1] - CAM.cy)))
        target = servo.target((float(pixel[0]), float(pixel[1])), joints, 0.1 * k, 0.1 * k)
        if target is None:
            continue
        joints = (profile.pan_rad(target.pan), profile.tilt_rad(target.tilt))
    return errors


def test_feedforward_aims_where_the_point_will_be_at_the_next_command():
    """An absolute-position head stops at each target and gets the next one a command period later: the target
    leads a drifting point by its rate times (image age + lead_extra_s + one command period). Leading by the age
    and lead_extra_s alone left the point trailing on every turn (bench.servo at 14 deg/s: 34 px mean, now 9)."""
    profile = PROFILES['evi_d30']
    p = ServoParams(gain=1.0, deadband_px=0.0)
    servo = FixationServo(CAM, profile, p)
    age, rate = 0.01, math.radians(10.0)
    wants = []
    for k in range(8):          # the point drifts in pan at ``rate`` while the head stands at 0
        t = k / 30.0
        pixel = (CAM.cx + CAM.fx * math.tan(rate * t), CAM.cy)
        wants.append(centring_angles(CAM, pixel, 0.0, 0.0)[0])
        target = servo.target(pixel, (0.0, 0.0), t, t + age)
    fitted = (wants[-1] - wants[0]) / (7 / 30.0)
    lead = age + p.lead_extra_s + 1.0 / p.max_command_rate_hz
    assert abs(fitted) > 0.9 * rate
    assert abs(target.pan - profile.pan_units(math.degrees(wants[-1] + fitted * lead))) <= 1


def test_a_seeded_rate_leads_a_new_point_before_its_images_give_one():
    """A vergence step's partner point drifts with the right head: reset with that rate, the first target already
    leads it (it was taken for still until four images had given a rate: up to 100 px behind on an arc); without a
    seed the first target is the plain centring one."""
    profile = PROFILES['evi_d30']
    p = ServoParams(gain=1.0, deadband_px=0.0)
    rate = math.radians(22.0)
    pixel = (CAM.cx + 30.0, CAM.cy)
    want = centring_angles(CAM, pixel, 0.0, 0.0)[0]
    lead = 0.01 + p.lead_extra_s + 1.0 / p.max_command_rate_hz
    servo = FixationServo(CAM, profile, p)
    servo.reset((rate, 0.0))
    seeded = servo.target(pixel, (0.0, 0.0), 0.0, 0.01)
    assert abs(seeded.pan - profile.pan_units(math.degrees(want + rate * lead))) <= 1
    servo.reset()
    plain = servo.target(pixel, (0.0, 0.0), 0.0, 0.01)
    assert abs(plain.pan - profile.pan_units(math.degrees(want))) <= 1
    assert servo.rate == (0.0, 0.0)


@pytest.mark.parametrize('world', [PanTiltCalibration(), INVERTED, PanTiltCalibration(-1.0, 1.0, 0.05, 0.0),
                                   PanTiltCalibration(1.0, -1.0, 0.0, -0.03)],
                         ids=['upright', 'inverted', 'pan_inverted_offset', 'tilt_inverted_offset'])
def test_servo_centres_the_point_whatever_the_signs(world):
    errors = _closed_loop(world, world)
    assert errors[0] > 20.0 and errors[-1] < 1.0, errors


def test_a_servo_ignoring_the_signs_drives_an_inverted_head_away():
    """The control for the test above: the same loop without the rig's signs runs off (so it can fail)."""
    errors = _closed_loop(INVERTED, None, steps=4)
    assert errors[-1] > 3 * errors[0], errors


def test_camera_node_servoes_an_inverted_head_and_publishes_device_angles(ros_context, tmp_path):
    """Rig file with pan_sign = tilt_sign = -1 for the right head: the rendered view follows the kinematic angles
    (minus the device's), the node must bring its point to the centre and hold it while the scene drifts, and
    its joint states are the device's angles (the bag contract), not the kinematic ones."""
    rig_path = tmp_path / 'rig.yaml'
    Rig(CAM, CAM, pan_tilt_right=INVERTED).save(rig_path)
    with ViscaEmulator('evi_d30', baud=115200) as emu:
        node = _node(ros_context, emu.link_path, str(rig_path), search_radius_px=30.0, border_margin_px=25.0,
                     vergence_enabled=False)
        scene = DriftingView(ros_context, node, emu, seed=5, kinematic=INVERTED.kinematic)
        peer, fixes, joints, truth, view = scene.peer, scene.fixes, scene.joints, scene.truth, scene.view
        ex = executor_for(ros_context, node, peer)
        try:
            spin_until(ex, lambda: scene.publish_frame() or time.monotonic() - scene.t0 > 4.0, timeout_s=10.0,
                       step_s=0.005)
            assert fixes and joints, 'node published nothing'
            assert {int(f.point.z) for f in fixes} == {0}
            f0 = fixes[0]
            key0 = (f0.header.stamp.sec, f0.header.stamp.nanosec)
            scene = view.scene_point((f0.point.x, f0.point.y), *INVERTED.kinematic(*truth[key0][:2]),
                                     *truth[key0][2:])
            t_first = f0.header.stamp.sec + 1e-9 * f0.header.stamp.nanosec
            late = [f for f in fixes if f.header.stamp.sec + 1e-9 * f.header.stamp.nanosec > t_first + 2.0]
            assert len(late) > 20
            errs = []
            for f in late:
                pan, tilt, ox, oy = truth[(f.header.stamp.sec, f.header.stamp.nanosec)]
                px = view.pixel_of(scene, *INVERTED.kinematic(pan, tilt), ox, oy)
                errs.append(math.hypot(px[0] - CAM.cx, px[1] - CAM.cy))
            assert np.mean(errs) < 3.0 and max(errs) < 6.0, f'error mean {np.mean(errs):.2f} max {max(errs):.2f} px'
            # the head turned the device's way: negative pan (kinematic +) to follow the scene drifting right
            jerr, pans = [], []
            for j in joints:
                pan, tilt = truth[(j.header.stamp.sec, j.header.stamp.nanosec)][:2]
                jerr.append(max(abs(j.position[0] - pan), abs(j.position[1] - tilt)))
                pans.append(j.position[0])
            assert math.degrees(float(np.percentile(jerr, 95))) < 0.2
            assert min(pans) < -math.radians(3.0), math.degrees(min(pans))
        finally:
            ex.shutdown(timeout_sec=1.0)
            node.destroy_node()
            peer.destroy_node()
