"""Message payloads -> core values (ROS-free, duck-typed: works on rclpy and rosbags messages alike).

The nodes and the offline replay both convert with these, so a bag and a live topic are read the same way.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fixego_ros.geometry.rig import CameraModel
from fixego_ros.geometry.rotation import Pose, from_quat_xyzw

# encoding -> (channels, dtype) of the encodings the pipeline accepts
ENCODINGS = {'mono8': (1, np.uint8), 'rgb8': (3, np.uint8), 'bgr8': (3, np.uint8)}


class ImageError(ValueError):
    """An Image message we cannot use; ``kind`` says which check failed (encoding, layout, size, decode)."""

    def __init__(self, message: str, kind: str = 'layout') -> None:
        super().__init__(message)
        self.kind = kind


def image_to_gray(msg: Any) -> np.ndarray:
    """Grey uint8 array of an Image (or CompressedImage) message; raises :class:`ImageError` with the reason."""
    if not hasattr(msg, 'encoding') and hasattr(msg, 'format'):
        return _compressed_to_gray(msg)
    if msg.encoding not in ENCODINGS:
        raise ImageError(f'unsupported encoding {msg.encoding!r} (use one of {sorted(ENCODINGS)})', 'encoding')
    ch, _ = ENCODINGS[msg.encoding]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0 or step < w * ch or len(msg.data) < step * h:
        raise ImageError(f'inconsistent image: {w}x{h}, step {step}, {len(msg.data)} bytes, {msg.encoding}')
    data = msg.data
    if not isinstance(data, (bytes, bytearray, memoryview, np.ndarray)):
        data = bytes(data)
    buf = np.frombuffer(data, dtype=np.uint8, count=step * h)
    img = buf.reshape(h, step)[:, : w * ch].reshape(h, w, ch)
    if ch == 1:
        return img[:, :, 0]
    import cv2
    code = cv2.COLOR_RGB2GRAY if msg.encoding == 'rgb8' else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(np.ascontiguousarray(img), code)


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
