"""The real rig: two camera_node (VISCA heads on serial ports), flow_node and estimator_node.

    ros2 launch fixego_ros fixego.launch.py right_port:=/dev/serial/by-id/... left_port:=/dev/serial/by-id/...

Images come from ``<side>_video_device`` (read by the camera node) or, when that is empty, from any camera
driver publishing ``<namespace>/<side>/image_raw``. Arguments: ``ros2 launch fixego_ros fixego.launch.py -s``;
README "Launch files".
"""

from launch import LaunchDescription
from launch.actions import OpaqueFunction

from fixego_ros.launch_support import COMMON_ARGUMENTS, PUBLISH_TF, Args, declare, pipeline_nodes

ARGUMENTS = (
    *COMMON_ARGUMENTS,
    ('right_port', None, 'serial device of the right VISCA head (e.g. /dev/serial/by-id/usb-...)'),
    ('left_port', None, 'serial device of the left VISCA head'),
    ('profile', 'evi_d30', 'VISCA camera profile of both heads (evi_d30 | evi_d100 | evi_d70 | evi_g20 | a '
                           'calibrate .json)'),
    ('right_video_device', '', "V4L2 device of the right camera read by its camera_node; '' = subscribe "
                               'right/image_raw'),
    ('left_video_device', '', "V4L2 device of the left camera; '' = subscribe left/image_raw"),
    ('use_sim_time', 'false', 'use /clock (true/false)'),
)


def _nodes(context):
    args = Args(context)
    cameras = {}
    for side in ('right', 'left'):
        cameras[side] = {'port': args[f'{side}_port'], 'profile': args['profile']}
        if args[f'{side}_video_device']:
            cameras[side]['video_device'] = args[f'{side}_video_device']
    return pipeline_nodes(args, cameras, use_sim_time=args.flag('use_sim_time'),
                          estimator={'publish_tf': args.choice('publish_tf', PUBLISH_TF)})


def generate_launch_description():
    return LaunchDescription([*declare(ARGUMENTS), OpaqueFunction(function=_nodes)])
