"""Helpers shared by every node: QoS, stamps, image conversion, log-once, diagnostics.

One place for each: nodes must use these rather than re-implement them.
"""

from __future__ import annotations

import contextlib
import faulthandler
import math
import sys
import time
from collections.abc import Callable, Iterable, Mapping

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose as PoseMsg
from geometry_msgs.msg import PoseWithCovarianceStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType, SetParametersResult
from rclpy.context import Context
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterUninitializedException,
)
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import Image, PointCloud2, PointField

from fixego_ros.geometry.rig import RigError
from fixego_ros.geometry.rotation import Pose, quat_xyzw
from fixego_ros.nodes.dds_profile import use_image_profile
from fixego_ros.pipeline.messages import (  # noqa: F401 - re-exported: nodes import them from here
    ENCODINGS,
    POINT_FIELD_TYPES,
    CloudError,
    ImageError,
    cloud_to_table,
    image_to_gray,
    msg_to_pose,
    stamp_to_sec,
)
from fixego_ros.pipeline.params import Getter, ParamsError, ParamSpec
from fixego_ros.threads import limit_threads

SENSOR_QOS: QoSProfile = qos_profile_sensor_data
RELIABLE_QOS = QoSProfile(depth=50)
# the simulator's ground truth: a reliable sample a loaded reader missed is resent after the next heartbeat (Fast DDS:
# every 3 s) only while the writer still holds it, and a reader that falls behind drops the oldest beyond its depth;
# so keep 10 s of 30 Hz frames on both sides (at depth 50 one loaded demo run lost two truth stamps mid-run, stop 90)
TRUTH_QOS = QoSProfile(depth=300)
# latched: occasional measurements (the vergence steps) whose recent ones a node started later must still get
LATCHED_QOS = QoSProfile(depth=20, durability=DurabilityPolicy.TRANSIENT_LOCAL)

# every node's default namespace (DESIGN.md §3): its topics are relative names inside it, so `-r __ns:=/robot1`
# (or a launch file's namespace) moves a whole rig; /diagnostics, /tf, /tf_static stay absolute
DEFAULT_NAMESPACE = 'fixego'


def in_namespace(kwargs: dict) -> dict:
    """Node constructor arguments with the default namespace unless the caller gave one (a ``__ns`` remap on the
    command line or in the context arguments still wins over both)."""
    return {'namespace': DEFAULT_NAMESPACE, **kwargs}


OK, WARN, ERROR, STALE = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR,
                          DiagnosticStatus.STALE)


_ROS_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
              float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING,
              list: ParameterType.PARAMETER_STRING_ARRAY}
_INT64 = (-(2**63), 2**63 - 1)
READ_ONLY_NOTE = 'read-only: taken at start (restart the node to change it)'


def parameter_descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """ROS descriptor of a spec: type, description, read-only flag, the range rclpy can check (the closed hull
    of the allowed values) and the exact rule in words (exclusive bounds, special values, finiteness)."""
    d = ParameterDescriptor(name=spec.name, type=_ROS_TYPES[spec.type], description=spec.description,
                            read_only=spec.read_only,
                            additional_constraints=spec.allowed() + (f'; {READ_ONLY_NOTE}' if spec.read_only else ''))
    lo, hi = spec.hull()
    if spec.type is float and (lo is not None or hi is not None):
        d.floating_point_range = [FloatingPointRange(from_value=-math.inf if lo is None else float(lo),
                                                     to_value=math.inf if hi is None else float(hi), step=0.0)]
    elif spec.type is int and (lo is not None or hi is not None):
        d.integer_range = [IntegerRange(from_value=_INT64[0] if lo is None else int(lo),
                                        to_value=_INT64[1] if hi is None else int(hi), step=0)]
    return d


Apply = Callable[[dict[str, object], Getter], None]


class NodeParams:
    """A node's parameters, declared from their specs (:mod:`fixego_ros.pipeline.params`); call it as the getter.

    Start: every override (``-p``, ``--params-file``, ``parameter_overrides``) is checked against its spec before
    anything is declared, so a bad one raises :class:`ParamsError` naming the parameter, the value and the range
    (:func:`run_node` prints it as one line and exits 2). Run time (``ros2 param set``): values are checked the
    same way by an on-set callback; read-only ones are refused by rclpy; the others go to the node's ``apply``
    (given to :meth:`start`), which puts them into effect or raises to refuse them, so a set never reports
    success without effect. An int given for a float parameter is taken as that float, as in ``fixego replay``.
    """

    def __init__(self, node: Node, specs: Mapping[str, ParamSpec]) -> None:
        self._node = node
        self.specs = dict(specs)
        self._apply: Apply | None = None
        # rclpy keeps the overrides it will apply at declaration here; checking them first gives our message
        overrides = getattr(node, '_parameter_overrides', {})
        for name, spec in self.specs.items():
            given = overrides.get(name)
            if given is None or given.type_ == Parameter.Type.NOT_SET:
                continue
            value = spec.check(given.value)
            if type(value) is not type(given.value):
                overrides[name] = Parameter(name, value=value)
        node.add_pre_set_parameters_callback(self._coerce)
        node.add_on_set_parameters_callback(self._on_set)
        for name, spec in self.specs.items():
            try:
                node.declare_parameter(name, Parameter.Type.STRING_ARRAY if spec.default is None else spec.default,
                                       parameter_descriptor(spec))
            except (InvalidParameterTypeException, InvalidParameterValueException) as e:
                raise ParamsError(f'parameter {name}: {e}') from None

    def __call__(self, name: str) -> object:
        """Current value (None for an unset string array)."""
        try:
            return self._node.get_parameter(name).value
        except ParameterUninitializedException:
            return None

    def overlay(self, changes: Mapping[str, object]) -> Getter:
        """Getter of the values a change would give (current ones where unchanged)."""
        return lambda name: changes[name] if name in changes else self(name)

    def start(self, apply: Apply, handles: Iterable[str]) -> None:
        """From now on run-time changes go to ``apply(changes, getter)``. ``handles`` must be exactly the
        parameters that are not read-only: one the node would not apply must be read-only, so no set of it
        can report success without effect."""
        live = {n for n, s in self.specs.items() if not s.read_only}
        if set(handles) != live:
            raise RuntimeError(f'{self._node.get_name()}: run-time handlers {sorted(set(handles))} do not match '
                               f'the parameters that are not read-only {sorted(live)}')
        self._apply = apply

    def _coerce(self, params: list[Parameter]) -> list[Parameter]:
        out = []
        for p in params:
            spec = self.specs.get(p.name)
            if spec is not None and spec.type is float and p.type_ == Parameter.Type.INTEGER:
                p = Parameter(p.name, value=float(p.value))
            out.append(p)
        return out

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        changes: dict[str, object] = {}
        for p in params:
            spec = self.specs.get(p.name)
            if spec is None or p.type_ == Parameter.Type.NOT_SET:
                continue
            try:
                changes[p.name] = spec.check(p.value)
            except ParamsError as e:
                return SetParametersResult(successful=False, reason=str(e))
        if self._apply is None or not changes:          # declaration (already checked), or none of ours
            return SetParametersResult(successful=True)
        fixed = sorted(n for n in changes if self.specs[n].read_only)
        if fixed:        # rclpy refuses read-only parameters before calling us; kept so it can never slip through
            return SetParametersResult(successful=False, reason=f'{", ".join(fixed)}: {READ_ONLY_NOTE}')
        try:
            self._apply(changes, self.overlay(changes))
        except ValueError as e:                          # ParamsError, or a combination the core refuses
            return SetParametersResult(successful=False, reason=str(e))
        self._node.get_logger().info('parameters set: ' + ', '.join(f'{k}={v!r}' for k, v in changes.items()))
        return SetParametersResult(successful=True)


def declare_parameters(node: Node, specs: Mapping[str, ParamSpec]) -> NodeParams:
    """Declare ``specs`` on ``node`` (see :class:`NodeParams`); returns the getter of the current values."""
    return NodeParams(node, specs)


def set_timer_period(timer, period_s: float) -> None:
    """Change a running timer's period (e.g. ``diagnostics_period_s`` set at run time)."""
    timer.timer_period_ns = round(period_s * 1e9)


# configuration errors a node reports as one line instead of a traceback
SETUP_ERRORS: tuple[type[Exception], ...] = (ParamsError, RigError)


def events_executor(context: Context) -> Executor:
    """rclpy's C++ ``EventsExecutor`` (``rclpy.experimental``): its wait for work and dispatch cost a fraction of the
    Python ``SingleThreadedExecutor``'s, which re-builds its wait set on every wake (the camera nodes wake ~100 times a
    second for images and timers). Not for a node whose subscriptions take the middleware's message info (it does not
    pass it: ``SystemError: null argument to internal routine``)."""
    from rclpy.experimental import EventsExecutor
    return EventsExecutor(context=context)


# how long a node's teardown (executor, node, context) may take before the process ends with exit code 1
TEARDOWN_LIMIT_S = 10.0


@contextlib.contextmanager
def bounded_teardown(limit_s: float):
    """End the process (exit code 1, every thread's traceback on stderr) if the block takes over ``limit_s``.

    Why: destroying a context's last node deletes its Fast DDS participant, and Fast DDS 2.14 (the PyPI wheel) can
    spin there for ever: ``DomainParticipant::set_listener(nullptr)`` busy-waits for a discovery callback in flight
    while that callback waits for the mutex the spinning thread holds (eProsima/Fast-DDS#6513; seen once in
    ``make test`` at stop 87, a test's node created and destroyed at once). The call holds the GIL, so no Python
    timer can act; ``faulthandler``'s watchdog is a C thread that can."""
    faulthandler.dump_traceback_later(limit_s, exit=True)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


def spin_node(factory: Callable[[], Node], args: list[str] | None = None, *,
              finished: Callable[[Node], bool] | None = None, domain_id: int | None = None,
              images: bool = False, executor: Callable[[Context], Executor] | None = None) -> Node | None:
    """``main`` of a node: init, spin until Ctrl-C, shutdown or ``finished(node)`` (for nodes that end by
    themselves), destroy the node, shut down. Returns the destroyed node (what it recorded, e.g. an exit
    code, stays readable); exceptions from ``factory`` propagate after the clean-up. ``images``: the node
    publishes images, so its participant gets the package's Fast DDS profile
    (:func:`~fixego_ros.nodes.dds_profile.use_image_profile`) unless the user set one. Every node computes with one
    BLAS and one OpenCV thread unless the environment sets a count (:func:`~fixego_ros.threads.limit_threads`).
    ``executor``: makes the node's executor from its context (default ``SingleThreadedExecutor``; see
    :func:`events_executor`). It is spun a bounded 0.1 s at a time until the context shuts down (Ctrl-C, SIGTERM):
    ``EventsExecutor.spin()`` went on spinning after SIGTERM. The teardown is bounded (:func:`bounded_teardown`)."""
    notes = [limit_threads(), use_image_profile() if images else '']
    rclpy.init(args=args, domain_id=domain_id)
    node, ex = None, None
    try:
        node = factory()
        for note in filter(None, notes):
            node.get_logger().info(note)
        ex = SingleThreadedExecutor(context=node.context) if executor is None else executor(node.context)
        ex.add_node(node)
        while node.context.ok() and not (finished is not None and finished(node)):
            ex.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        with bounded_teardown(TEARDOWN_LIMIT_S):
            if ex is not None:
                ex.shutdown(timeout_sec=1.0)
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
    return node


def run_node(factory: Callable[[], Node], prog: str, args: list[str] | None = None, *,
             finished: Callable[[Node], bool] | None = None, images: bool = False,
             executor: Callable[[Context], Executor] | None = None) -> int:
    """:func:`spin_node` for a node's ``main``: a bad parameter or rig file ends it with one line on stderr
    (``prog: parameter NAME: VALUE ... (allowed: ...)``) and exit code 2, not a traceback; 0 otherwise."""
    try:
        spin_node(factory, args, finished=finished, images=images, executor=executor)
    except SETUP_ERRORS as e:
        print(f'{prog}: {e}', file=sys.stderr)
        return 2
    return 0


class CameraInfoIntrinsics:
    """A node's use of ``<side>/camera_info`` (:mod:`fixego_ros.pipeline.camera_info`): intrinsics the rig file
    leaves out come from each camera's first CameraInfo (``on_rig(rig)`` is called with the completed rig), and
    a CameraInfo that disagrees with the rig file is logged once as an error and reported on /diagnostics
    (:meth:`status`, ERROR) while the rig file is kept. Subscribed with sensor-data QoS (matches reliable and
    best-effort publishers)."""

    def __init__(self, node: Node, rig, sides: Iterable[str], on_rig: Callable[[object], None] | None = None) -> None:
        from sensor_msgs.msg import CameraInfo

        from fixego_ros.pipeline.camera_info import IntrinsicsFromInfo
        self.node, self.sides, self.on_rig = node, tuple(sides), on_rig
        self.fill = IntrinsicsFromInfo(rig)
        self._logged: set[str] = set()
        for side in self.sides:
            node.create_subscription(CameraInfo, f'{side}/camera_info',
                                     lambda m, s=side: self._on_info(s, m), SENSOR_QOS)

    @property
    def rig(self):
        return self.fill.rig

    def ready(self, sides: Iterable[str] | None = None) -> bool:
        return all(self.fill.ready(s) for s in (self.sides if sides is None else sides))

    def _on_info(self, side: str, msg) -> None:
        if self.fill.on_info(side, msg):
            self.node.get_logger().info(f'{side} intrinsics from {side}/camera_info: {self.fill.rig.camera(side)}')
            if self.on_rig is not None:
                self.on_rig(self.fill.rig)
        for s, text in self.fill.errors.items():
            if s not in self._logged:
                self._logged.add(s)
                self.node.get_logger().error(text)

    def wait(self, timeout_s: float, sides: Iterable[str] | None = None) -> None:
        """Spin this node (nothing else is subscribed yet) until the ``sides`` have intrinsics, at most
        ``timeout_s``; RigError saying what is missing otherwise."""
        import time

        from rclpy.executors import SingleThreadedExecutor
        sides = tuple(self.sides if sides is None else sides)
        if self.ready(sides):
            return
        missing = ', '.join(self.fill.rig.missing_intrinsics())
        self.node.get_logger().info(f'the rig file gives no intrinsics for {missing}:'
                                    f' waiting up to {timeout_s:g} s for camera_info')
        ex = SingleThreadedExecutor(context=self.node.context)
        ex.add_node(self.node)
        try:
            deadline = time.monotonic() + timeout_s
            while not self.ready(sides) and time.monotonic() < deadline and self.node.context.ok():
                ex.spin_once(timeout_sec=min(0.1, max(0.0, deadline - time.monotonic())))
        finally:
            ex.remove_node(self.node)
            ex.shutdown(timeout_sec=1.0)
        if not self.ready(sides):
            missing = [s for s in sides if not self.fill.ready(s)]
            why = '; '.join(self.fill.errors[s] for s in missing if s in self.fill.errors)
            raise RigError(f'no intrinsics for the {" and ".join(missing)} camera: none in the rig file and no usable '
                           f'{" / ".join(f"{s}/camera_info" for s in missing)} within {timeout_s:g} s'
                           + (f' ({why})' if why else ''))

    def status(self, name: str) -> DiagnosticStatus:
        """OK (where each camera's intrinsics come from), WARN while one is missing, ERROR on a disagreement."""
        f = self.fill
        values = {f'{s}_intrinsics': f.source.get(s, 'missing') for s in self.sides}
        errors = [f.errors[s] for s in self.sides if s in f.errors]
        missing = [s for s in self.sides if not f.ready(s)]
        if errors:
            return diagnostic_status(name, 'intrinsics', ERROR, '; '.join(errors), values)
        if missing:
            return diagnostic_status(name, 'intrinsics', WARN, f'waiting for {", ".join(missing)} camera_info '
                                                               '(no intrinsics in the rig file)', values)
        return diagnostic_status(name, 'intrinsics', OK, 'intrinsics known', values)


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


def transform_msg(parent: str, child: str, pose: Pose, stamp: Time):
    """geometry_msgs/TransformStamped of a (parent, child, Pose) tuple of :mod:`fixego_ros.geometry.frames`."""
    from geometry_msgs.msg import TransformStamped
    tf = TransformStamped()
    tf.header.stamp = stamp
    tf.header.frame_id = parent
    tf.child_frame_id = child
    p = pose_to_msg(pose)
    tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = (
        p.position.x, p.position.y, p.position.z)
    tf.transform.rotation = p.orientation
    return tf


def tf_broadcaster(node: Node, static: bool = False):
    """A tf2_ros (Static)TransformBroadcaster, or None when tf2_ros is not importable (DESIGN.md §3: TF is
    published only on a full ROS install, never required)."""
    try:
        from tf2_ros import StaticTransformBroadcaster, TransformBroadcaster
    except ImportError:
        return None
    return StaticTransformBroadcaster(node) if static else TransformBroadcaster(node)


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


def queue_wait_s(info: Mapping[str, int] | None) -> float | None:
    """Seconds a message waited between its arrival in this process (the middleware's receive time, on the system
    clock) and its callback (``info``: the message info rclpy gives a two-argument callback); None when there is
    no receive time."""
    received = (info or {}).get('received_timestamp') or 0
    return max(0.0, (time.time_ns() - received) * 1e-9) if received > 0 else None


def transport_s(info: Mapping[str, int] | None) -> float | None:
    """Seconds from a message's publication (its source timestamp) to its arrival in this process (receive
    timestamp), both the middleware's on the system clock: the transport alone, e.g. of an image over DDS; None
    when either is missing."""
    sent, received = ((info or {}).get(k) or 0 for k in ('source_timestamp', 'received_timestamp'))
    return max(0.0, (received - sent) * 1e-9) if sent > 0 and received > 0 else None


def percentile_values(name: str, values: Iterable[float]) -> dict[str, str]:
    """``name_p50`` / ``name_p95`` (2 decimals) of recent timings, the keys ``fixego_ros.demo.report`` reads back."""
    a = np.asarray(list(values), dtype=float)
    return {f'{name}_p50': f'{np.median(a):.2f}', f'{name}_p95': f'{np.percentile(a, 95):.2f}'}


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
    msg.fields = [PointField(name=name, offset=int(off), datatype=POINT_FIELD_TYPES[dt], count=1)
                  for name, (dt, off) in rows.dtype.fields.items()]
    msg.is_bigendian = False
    msg.point_step = int(rows.dtype.itemsize)
    msg.row_step = msg.point_step * msg.width
    msg.data = np.ascontiguousarray(rows).tobytes()
    msg.is_dense = True
    return msg
