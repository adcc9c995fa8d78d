"""Helpers shared by every node: QoS, stamps, image conversion, log-once, diagnostics.

One place for each: nodes must use these rather than re-implement them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import Image

SENSOR_QOS: QoSProfile = qos_profile_sensor_data
RELIABLE_QOS = QoSProfile(depth=50)

# sensor_msgs/Image encodings we accept -> (channels, dtype)
ENCODINGS = {'mono8': (1, np.uint8), 'rgb8': (3, np.uint8), 'bgr8': (3, np.uint8)}

OK, WARN, ERROR, STALE = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR,
                          DiagnosticStatus.STALE)


class ImageError(ValueError):
    """An Image message we cannot use (unknown encoding, inconsistent size)."""


def stamp_to_sec(stamp: Time) -> float:
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def sec_to_stamp(t: float) -> Time:
    if not math.isfinite(t) or t < 0:
        raise ValueError(f'stamp must be finite and >= 0, got {t}')
    ns = round(t * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def image_to_gray(msg: Image) -> np.ndarray:
    """Grey uint8 array of an Image message; raises :class:`ImageError` with the reason."""
    if msg.encoding not in ENCODINGS:
        raise ImageError(f'unsupported encoding {msg.encoding!r} (use one of {sorted(ENCODINGS)})')
    ch, _ = ENCODINGS[msg.encoding]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0 or step < w * ch or len(msg.data) < step * h:
        raise ImageError(f'inconsistent image: {w}x{h}, step {step}, {len(msg.data)} bytes, {msg.encoding}')
    buf = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, (bytes, bytearray, memoryview))
                        else msg.data, dtype=np.uint8, count=step * h)
    img = buf.reshape(h, step)[:, : w * ch].reshape(h, w, ch)
    if ch == 1:
        return img[:, :, 0]
    import cv2
    code = cv2.COLOR_RGB2GRAY if msg.encoding == 'rgb8' else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(np.ascontiguousarray(img), code)


def array_to_image(img: np.ndarray, stamp: Time, frame_id: str, encoding: str | None = None) -> Image:
    """Image message of a uint8 array (H, W) -> mono8 or (H, W, 3) -> rgb8 unless ``encoding`` says bgr8."""
    img = np.ascontiguousarray(img, dtype=np.uint8)
    if img.ndim == 2:
        encoding = encoding or 'mono8'
        ch = 1
    elif img.ndim == 3 and img.shape[2] == 3:
        encoding = encoding or 'rgb8'
        ch = 3
    else:
        raise ImageError(f'cannot encode array of shape {img.shape}')
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(img.shape[0]), int(img.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = int(img.shape[1] * ch)
    msg.data = img.tobytes()
    return msg


class OnceLogger:
    """Log a condition once when it starts (and once when it clears), never per frame."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self._active: set[str] = set()

    def warn(self, key: str, text: str) -> None:
        if key not in self._active:
            self._active.add(key)
            self._node.get_logger().warning(text)

    def error(self, key: str, text: str) -> None:
        if key not in self._active:
            self._active.add(key)
            self._node.get_logger().error(text)

    def clear(self, key: str, text: str | None = None) -> None:
        if key in self._active:
            self._active.discard(key)
            if text:
                self._node.get_logger().info(text)

    def active(self, key: str) -> bool:
        return key in self._active


def diagnostic_status(name: str, hardware_id: str, level: bytes, message: str,
                      values: dict[str, object] | Iterable[tuple[str, object]] = ()) -> DiagnosticStatus:
    """One DiagnosticStatus with stringified key/values."""
    items = values.items() if isinstance(values, dict) else values
    return DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=str(k), value=str(v)) for k, v in items])


def publish_diagnostics(node: Node, publisher, statuses: list[DiagnosticStatus]) -> None:
    """Publish a DiagnosticArray stamped with the node's clock."""
    arr = DiagnosticArray()
    arr.header.stamp = node.get_clock().now().to_msg()
    arr.status = statuses
    publisher.publish(arr)
