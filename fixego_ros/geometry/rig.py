"""The rig model: two calibrated pan/tilt cameras and the calibration file of DESIGN.md §4.

Frames (DESIGN.md §2): a camera's optical frame is x right, y down, z forward. Its *zero-pose frame*
is the optical frame at pan = tilt = 0, and ``R_zero_cam(pan, tilt) = R_y(pan) R_x(tilt)``. The rig
frame is the right camera's zero-pose frame; the left zero-pose frame has rotation ``R_L`` and centre
``c_L`` in the rig frame. Joint angles as the device reports them are mapped to kinematic angles by
the rig file's ``pan_tilt`` block: ``angle = sign * reading + offset``.
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
import math
import numbers
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from fixego_ros.geometry.rotation import Pose, default_mount, from_quat_xyzw, quat_xyzw, rot_x, rot_y

SIDES = ('right', 'left')


class RigError(ValueError):
    """A rig file or dictionary is missing a key or has a bad value; the message names the key."""


def pan_tilt_rotation(pan: float, tilt: float) -> np.ndarray:
    """``R_zero_cam``: optical frame at (pan, tilt) expressed in the zero-pose frame."""
    return rot_y(pan) @ rot_x(tilt)


def pan_tilt_for_direction(d: np.ndarray) -> tuple[float, float]:
    """Kinematic (pan, tilt) whose optical axis points along ``d`` (zero-pose frame): inverse of
    ``pan_tilt_rotation(pan, tilt) @ [0, 0, 1]``."""
    x, y, z = (float(v) for v in d)
    return float(np.arctan2(x, z)), float(np.arctan2(-y, np.hypot(x, z)))


def normalize_rays(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the rows of ``v`` (shape (N, 3) or (3,))."""
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with OpenCV's 5-parameter distortion (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=float)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist_array != 0.0))

    @property
    def center(self) -> np.ndarray:
        """Principal point (where the fixation servo keeps its point)."""
        return np.array([self.cx, self.cy])

    def horizontal_fov(self) -> float:
        """Horizontal angle of view in rad (pinhole, ignoring distortion)."""
        return float(2.0 * np.arctan2(self.width / 2.0, self.fx))

    def pixels_to_rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit rays in the optical frame for pixels (N, 2), undistorting with OpenCV."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if uv.size == 0:
            return np.zeros((0, 3))
        if self.has_distortion:
            # iterative with a tight criterion: the default 5 iterations leave ~px errors at the corners
            xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist_array, None, None, None,
                                     (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)).reshape(-1, 2)
        else:
            xy = np.column_stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy])
        return normalize_rays(np.column_stack([xy, np.ones(len(xy))]))

    def rays_to_pixels(self, rays: np.ndarray, distort: bool = True) -> np.ndarray:
        """Pixels (N, 2) of optical-frame rays (N, 3) with z > 0; ``distort=False`` gives ideal pixels."""
        rays = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
        xy = rays[:, :2] / rays[:, 2:3]
        if distort and self.has_distortion:
            pts = np.column_stack([xy, np.ones(len(xy))]).reshape(-1, 1, 3)
            uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist_array)
            return uv.reshape(-1, 2)
        return np.column_stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy])

    def to_dict(self) -> dict[str, Any]:
        return {'width': int(self.width), 'height': int(self.height), 'fx': float(self.fx), 'fy': float(self.fy),
                'cx': float(self.cx), 'cy': float(self.cy), 'dist': [float(d) for d in self.dist]}


@dataclass(frozen=True)
class PanTiltCalibration:
    """Maps the device's joint angles (rad) to the kinematic angles of DESIGN.md §2."""

    pan_sign: float = 1.0
    tilt_sign: float = 1.0
    pan_offset: float = 0.0
    tilt_offset: float = 0.0

    def kinematic(self, pan_reading: float, tilt_reading: float) -> tuple[float, float]:
        return (self.pan_sign * pan_reading + self.pan_offset,
                self.tilt_sign * tilt_reading + self.tilt_offset)

    def reading(self, pan: float, tilt: float) -> tuple[float, float]:
        """Inverse of :meth:`kinematic`: what the device reports for kinematic (pan, tilt)."""
        return ((pan - self.pan_offset) / self.pan_sign, (tilt - self.tilt_offset) / self.tilt_sign)

    def to_dict(self) -> dict[str, float]:
        return {'pan_sign': float(self.pan_sign), 'tilt_sign': float(self.tilt_sign),
                'pan_offset': float(self.pan_offset), 'tilt_offset': float(self.tilt_offset)}


@dataclass(frozen=True)
class Rig:
    """Two cameras, the left camera's zero pose in the rig frame, each camera's pan/tilt calibration and
    the mount: the rig frame in ``base_link`` (``rig_in_base_link``; None = the default axes of DESIGN.md §2)."""

    right: CameraModel | None            # None: no intrinsics in the rig file (they come from camera_info)
    left: CameraModel | None
    R_L: np.ndarray = field(default_factory=lambda: np.eye(3))
    c_L: np.ndarray = field(default_factory=lambda: np.array([-0.2, 0.0, 0.0]))
    pan_tilt_right: PanTiltCalibration = PanTiltCalibration()
    pan_tilt_left: PanTiltCalibration = PanTiltCalibration()
    extra: dict[str, Any] = field(default_factory=dict)
    mount: Pose | None = None
    expected_size: dict[str, tuple[int, int]] = field(default_factory=dict)   # of cameras without intrinsics

    @property
    def rig_in_base_link(self) -> Pose:
        """The mount, the default one when the rig file gives none."""
        return default_mount() if self.mount is None else self.mount

    def camera(self, side: str) -> CameraModel:
        cam = {'right': self.right, 'left': self.left}[_check_side(side)]
        if cam is None:
            raise RigError(f'the rig file gives no intrinsics for the {side} camera (they come from its '
                           f'camera_info, or give them in the rig file or as {side}: {{calibration: FILE.yaml}})')
        return cam

    def missing_intrinsics(self) -> tuple[str, ...]:
        """The sides whose intrinsics the rig file does not give."""
        return tuple(side for side in SIDES if {'right': self.right, 'left': self.left}[side] is None)

    def require_intrinsics(self, who: str, sides: tuple[str, ...] = SIDES) -> None:
        """RigError naming ``who`` when a side it needs has no intrinsics."""
        missing = [s for s in self.missing_intrinsics() if s in sides]
        if missing:
            raise RigError(f'{who} needs the intrinsics of the {" and ".join(missing)} camera in the rig file '
                           f'(or a calibration file: {missing[0]}: {{calibration: FILE.yaml}})')

    def with_camera(self, side: str, camera: CameraModel) -> Rig:
        """This rig with ``side``'s intrinsics set (e.g. from the first CameraInfo)."""
        return dataclasses.replace(self, **{_check_side(side): camera})

    def calibration(self, side: str) -> PanTiltCalibration:
        return {'right': self.pan_tilt_right, 'left': self.pan_tilt_left}[_check_side(side)]

    def zero_rotation(self, side: str) -> np.ndarray:
        """Zero-pose frame of ``side`` expressed in the rig frame."""
        return np.eye(3) if _check_side(side) == 'right' else self.R_L

    def center(self, side: str) -> np.ndarray:
        """Projection centre of ``side`` in the rig frame."""
        return np.zeros(3) if _check_side(side) == 'right' else np.asarray(self.c_L, dtype=float)

    def cam_to_rig(self, side: str, pan_reading: float, tilt_reading: float) -> np.ndarray:
        """Rotation of the camera's optical frame into the rig frame at the given joint readings."""
        pan, tilt = self.calibration(side).kinematic(pan_reading, tilt_reading)
        return self.zero_rotation(side) @ pan_tilt_rotation(pan, tilt)

    def aim_readings(self, side: str, point_rig: np.ndarray) -> tuple[float, float]:
        """Joint readings that put the rig-frame point on the optical axis of ``side``."""
        d = self.zero_rotation(side).T @ (np.asarray(point_rig, dtype=float) - self.center(side))
        return self.calibration(side).reading(*pan_tilt_for_direction(d))

    def pixels_to_rig_rays(self, side: str, uv: np.ndarray, pan_reading: float,
                           tilt_reading: float) -> np.ndarray:
        """Rig-frame unit rays (N, 3) of pixels seen by ``side`` at the given joint readings."""
        rays = self.camera(side).pixels_to_rays(uv)
        return rays @ self.cam_to_rig(side, pan_reading, tilt_reading).T

    def rig_points_to_pixels(self, side: str, points: np.ndarray, pan_reading: float,
                             tilt_reading: float) -> np.ndarray:
        """Pixels (N, 2) of rig-frame points seen by ``side`` at the given joint readings (NaN behind it); the
        inverse of :meth:`pixels_to_rig_rays`."""
        d = (np.asarray(points, float).reshape(-1, 3) - self.center(side)) @ self.cam_to_rig(side, pan_reading,
                                                                                             tilt_reading)
        out = np.full((len(d), 2), np.nan)
        front = d[:, 2] > 1e-6
        if np.any(front):
            out[front] = self.camera(side).rays_to_pixels(d[front])
        return out

    def to_dict(self) -> dict[str, Any]:
        out = dict(self.extra)
        for side, cam in (('right', self.right), ('left', self.left)):
            if cam is not None:
                out[side] = cam.to_dict()
            elif side in self.expected_size:
                out[side] = dict(zip(('width', 'height'), self.expected_size[side], strict=True))
        out.update({
            'left_in_rig': {'translation': [float(x) for x in self.c_L],
                            'rotation_xyzw': [float(x) for x in quat_xyzw(self.R_L)]},
            'pan_tilt': {'right': self.pan_tilt_right.to_dict(), 'left': self.pan_tilt_left.to_dict()},
        })
        if self.mount is not None:
            out['rig_in_base_link'] = {'translation': [float(x) for x in self.mount.t],
                                       'rotation_xyzw': [float(x) for x in quat_xyzw(self.mount.R)]}
        return out

    def save(self, path: str | Path) -> None:
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))


def _check_side(side: str) -> str:
    if side not in SIDES:
        raise ValueError(f"side must be 'right' or 'left', got {side!r}")
    return side


# the fixed blocks of DESIGN.md §4: inside them every key is known, so a misspelt one is an error (it would
# otherwise fall back to a default without a word); unknown top-level keys are extra data, kept and reported
TOP_KEYS = ('right', 'left', 'left_in_rig', 'pan_tilt', 'rig_in_base_link')
CAMERA_KEYS = ('width', 'height', 'fx', 'fy', 'cx', 'cy', 'dist')
POSE_KEYS = ('translation', 'rotation_xyzw')
PAN_TILT_KEYS = ('pan_sign', 'tilt_sign', 'pan_offset', 'tilt_offset')
QUATERNION_NORM_TOL = 1e-3   # hand-written quaternions (0.7071...) pass; a wrong one (norm 2, 0) does not

_log = logging.getLogger(__name__)


def _did_you_mean(key: str, known: tuple[str, ...]) -> str:
    """The closest known key by spelling, else one the key abbreviates or extends (dist / distortion)."""
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.6) or [
        k for k in known if min(len(k), len(key)) >= 3 and (key.startswith(k) or k.startswith(key))][:1]
    return f" (did you mean '{close[0]}'?)" if close else ''


def _known_keys(block: dict[Any, Any], known: tuple[str, ...], where: str) -> None:
    for key in block:
        if key not in known:
            raise RigError(f'rig file: unknown key {where}.{key}{_did_you_mean(str(key), known)}; '
                           f'{where} takes {", ".join(known)}')


def _is_number(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _number(d: dict[str, Any], key: str, where: str, positive: bool = False) -> float:
    if key not in d:
        raise RigError(f'rig file: missing key {where}.{key}')
    if not _is_number(d[key]):
        raise RigError(f'rig file: {where}.{key} must be a number, got {d[key]!r}')
    value = float(d[key])
    if not np.isfinite(value):
        raise RigError(f'rig file: {where}.{key} must be finite, got {value}')
    if positive and value <= 0:
        raise RigError(f'rig file: {where}.{key} must be > 0, got {value}')
    return value


def _vector(d: dict[str, Any], key: str, where: str, length: int) -> np.ndarray:
    if key not in d:
        raise RigError(f'rig file: missing key {where}.{key}')
    v = d[key]
    if not isinstance(v, (list, tuple)) or len(v) != length or not all(_is_number(x) for x in v):
        raise RigError(f'rig file: {where}.{key} must be a list of {length} numbers, got {v!r}')
    out = np.asarray(v, dtype=float)
    if not np.all(np.isfinite(out)):
        raise RigError(f'rig file: {where}.{key} must be a list of {length} finite numbers, got {v!r}')
    return out


def _mapping(d: Any, key: str, where: str) -> dict[str, Any]:
    if not isinstance(d, dict) or key not in d:
        raise RigError(f'rig file: missing key {where + "." if where else ""}{key}')
    if not isinstance(d[key], dict):
        raise RigError(f'rig file: {where + "." if where else ""}{key} must be a mapping, got {d[key]!r}')
    return d[key]


def _rotation(d: dict[str, Any], where: str) -> np.ndarray:
    q = _vector(d, 'rotation_xyzw', where, 4)
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > QUATERNION_NORM_TOL:
        raise RigError(f'rig file: {where}.rotation_xyzw must be a unit quaternion (x, y, z, w), got {q.tolist()} '
                       f'of norm {n:.6g}')
    try:
        return from_quat_xyzw(q)
    except ValueError as e:
        raise RigError(f'rig file: {where}.rotation_xyzw: {e}') from None


def _pose_block(d: dict[str, Any], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(translation, rotation matrix) of a ``{translation, rotation_xyzw}`` block."""
    block = _mapping(d, key, '')
    _known_keys(block, POSE_KEYS, key)
    return _vector(block, 'translation', key, 3), _rotation(block, key)


MAX_IMAGE_SIDE = 16384          # px
MAX_DISTORTION = 100.0          # |k1..k3, p1, p2|: beyond this no lens model is meant
MIN_BASELINE_M, MAX_BASELINE_M = 1e-3, 100.0   # the rig's scale comes from the baseline: zero is no rig


INTRINSIC_KEYS = ('fx', 'fy', 'cx', 'cy', 'dist')
DIST_TOL = 1e-6        # camera_info vs rig file: distortion coefficients differ beyond this
PX_TOL = 0.5           # ... focal lengths or principal point differ beyond this (px)


def camera_model(width: Any, height: Any, fx: float, fy: float, cx: float, cy: float, dist: Any,
                 where: str) -> CameraModel:
    """A checked :class:`CameraModel`: a real camera's numbers, so a typo (an exponent, a wrong unit) is an
    error naming ``where``, not a trajectory. ``dist``: OpenCV/plumb_bob (k1, k2, p1, p2, k3); an empty or
    shorter list is padded with zeros."""
    if not (_is_number(width) and _is_number(height) and width == int(width) and height == int(height)
            and width > 0 and height > 0):
        raise RigError(f'{where}.width/height must be integers > 0, got {width!r} x {height!r}')
    width, height = int(width), int(height)
    dist = np.asarray(list(dist) + [0.0] * (5 - len(dist)), dtype=float)
    if not (width <= MAX_IMAGE_SIDE and height <= MAX_IMAGE_SIDE):
        raise RigError(f'{where}: image {width:g} x {height:g} px is larger than {MAX_IMAGE_SIDE} px a side')
    for k, f in (('fx', fx), ('fy', fy)):
        if not (math.isfinite(f) and 0.05 * width <= f <= 100.0 * width):
            raise RigError(f'{where}.{k} = {f:g} px is not a focal length for a {width:g} px wide image '
                           f'(expected {0.05 * width:g}..{100 * width:g}: 0.6..170 deg of view)')
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise RigError(f'{where}: principal point ({cx:g}, {cy:g}) lies outside the {width:g} x {height:g} image')
    if dist.shape != (5,) or not np.all(np.isfinite(dist)):
        raise RigError(f'{where}.dist {dist.tolist()}: not 5 finite coefficients (plumb_bob: k1, k2, p1, p2, k3)')
    if np.any(np.abs(dist) > MAX_DISTORTION):
        raise RigError(f'{where}.dist {dist.tolist()}: coefficients beyond +-{MAX_DISTORTION:g} are not a lens model')
    return CameraModel(width, height, float(fx), float(fy), float(cx), float(cy), tuple(float(x) for x in dist))


def camera_from_calibration(data: Any, where: str) -> CameraModel:
    """The camera of a camera_calibration / camera_info_manager YAML (``image_width``, ``image_height``,
    ``camera_matrix: {rows, cols, data}``, ``distortion_model`` plumb_bob, ``distortion_coefficients``)."""
    if not isinstance(data, dict):
        raise RigError(f'{where}: not a camera calibration file (a mapping with image_width, camera_matrix, ...)')

    def matrix(key: str, size: int | None) -> list[float]:
        m = data.get(key)
        if not isinstance(m, dict) or not isinstance(m.get('data'), list):
            raise RigError(f'{where}: missing {key}: {{rows, cols, data}}')
        values = m['data']
        if (size is not None and len(values) != size) or not all(_is_number(x) for x in values):
            raise RigError(f'{where}: {key}.data must be {size or "a list of"} numbers, got {values!r}')
        return [float(x) for x in values]
    for key in ('image_width', 'image_height'):
        if key not in data:
            raise RigError(f'{where}: missing {key}')
    model = data.get('distortion_model', 'plumb_bob')
    if model != 'plumb_bob':
        raise RigError(f"{where}: distortion_model {model!r} is not supported (plumb_bob only)")
    K = matrix('camera_matrix', 9)
    dist = matrix('distortion_coefficients', None) if 'distortion_coefficients' in data else []
    if len(dist) > 5:
        raise RigError(f'{where}: plumb_bob takes 5 distortion coefficients, got {len(dist)}')
    return camera_model(data['image_width'], data['image_height'], K[0], K[4], K[2], K[5], dist, where)


def load_calibration_file(path: str | Path) -> CameraModel:
    """:func:`camera_from_calibration` of a YAML file; RigError naming the file."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as e:
        raise RigError(f'camera calibration {path}: cannot read ({e.strerror})') from None
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise RigError(f'camera calibration {path}: not valid YAML ({" ".join(str(e).split())})') from None
    return camera_from_calibration(data, f'camera calibration {path}')


def _camera(d: dict[str, Any], side: str, base_dir: Path | None) -> CameraModel | None:
    """The side's intrinsics, or None when the rig file leaves them to camera_info (no block, or a block without
    fx, fy, cx, cy, dist: then width and height, when given, must match the CameraInfo)."""
    if side not in d or d[side] is None:
        return None
    c = _mapping(d, side, '')
    _known_keys(c, CAMERA_KEYS + ('calibration',), side)
    if 'calibration' in c:
        if set(c) != {'calibration'}:
            raise RigError(f'rig file: {side}.calibration names a calibration file: give no other {side} keys '
                           f'(got {", ".join(sorted(k for k in c if k != "calibration"))})')
        if not isinstance(c['calibration'], str) or not c['calibration']:
            raise RigError(f'rig file: {side}.calibration must be a file name, got {c["calibration"]!r}')
        path = Path(c['calibration']).expanduser()
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path          # relative to the rig file
        return load_calibration_file(path)
    if not any(k in c for k in INTRINSIC_KEYS):
        return None
    width, height = _number(c, 'width', side, True), _number(c, 'height', side, True)
    dist = _vector(c, 'dist', side, 5) if 'dist' in c else np.zeros(5)
    fx, fy, cx, cy = (_number(c, 'fx', side, True), _number(c, 'fy', side, True), _number(c, 'cx', side),
                      _number(c, 'cy', side))
    return camera_model(width, height, fx, fy, cx, cy, dist, f'rig file: {side}')


def _expected_sizes(d: dict[str, Any]) -> dict[str, tuple[int, int]]:
    """width/height of camera blocks without intrinsics (checked against the CameraInfo)."""
    out = {}
    for side in SIDES:
        c = d.get(side)
        if isinstance(c, dict) and 'calibration' not in c and not any(k in c for k in INTRINSIC_KEYS) and c:
            w, h = _number(c, 'width', side, True), _number(c, 'height', side, True)
            if w != int(w) or h != int(h):
                raise RigError(f'rig file: {side}.width/height must be integers, got {c["width"]!r} x {c["height"]!r}')
            out[side] = (int(w), int(h))
    return out


def _calibration(d: dict[str, Any], side: str) -> PanTiltCalibration:
    if 'pan_tilt' not in d:
        return PanTiltCalibration()
    c = _mapping(d, 'pan_tilt', '')
    _known_keys(c, SIDES, 'pan_tilt')
    if side not in c:
        return PanTiltCalibration()
    c = _mapping(c, side, 'pan_tilt')
    where = f'pan_tilt.{side}'
    _known_keys(c, PAN_TILT_KEYS, where)
    values = {k: _number(c, k, where) for k in PAN_TILT_KEYS if k in c}
    for k in ('pan_offset', 'tilt_offset'):
        if k in values and abs(values[k]) > math.pi:
            raise RigError(f'rig file: {where}.{k} = {values[k]:g} rad is beyond +-pi (offsets are in radians)')
    for k in ('pan_sign', 'tilt_sign'):
        if k in values and values[k] not in (1.0, -1.0):
            raise RigError(f'rig file: {where}.{k} must be 1 or -1, got {values[k]}')
    return PanTiltCalibration(**values)


def rig_from_dict(d: Any, warnings: list[str] | None = None, base_dir: Path | None = None) -> Rig:
    """Validate a parsed rig file (DESIGN.md §4); :class:`RigError` names the offending key, where it is and,
    for a misspelt one, the closest known key. Unknown top-level keys are allowed (kept in ``Rig.extra``)
    but reported: appended to ``warnings`` when given, otherwise logged. A camera may be left out (or give only
    width/height): its intrinsics then come from its camera_info; ``right: {calibration: FILE}`` reads a
    camera_calibration YAML, relative to ``base_dir`` (the rig file's directory)."""
    if not isinstance(d, dict):
        raise RigError(f'rig file: top level must be a mapping with keys right, left, left_in_rig, got {d!r}')
    right, left = _camera(d, 'right', base_dir), _camera(d, 'left', base_dir)
    sizes = _expected_sizes(d)
    c_L, R_L = _pose_block(d, 'left_in_rig')
    baseline = float(np.linalg.norm(c_L))
    if not MIN_BASELINE_M <= baseline <= MAX_BASELINE_M:
        raise RigError(f'rig file: left_in_rig.translation {c_L.tolist()}: a baseline of {baseline:g} m is not a '
                       f'rig ({MIN_BASELINE_M:g}..{MAX_BASELINE_M:g} m; the left camera centre, in metres)')
    mount = None
    if 'rig_in_base_link' in d:
        t_m, R_m = _pose_block(d, 'rig_in_base_link')
        if float(np.linalg.norm(t_m)) > MAX_BASELINE_M:
            raise RigError(f'rig file: rig_in_base_link.translation {t_m.tolist()}: {np.linalg.norm(t_m):g} m from '
                           f'base_link is not a mount (at most {MAX_BASELINE_M:g} m; metres)')
        mount = Pose(R_m, t_m)
    calibrations = _calibration(d, 'right'), _calibration(d, 'left')
    known = {'right', 'left', 'left_in_rig', 'pan_tilt', 'rig_in_base_link'}
    extra = {k: v for k, v in d.items() if k not in known}
    notes = [f'rig file: unknown top-level key {k!r} kept as extra data{_did_you_mean(str(k), TOP_KEYS)}'
             for k in extra if k not in TOP_KEYS]
    if warnings is None:
        for note in notes:
            _log.warning(note)
    else:
        warnings.extend(notes)
    return Rig(right, left, R_L, c_L, *calibrations, extra, mount, sizes)


MAX_RIG_FILE_BYTES = 1 << 20    # a rig file is a few hundred bytes; anything this large is the wrong file


def load_rig(path: str | Path, warnings: list[str] | None = None) -> Rig:
    """Load and validate a rig YAML file; errors and ``warnings`` (see :func:`rig_from_dict`) name the file."""
    path = Path(path)
    try:
        if not path.is_file():
            raise RigError(f'rig file {path}: ' + ('not a regular file' if path.exists() else 'does not exist'))
        if path.stat().st_size > MAX_RIG_FILE_BYTES:
            raise RigError(f'rig file {path}: larger than {MAX_RIG_FILE_BYTES} bytes, not a rig file')
        data = yaml.safe_load(path.read_text())
    except UnicodeDecodeError:
        raise RigError(f'rig file {path}: not text (UTF-8)') from None
    except OSError as e:
        raise RigError(f'rig file {path}: cannot read ({e.strerror})') from None
    except yaml.YAMLError as e:
        raise RigError(f'rig file {path}: not valid YAML ({" ".join(str(e).split())})') from None
    notes: list[str] = []
    try:
        rig = rig_from_dict(data, notes, path.parent)
    except RigError as e:
        raise RigError(f'{path}: {e}') from None
    notes = [f'{path}: {n}' for n in notes]
    if warnings is None:
        for note in notes:
            _log.warning(note)
    else:
        warnings.extend(notes)
    return rig


def default_rig_path() -> Path:
    """``config/rig.yaml`` of the installed package (share/) or of the source tree."""
    here = Path(__file__).resolve().parents[2] / 'config' / 'rig.yaml'
    if here.exists():
        return here
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory('fixego_ros')) / 'config' / 'rig.yaml'
    except Exception:  # ament index absent or package not installed
        return here


def make_rig(width: int = 640, height: int = 480, hfov_deg: float = 21.0, baseline: float = 0.2,
             dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)) -> Rig:
    """A rig of two identical cameras side by side (left camera at x = -baseline), as in the papers."""
    f = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
    cam = CameraModel(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0, tuple(dist))
    return Rig(cam, cam, np.eye(3), np.array([-baseline, 0.0, 0.0]))
