"""Package shape: ``colcon build`` (colcon from PyPI) installs what ``ros2 run`` needs; core is ROS-free."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _console_scripts() -> list[str]:
    text = (ROOT / 'setup.py').read_text()
    return [line.split('=')[0].strip().strip("'\"") for line in text.splitlines()
            if 'fixego_ros.' in line and ':main' in line]


def test_colcon_build_installs_executables_and_ament_marker(tmp_path):
    colcon = shutil.which('colcon') or str(Path(sys.executable).parent / 'colcon')
    if not Path(colcon).exists():
        pytest.fail('colcon is not installed (it is a test extra: pip install -e .[test])')
    src = tmp_path / 'src' / 'fixego_ros'
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns('.venv', '.git', 'build', 'install', 'log',
                                                             '*.egg-info', '__pycache__', 'bags', 'docs'))
    env = dict(os.environ, PATH=f'{Path(sys.executable).parent}:{os.environ.get("PATH", "")}')
    proc = subprocess.run([colcon, 'build', '--base-paths', 'src', '--event-handlers', 'console_direct-'],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    install = tmp_path / 'install' / 'fixego_ros'
    assert (install / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'fixego_ros').exists()
    assert (install / 'share' / 'fixego_ros' / 'package.xml').exists()
    assert (install / 'share' / 'fixego_ros' / 'config' / 'rig.yaml').exists()
    for launch in ('fixego.launch.py', 'sim.launch.py', 'replay.launch.py'):
        assert (install / 'share' / 'fixego_ros' / 'launch' / launch).exists(), launch
    scripts = _console_scripts()
    assert 'fixego' in scripts
    for exe in scripts:
        path = install / 'lib' / 'fixego_ros' / exe
        assert path.exists() and os.access(path, os.X_OK), exe


def test_core_does_not_import_rclpy():
    """Every module outside ``nodes`` (and the bag/CDR helpers that serialise with rclpy) stays ROS-free."""
    code = (
        'import importlib, pkgutil, sys, fixego_ros\n'
        'skip = ("fixego_ros.nodes", "fixego_ros.bench", "fixego_ros.sim.bag_writer", "fixego_ros.sim.cli",\n'
        '        "fixego_ros.sim.run")\n'
        'for m in pkgutil.walk_packages(fixego_ros.__path__, "fixego_ros."):\n'
        '    if not m.name.startswith(skip):\n'
        '        importlib.import_module(m.name)\n'
        '        assert "rclpy" not in sys.modules, m.name + " imported rclpy"\n'
    )
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
