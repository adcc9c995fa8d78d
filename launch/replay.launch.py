"""The live nodes on a recorded bag: bag_player (publishing /clock), passive camera nodes (they follow the
recorded joint states and only track), flow_node and estimator_node on sim time.

    ros2 launch fixego_ros replay.launch.py bag:=bags/walk

``rig_file`` defaults to ``<bag>/rig.yaml`` (the calibration belongs to the bag). The bag keeps its topic
names (``/fixego/...``); with another ``namespace`` the player renames the contract's input topics into it.
``fixego replay`` does the same offline, deterministically and faster than real time.
"""

import os

from launch import LaunchDescription
from launch.actions import OpaqueFunction

from fixego_ros.launch_support import COMMON_ARGUMENTS, PUBLISH_TF, Args, declare, node, pipeline_nodes

ARGUMENTS = (
    *COMMON_ARGUMENTS,
    ('bag', None, 'rosbag2 directory (or .mcap file) to play'),
    ('bag_namespace', '/fixego', 'namespace of the input topics in the bag'),
    ('rate', '1.0', 'playback speed factor (0 = as fast as possible)'),
    ('start_delay_s', '3.0', 'the player waits this long for the nodes to subscribe before the first message'),
)
# the contract's inputs a bag carries (DESIGN.md §3), renamed into the launch namespace when it differs
INPUTS = ('right/image_raw', 'left/image_raw', 'right/camera_info', 'left/camera_info', 'right/joint_states',
          'left/joint_states', 'ground_truth/pose', 'vergence')


def _nodes(context):
    args = Args(context)
    bag = args['bag']
    if not args['rig_file']:
        context.launch_configurations['rig_file'] = os.path.join(
            bag if os.path.isdir(bag) else os.path.dirname(bag), 'rig.yaml')
    ns, bag_ns = '/' + args['namespace'].strip('/'), '/' + args['bag_namespace'].strip('/')
    player = {'bag': bag, 'rate': args.number('rate'), 'publish_clock': True,
              'start_delay_s': args.number('start_delay_s')}
    if ns != bag_ns:
        player['remap'] = [f'{bag_ns}/{t}:={ns.rstrip("/")}/{t}' for t in INPUTS]
    cameras = {side: {'passive': True} for side in ('right', 'left')}
    return [*pipeline_nodes(args, cameras, use_sim_time=True,
                           estimator={'publish_tf': args.choice('publish_tf', PUBLISH_TF)}),
            node(args, 'bag_player', 'bag_player', player, respawn=False)]


def generate_launch_description():
    return LaunchDescription([*declare(ARGUMENTS), OpaqueFunction(function=_nodes)])
