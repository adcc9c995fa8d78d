"""One definition per parameter: the core's config dataclasses default to what the nodes' specs build.

The specs (``fixego_ros.pipeline.params``) are what a user gets from the nodes, ``fixego replay`` and the config
files; the dataclasses are what a script or test gets from ``EstimatorConfig()``, ``FlowParams()``... The two must
not tell different stories. Values the builders derive from the rig (angles = pixels / focal length) are
compared for the default rig (config/rig.yaml), which is what the dataclass comments say they are.
"""

from __future__ import annotations

import dataclasses
import math

import pytest

from fixego_ros.estimation.config import EstimatorConfig, papers_config
from fixego_ros.estimation.twoframe import SolverConfig
from fixego_ros.geometry.rig import default_rig_path, load_rig
from fixego_ros.pipeline.frontend import KeyframePolicy
from fixego_ros.pipeline.params import (
    CAMERA_NODE_PARAMS,
    ESTIMATOR_PARAMS,
    FIXATION_PARAMS,
    FLOW_PARAMS,
    estimator_config,
    fixation_params,
    flow_params,
    keyframe_policy,
    params_getter,
    sync_params,
)
from fixego_ros.pipeline.sync import SyncParams
from fixego_ros.tracking.fixation import FixationParams
from fixego_ros.tracking.flow import FlowParams

RIG = load_rig(default_rig_path())


def _differences(built: object, default: object, prefix: str = '') -> list[str]:
    out = []
    for f in dataclasses.fields(default):
        a, b = getattr(built, f.name), getattr(default, f.name)
        if dataclasses.is_dataclass(b):
            out += _differences(a, b, f'{prefix}{f.name}.')
        elif a != b:
            out.append(f'{prefix}{f.name}: the spec builds {a!r}, the dataclass defaults to {b!r}')
    return out


def _camera_node_builders():
    pytest.importorskip('rclpy')
    from fixego_ros.nodes.camera_node import CameraNode, servo_params
    from fixego_ros.tracking.servo import ServoParams
    from fixego_ros.tracking.vergence import VergenceParams, VergenceSchedule
    g = params_getter(CAMERA_NODE_PARAMS)
    return [(servo_params(g), ServoParams()), (CameraNode._vergence_params(None, g), VergenceParams()),
            (CameraNode._vergence_schedule(g), VergenceSchedule())]


CORE = {
    'FixationParams': lambda: (fixation_params(params_getter(FIXATION_PARAMS)), FixationParams()),
    'FlowParams': lambda: (flow_params(params_getter(FLOW_PARAMS)), FlowParams()),
    'KeyframePolicy': lambda: (keyframe_policy(params_getter(FLOW_PARAMS)), KeyframePolicy()),
    'SyncParams': lambda: (sync_params(params_getter(FLOW_PARAMS)), SyncParams()),
    'EstimatorConfig': lambda: (estimator_config(params_getter(ESTIMATOR_PARAMS), RIG), EstimatorConfig()),
}


@pytest.mark.parametrize('name', list(CORE))
def test_core_dataclass_defaults_are_the_node_defaults(name):
    built, default = CORE[name]()
    assert _differences(built, default) == []


def test_camera_node_dataclass_defaults_are_the_node_defaults():
    for built, default in _camera_node_builders():
        assert _differences(built, default) == [], type(default).__name__


def test_the_comparison_sees_nested_and_rig_derived_fields():
    """The walk reaches the solver and the smoother, and the rig-derived angles differ on another rig (so
    the equality above is about the default rig, as documented, not a coincidence of the walk)."""
    built = estimator_config(params_getter(ESTIMATOR_PARAMS, {'loss': 'cauchy', 'smoother_lag_s': 5.0}), RIG)
    assert {d.split(':')[0] for d in _differences(built, EstimatorConfig())} == {'solver.loss', 'smoother.lag_s'}
    rig = load_rig(default_rig_path())
    other = dataclasses.replace(rig, right=dataclasses.replace(rig.right, fx=500.0))
    diff = _differences(estimator_config(params_getter(ESTIMATOR_PARAMS), other), EstimatorConfig())
    assert {d.split(':')[0] for d in diff} == {'solver.sigma', 'solver.min_parallax', 'solver.camera_parallax'}
    assert SolverConfig().sigma == 1.0 / RIG.right.fx
    assert math.isclose(SolverConfig().min_parallax, 0.3 / RIG.right.fx)


def test_papers_config_is_what_paper_sim_measured_with():
    """``fixego paper-sim`` and the core benchmark keep the configuration their published numbers came from."""
    c = papers_config(window=5)
    assert (c.window, c.mode, c.max_step_translation, c.max_step_rotation, c.max_speed, c.constant_speed) == (
        5, 'paper', 1.0, 0.35, math.inf, False)
    assert (c.solver.loss, c.solver.max_nfev, c.solver.min_parallax) == ('linear', 60, 1e-7)


# ------------------------------------------------------------------------------ the generated reference
def test_parameter_reference_equals_what_the_specs_generate(tmp_path):
    """docs/parameters.md is generated: regenerate it (--write-docs) after changing a spec."""
    from pathlib import Path

    from fixego_ros.pipeline.params import NODE_PARAMS, main, render_docs
    committed = Path(__file__).resolve().parents[1] / 'docs' / 'parameters.md'
    assert committed.read_text() == render_docs(), 'run: python -m fixego_ros.pipeline.params --write-docs ' \
                                                   'docs/parameters.md'
    text = render_docs()
    sections = {part.split('\n', 1)[0]: part for part in text.split('\n## ')[1:]}
    assert list(sections) == list(NODE_PARAMS)                 # one table per node, every parameter a row
    for node, table in NODE_PARAMS.items():
        rows = [line for line in sections[node].splitlines() if line.startswith('| `')]
        assert [r.split('`')[1] for r in rows] == list(table)
        for row, spec in zip(rows, table.values(), strict=True):
            cells = [c.strip() for c in row.strip('|').split(' | ')]
            assert cells[4] == ('read-only' if spec.read_only else 'run-time'), row
    stale = tmp_path / 'parameters.md'
    stale.write_text(text.replace('| `servo_gain` | float | `0.9`', '| `servo_gain` | float | `0.8`'))
    assert main(['--check-docs', str(stale)]) == 1
    assert main(['--write-docs', str(stale)]) == 0 and main(['--check-docs', str(stale)]) == 0
