"""``spin_node`` runs a node on the executor it is given until the node says it is finished or the context shuts
down, with either executor the nodes use (the Python ``SingleThreadedExecutor`` and rclpy's C++ ``EventsExecutor``
for the simulated rig and the camera nodes), and a node process ends promptly and cleanly on SIGINT and SIGTERM."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from std_msgs.msg import Int32

from fixego_ros.nodes.common import RELIABLE_QOS, events_executor, spin_node


def _echo_node():
    """A node that publishes a count on a 20 ms timer and counts what it receives of it."""
    from rclpy.node import Node

    node = Node('spin_test')
    node.sent, node.got = 0, []
    pub = node.create_publisher(Int32, 'spin_test_count', RELIABLE_QOS)
    node.create_subscription(Int32, 'spin_test_count', lambda m: node.got.append(m.data), RELIABLE_QOS)

    def tick() -> None:
        pub.publish(Int32(data=node.sent))
        node.sent += 1
    node.create_timer(0.02, tick)
    return node


@pytest.mark.parametrize('executor', [None, events_executor], ids=['single_threaded', 'events'])
def test_spin_node_delivers_timers_and_messages_until_the_node_is_finished(executor):
    t0 = time.monotonic()
    node = spin_node(_echo_node, [], finished=lambda n: len(n.got) >= 10, domain_id=87, executor=executor)
    assert time.monotonic() - t0 < 30.0
    assert node.got[:10] == list(range(node.got[0], node.got[0] + 10))     # in order, none lost (reliable)
    assert node.sent >= 10


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_a_camera_node_on_the_events_executor_ends_at_once_on_a_signal(sig, tmp_path):
    env = {**os.environ, 'ROS_DOMAIN_ID': '88', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    proc = subprocess.Popen([sys.executable, '-P', '-m', 'fixego_ros.nodes.camera_node', '--ros-args',
                             '-p', 'side:=right', '-p', f'port:={tmp_path / "no_such_port"}'],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        deadline = time.monotonic() + 60.0
        lines = []
        while time.monotonic() < deadline:      # spinning once it has logged its thread note
            line = proc.stdout.readline()
            lines.append(line)
            if 'compute threads' in line or not line:
                break
        assert any('compute threads' in s for s in lines), ''.join(lines)
        time.sleep(0.5)
        proc.send_signal(sig)
        assert proc.wait(timeout=10.0) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10.0)


def test_a_node_whose_teardown_hangs_ends_after_the_limit():
    """A teardown that never returns (Fast DDS can spin for ever deleting a participant, holding the GIL) ends the
    process with exit code 1 and the tracebacks on stderr, after ``TEARDOWN_LIMIT_S``; without the bound it would
    run until killed."""
    code = """
import fixego_ros.nodes.common as common
from rclpy.node import Node

class Stuck(Node):
    def destroy_node(self):
        while True:         # holds the GIL, as the C call does
            pass

common.TEARDOWN_LIMIT_S = 1.0
common.spin_node(lambda: Stuck('stuck_teardown'), [], finished=lambda n: True, domain_id=89)
print('returned')
"""
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 1, (p.returncode, p.stdout, p.stderr)
    assert 'returned' not in p.stdout
    assert 'destroy_node' in p.stderr and 'Timeout' in p.stderr, p.stderr
    assert time.monotonic() - t0 < 60.0


def test_a_normal_teardown_leaves_no_watchdog_armed():
    """After a clean teardown the process goes on: the watchdog is cancelled, not left to kill it later."""
    code = """
import time
import fixego_ros.nodes.common as common
from rclpy.node import Node
common.TEARDOWN_LIMIT_S = 1.0
common.spin_node(lambda: Node('clean_teardown'), [], finished=lambda n: True, domain_id=89)
time.sleep(2.0)
print('alive')
"""
    p = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and 'alive' in p.stdout, (p.returncode, p.stdout, p.stderr)
