"""Helpers shared by every node: QoS, stamps, image conversion, log-once, diagnostics.

One place for each: nodes must use these rather than re-implement them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose as PoseMsg
from geometry_msgs.msg import PoseWithCovarianceStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import Image, PointCloud2, PointField

from fixego_ros.geometry.rotation import Pose, quat_xyzw
from fixego_ros.pipeline.messages import (  # noqa: F401 - re-exported: nodes import them from here
    ENCODINGS,
    ImageError,
    image_to_gray,
    msg_to_pose,
    stamp_to_sec,
)

SENSOR_QOS: QoSProfile = qos_profile_sensor_data
RELIABLE_QOS = QoSProfile(depth=50)
# latched: a one-off measurement (the vergence step) that a node started later must still get
LATCHED_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)

OK, WARN, ERROR, STALE = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR,
                          DiagnosticStatus.STALE)


class CloudError(ValueError):
    """A PointCloud2 whose layout does not match the table we expect."""


# numpy scalar type -> PointField datatype (sensor_msgs_py is not available as a wheel)
_POINT_FIELD_TYPES = {np.dtype('<i1'): PointField.INT8, np.dtype('<u1'): PointField.UINT8,
                      np.dtype('<i2'): PointField.INT16, np.dtype('<u2'): PointField.UINT16,
                      np.dtype('<i4'): PointField.INT32, np.dtype('<u4'): PointField.UINT32,
                      np.dtype('<f4'): PointField.FLOAT32, np.dtype('<f8'): PointField.FLOAT64}


def declare_parameters(node: Node, params: dict[str, tuple[object, str]]) -> Callable[[str], object]:
    """Declare ``name -> (default, description)`` on ``node``; returns a getter of the current values."""
    for name, (default, text) in params.items():
        node.declare_parameter(name, default, ParameterDescriptor(description=text))
    return lambda name: node.get_parameter(name).value


def spin_node(factory: Callable[[], Node], args: list[str] | None = None, *,
              finished: Callable[[Node], bool] | None = None, domain_id: int | None = None) -> Node | None:
    """``main`` of a node: init, spin until Ctrl-C, shutdown or ``finished(node)`` (for nodes that end by
    themselves), destroy the node, shut down. Returns the destroyed node (what it recorded, e.g. an exit
    code, stays readable); exceptions from ``factory`` propagate after the clean-up."""
    rclpy.init(args=args, domain_id=domain_id)
    node = None
    try:
        node = factory()
        if finished is None:
            rclpy.spin(node)
        else:
            while rclpy.ok() and not finished(node):
                rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return node


def sec_to_stamp(t: float) -> Time:
    if not math.isfinite(t) or t < 0:
        raise ValueError(f'stamp must be finite and >= 0, got {t}')
    ns = round(t * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def pose_to_msg(pose: Pose, out: PoseMsg | None = None) -> PoseMsg:
    """geometry_msgs/Pose of a :class:`Pose` (filled into ``out`` when given)."""
    out = out if out is not None else PoseMsg()
    out.position.x, out.position.y, out.position.z = (float(x) for x in pose.t)
    o = out.orientation
    o.x, o.y, o.z, o.w = (float(x) for x in quat_xyzw(pose.R))
    return out


def vergence_to_msg(stamp: Time, point_rig: np.ndarray, cov_rig: np.ndarray) -> PoseWithCovarianceStamped:
    """/fixego/vergence message: the vergence point in ``rig`` with its 3x3 covariance in the position block;
    the orientation carries no information (identity, variance 1e6). camera_node and the simulator's bags
    both write it this way."""
    out = PoseWithCovarianceStamped()
    out.header.stamp = stamp
    out.header.frame_id = 'rig'
    pos = out.pose.pose.position
    pos.x, pos.y, pos.z = (float(x) for x in point_rig)
    out.pose.pose.orientation.w = 1.0
    cov = np.zeros((6, 6))
    cov[:3, :3] = cov_rig
    cov[3:, 3:] = np.eye(3) * 1e6
    out.pose.covariance = [float(x) for x in cov.ravel()]
    return out


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


def table_to_cloud(rows: np.ndarray, stamp: Time, frame_id: str) -> PointCloud2:
    """PointCloud2 carrying a packed little-endian structured array, one point per row."""
    msg = PointCloud2()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = 1, len(rows)
    msg.fields = [PointField(name=name, offset=int(off), datatype=_POINT_FIELD_TYPES[dt], count=1)
                  for name, (dt, off) in rows.dtype.fields.items()]
    msg.is_bigendian = False
    msg.point_step = int(rows.dtype.itemsize)
    msg.row_step = msg.point_step * msg.width
    msg.data = np.ascontiguousarray(rows).tobytes()
    msg.is_dense = True
    return msg


def cloud_to_table(msg: PointCloud2, dtype: np.dtype) -> np.ndarray:
    """The structured array of a PointCloud2 written by :func:`table_to_cloud`; :class:`CloudError`
    names what does not match (fields, types, offsets, sizes)."""
    want = {name: (_POINT_FIELD_TYPES[dt], int(off)) for name, (dt, off) in dtype.fields.items()}
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
    data = msg.data if isinstance(msg.data, (bytes, bytearray, memoryview)) else bytes(msg.data)
    return np.frombuffer(data, dtype=dtype, count=n).copy()
