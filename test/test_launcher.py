"""The demo's node processes import the package this process imports, wherever they are started from."""

from __future__ import annotations

import subprocess
import sys

from fixego_ros.demo.launcher import NodeSpec


def _run_from(cwd, module: str) -> subprocess.CompletedProcess:
    argv = NodeSpec('probe', module).argv()
    return subprocess.run(argv[:argv.index('--ros-args')], cwd=cwd, capture_output=True, text=True, timeout=60)


def test_a_node_started_in_a_folder_with_another_fixego_ros_imports_this_one(tmp_path):
    """``fixego demo`` run from a checkout started that checkout's nodes, not the ones ``PYTHONPATH`` named, so a
    comparison of two codes ran the same nodes on both sides (stop 68). A decoy package in the working directory
    that fails on import shows which one a node gets."""
    decoy = tmp_path / 'fixego_ros'
    (decoy / 'geometry').mkdir(parents=True)
    (decoy / '__init__.py').write_text('raise SystemExit(3)\n')
    (decoy / 'geometry' / '__init__.py').write_text('')
    (decoy / 'geometry' / 'rotation.py').write_text('')
    done = _run_from(tmp_path, 'fixego_ros.geometry.rotation')
    assert done.returncode == 0, done.stderr
    # the control: a plain ``python -m`` there takes the decoy
    plain = subprocess.run([sys.executable, '-m', 'fixego_ros.geometry.rotation'], cwd=tmp_path,
                           capture_output=True, text=True, timeout=60)
    assert plain.returncode == 3
