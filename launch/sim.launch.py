"""The simulated rig, live: sim_rig_node (two VISCA heads emulated on pseudo-terminals, rendered images and
ground truth) and the same four nodes as ``fixego.launch.py``, the camera nodes driving the emulated heads.

    ros2 launch fixego_ros sim.launch.py trajectory:=circle

sim_rig_node links its ptys into a directory made fresh for each launch (``pty_link_dir``), so the camera
nodes get their ports before the ptys exist and connect once they do (the VISCA driver retries). The rig
keeps rendering its final pose at the end (or loops with ``loop:=true``). ``fixego demo`` runs the same
pipeline without ``ros2 launch`` and writes a report.
"""

import os
import tempfile
import uuid

from launch import LaunchDescription
from launch.actions import OpaqueFunction

from fixego_ros.launch_support import COMMON_ARGUMENTS, PUBLISH_TF, Args, declare, node, pipeline_nodes

ARGUMENTS = (
    *COMMON_ARGUMENTS,
    ('trajectory', 'paper', 'rig trajectory: paper | straight | circle | random | walk'),
    ('speed', '0.0', 'rig speed in m/s (0: the trajectory default)'),
    ('duration', '0.0', 'truncate the trajectory to this many seconds (0: whole)'),
    ('fps', '30.0', 'frame rate of both cameras'),
    ('seed', '0', 'seed of the world, noise and the random trajectory'),
    ('loop', 'false', 'restart the trajectory at its end (true/false)'),
    ('use_sim_time', 'false', 'use /clock (true/false; the simulated rig stamps with the wall clock)'),
)


def _nodes(context):
    args = Args(context)
    links = os.path.join(tempfile.gettempdir(), f'fixego_sim_{uuid.uuid4().hex[:12]}')
    sim = node(args, 'sim_rig_node', 'sim_rig_node', {
        'trajectory': args['trajectory'], 'speed': args.number('speed'), 'duration': args.number('duration'),
        'fps': args.number('fps'), 'seed': int(args.number('seed')), 'loop': args.flag('loop'),
        'exit_at_end': False, 'pty_file': '', 'pty_link_dir': links}, respawn=False)  # new ptys on a restart
    cameras = {side: {'port': os.path.join(links, side)} for side in ('right', 'left')}
    return [sim, *pipeline_nodes(args, cameras, use_sim_time=args.flag('use_sim_time'),
                                 estimator={'publish_tf': args.choice('publish_tf', PUBLISH_TF)})]


def generate_launch_description():
    return LaunchDescription([*declare(ARGUMENTS), OpaqueFunction(function=_nodes)])
