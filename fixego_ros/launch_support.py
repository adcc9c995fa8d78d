"""What the launch files in ``launch/`` share: their common arguments and the pipeline's nodes.

``fixego.launch.py`` (real rig), ``sim.launch.py`` (simulated rig) and ``replay.launch.py`` (a bag) each
declare :data:`COMMON_ARGUMENTS` plus their own, and build their nodes in an ``OpaqueFunction`` with
:func:`pipeline_nodes`, so the argument values are plain strings there. Every node runs in the launch
``namespace`` (default ``fixego``: the contract's topic names) and takes first its own generated
``<config_dir>/<node>.yaml`` (keyed ``/**``, so it applies under the launch's node names), then
``params_file`` if given (any node's blocks: ``/**``, ``/**/flow_node``, ``/**/right_camera_node``), then the
launch arguments. Importing this module needs neither ``launch`` nor ``launch_ros`` (they are imported when
the functions run, i.e. under ``ros2 launch``), so the package stays importable without them.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

PACKAGE = 'fixego_ros'

# (name, default, description); default None = required
Argument = tuple[str, str | None, str]

COMMON_ARGUMENTS: tuple[Argument, ...] = (
    ('namespace', 'fixego', 'namespace of every node and topic (the contract: fixego; robot1 gives /robot1/pose ...)'),
    ('config_dir', '', "directory with <node>.yaml for each node; '' = the installed share/fixego_ros/config"),
    ('params_file', '', "one more ROS 2 parameter file given to every node after its own (blocks /**, "
                        "/**/flow_node, /**/right_camera_node ...); '' = none"),
    ('rig_file', '', "rig calibration YAML (DESIGN.md §4); '' = the nodes' rig_file (the installed config/rig.yaml)"),
    ('respawn', 'false', 'restart a node that exits (true/false)'),
    ('respawn_delay', '2.0', 'seconds before a respawn'),
    ('publish_tf', 'auto', 'estimator broadcasts odom -> base_link when tf2_ros is importable: auto (only without '
                           'a speed source), true or false'),
)

PUBLISH_TF = ('auto', 'true', 'false')

TRUE, FALSE = ('true', '1', 'yes', 'on'), ('false', '0', 'no', 'off')


def declare(arguments: Sequence[Argument]) -> list:
    """``DeclareLaunchArgument`` of each (name, default, description)."""
    from launch.actions import DeclareLaunchArgument

    return [DeclareLaunchArgument(name, description=text) if default is None
            else DeclareLaunchArgument(name, default_value=default, description=text)
            for name, default, text in arguments]


def flag(text: str, name: str) -> bool:
    """A boolean launch argument; anything but true/false (1/0, yes/no, on/off) is an error naming it."""
    t = text.strip().lower()
    if t in TRUE:
        return True
    if t in FALSE:
        return False
    raise ValueError(f'launch argument {name}:={text!r} must be true or false')


def choice(text: str, name: str, choices: Sequence[str]) -> str:
    """A launch argument that must be one of ``choices``; anything else is an error naming it."""
    t = text.strip().lower()
    if t not in choices:
        raise ValueError(f'launch argument {name}:={text!r} must be one of {", ".join(choices)}')
    return t


def number(text: str, name: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ValueError(f'launch argument {name}:={text!r} must be a number') from None


def installed_config_dir() -> str:
    from ament_index_python.packages import get_package_share_directory

    return os.path.join(get_package_share_directory(PACKAGE), 'config')


class Args:
    """The launch arguments' values in an ``OpaqueFunction`` (strings, as given or defaulted)."""

    def __init__(self, context) -> None:
        self._context = context

    def __getitem__(self, name: str) -> str:
        from launch.substitutions import LaunchConfiguration

        return str(LaunchConfiguration(name).perform(self._context))

    def flag(self, name: str) -> bool:
        return flag(self[name], name)

    def number(self, name: str) -> float:
        return number(self[name], name)

    def choice(self, name: str, choices: Sequence[str]) -> str:
        return choice(self[name], name, choices)


def node(args: Args, executable: str, name: str, params: Mapping[str, object], *, config: str | None = None,
         use_sim_time: bool = False, respawn: bool | None = None):
    """One ``launch_ros`` Node of the package in the launch namespace: ``<config_dir>/<config>.yaml`` (default:
    the executable's), ``params_file``, then ``params`` (and ``use_sim_time``; ``rig_file`` when given)."""
    from launch_ros.actions import Node

    config_dir = args['config_dir'] or installed_config_dir()
    files: list[object] = [os.path.join(config_dir, f'{config or executable}.yaml')]
    if args['params_file']:
        files.append(args['params_file'])
    values = dict(params)
    if use_sim_time:
        values['use_sim_time'] = True
    if args['rig_file'] and executable != 'bag_player':
        values['rig_file'] = args['rig_file']
    respawn = args.flag('respawn') if respawn is None else respawn
    return Node(package=PACKAGE, executable=executable, name=name, namespace=args['namespace'],
                parameters=[*files, values], respawn=respawn, respawn_delay=args.number('respawn_delay'),
                output='screen', emulate_tty=True)


def pipeline_nodes(args: Args, cameras: Mapping[str, Mapping[str, object]], *, use_sim_time: bool,
                   estimator: Mapping[str, object] | None = None) -> list:
    """``right_camera_node`` and ``left_camera_node`` (``cameras[side]``: their parameters besides ``side``),
    ``flow_node`` and ``estimator_node`` (``estimator``: its parameters)."""
    nodes = [node(args, 'camera_node', f'{side}_camera_node', {**cameras[side], 'side': side},
                  use_sim_time=use_sim_time) for side in ('right', 'left')]
    nodes.append(node(args, 'flow_node', 'flow_node', {}, use_sim_time=use_sim_time))
    nodes.append(node(args, 'estimator_node', 'estimator_node', dict(estimator or {}), use_sim_time=use_sim_time))
    return nodes
