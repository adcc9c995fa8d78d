"""Message payloads -> core values (ROS-free, duck-typed: works on rclpy and rosbags messages alike).

The nodes and the offline replay both convert with these, so a bag and a live topic are read the same way.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fixego_ros.geometry.rig import CameraModel
from fixego_ros.geometry.rotation import Pose, from_quat_xyzw
from fixego_ros.tracking.fixation import NO_FIXATION_ID

# encoding -> (bytes per pixel, how it becomes grey). ROS's ``yuv422`` is UYVY (U Y V Y per two pixels) and
# ``yuv422_yuy2`` is YUYV; grey is their Y. ``mono16`` keeps its high byte (>> 8): the tracker works on 8 bits,
# and a 16-bit camera's useful range is its top.
ENCODINGS = {'mono8': (1, 'mono'), 'rgb8': (3, 'rgb'), 'bgr8': (3, 'bgr'), 'mono16': (2, 'mono16'),
             'yuv422': (2, 'uyvy'), 'yuv422_yuy2': (2, 'yuyv')}


class ImageError(ValueError):
    """An Image message we cannot use; ``kind`` says which check failed (encoding, layout, size, decode)."""

    def __init__(self, message: str, kind: str = 'layout') -> None:
        super().__init__(message)
        self.kind = kind


def image_to_gray(msg: Any) -> np.ndarray:
    """Grey uint8 array of an Image (or CompressedImage) message; raises :class:`ImageError` with the reason.
    Rows may be padded (``step`` > width * bytes per pixel)."""
    if not hasattr(msg, 'encoding') and hasattr(msg, 'format'):
        return _compressed_to_gray(msg)
    if msg.encoding not in ENCODINGS:
        raise ImageError(f'unsupported encoding {msg.encoding!r} (use one of {sorted(ENCODINGS)})', 'encoding')
    bpp, kind = ENCODINGS[msg.encoding]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ImageError(f'inconsistent image: {w}x{h} ({msg.encoding})')
    if step < w * bpp:
        raise ImageError(f'inconsistent image: step {step} bytes is less than width {w} x {bpp} bytes per pixel '
                         f'({msg.encoding})')
    if len(msg.data) < step * h:
        raise ImageError(f'inconsistent image: {len(msg.data)} bytes of data, {w}x{h} {msg.encoding} with step '
                         f'{step} needs {step * h}')
    if kind in ('uyvy', 'yuyv') and w % 2:
        raise ImageError(f'inconsistent image: {msg.encoding} needs an even width (two pixels share U and V), got {w}')
    data = msg.data
    if not isinstance(data, (bytes, bytearray, memoryview, np.ndarray)):
        data = bytes(data)
    buf = np.frombuffer(data, dtype=np.uint8, count=step * h)
    rows = buf.reshape(h, step)[:, : w * bpp]
    if kind == 'mono':
        return rows
    if kind == 'mono16':
        big = bool(getattr(msg, 'is_bigendian', False))
        return rows.reshape(h, w, 2)[:, :, 0 if big else 1].copy()      # the high byte: value >> 8
    import cv2
    img = np.ascontiguousarray(rows).reshape(h, w, bpp)
    code = {'rgb': cv2.COLOR_RGB2GRAY, 'bgr': cv2.COLOR_BGR2GRAY, 'uyvy': cv2.COLOR_YUV2GRAY_UYVY,
            'yuyv': cv2.COLOR_YUV2GRAY_YUY2}[kind]
    return cv2.cvtColor(img, code)


def _compressed_to_gray(msg: Any) -> np.ndarray:
    import cv2
    data = msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(bytes(msg.data), np.uint8)
    gray = cv2.imdecode(data.astype(np.uint8, copy=False), cv2.IMREAD_GRAYSCALE) if data.size else None
    if gray is None:
        raise ImageError(f'CompressedImage ({msg.format!r}, {data.size} bytes) does not decode', 'decode')
    return gray


def gray_for_camera(msg: Any, camera: CameraModel) -> np.ndarray:
    """:func:`image_to_gray` plus the check that the image has the rig camera's size."""
    gray = image_to_gray(msg)
    if gray.shape != (camera.height, camera.width):
        raise ImageError(f'{gray.shape[1]}x{gray.shape[0]} image, but the rig file says '
                         f'{camera.width}x{camera.height}', 'size')
    return gray


def stamp_to_sec(stamp: Any) -> float:
    """builtin_interfaces/Time -> seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def msg_to_pose(msg: Any) -> Pose:
    """:class:`Pose` of a geometry_msgs/Pose; ValueError for a non-finite or zero quaternion."""
    p, o = msg.position, msg.orientation
    t = np.array([p.x, p.y, p.z], dtype=float)
    if not np.all(np.isfinite(t)):
        raise ValueError(f'non-finite position {t.tolist()}')
    return Pose(from_quat_xyzw(np.array([o.x, o.y, o.z, o.w], dtype=float)), t)


def pan_tilt(msg: Any, side: str) -> tuple[float, float]:
    """(pan, tilt) of a sensor_msgs/JointState by the joint names ``<side>_pan``, ``<side>_tilt``;
    ValueError when either is missing (the values may still be non-finite: the caller checks)."""
    names = list(msg.name)
    try:
        i, j = names.index(f'{side}_pan'), names.index(f'{side}_tilt')
        return float(msg.position[i]), float(msg.position[j])
    except (ValueError, IndexError):
        raise ValueError(f'{side} joint_states without {side}_pan and {side}_tilt positions') from None


def joint_sigma(msg: Any, side: str) -> float:
    """The larger 1-sigma (rad) of ``<side>_pan`` and ``<side>_tilt`` that camera_node puts in a JointState's
    ``effort`` (it has no covariance field; a pan/tilt head reports no torque). 0.0 = not given (a bag from another
    recorder, or one written before the simulator stated its readings' quantisation), or anything negative or
    non-finite there."""
    names = list(msg.name)
    effort = list(msg.effort)
    try:
        values = [float(effort[names.index(f'{side}_{axis}')]) for axis in ('pan', 'tilt')]
    except (ValueError, IndexError):
        return 0.0
    return max(values) if all(math.isfinite(v) and v >= 0.0 for v in values) else 0.0


def fixation_from_msg(msg: Any) -> tuple[tuple[float, float] | None, int]:
    """(pixel, fixation id) of a ``<side>/fixation`` geometry_msgs/PointStamped: x, y = pixel, z = id. A negative
    z is camera_node's explicit "no valid fixation at this stamp" (z = -1, x = y = 0): (None, NO_FIXATION_ID).
    ValueError for a non-finite id, or a non-finite pixel with a valid id."""
    p = msg.point
    z = float(p.z)
    if not math.isfinite(z):
        raise ValueError(f'non-finite fixation id {z}')
    if z < 0:
        return None, NO_FIXATION_ID
    x, y = float(p.x), float(p.y)
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f'non-finite fixation pixel ({x}, {y})')
    return (x, y), round(z)


class CloudError(ValueError):
    """A PointCloud2 whose layout does not match the table we expect."""


# numpy scalar type -> sensor_msgs/PointField datatype constant (sensor_msgs_py is not available as a wheel)
POINT_FIELD_TYPES = {np.dtype('<i1'): 1, np.dtype('<u1'): 2, np.dtype('<i2'): 3, np.dtype('<u2'): 4,
                     np.dtype('<i4'): 5, np.dtype('<u4'): 6, np.dtype('<f4'): 7, np.dtype('<f8'): 8}


def cloud_to_table(msg: Any, dtype: np.dtype) -> np.ndarray:
    """The structured array of a PointCloud2 (an rclpy or a rosbags one) whose points are the rows of ``dtype``,
    packed little endian (``nodes.common.table_to_cloud`` writes them); :class:`CloudError` names what does not
    match (fields, types, offsets, sizes)."""
    want = {name: (POINT_FIELD_TYPES[dt], int(off)) for name, (dt, off) in dtype.fields.items()}
    have = {f.name: (int(f.datatype), int(f.offset)) for f in msg.fields}
    if want != have:
        bad = sorted(n for n in set(want) | set(have) if want.get(n) != have.get(n))
        raise CloudError(f'point fields do not match the expected layout: {bad}')
    if msg.is_bigendian:
        raise CloudError('big-endian point clouds are not supported')
    if int(msg.point_step) != dtype.itemsize:
        raise CloudError(f'point_step {msg.point_step}, expected {dtype.itemsize}')
    n = int(msg.width) * int(msg.height)
    if len(msg.data) != n * dtype.itemsize:
        raise CloudError(f'{len(msg.data)} data bytes for {n} points of {dtype.itemsize} bytes')
    data = msg.data if isinstance(msg.data, (bytes, bytearray, memoryview, np.ndarray)) else bytes(msg.data)
    return np.frombuffer(data, dtype=dtype, count=n).copy()
