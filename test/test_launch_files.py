"""The launch files in ``launch/`` (``launch`` and ``launch_ros`` are not available as wheels): each one is
imported with small stand-ins for the launch API and its ``generate_launch_description()`` evaluated, and
what it would start is checked against the package: executables are setup.py's console scripts, every
parameter is in its node's spec and allowed there, every parameter file exists (the installed config dir is
this repository's config/), every launch argument read is declared and every declared one is read, and
setup.py installs the launch files."""

from __future__ import annotations

import importlib.util
import re
import sys
import types
from pathlib import Path

import pytest
import yaml

from fixego_ros.pipeline.params import NODE_PARAMS, load_params_file

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'launch'
FILES = ('fixego.launch.py', 'sim.launch.py', 'replay.launch.py')
ROS_PARAMS = {'use_sim_time'}          # declared by rclpy itself, not by our specs


# ---------------------------------------------------------------------------------------------- stand-ins
class _Entity:
    def __init__(self, *args, **kwargs) -> None:
        self.args, self.kwargs = args, kwargs


class LaunchDescription(_Entity):
    pass


class DeclareLaunchArgument(_Entity):
    @property
    def name(self) -> str:
        return self.args[0]


class OpaqueFunction(_Entity):
    pass


class Node(_Entity):
    pass


class LaunchConfiguration:
    def __init__(self, name: str) -> None:
        self.name = name

    def perform(self, context) -> str:
        context.read.add(self.name)
        if self.name not in context.launch_configurations:
            raise KeyError(f'launch argument {self.name!r} read but not declared (or required and not given)')
        return context.launch_configurations[self.name]


class Context:
    def __init__(self, configurations: dict[str, str]) -> None:
        self.launch_configurations = dict(configurations)
        self.read: set[str] = set()


@pytest.fixture
def launch_api(monkeypatch):
    """Stand-in modules for launch, launch.actions, launch.substitutions, launch_ros.actions and
    ament_index_python.packages (the package share directory is this repository)."""
    mods = {
        'launch': {'LaunchDescription': LaunchDescription},
        'launch.actions': {'DeclareLaunchArgument': DeclareLaunchArgument, 'OpaqueFunction': OpaqueFunction},
        'launch.substitutions': {'LaunchConfiguration': LaunchConfiguration},
        'launch_ros': {},
        'launch_ros.actions': {'Node': Node},
        'ament_index_python': {},
        'ament_index_python.packages': {'get_package_share_directory':
                                        lambda pkg: str(ROOT) if pkg == 'fixego_ros' else pytest.fail(pkg)},
    }
    for name, attrs in mods.items():
        m = types.ModuleType(name)
        m.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, name, m)


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name.replace('.', '_'), LAUNCH / name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _evaluate(name: str, **given: str) -> tuple[list[DeclareLaunchArgument], list[Node], Context]:
    """The declared arguments and the nodes of a launch file, with ``given`` argument values."""
    ld = _load(name).generate_launch_description()
    assert isinstance(ld, LaunchDescription)
    entities = ld.args[0]
    declared = [e for e in entities if isinstance(e, DeclareLaunchArgument)]
    names = [d.name for d in declared]
    assert len(names) == len(set(names)), names
    unknown = set(given) - set(names)
    assert not unknown, f'{name}: arguments not declared: {unknown}'
    config = {d.name: d.kwargs['default_value'] for d in declared if 'default_value' in d.kwargs}
    config.update(given)
    context = Context(config)
    nodes: list[Node] = []
    for e in entities:
        if isinstance(e, OpaqueFunction):
            nodes += e.kwargs['function'](context)
        else:
            assert isinstance(e, DeclareLaunchArgument), e
    return declared, nodes, context


def _console_scripts() -> set[str]:
    text = (ROOT / 'setup.py').read_text()
    return set(re.findall(r"'(\w+) = fixego_ros\.[\w.]+:main'", text))


REQUIRED = {'fixego.launch.py': {'right_port': '/dev/ttyUSB0', 'left_port': '/dev/ttyUSB1'},
            'sim.launch.py': {}, 'replay.launch.py': {'bag': str(ROOT / 'bags' / 'walk')}}


# ---------------------------------------------------------------------------------------------- tests
@pytest.mark.parametrize('name', FILES)
def test_launch_file_nodes_fit_the_package(launch_api, name):
    declared, nodes, context = _evaluate(name, **REQUIRED[name])
    required = {d.name for d in declared if 'default_value' not in d.kwargs}
    assert required == set(REQUIRED[name])
    assert context.read == {d.name for d in declared}, 'declared but never read: ' + str(
        {d.name for d in declared} - context.read)
    scripts = _console_scripts()
    names = [n.kwargs['name'] for n in nodes]
    assert len(names) == len(set(names)), names
    assert {'right_camera_node', 'left_camera_node', 'flow_node', 'estimator_node'} <= set(names)
    for n in nodes:
        kw = n.kwargs
        exe = kw['executable']
        assert kw['package'] == 'fixego_ros' and exe in scripts, exe
        assert kw['namespace'] == 'fixego', kw['name']
        files = [p for p in kw['parameters'] if not isinstance(p, dict)]
        values = [p for p in kw['parameters'] if isinstance(p, dict)]
        # its own generated config file first (keyed /**: applies under the launch's node name)
        assert Path(files[0]) == ROOT / 'config' / f'{exe}.yaml', files
        for f in files:
            assert Path(f).is_file(), f
            assert list(yaml.safe_load(Path(f).read_text())) == ['/**'], f
            load_params_file(f, exe)                   # checked against the spec
        spec = NODE_PARAMS[exe]
        for v in values:
            for key, value in v.items():
                assert key in spec or key in ROS_PARAMS, f'{name}: {kw["name"]}: unknown parameter {key}'
                if key in spec:
                    spec[key].check(value)
        if kw['name'].endswith('_camera_node'):
            assert {k: v for d in values for k, v in d.items()}['side'] == kw['name'].split('_')[0]
        assert isinstance(kw['respawn'], bool) and kw['respawn_delay'] == 2.0


def test_fixego_launch_wires_the_ports_and_the_arguments(launch_api):
    _, nodes, _ = _evaluate('fixego.launch.py', right_port='/dev/r', left_port='/dev/l', namespace='robot1',
                            respawn='true', respawn_delay='5', publish_tf='false', rig_file='/x/rig.yaml',
                            params_file=str(ROOT / 'config' / 'flow_node.yaml'), right_video_device='/dev/video2')
    by = {n.kwargs['name']: n.kwargs for n in nodes}
    assert set(by) == {'right_camera_node', 'left_camera_node', 'flow_node', 'estimator_node'}
    params = {k: {key: v for p in kw['parameters'] if isinstance(p, dict) for key, v in p.items()}
              for k, kw in by.items()}
    assert params['right_camera_node']['port'] == '/dev/r' and params['left_camera_node']['port'] == '/dev/l'
    assert params['right_camera_node']['video_device'] == '/dev/video2'
    assert 'video_device' not in params['left_camera_node']
    assert params['estimator_node']['publish_tf'] == 'false'
    for kw in by.values():
        assert kw['namespace'] == 'robot1' and kw['respawn'] is True and kw['respawn_delay'] == 5.0
        # own file, then the extra parameter file, then the launch arguments (later wins in ROS)
        assert kw['parameters'][1] == str(ROOT / 'config' / 'flow_node.yaml')
        assert isinstance(kw['parameters'][-1], dict) and kw['parameters'][-1]['rig_file'] == '/x/rig.yaml'
        assert 'use_sim_time' not in kw['parameters'][-1]
    with pytest.raises(ValueError, match='respawn'):
        _evaluate('fixego.launch.py', right_port='/dev/r', left_port='/dev/l', respawn='maybe')
    with pytest.raises(KeyError, match='left_port'):            # required
        _evaluate('fixego.launch.py', right_port='/dev/r')


def test_sim_launch_gives_the_camera_nodes_the_sim_nodes_pty_links(launch_api):
    _, nodes, _ = _evaluate('sim.launch.py', trajectory='circle', fps='15')
    by = {n.kwargs['name']: n.kwargs['parameters'][-1] for n in nodes}
    sim = by['sim_rig_node']
    assert sim['trajectory'] == 'circle' and sim['fps'] == 15.0 and sim['pty_link_dir']
    assert sim['exit_at_end'] is False and sim['pty_file'] == ''
    for side in ('right', 'left'):
        assert by[f'{side}_camera_node']['port'] == str(Path(sim['pty_link_dir']) / side)
    _, again, _ = _evaluate('sim.launch.py')
    other = {n.kwargs['name']: n.kwargs['parameters'][-1] for n in again}['sim_rig_node']['pty_link_dir']
    assert other != sim['pty_link_dir']          # a fresh directory per launch: no stale link from a killed run


def test_replay_launch_plays_the_bag_into_passive_nodes_on_sim_time(launch_api):
    walk = ROOT / 'bags' / 'walk'
    _, nodes, _ = _evaluate('replay.launch.py', bag=str(walk))
    by = {n.kwargs['name']: n.kwargs['parameters'][-1] for n in nodes}
    player = by.pop('bag_player')
    assert player['bag'] == str(walk) and player['publish_clock'] is True and 'remap' not in player
    assert 'use_sim_time' not in player              # the player drives /clock
    for name, p in by.items():
        assert p['use_sim_time'] is True and p['rig_file'] == str(walk / 'rig.yaml'), name
    assert by['right_camera_node']['passive'] is True and by['left_camera_node']['passive'] is True
    # another namespace: the contract's input topics are renamed into it by the player
    _, nodes, _ = _evaluate('replay.launch.py', bag=str(walk), namespace='robot1')
    player = {n.kwargs['name']: n.kwargs['parameters'][-1] for n in nodes}['bag_player']
    assert '/fixego/right/image_raw:=/robot1/right/image_raw' in player['remap']
    assert all(n.kwargs['namespace'] == 'robot1' for n in nodes)


def test_setup_installs_the_launch_files():
    text = (ROOT / 'setup.py').read_text()
    assert "('share/' + package_name + '/launch', glob('launch/*.launch.py'))" in text
    assert sorted(p.name for p in LAUNCH.glob('*.launch.py')) == sorted(FILES)
