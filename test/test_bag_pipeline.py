"""A shipped bag through ``bag_player`` into the live nodes (separate processes over DDS, sim time),
recorded on the way by ``fixego record`` and the recording replayed offline: the whole bag round trip."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import executor_for, private_domain_id, spin_until

from fixego_ros.evaluation.metrics import evaluate
from fixego_ros.evaluation.tum import read_tum

WALK = Path(__file__).resolve().parents[1] / 'bags' / 'walk'
INPUTS = ['/fixego/right/image_raw', '/fixego/left/image_raw', '/fixego/right/joint_states',
          '/fixego/left/joint_states', '/fixego/ground_truth/pose']


def test_bag_player_drives_live_nodes_and_recording_replays(ros_context, tmp_path):
    from geometry_msgs.msg import PoseStamped
    from rclpy.node import Node

    from fixego_ros.demo.launcher import Launcher, NodeSpec
    from fixego_ros.nodes.common import RELIABLE_QOS, msg_to_pose, stamp_to_sec

    env = {**os.environ, 'ROS_DOMAIN_ID': str(private_domain_id())}
    launcher = Launcher(tmp_path / 'logs', env)
    common = {'use_sim_time': True, 'rig_file': str(WALK / 'rig.yaml')}
    node = Node('bag_pipeline_probe', context=ros_context)
    poses: list[tuple[float, object]] = []
    node.create_subscription(PoseStamped, '/fixego/pose',
                             lambda m: poses.append((stamp_to_sec(m.header.stamp), msg_to_pose(m.pose))), RELIABLE_QOS)
    ex = executor_for(ros_context, node)
    recorder = None
    try:
        for side in ('right', 'left'):
            launcher.start(NodeSpec(f'{side}_camera_node', 'fixego_ros.nodes.camera_node', {**common, 'side': side}))
        launcher.start(NodeSpec('flow_node', 'fixego_ros.nodes.flow_node', common))
        launcher.start(NodeSpec('estimator_node', 'fixego_ros.nodes.estimator_node', common))
        recorded = tmp_path / 'recorded'
        recorder = subprocess.Popen([sys.executable, '-m', 'fixego_ros.cli', 'record', str(recorded), *INPUTS],
                                    env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

        def ready() -> bool:   # camera, flow and estimator nodes subscribed before the first message
            return (all(node.count_subscribers(f'/fixego/{s}/image_raw') >= 2 for s in ('right', 'left'))
                    and node.count_subscribers('/fixego/flow/observation') >= 1)
        assert spin_until(ex, ready, timeout_s=90.0), f'nodes not up: {launcher.exited()}'
        # the recorder subscribes once it discovers the player's publishers (every 1 s), like rosbag2: the
        # player's start delay leaves it time, and the replay below needs only part of the recording
        player = launcher.start(NodeSpec('bag_player', 'fixego_ros.nodes.bag_player',
                                         {'bag': str(WALK), 'rate': 1.0, 'publish_clock': True, 'start_delay_s': 3.0}))
        assert spin_until(ex, lambda: player.poll() is not None, timeout_s=90.0), 'bag_player did not finish'
        assert player.returncode == 0, launcher.log_tail('bag_player')
        spin_until(ex, lambda: False, timeout_s=2.0)          # the last frames' poses
        recorder.send_signal(signal.SIGINT)
        out, err = recorder.communicate(timeout=30)
        assert recorder.returncode == 0, err
        assert 'dropped 0' in out, out
    finally:
        if recorder is not None and recorder.poll() is None:
            recorder.kill()
        codes = launcher.stop_all()
        ex.shutdown()
        node.destroy_node()

    # live estimate: one pose per frame that went through, finite, and following the walk
    assert len(poses) >= 20, f'{len(poses)} poses; flow_node log:\n{launcher.log_tail("flow_node")}'
    stamps = np.array([s for s, _ in poses])
    assert np.all(np.diff(stamps) > 0) and all(p.is_finite() for _, p in poses)
    gt_stamps, gt_poses = read_tum(WALK / 'ground_truth.tum')
    s = evaluate(stamps, [p for _, p in poses], gt_stamps, gt_poses, anchor_first=True).summary
    assert s['poses']['associated'] == len(poses)                  # stamps are the bag's image stamps
    assert 0.3 < s['path_length_m']['ratio'] < 3.0, s['path_length_m']
    assert s['position_error_m']['mean'] < 2.0, s['position_error_m']
    assert all(c in (0, -signal.SIGINT) for c in codes.values() if c is not None), codes

    # the recording replays offline like the shipped bag
    cmd = [sys.executable, '-m', 'fixego_ros.cli', 'replay', str(recorded), '--rig', str(WALK / 'rig.yaml'),
           '--out', str(tmp_path / 'est.tum'), '--no-progress']
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert p.returncode == 0, p.stderr
    rec_stamps, _ = read_tum(tmp_path / 'est.tum')
    assert len(rec_stamps) >= 15 and 'ATE rmse' in p.stdout
