"""The flow observation as a flat table of rows: what ``flow_node`` publishes and ``estimator_node`` reads.

Standard message types only (DESIGN.md §1), so a frame's observation travels as a
``sensor_msgs/PointCloud2`` whose points are the rows below (one field per column, little endian,
packed). ``header.stamp`` is the frame's stamp t, ``header.frame_id`` is ``rig``.

Columns: ``side`` (uint8: 0 right, 1 left), ``kind`` (uint8), ``flags`` (uint8, bit 0: frame t is a
keyframe, i.e. later flow starts from it), ``fixation_id`` (int32), ``t0`` (float64: stamp of the
keyframe the flow starts from; 0 when there is none), ``x0 y0 z0``, ``x1 y1 z1``, ``sigma`` (float64).

- ``kind`` 0, one row per camera present at t: ``x1 y1 z1`` = the fixation ray at t (rig frame at t;
  all zero and ``fixation_id`` = -1 when the camera has no valid fixation), ``x0 y0 z0`` = rotation
  vector of the camera's optical frame in the rig frame at t (pan/tilt applied), ``sigma`` = the 1-sigma (rad) of
  the pan/tilt readings behind it (``CameraFrame.joint_sigma``; 0 when not given, and in every other row).
- ``kind`` 1, one row per flow point: ``x0 y0 z0`` = its ray at t0 (rig frame at t0), ``x1 y1 z1`` = the
  ray of the same scene point at t (rig frame at t). ``fixation_id`` repeats the camera row's.
- ``kind`` 2, one row per live point track of the camera at t (``CameraFrame.track_ids/track_rays``):
  ``x0`` = the track id, an integer carried exactly by the float64 (ids are 0 <= id < 2**53; PointCloud2
  has no 64-bit integer field), ``y0 = z0 = 0``, ``x1 y1 z1`` = the track's ray at t (rig frame at t).
  ``fixation_id`` repeats the camera row's. Ids are unique within a camera.

Decoding validates everything (sides, kinds, finite values, unit rays) and raises
:class:`ObservationError` with the reason, so a malformed message is rejected as a whole.
"""

from __future__ import annotations

import numpy as np

from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.geometry.rig import SIDES
from fixego_ros.geometry.rotation import exp_so3, log_so3

KIND_CAMERA, KIND_FLOW, KIND_TRACK = 0, 1, 2
MAX_TRACK_ID = 2**53 - 1     # largest id a float64 holds exactly
FLAG_KEYFRAME = 1
ROW_DTYPE = np.dtype([('side', '<u1'), ('kind', '<u1'), ('flags', '<u1'), ('fixation_id', '<i4'), ('t0', '<f8'),
                      ('x0', '<f8'), ('y0', '<f8'), ('z0', '<f8'), ('x1', '<f8'), ('y1', '<f8'), ('z1', '<f8'),
                      ('sigma', '<f8')])
_A = ('x0', 'y0', 'z0')
_B = ('x1', 'y1', 'z1')


class ObservationError(ValueError):
    """A flow observation that cannot be used (and why)."""


def _set(rows: np.ndarray, names: tuple[str, str, str], values: np.ndarray) -> None:
    for i, n in enumerate(names):
        rows[n] = values[:, i]


def _get(rows: np.ndarray, names: tuple[str, str, str]) -> np.ndarray:
    return np.stack([rows[n] for n in names], axis=1).astype(np.float64)


def observation_to_rows(obs: FrameObservation) -> np.ndarray:
    """Rows of one observation (see the module docstring)."""
    t0 = float(obs.prev_stamp) if obs.prev_stamp is not None else 0.0
    flags = FLAG_KEYFRAME if obs.keyframe else 0
    parts = []
    for si, side in enumerate(SIDES):
        cam = obs.camera(side)
        if cam is None:
            continue
        has_fix = cam.fixation_ray is not None and bool(np.all(np.isfinite(cam.fixation_ray)))
        fid = int(cam.fixation_id) if has_fix else -1
        head = np.zeros(1, ROW_DTYPE)
        head['side'], head['kind'], head['fixation_id'], head['t0'], head['flags'] = si, KIND_CAMERA, fid, t0, flags
        _set(head, _A, log_so3(np.asarray(cam.cam_to_rig, float)).reshape(1, 3))
        head['sigma'] = float(cam.joint_sigma)
        if has_fix:
            _set(head, _B, np.asarray(cam.fixation_ray, float).reshape(1, 3))
        flow = np.zeros(len(cam.flow_prev), ROW_DTYPE)
        flow['side'], flow['kind'], flow['fixation_id'], flow['t0'], flow['flags'] = si, KIND_FLOW, fid, t0, flags
        if len(flow):
            _set(flow, _A, np.asarray(cam.flow_prev, float))
            _set(flow, _B, np.asarray(cam.flow_curr, float))
        ids = np.asarray(cam.track_ids).reshape(-1)
        tracks = np.zeros(len(ids), ROW_DTYPE)
        tracks['side'], tracks['kind'], tracks['fixation_id'], tracks['t0'], tracks['flags'] = \
            si, KIND_TRACK, fid, t0, flags
        if len(tracks):
            if np.any(ids < 0) or np.any(ids > MAX_TRACK_ID):
                raise ObservationError(f'{side}: track ids must be in [0, 2**53)')
            tracks['x0'] = ids.astype(np.float64)
            _set(tracks, _B, np.asarray(cam.track_rays, float).reshape(-1, 3))
        parts += [head, flow, tracks]
    return np.concatenate(parts) if parts else np.zeros(0, ROW_DTYPE)


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    n = np.linalg.norm(v, axis=1)
    if np.any(np.abs(n - 1.0) > 1e-3):
        raise ObservationError(f'{what}: rays must be unit vectors (norms {n.min():.3g}..{n.max():.3g})')
    return v / n[:, None]


def _tracks(rows: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """Track ids (int64) and rays of a camera's track rows, validated."""
    if not len(rows):
        return np.zeros(0, np.int64), np.zeros((0, 3))
    x = rows['x0'].astype(np.float64)
    if np.any(x < 0) or np.any(x > MAX_TRACK_ID) or np.any(x != np.floor(x)):
        raise ObservationError(f'{side}: track ids must be integers in [0, 2**53)')
    if np.any(rows['y0'] != 0.0) or np.any(rows['z0'] != 0.0):
        raise ObservationError(f'{side}: track rows must have y0 = z0 = 0')
    ids = x.astype(np.int64)
    if len(np.unique(ids)) != len(ids):
        raise ObservationError(f'{side}: repeated track ids')
    return ids, _unit(_get(rows, _B), f'{side} tracks')


def rows_to_observation(stamp: float, rows: np.ndarray) -> FrameObservation:
    """The observation of a row table; raises :class:`ObservationError` on anything malformed."""
    if rows.dtype.names is None or set(ROW_DTYPE.names) - set(rows.dtype.names):
        raise ObservationError(f'missing columns: {sorted(set(ROW_DTYPE.names) - set(rows.dtype.names or ()))}')
    if not np.isfinite(stamp):
        raise ObservationError('non-finite stamp')
    floats = np.stack([rows[n].astype(np.float64) for n in ('t0', *_A, *_B, 'sigma')], axis=1) if len(rows) else \
        np.zeros((0, 8))
    if not np.all(np.isfinite(floats)):
        raise ObservationError(f'{int(np.sum(~np.all(np.isfinite(floats), axis=1)))} rows with NaN/inf values')
    if np.any(rows['sigma'] < 0.0):
        raise ObservationError('negative joint sigma')
    if np.any(rows['side'] >= len(SIDES)):
        raise ObservationError(f'unknown side index {int(rows["side"].max())} (0 right, 1 left)')
    if np.any(rows['kind'] > KIND_TRACK):
        raise ObservationError(f'unknown row kind {int(rows["kind"].max())}')
    t0s = np.unique(rows['t0'])
    if len(t0s) > 1:
        raise ObservationError(f'rows disagree on the previous stamp t0: {t0s.tolist()[:4]}')
    t0 = float(t0s[0]) if len(t0s) else 0.0
    if len(np.unique(rows['flags'])) > 1:
        raise ObservationError('rows disagree on the frame flags')
    keyframe = bool(rows['flags'][0] & FLAG_KEYFRAME) if len(rows) else None
    if t0 >= stamp and t0 != 0.0:
        raise ObservationError(f'previous stamp t0 = {t0:.6f} is not before the frame stamp {stamp:.6f}')
    cams: dict[str, CameraFrame | None] = {}
    for si, side in enumerate(SIDES):
        head = rows[(rows['side'] == si) & (rows['kind'] == KIND_CAMERA)]
        flow = rows[(rows['side'] == si) & (rows['kind'] == KIND_FLOW)]
        track = rows[(rows['side'] == si) & (rows['kind'] == KIND_TRACK)]
        if len(head) > 1:
            raise ObservationError(f'{side}: {len(head)} camera rows (expected at most 1)')
        if len(head) == 0:
            if len(flow) or len(track):
                raise ObservationError(f'{side}: flow or track rows without a camera row')
            cams[side] = None
            continue
        rvec = _get(head, _A)[0]
        if np.linalg.norm(rvec) > np.pi + 1e-6:
            raise ObservationError(f'{side}: camera rotation vector longer than pi')
        fid = int(head['fixation_id'][0])
        ray = _unit(_get(head, _B), f'{side} fixation')[0] if fid >= 0 else None
        prev = _unit(_get(flow, _A), f'{side} flow at t0') if len(flow) else np.zeros((0, 3))
        curr = _unit(_get(flow, _B), f'{side} flow at t') if len(flow) else np.zeros((0, 3))
        cams[side] = CameraFrame(ray, fid, exp_so3(rvec), prev, curr, *_tracks(track, side),
                                 joint_sigma=float(head['sigma'][0]))
    return FrameObservation(float(stamp), cams['right'], cams['left'], t0 if t0 > 0.0 else None, keyframe)
