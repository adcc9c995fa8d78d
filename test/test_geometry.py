"""Rotation/composition helpers (property tests) and the rig model (pixels <-> rays, kinematics, file)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fixego_ros.geometry.rig import (
    CameraModel,
    RigError,
    default_rig_path,
    load_rig,
    make_rig,
    pan_tilt_rotation,
    rig_from_dict,
)
from fixego_ros.geometry.rotation import (
    Pose,
    base_link_pose_to_rig,
    exp_so3,
    from_quat_xyzw,
    log_so3,
    quat_xyzw,
    rig_pose_to_base_link,
    rotation_error_paper,
    skew,
)

finite = st.floats(-3.0, 3.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
rotvec = st.tuples(*[st.floats(-1.8, 1.8)] * 3).map(np.array)
poses = st.tuples(rotvec, vec3).map(lambda p: Pose.from_rvec(*p))


@given(rotvec)
def test_exp_log_roundtrip_and_orthonormal(w):
    R = exp_so3(w)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    if np.linalg.norm(w) < np.pi - 1e-6:
        assert np.allclose(log_so3(R), w, atol=1e-9)


@given(vec3, vec3)
def test_skew_is_cross(a, b):
    assert np.allclose(skew(a) @ b, np.cross(a, b))


@settings(max_examples=60)
@given(poses, poses, poses, vec3)
def test_composition_associative_and_applies_in_order(a, b, c, x):
    left, right = (a @ b) @ c, a @ (b @ c)
    assert np.allclose(left.R, right.R, atol=1e-12) and np.allclose(left.t, right.t, atol=1e-9)
    assert np.allclose((a @ b).apply(x), a.apply(b.apply(x)), atol=1e-9)


@given(poses)
def test_inverse(p):
    e = p @ p.inverse()
    assert np.allclose(e.R, np.eye(3), atol=1e-12) and np.allclose(e.t, 0, atol=1e-9)


@given(rotvec)
def test_quaternion_roundtrip(w):
    R = exp_so3(w)
    q = quat_xyzw(R)
    assert q[3] >= 0 and np.isclose(np.linalg.norm(q), 1)
    assert np.allclose(from_quat_xyzw(q), R, atol=1e-12)


@given(rotvec)
def test_quaternion_is_scipys_to_the_bit(w):
    # the plain-float formula replaced Rotation.from_matrix for speed: TUM files and messages must not change
    R = exp_so3(w)
    q = Rotation.from_matrix(R).as_quat()
    assert np.array_equal(quat_xyzw(R), -q if q[3] < 0 else q)


def test_quaternion_of_a_half_turn():
    for R in (np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])):
        q = quat_xyzw(R)
        assert np.allclose(from_quat_xyzw(q), R, atol=1e-12) and q[3] >= 0


@given(poses)
def test_base_link_conversion_roundtrip_and_axes(p):
    back = base_link_pose_to_rig(rig_pose_to_base_link(p))
    assert np.allclose(back.R, p.R) and np.allclose(back.t, p.t)


def test_base_link_axes():
    # moving forward along the rig's optical z is +x in base_link; rig down (+y) is base_link -z
    assert np.allclose(rig_pose_to_base_link(Pose(np.eye(3), np.array([0, 0, 1.0]))).t, [1, 0, 0])
    assert np.allclose(rig_pose_to_base_link(Pose(np.eye(3), np.array([0, 1.0, 0]))).t, [0, 0, -1])
    assert np.allclose(rig_pose_to_base_link(Pose(np.eye(3), np.array([1.0, 0, 0]))).t, [0, -1, 0])


def test_quaternion_rejects_bad_input():
    with pytest.raises(ValueError):
        from_quat_xyzw(np.zeros(4))
    with pytest.raises(ValueError):
        from_quat_xyzw(np.array([np.nan, 0, 0, 1]))


def test_rotation_error_is_papers_measure():
    R = exp_so3([0, 0.01, 0])
    assert rotation_error_paper(R, R) == pytest.approx(0.0, abs=1e-12)
    assert rotation_error_paper(exp_so3([0, 0.02, 0]), R) == pytest.approx(1.0)


def test_pan_tilt_signs_follow_design():
    z = np.array([0, 0, 1.0])
    assert pan_tilt_rotation(0.3, 0.0) @ z @ np.array([1, 0, 0]) > 0     # +pan looks right (+x)
    assert pan_tilt_rotation(0.0, 0.3) @ z @ np.array([0, 1, 0]) < 0     # +tilt looks up (-y)


def test_pixels_rays_roundtrip_with_distortion():
    cam = CameraModel(640, 480, 600.0, 610.0, 320.0, 240.0, (-0.2, 0.05, 0.001, -0.001, 0.0))
    uv = np.array([[10.0, 20.0], [320.0, 240.0], [600.0, 450.0]])
    rays = cam.pixels_to_rays(uv)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
    assert np.allclose(cam.rays_to_pixels(rays), uv, atol=1e-3)
    assert np.allclose(rays[1], [0, 0, 1])


def test_rig_rays_apply_calibration():
    rig = make_rig()
    centre = rig.right.center[None]
    assert np.allclose(rig.pixels_to_rig_rays('right', centre, 0.0, 0.0), [[0, 0, 1]])
    d = rig.pixels_to_rig_rays('left', centre, np.radians(30), 0.0)[0]
    assert np.isclose(np.degrees(np.arctan2(d[0], d[2])), 30.0)


def test_default_rig_file_loads_and_roundtrips(tmp_path):
    rig = load_rig(default_rig_path())
    assert rig.right.width == 640 and np.allclose(rig.c_L, [-0.2, 0, 0])
    assert 20.0 < np.degrees(rig.right.horizontal_fov()) < 22.0
    rig.save(tmp_path / 'r.yaml')
    again = load_rig(tmp_path / 'r.yaml')
    assert again.right == rig.right and np.allclose(again.R_L, rig.R_L)


@pytest.mark.parametrize('mutate, key', [
    (lambda d: d['right'].pop('fx'), 'right.fx'),
    (lambda d: d['right'].__setitem__('fy', 'abc'), 'right.fy'),
    (lambda d: d['left'].__setitem__('fx', -3.0), 'left.fx'),
    (lambda d: d['right'].__setitem__('dist', [0, 0]), 'right.dist'),
    (lambda d: d['left_in_rig'].__setitem__('rotation_xyzw', [0, 0, 0, 0]), 'left_in_rig.rotation_xyzw'),
    (lambda d: d['left_in_rig'].pop('translation'), 'left_in_rig.translation'),
    (lambda d: d['pan_tilt']['left'].__setitem__('pan_sign', 2), 'pan_tilt.left.pan_sign'),
    (lambda d: d['right'].__setitem__('cx', float('nan')), 'right.cx'),
])
def test_rig_errors_name_the_key(mutate, key):
    d = yaml.safe_load(default_rig_path().read_text())
    mutate(d)
    with pytest.raises(RigError, match=key.replace('.', r'\.')):
        rig_from_dict(d)


def test_rig_file_errors_name_the_file(tmp_path):
    p = tmp_path / 'bad.yaml'
    p.write_text('right: [1, 2\n')
    with pytest.raises(RigError, match='not valid YAML'):
        load_rig(p)
    with pytest.raises(RigError, match=r'missing\.yaml: does not exist'):
        load_rig(tmp_path / 'missing.yaml')
    with pytest.raises(RigError, match='not a regular file'):
        load_rig(tmp_path)
    p.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(RigError, match=r'bad.yaml: not text \(UTF-8\)'):
        load_rig(p)


# ------------------------------------------------------------------------------------ rig file: keys and values
@pytest.mark.parametrize('mutate, match', [
    (lambda d: d['pan_tilt']['right'].update(pan_offst=0.1),
     r"unknown key pan_tilt\.right\.pan_offst \(did you mean 'pan_offset'\?\)"),
    (lambda d: d['right'].update(fxx=1700.0), r"unknown key right\.fxx \(did you mean 'fx'\?\)"),
    (lambda d: d['left'].update(distortion=[0, 0, 0, 0, 0]), r"unknown key left\.distortion \(did you mean 'dist"),
    (lambda d: d['left_in_rig'].update(rotation=[0, 0, 0, 1]),
     r"unknown key left_in_rig\.rotation \(did you mean 'rotation_xyzw'\?\)"),
    (lambda d: d['pan_tilt'].update(rigth={'pan_sign': 1}), r"unknown key pan_tilt\.rigth \(did you mean 'right'\?\)"),
    (lambda d: d.update(rig_in_base_link={'translation': [0, 0, 0], 'rotation_xyz': [0, 0, 0, 1]}),
     r"unknown key rig_in_base_link\.rotation_xyz \(did you mean 'rotation_xyzw'\?\)"),
    (lambda d: d['right'].update(width='640'), r'right\.width must be a number'),
    (lambda d: d['right'].update(fx=True), r'right\.fx must be a number'),
    (lambda d: d['right'].update(cy=float('inf')), r'right\.cy must be finite'),
    (lambda d: d['right'].update(width=640.5), r'right\.width/height must be integers'),
    (lambda d: d['right'].update(dist=[0, 0, 0, 0, 0, 0]), r'right\.dist must be a list of 5 numbers'),
    (lambda d: d['right'].update(dist=['0', 0, 0, 0, 0]), r'right\.dist must be a list of 5 numbers'),
    (lambda d: d['left_in_rig'].update(translation=[0.2, 0.0]), r'left_in_rig\.translation must be a list of 3'),
    (lambda d: d['left_in_rig'].update(translation=[0.2, float('nan'), 0.0]), r'left_in_rig\.translation .* finite'),
    (lambda d: d['left_in_rig'].update(rotation_xyzw=[0, 0, 0, 2]), r'left_in_rig\.rotation_xyzw must be a unit '
                                                                    r'quaternion .* of norm 2'),
    (lambda d: d['left_in_rig'].update(rotation_xyzw=[0, 0, 0, 0]), r'rotation_xyzw must be a unit quaternion'),
    (lambda d: d.update(rig_in_base_link={'translation': [0, 0, 0], 'rotation_xyzw': [1, 1, 0, 0]}),
     r'rig_in_base_link\.rotation_xyzw must be a unit quaternion'),
    (lambda d: d.update(pan_tilt=[1, 2]), r'pan_tilt must be a mapping'),
    (lambda d: d['pan_tilt']['left'].update(tilt_offset='0.1'), r'pan_tilt\.left\.tilt_offset must be a number'),
    # plausibility: typos that would otherwise give a garbage trajectory
    (lambda d: d['right'].update(fx=1e308), r'right\.fx = 1e\+308 px is not a focal length'),
    (lambda d: d['left'].update(fy=1e-300), r'left\.fy = 1e-300 px is not a focal length'),
    (lambda d: d['right'].update(cx=5000.0), r'right: principal point \(5000, .*\) lies outside'),
    (lambda d: d['right'].update(dist=[1e10, 0, 0, 0, 0]), r'right\.dist .* not a lens model'),
    (lambda d: d['left_in_rig'].update(translation=[0.0, 0.0, 0.0]), r'a baseline of 0 m is not a rig'),
    (lambda d: d['left_in_rig'].update(translation=[-1e300, 0.0, 0.0]),
     r'\[-1e\+300, 0.0, 0.0\]: a baseline of .* m is not a rig'),
    (lambda d: d['pan_tilt']['right'].update(tilt_offset=1e300), r'tilt_offset = 1e\+300 rad is beyond'),
    (lambda d: d['right'].update(width=10**6), r'larger than 16384 px'),
])
def test_rig_file_misspelt_keys_and_bad_values_are_errors_naming_the_key(mutate, match):
    """Inside the fixed blocks a misspelt key would silently fall back to a default: it is an error naming the
    key, where it is, and the closest known one."""
    d = yaml.safe_load(default_rig_path().read_text())
    mutate(d)
    with pytest.raises(RigError, match=match):
        rig_from_dict(d)


def test_rig_file_unknown_top_level_keys_are_kept_and_reported(tmp_path, caplog):
    d = yaml.safe_load(default_rig_path().read_text())
    d['notes'] = 'rig of bench 2'
    d['pan_tlit'] = {'right': {'pan_offset': 0.1}}
    d['rig_in_base_link'] = {'translation': [0.1, 0, 1.2], 'rotation_xyzw': [0.5, -0.5, 0.5, -0.5]}
    notes: list[str] = []
    rig = rig_from_dict(d, notes)
    assert len(notes) == 2, notes
    assert "'notes'" in notes[0] and "'pan_tlit'" in notes[1] and "did you mean 'pan_tilt'" in notes[1]
    assert rig.extra['notes'] == 'rig of bench 2' and 'rig_in_base_link' not in rig.extra   # a known key
    np.testing.assert_allclose(rig.mount.t, [0.1, 0, 1.2])
    path = tmp_path / 'r.yaml'
    rig.save(path)
    notes = []
    load_rig(path, notes)
    assert len(notes) == 2 and all(n.startswith(f'{path}: ') for n in notes)
    with caplog.at_level('WARNING'):          # no list given: logged, never silent
        load_rig(path)
    assert sum('unknown top-level key' in r.getMessage() for r in caplog.records) == 2
    # hand-written quaternions with 4 decimals are unit enough
    d = yaml.safe_load(default_rig_path().read_text())
    d['left_in_rig']['rotation_xyzw'] = [0.0, 0.7071, 0.0, 0.7071]
    assert np.allclose(rig_from_dict(d, []).R_L @ [0, 0, 1], [1, 0, 0], atol=1e-6)
