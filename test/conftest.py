"""Shared fixtures. ROS tests get a private rclpy context on a private domain id, so they never see
other ROS traffic, and DDS discovery stays on localhost."""

from __future__ import annotations

import os
import random

import pytest

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('MPLBACKEND', 'Agg')


def private_domain_id() -> int:
    """A domain id unlikely to collide with anything else on this machine (0..101 and 215..232 valid)."""
    return random.Random(os.getpid()).randint(120, 200)


@pytest.fixture(scope='session')
def _ros_session():
    """The session's rclpy Context (see :func:`ros_context`) and a node of its own that outlives every test's."""
    rclpy = pytest.importorskip('rclpy')
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx, domain_id=private_domain_id())
    keeper = rclpy.create_node('fixego_test_session', context=ctx)
    try:
        yield ctx
    finally:
        keeper.destroy_node()
        if ctx.ok():
            rclpy.shutdown(context=ctx)


@pytest.fixture
def ros_context(_ros_session):
    """An initialised rclpy Context on a private domain, shared by the session's ROS tests (each destroys its nodes).

    Why shared, with a node that outlives the tests': deleting a context's last node deletes its Fast DDS
    participant, and the Fast DDS 2.14 of the wheels can spin there for ever (eProsima/Fast-DDS#6513; at stop 87
    ``make test`` hung 20 min in a test that created a node and destroyed it at once, one context per test then).
    So a session deletes one participant, not one per test."""
    if not _ros_session.ok():
        pytest.fail('the session\'s rclpy context was shut down by an earlier test')
    return _ros_session


def executor_for(context, *nodes, factory=None):
    """A SingleThreadedExecutor on ``context`` spinning ``nodes`` (the node under test and its peers), or the one
    ``factory(context)`` makes (a node's own, e.g. ``events_executor``)."""
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=context) if factory is None else factory(context)
    for n in nodes:
        ex.add_node(n)
    return ex


def spin_until(executor, predicate, timeout_s: float = 5.0, step_s: float = 0.02) -> bool:
    """Spin ``executor`` until ``predicate()`` is true or ``timeout_s`` passes; returns the predicate."""
    import time
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=step_s)
    return bool(predicate())


@pytest.fixture
def visca_rig():
    """A VISCA camera emulator on a pty (EVI-D30, 115200 baud) and our driver connected to it."""
    from fixego_ros.visca.driver import ViscaCamera
    from fixego_ros.visca.emulator import ViscaEmulator
    emu = ViscaEmulator('evi_d30', baud=115200)
    port = emu.start()
    cam = ViscaCamera(port, baud=115200, timeout_s=0.2, backoff_s=(0.02, 0.2)).open()
    yield emu, cam
    cam.close()
    emu.stop()


class DriftingView:
    """A peer node that shows the right camera a synthetic textured view drifting at 12 / -6 px/s (from 30 / -20
    px off centre), rendered at 30 Hz at the emulated head's angles, and collects what the camera node
    publishes. ``kinematic`` maps the device angles to the rendered ones (the rig file's calibration); ``truth``
    maps each image stamp to (device pan, tilt, drift x, y). Call :meth:`publish_frame` in a spin predicate."""

    def __init__(self, context, node, emu, seed: int, kinematic=None) -> None:
        import time

        import rclpy
        from geometry_msgs.msg import PointStamped
        from sensor_msgs.msg import Image, JointState

        from fixego_ros.bench.servo import SyntheticView
        from fixego_ros.nodes.common import RELIABLE_QOS, SENSOR_QOS
        self.node, self.emu = node, emu
        self.kinematic = kinematic or (lambda pan, tilt: (pan, tilt))
        self.peer = rclpy.create_node('peer', context=context)
        self.fixes: list = []           # valid fixations (id >= 0)
        self.no_fixes: list = []        # the node's "no valid fixation at this stamp" messages (id -1)
        self.joints: list = []
        self.truth: dict[tuple[int, int], tuple[float, float, float, float]] = {}
        self.peer.create_subscription(PointStamped, '/fixego/right/fixation',
                                      lambda m: (self.fixes if m.point.z >= 0 else self.no_fixes).append(m),
                                      RELIABLE_QOS)
        self.peer.create_subscription(JointState, '/fixego/right/joint_states', self.joints.append, RELIABLE_QOS)
        self.pub = self.peer.create_publisher(Image, '/fixego/right/image_raw', SENSOR_QOS)
        self.view = SyntheticView(node.rig.camera('right'), seed=seed)
        self.t0 = self._next = time.monotonic()

    def publish_frame(self) -> bool:
        """Publish the next image when it is due; always False (for use in ``spin_until`` predicates)."""
        import time

        from fixego_ros.nodes.common import array_to_image, sec_to_stamp
        now = time.monotonic()
        if now >= self._next:
            self._next = now + 1 / 30
            el = now - self.t0
            ox, oy = 30.0 + 12.0 * el, -20.0 - 6.0 * el      # start off-centre, then drift
            pan, tilt = self.emu.pan_tilt_rad(now)
            stamp = sec_to_stamp(self.node.get_clock().now().nanoseconds * 1e-9)
            self.truth[(stamp.sec, stamp.nanosec)] = (pan, tilt, ox, oy)
            self.pub.publish(array_to_image(self.view.render(*self.kinematic(pan, tilt), ox, oy), stamp,
                                            'right_optical_frame'))
        return False


def perturb_resection(monkeypatch, k_bad: int, turn_deg: float) -> None:
    """Frame ``k_bad``'s resection turns the rig ``turn_deg`` further about its vertical axis than it found (the
    wrong minimum of a one-camera pose fit; docs/results.md "Stop 72")."""
    import math

    import numpy as np

    from fixego_ros.estimation.smoother import Smoother
    from fixego_ros.geometry.rotation import exp_so3

    resect = Smoother._resect
    turn = exp_so3(np.array([0.0, math.radians(turn_deg), 0.0]))

    def bad(self, obs, start):
        pose = resect(self, obs, start)
        return type(pose)(pose.R @ turn, pose.t) if self._index == k_bad else pose

    monkeypatch.setattr(Smoother, '_resect', bad)
