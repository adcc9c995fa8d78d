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


@pytest.fixture
def ros_context():
    """An initialised rclpy Context on a private domain, shut down after the test."""
    rclpy = pytest.importorskip('rclpy')
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx, domain_id=private_domain_id())
    try:
        yield ctx
    finally:
        if ctx.ok():
            rclpy.shutdown(context=ctx)


def executor_for(context, *nodes):
    """A SingleThreadedExecutor on ``context`` spinning ``nodes`` (the node under test and its peers)."""
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=context)
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
