"""Intrinsics the rig file leaves out: camera_calibration YAML files named by the rig file, the first CameraInfo
of each camera (merge, disagreement with the rig file), and ``fixego replay`` of a bag whose rig file has none."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from fixego_ros.geometry.rig import CameraModel, RigError, default_rig_path, load_rig, rig_from_dict
from fixego_ros.pipeline.camera_info import IntrinsicsFromInfo, camera_from_info, disagreement

BAGS = Path(__file__).resolve().parents[1] / 'bags'
CAM = CameraModel(640, 480, 1700.5, 1702.0, 319.5, 241.0, (-0.12, 0.05, 0.001, -0.0005, 0.0))

CALIBRATION = """image_width: 640
image_height: 480
camera_name: right_evi
camera_matrix:
  rows: 3
  cols: 3
  data: [1700.5, 0, 319.5, 0, 1702.0, 241.0, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.12, 0.05, 0.001, -0.0005, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [1700.5, 0, 319.5, 0, 0, 1702.0, 241.0, 0, 0, 0, 1, 0]
"""


def info(cam: CameraModel = CAM, **change) -> SimpleNamespace:
    msg = SimpleNamespace(width=cam.width, height=cam.height, distortion_model='plumb_bob', d=list(cam.dist),
                          k=[cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0])
    for k, v in change.items():
        setattr(msg, k, v)
    return msg


def rig_dict(**sides) -> dict:
    d = yaml.safe_load(default_rig_path().read_text())
    for side, block in sides.items():
        if block is None:
            d.pop(side)
        else:
            d[side] = block
    return d


# ---------------------------------------------------------------------------------------------- load
def test_rig_file_names_calibration_files_relative_to_itself(tmp_path):
    (tmp_path / 'cal').mkdir()
    (tmp_path / 'cal' / 'right.yaml').write_text(CALIBRATION)
    d = rig_dict(right={'calibration': 'cal/right.yaml'}, left=None)
    (tmp_path / 'rig.yaml').write_text(yaml.safe_dump(d))
    rig = load_rig(tmp_path / 'rig.yaml', [])
    assert rig.right == CAM
    assert rig.left is None and rig.missing_intrinsics() == ('left',)
    with pytest.raises(RigError, match='no intrinsics for the left camera'):
        rig.camera('left')
    with pytest.raises(RigError, match='the simulator needs the intrinsics of the left camera'):
        rig.require_intrinsics('the simulator')
    rig.require_intrinsics('camera_node', ('right',))
    # saved, the rig is self-contained: the numbers inline
    rig.save(tmp_path / 'saved.yaml')
    assert load_rig(tmp_path / 'saved.yaml', []).right == CAM


@pytest.mark.parametrize('text, match', [
    (CALIBRATION.replace('plumb_bob', 'equidistant'), "distortion_model 'equidistant' is not supported"),
    (CALIBRATION.replace('1700.5, 0, 319.5', '1700.5, 0'), r'camera_matrix\.data must be 9 numbers'),
    (CALIBRATION.replace('image_width: 640\n', ''), 'missing image_width'),
    (CALIBRATION.replace('1702.0, 241.0, 0, 0, 1]', '1702.0, 2410.0, 0, 0, 1]'), 'principal point'),
    (': [', 'not valid YAML'),
])
def test_bad_calibration_files_are_errors_naming_the_file(tmp_path, text, match):
    (tmp_path / 'right.yaml').write_text(text)
    (tmp_path / 'rig.yaml').write_text(yaml.safe_dump(rig_dict(right={'calibration': 'right.yaml'})))
    with pytest.raises(RigError, match=match) as e:
        load_rig(tmp_path / 'rig.yaml')
    assert 'right.yaml' in str(e.value)


def test_calibration_excludes_inline_intrinsics_and_a_missing_file_is_named(tmp_path):
    (tmp_path / 'rig.yaml').write_text(yaml.safe_dump(rig_dict(right={'calibration': 'r.yaml', 'fx': 500.0})))
    with pytest.raises(RigError, match='give no other right keys'):
        load_rig(tmp_path / 'rig.yaml')
    (tmp_path / 'rig.yaml').write_text(yaml.safe_dump(rig_dict(right={'calibration': 'nope.yaml'})))
    with pytest.raises(RigError, match=r'nope\.yaml: cannot read'):
        load_rig(tmp_path / 'rig.yaml')


# ---------------------------------------------------------------------------------------------- merge
def test_missing_intrinsics_come_from_the_first_camera_info():
    rig = rig_from_dict(rig_dict(right=None, left={'width': 640, 'height': 480}), [])
    assert rig.missing_intrinsics() == ('right', 'left')
    fill = IntrinsicsFromInfo(rig)
    assert not fill.ready('right')
    assert fill.on_info('right', info()) and fill.rig.right == CAM and fill.ready('right')
    assert not fill.on_info('right', info(k=[1.0] * 9))          # only the first is examined
    other = CameraModel(320, 240, 800.0, 800.0, 160.0, 120.0)
    assert not fill.on_info('left', info(other))                 # the rig file says 640x480: not used
    assert 'rig file says 640x480 but left/camera_info is 320x240' in fill.errors['left']
    assert fill.rig.left is None and fill.source == {'right': 'camera_info'}


def test_camera_info_agreeing_with_the_rig_file_is_silent_and_a_disagreement_names_both():
    rig = rig_from_dict(rig_dict(right=CAM.to_dict()), [])
    fill = IntrinsicsFromInfo(rig)
    cam = CameraModel(640, 480, CAM.fx + 0.4, CAM.fy - 0.4, CAM.cx, CAM.cy, tuple(x + 5e-7 for x in CAM.dist))
    assert not fill.on_info('right', info(cam)) and fill.errors == {}      # within 0.5 px and 1e-6
    for changed, what in ((CameraModel(640, 480, CAM.fx + 0.6, CAM.fy, CAM.cx, CAM.cy, CAM.dist), 'K'),
                          (CameraModel(640, 480, CAM.fx, CAM.fy, CAM.cx, CAM.cy, (-0.12, 0.05, 0.001, -0.0005, 1e-5)),
                           'D'),
                          (CameraModel(800, 600, CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.dist), 'image size')):
        assert what in disagreement(CAM, changed)
        fill = IntrinsicsFromInfo(rig)
        assert not fill.on_info('right', info(changed))
        err = fill.errors['right']
        assert f'disagree on {what}' in err and 'fx 1700.5' in err and 'using the rig file' in err
        assert fill.rig.right == CAM


@pytest.mark.parametrize('change, match', [
    ({'k': [0.0] * 9}, 'not a calibrated camera matrix'),
    ({'distortion_model': 'rational_polynomial', 'd': [0.0] * 8}, "'rational_polynomial' is not supported"),
    ({'d': [0.0] * 6}, '5 distortion coefficients'),
])
def test_unusable_camera_info_is_explained(change, match):
    with pytest.raises(ValueError, match=match):
        camera_from_info(info(**change))
    assert camera_from_info(info(d=[])).dist == (0.0,) * 5           # empty D: no distortion
    fill = IntrinsicsFromInfo(rig_from_dict(rig_dict(right=None), []))
    assert not fill.on_info('right', info(**change))
    assert 'no intrinsics for the right camera' in fill.errors['right']


# ---------------------------------------------------------------------------------------------- replay
def _replay(bag: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'fixego_ros.cli', 'replay', str(bag), '--out', str(out),
                           '--no-progress', '--quiet'], capture_output=True, text=True, timeout=300)


def test_replay_takes_the_bags_camera_info_when_the_rig_file_has_no_intrinsics(tmp_path):
    src = BAGS / 'walk'
    bag = tmp_path / 'walk'
    shutil.copytree(src, bag)
    d = yaml.safe_load((src / 'rig.yaml').read_text())
    assert 'right' in d and 'left' in d
    d.pop('right')
    d['left'] = {'width': d['left']['width'], 'height': d['left']['height']}
    (bag / 'rig.yaml').write_text(yaml.safe_dump(d))
    ref, got = _replay(src, tmp_path / 'ref' / 'est.tum'), _replay(bag, tmp_path / 'got' / 'est.tum')
    assert ref.returncode == 0 and got.returncode == 0, got.stderr
    # the simulator writes the rig's intrinsics into camera_info: the same numbers, the same trajectory
    assert (tmp_path / 'got' / 'est.tum').read_bytes() == (tmp_path / 'ref' / 'est.tum').read_bytes()
    assert 'error' not in got.stderr
    # a rig file that disagrees with the bag's camera_info: said, and the rig file is used
    d = yaml.safe_load((src / 'rig.yaml').read_text())
    d['right']['fx'] += 3.0
    (bag / 'rig.yaml').write_text(yaml.safe_dump(d))
    p = _replay(bag, tmp_path / 'dis' / 'est.tum')
    assert p.returncode == 0 and 'error: right intrinsics: the rig file and right/camera_info disagree on K' \
        in p.stderr, p.stderr


def test_replay_without_intrinsics_anywhere_fails_with_one_line(tmp_path):
    from test_replay import rewrite
    bag = rewrite(BAGS / 'walk', tmp_path / 'noinfo', lambda topic, msgtype, msg, t:
                  [] if topic.endswith('camera_info') else [(topic, msgtype, msg, t)], frames=3)
    d = yaml.safe_load((bag / 'rig.yaml').read_text())
    d.pop('left')
    (bag / 'rig.yaml').write_text(yaml.safe_dump(d))
    p = _replay(bag, tmp_path / 'est.tum')
    assert p.returncode == 2 and 'Traceback' not in p.stderr
    assert 'no intrinsics for the left camera' in p.stderr and '/fixego/left/camera_info' in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_the_simulator_needs_the_intrinsics_in_the_rig_file(tmp_path):
    from fixego_ros.cli_options import OptionError
    from fixego_ros.sim.cli import read_rig
    (tmp_path / 'rig.yaml').write_text(yaml.safe_dump(rig_dict(left=None)))
    with pytest.raises(OptionError, match=r'the simulator .* needs the intrinsics of the left camera'):
        read_rig(tmp_path / 'rig.yaml')
