"""Parameters (issue 15): one spec per parameter gives the ROS descriptors, config/<node>.yaml and every check.

Out-of-range, non-finite and wrong-typed values are refused at start (nodes: one line, exit 2; ``fixego
replay``: the same line) and at run time (``ros2 param set``: refused with the reason); a valid run-time
change takes effect, a read-only parameter is refused, and no set reports success without effect.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fixego_ros.pipeline import odometry
from fixego_ros.pipeline.params import (
    ESTIMATOR_NODE_PARAMS,
    ESTIMATOR_PARAMS,
    FLOW_PARAMS,
    NODE_PARAMS,
    ParamsError,
    load_params_file,
    main,
    params_getter,
    parse_value,
    render_config,
    write_config,
)

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'config'
WALK = ROOT / 'bags' / 'walk'


# ---------------------------------------------------------------------------------------------- the specs
def test_every_parameter_of_every_node_has_a_type_and_a_range():
    for node, table in NODE_PARAMS.items():
        for name, spec in table.items():
            assert spec.name == name and spec.description, (node, name)
            assert spec.type in (bool, int, float, str, list), (node, name)
            if spec.type in (int, float):
                assert spec.min is not None or spec.max is not None, f'{node}.{name}: no range'
            if spec.type is float:
                for bad in (math.nan, math.inf, -math.inf):
                    with pytest.raises(ParamsError, match='not finite'):
                        spec.check(bad)
            if spec.default is not None:
                assert spec.check(spec.default) == spec.default


def test_config_files_equal_what_the_specs_generate(tmp_path):
    for node in NODE_PARAMS:
        path = CONFIG / f'{node}.yaml'
        assert path.read_text() == render_config(node), f'{path} is stale: python -m fixego_ros.pipeline.params ' \
                                                        '--write-config config/'
        assert load_params_file(path, node) == {k: s.default for k, s in NODE_PARAMS[node].items()
                                                if s.default is not None}
    assert main(['--check-config', str(CONFIG)]) == 0
    write_config(tmp_path)
    assert main(['--check-config', str(tmp_path)]) == 0
    (tmp_path / 'flow_node.yaml').write_text('flow_node: {}\n')
    assert main(['--check-config', str(tmp_path)]) == 1


@pytest.mark.parametrize('name, value, match', [
    ('max_speed', -1.0, r'parameter max_speed: -1\.0 is out of range \(allowed: finite float > 0\)'),
    ('max_speed', math.nan, r'parameter max_speed: nan is not finite'),
    ('max_speed', math.inf, r'parameter max_speed: inf is not finite'),
    ('max_lag_s', -1.0, r'parameter max_lag_s: -1\.0 is out of range \(allowed: finite float >= 0\)'),
    ('diagnostics_period_s', 0.0, r'diagnostics_period_s: 0\.0 is out of range \(allowed: finite float in '
                                  r'\[0\.05, 3600\]\)'),
    ('window', 2, r'window: 2 is out of range \(allowed: integer in \[3, 10\], or 0 or 1\)'),
    ('window', 3.0, r'window: 3\.0 has the wrong type'),
    ('mode', 'jiont', r"mode: 'jiont' is not allowed \(did you mean 'joint'\?\)"),
    ('velocity_prior', 1, r'velocity_prior: 1 has the wrong type \(allowed: true or false\)'),
    ('max_speed', 'fast', r"max_speed: 'fast' has the wrong type"),
])
def test_specs_refuse_with_one_line_naming_parameter_value_and_range(name, value, match):
    with pytest.raises(ParamsError, match=match) as e:
        ESTIMATOR_NODE_PARAMS[name].check(value)
    assert '\n' not in str(e.value)


def test_an_int_for_a_float_parameter_is_that_float():
    assert ESTIMATOR_NODE_PARAMS['max_speed'].check(2) == 2.0
    assert isinstance(ESTIMATOR_NODE_PARAMS['max_speed'].check(2), float)


# ---------------------------------------------------------------------------------------------- replay's path
def test_params_getter_and_params_files_check_every_value(tmp_path):
    """``fixego replay`` builds its settings with params_getter over the tables (and load_params_file)."""
    with pytest.raises(ParamsError, match=r'max_speed: -1\.0 is out of range'):
        params_getter(ESTIMATOR_PARAMS, {'max_speed': -1.0})
    with pytest.raises(ParamsError, match='fb_max_px: nan is not finite'):
        params_getter(FLOW_PARAMS, {'fb_max_px': math.nan})
    assert params_getter(ESTIMATOR_PARAMS, {'max_speed': 3})('max_speed') == 3.0
    assert params_getter(ESTIMATOR_PARAMS, {'not_a_parameter': -1})('max_speed') == 1.5
    # replay/cli.py merges the legacy (default, description) pairs of pipeline.odometry: their ranges still apply
    legacy = {**ESTIMATOR_PARAMS, **odometry.SPEED_PARAMS}
    with pytest.raises(ParamsError, match=r'speed_default_std: -1\.0 is out of range'):
        params_getter(legacy, {'speed_default_std': -1.0})
    f = tmp_path / 'p.yaml'
    f.write_text('estimator_node:\n  ros__parameters:\n    max_speed: .nan\n')
    with pytest.raises(ParamsError, match=r'p\.yaml: estimator_node: parameter max_speed: nan is not finite'):
        load_params_file(f, 'estimator_node')
    f.write_text('estimator_node:\n  ros__parameters:\n    diagnostics_period_s: 0.0\n')
    with pytest.raises(ParamsError, match=r'diagnostics_period_s: 0\.0 is out of range'):
        load_params_file(f, 'estimator_node')


def _replay(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'fixego_ros.cli', 'replay', str(WALK), *map(str, args),
                           '--no-progress'], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize('option, expect', [
    (('-p', 'max_speed:=-1.0'), 'parameter max_speed: -1.0 is out of range (allowed: finite float > 0)'),
    (('-p', 'max_speed:=.nan'), 'parameter max_speed: nan is not finite (allowed: finite float > 0)'),
    (('-p', 'speed_max_age_s:=0'), 'parameter speed_max_age_s: 0 is out of range'),
    (('-p', 'preset:=paper', '-p', 'paper_region_px:=500'), 'flow parameters do not fit together'),
    ('params_file', 'estimator_node: parameter max_step_rotation_deg: -5.0 is out of range'),
    (('-p', 'min_eig:=['), "parameter min_eig: '[' is not a YAML value"),
    (('-p', 'vergence_topic:=/fixego/vergence'), 'not used by replay (use --vergence-topic)'),
    (('-p', 'no_such_thing:=1'), "unknown parameter 'no_such_thing'"),
])
def test_replay_refuses_bad_parameters_with_one_line(tmp_path, option, expect):
    if option == 'params_file':
        f = tmp_path / 'bad.yaml'
        f.write_text('estimator_node:\n  ros__parameters:\n    max_step_rotation_deg: -5.0\n')
        option = ('--params-file', f)
    p = _replay('--out', tmp_path / 'est.tum', *option)
    assert p.returncode == 2, p.stderr
    assert expect in p.stderr and 'Traceback' not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert not (tmp_path / 'est.tum').exists()


# ---------------------------------------------------------------------------------------------- nodes at start
def _node_process(module: str, *ros_args: str) -> subprocess.CompletedProcess:
    from conftest import private_domain_id
    env = {**os.environ, 'ROS_DOMAIN_ID': str(private_domain_id() + 2)}
    return subprocess.run([sys.executable, '-m', f'fixego_ros.nodes.{module}', '--ros-args', *ros_args],
                          capture_output=True, text=True, timeout=60, env=env)


@pytest.mark.parametrize('module, args, expect', [
    ('estimator_node', ('-p', 'max_speed:=-1.0'), 'estimator_node: parameter max_speed: -1.0 is out of range '
                                                  '(allowed: finite float > 0)'),
    ('estimator_node', ('-p', 'diagnostics_period_s:=0.0'), 'estimator_node: parameter diagnostics_period_s: 0.0 '
                                                            'is out of range (allowed: finite float in [0.05, 3600])'),
    ('flow_node', ('-p', 'fb_max_px:=.nan'), 'flow_node: parameter fb_max_px: nan is not finite'),
    ('camera_node', ('-p', 'side:=middle'), "camera_node: parameter side: 'middle' is not allowed"),
    ('estimator_node', 'params_file', 'estimator_node: parameter max_lag_s: -1.0 is out of range'),
])
def test_node_refuses_a_bad_parameter_at_start_with_one_line_and_exit_2(tmp_path, module, args, expect):
    if args == 'params_file':
        f = tmp_path / 'p.yaml'
        f.write_text('/**/estimator_node:\n  ros__parameters:\n    max_lag_s: -1.0\n')    # in any namespace
        args = ('--params-file', str(f))
    p = _node_process(module, *args)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip() == expect or (expect in p.stderr and len(p.stderr.strip().splitlines()) == 1), p.stderr
    assert 'Traceback' not in p.stderr


def _rig_file(tmp_path) -> str:
    from fixego_ros.geometry.rig import make_rig
    path = tmp_path / 'rig.yaml'
    make_rig(320, 240).save(path)
    return str(path)


@pytest.mark.parametrize('name, value', [('max_speed', -1.0), ('max_speed', math.nan), ('max_lag_s', -1.0),
                                         ('diagnostics_period_s', 0.0), ('max_future_s', 0.0),
                                         ('refinement', 'slidnig')])
def test_estimator_node_refuses_bad_overrides_before_declaring(ros_context, tmp_path, name, value):
    from rclpy.parameter import Parameter

    from fixego_ros.nodes.estimator_node import EstimatorNode
    with pytest.raises(ParamsError, match=f'parameter {name}: '):
        EstimatorNode(context=ros_context, parameter_overrides=[Parameter('rig_file', value=_rig_file(tmp_path)),
                                                                Parameter(name, value=value)])


def test_descriptors_carry_range_description_and_read_only(ros_context, tmp_path):
    from rclpy.parameter import Parameter

    from fixego_ros.nodes.estimator_node import EstimatorNode
    node = EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter('rig_file', value=_rig_file(tmp_path)), Parameter('max_speed', value=2)])   # int -> 2.0
    try:
        assert node.get_parameter('max_speed').value == 2.0 and node.config.max_speed == 2.0
        d = node.describe_parameter('max_speed')
        assert d.description.startswith('m/s;') and not d.read_only
        assert d.floating_point_range[0].from_value == 0.0 and d.floating_point_range[0].to_value == math.inf
        assert d.additional_constraints == 'finite float > 0'
        d = node.describe_parameter('diagnostics_period_s')
        assert (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value) == (0.05, 3600.0)
        d = node.describe_parameter('window')
        assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (0, 10) and d.read_only
        assert 'or 0 or 1' in d.additional_constraints and 'read-only' in d.additional_constraints
        assert node.describe_parameter('rig_file').read_only
    finally:
        node.destroy_node()


# ---------------------------------------------------------------------------------------------- run time
def _set(node, name, value):
    from rclpy.parameter import Parameter
    return node.set_parameters([Parameter(name, value=value)])[0]


def test_estimator_node_run_time_changes_over_the_parameter_service(ros_context, tmp_path):
    """``ros2 param set`` is a SetParameters service call: valid thresholds take effect, bad values and
    read-only parameters are refused with the reason, and a refused set changes nothing."""
    import rclpy
    from conftest import executor_for, spin_until
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    from fixego_ros.nodes.estimator_node import EstimatorNode

    node = EstimatorNode(context=ros_context, parameter_overrides=[Parameter('rig_file', value=_rig_file(tmp_path))])
    probe = rclpy.create_node('param_probe', context=ros_context)
    ex = executor_for(ros_context, node, probe)
    client = AsyncParameterClient(probe, '/fixego/estimator_node')
    try:
        assert spin_until(ex, lambda: client.services_are_ready(), 10.0)

        def remote_set(name, value):
            fut = client.set_parameters([Parameter(name, value=value)])
            assert spin_until(ex, fut.done, 10.0)
            return fut.result().results[0]

        r = remote_set('max_speed', 3.0)
        assert r.successful and node.estimator.config.max_speed == 3.0
        r = remote_set('max_step_rotation_deg', 10.0)
        assert r.successful and node.estimator.config.max_step_rotation == pytest.approx(math.radians(10.0))
        assert node.estimator.config.max_speed == 3.0                       # the other one kept
        # rclpy checks the descriptor's closed range first ('Parameter max_speed out of range Min: 0.0, Max: inf,
        # value: -1.0'); what it cannot express (an open bound, finiteness) is refused by the node's callback
        for name, value, reason in [('max_speed', -1.0, 'max_speed out of range'),
                                    ('max_speed', 0.0, 'max_speed: 0.0 is out of range (allowed: finite float > 0)'),
                                    ('max_speed', math.nan, 'max_speed'),
                                    ('max_speed', 'fast', 'type'),
                                    ('rig_file', '/tmp/other.yaml', 'read-only'),
                                    ('window', 5, 'read-only'),
                                    ('diagnostics_period_s', 0.0, 'diagnostics_period_s out of range')]:
            r = remote_set(name, value)
            assert not r.successful and reason in r.reason, (name, value, r.reason)
        assert node.estimator.config.max_speed == 3.0 and node.get_parameter('max_speed').value == 3.0
        assert node.get_parameter('rig_file').value != '/tmp/other.yaml'
        r = remote_set('max_speed', 4)                                       # an int for a float: taken as 4.0
        assert r.successful and node.estimator.config.max_speed == 4.0
    finally:
        ex.shutdown()
        probe.destroy_node()
        node.destroy_node()
    # node-level bounds and the diagnostics timer
    node = EstimatorNode(context=ros_context, parameter_overrides=[Parameter('rig_file', value=_rig_file(tmp_path))])
    try:
        for name, value, attr in [('max_lag_s', 0.5, 'max_lag_s'), ('max_keyframe_lag_s', 2.0, 'max_keyframe_lag_s'),
                                  ('max_future_s', 5.0, 'max_future_s'), ('backward_reset_count', 4,
                                                                          'backward_reset_count'),
                                  ('backward_reset_s', 9.0, 'backward_reset_s')]:
            assert _set(node, name, value).successful and getattr(node, attr) == value
        assert _set(node, 'diagnostics_period_s', 0.25).successful
        assert node.diag_timer.timer_period_ns == 250_000_000
        assert not _set(node, 'velocity_prior', 1).successful
        assert _set(node, 'velocity_prior', True).successful and node.estimator.config.velocity_prior
    finally:
        node.destroy_node()


def test_flow_node_run_time_changes_take_effect(ros_context, tmp_path):
    from rclpy.parameter import Parameter

    from fixego_ros.nodes.flow_node import FlowNode
    node = FlowNode(context=ros_context, parameter_overrides=[Parameter('rig_file', value=_rig_file(tmp_path))])
    try:
        assert _set(node, 'fb_max_px', 0.8).successful and node.frontend.params.fb_max_px == 0.8
        assert _set(node, 'ransac_px', 0.0).successful and node.frontend.params.ransac_px == 0.0
        assert _set(node, 'register_period_s', 0.0).successful and node.frontend.params.register_period_s == 0.0
        assert _set(node, 'keyframe_max_frames', 3).successful and node.frontend.keyframes.max_frames == 3
        assert _set(node, 'slop_s', 0.02).successful and node.sync.params.slop_s == 0.02
        assert _set(node, 'max_wait_s', 0.5).successful and node.sync.params.max_wait_s == 0.5
        for name, value in [('fb_max_px', 0.0), ('fb_max_px', math.inf), ('keyframe_min_tracked_fraction', 1.5),
                            ('preset', 'paper'), ('window_px', 50), ('observation_topic', '/x')]:
            r = _set(node, name, value)
            assert not r.successful and r.reason, (name, value)
        assert node.frontend.params.fb_max_px == 0.8 and node.frontend.params.preset == 'full'
    finally:
        node.destroy_node()


def test_camera_node_run_time_changes_take_effect(ros_context, tmp_path):
    from rclpy.parameter import Parameter

    from fixego_ros.nodes.camera_node import CameraNode
    node = CameraNode(context=ros_context, parameter_overrides=[Parameter('rig_file', value=_rig_file(tmp_path)),
                                                                Parameter('side', value='left')])
    try:
        assert _set(node, 'ncc_min', 0.5).successful and node.tracker.params.ncc_min == 0.5
        assert _set(node, 'search_radius_px', 20.0).successful and node.tracker.params.search_radius_px == 20.0
        assert node.tracker.params.ncc_min == 0.5
        assert _set(node, 'servo_gain', 0.5).successful and node.servo.params.gain == 0.5
        assert _set(node, 'limit_margin_deg', 10.0).successful
        assert node.limits.margin_rad == pytest.approx(math.radians(10.0))
        assert _set(node, 'joint_max_wait_s', 0.1).successful and node.joint_max_wait_s == 0.1
        for name, value in [('ncc_min', 2.0), ('servo_gain', -0.1), ('side', 'right'), ('port', '/dev/ttyUSB0'),
                            ('template_half_px', 5), ('vergence_timeout_s', 5.0)]:
            r = _set(node, name, value)
            assert not r.successful and r.reason, (name, value)
        assert node.side == 'left' and node.tracker.params.ncc_min == 0.5
    finally:
        node.destroy_node()


def test_a_node_cannot_start_with_a_run_time_parameter_it_does_not_apply(ros_context):
    """NodeParams.start insists that the handled names are exactly the non-read-only ones."""
    import rclpy

    from fixego_ros.nodes.common import declare_parameters
    from fixego_ros.pipeline.params import FLOW_PARAMS
    node = rclpy.create_node('spec_check', context=ros_context)
    try:
        g = declare_parameters(node, {k: FLOW_PARAMS[k] for k in ('fb_max_px', 'preset')})
        with pytest.raises(RuntimeError, match='fb_max_px'):
            g.start(lambda changes, getter: None, ())
        g.start(lambda changes, getter: None, ('fb_max_px',))
    finally:
        node.destroy_node()


# ------------------------------------------------------------------------------- parameter-file structure
@pytest.mark.parametrize('text, message', [
    ('flow_node:\n  ros__parameters:\n    bogus: 1\n', "unknown parameter 'bogus'"),
    ('flow_node:\n  ros__parameters:\n    min_eg: 0.001\n', "did you mean 'min_eig'"),
    ('bogus_node:\n  ros__parameters:\n    min_eig: 0.001\n', "unknown node 'bogus_node'"),
    ('flow_node:\n  min_eig: 0.001\n', 'expected only ros__parameters'),
    ('flow_node:\n  ros__parameters:\n    - min_eig\n', 'expected only ros__parameters'),
    ('- a\n', 'not a ROS 2 parameter file'),
    ('42\n', 'not a ROS 2 parameter file'),
    ('/fixego/flow_node:\n  ros__parameters:\n    min_eig: .nan\n', 'not finite'),
    ('right_camera_node:\n  ros__parameters:\n    ncc_min: 2.0\n', 'out of range'),
    ('/**:\n  ros__parameters:\n    nonsense: 1\n', "unknown parameter 'nonsense'"),
    ('flow_node:\n  ros__parameters: [\n', 'cannot read parameters'),
])
def test_parameter_file_structure_and_names_are_checked(tmp_path, text, message):
    f = tmp_path / 'p.yaml'
    f.write_text(text)
    with pytest.raises(ParamsError, match=message) as e:
        load_params_file(f, 'flow_node')
    assert str(f) in str(e.value) and '\n' not in str(e.value)


def test_parameter_file_blocks_apply_by_node_name_namespace_and_wildcard(tmp_path):
    f = tmp_path / 'p.yaml'
    f.write_text('/**:\n  ros__parameters:\n    min_eig: 0.002\n    diagnostics_period_s: 2.0\n'
                 '/robot1/flow_node:\n  ros__parameters:\n    lk_win: 15\n'
                 'right_camera_node:\n  ros__parameters:\n    ncc_min: 0.5\n')
    assert load_params_file(f, 'flow_node') == {'min_eig': 0.002, 'diagnostics_period_s': 2.0, 'lk_win': 15}
    assert load_params_file(f, 'estimator_node') == {'diagnostics_period_s': 2.0}


def test_numbers_written_without_a_dot_are_numbers():
    """YAML 1.1 reads 1e6 as a string; ROS reads it as a number, and so do we."""
    spec = NODE_PARAMS['estimator_node']['fixation_weight']
    assert spec.check('1e6') == 1e6 and spec.check(parse_value('fixation_weight', '1e-3')) == 1e-3
    with pytest.raises(ParamsError, match='out of range'):
        spec.check('1e308')
    with pytest.raises(ParamsError, match='is not a YAML value'):
        parse_value('min_eig', '[')


def test_generated_files_apply_under_any_node_name_but_replay_gives_each_to_its_node(tmp_path):
    """config/<node>.yaml is one /** block (ROS applies it to the node whatever its name or namespace); its
    marker line tells fixego replay, which reads several nodes' files, whose block it is: fb_max_px is the
    fixation tracker's (1.0) in camera_node.yaml and the flow's (0.5) in flow_node.yaml, in either order."""
    import argparse

    import yaml

    from fixego_ros.geometry.rig import load_rig
    from fixego_ros.pipeline.params import file_node
    from fixego_ros.replay.cli import settings_from_args

    for node in NODE_PARAMS:
        path = CONFIG / f'{node}.yaml'
        assert list(yaml.safe_load(path.read_text())) == ['/**'] and file_node(path) == node
    assert load_params_file(CONFIG / 'camera_node.yaml', 'flow_node') == {}
    assert load_params_file(CONFIG / 'flow_node.yaml', 'camera_node') == {}
    rig = load_rig(CONFIG / 'rig.yaml')
    files = [CONFIG / 'camera_node.yaml', CONFIG / 'flow_node.yaml', CONFIG / 'estimator_node.yaml']
    for order in (files, files[::-1]):
        args = argparse.Namespace(params_file=order, preset=None, keyframe_max_frames=None, window=None, mode=None,
                                  speed_topic=None, speed_default_std=None, param=[], vergence_topic=None,
                                  fixations=None, inputs=None)
        s = settings_from_args(args, rig)
        assert s.fixation.fb_max_px == 1.0 and s.flow.fb_max_px == 0.5
    # a file without the marker: its /** block reaches every node that has the parameter, as in ROS
    f = tmp_path / 'p.yaml'
    f.write_text('/**:\n  ros__parameters:\n    fb_max_px: 0.8\n')
    assert load_params_file(f, 'camera_node') == {'fb_max_px': 0.8} == load_params_file(f, 'flow_node')
