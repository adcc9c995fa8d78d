"""estimator_node: flow observations in, trajectory out (DESIGN.md §3).

Topics are relative names in the node namespace (default ``/fixego``). Subscribes ``flow/observation``
(sensor_msgs/PointCloud2, the row table of :mod:`fixego_ros.pipeline.observation`) and feeds the back end
(:func:`~fixego_ros.estimation.backend.make_backend`): by default the metric fixed-lag smoother
(:mod:`fixego_ros.estimation.smoother`), or with ``refinement: local`` the papers' two-frame solve plus local BA.
Publishes ``pose`` and ``odom`` (covariance from the smoother's marginals; a large position term while the scale
is unobserved) every frame, ``path`` (the smoother's revisions of recent frames applied) and ``path_raw``
(two-frame only) at most once per
``path_publish_period_s`` of observation time plus once when the poses stop coming (so the last Path holds the
whole run, up to ``path_max_length`` poses), and ``/diagnostics``, all in ``odom_frame`` / ``base_frame``. When
tf2_ros is importable: TF ``odom -> base_link`` (``publish_tf``: auto = only without a speed source, whose robot
usually broadcasts it) and, once, the static ``base_link -> rig -> right_zero / left_zero`` of the rig file
(``publish_static_tf``). ``~/reset`` (std_srvs/Trigger) restarts the trajectory.

Scale aid (off by default): with ``speed_topic`` set it subscribes that nav_msgs/Odometry (e.g. wheel
odometry; twist in ``base_frame``, REP-105) and forwards each valid sample, in stamp order, to
the back end's ``add_velocity`` as the rig-frame velocity and covariance (:mod:`fixego_ros.pipeline.odometry`;
an all-zero covariance means unknown and becomes ``speed_default_std``). A sample older than
``speed_max_age_s`` relative to the newest frame is not used (dropped as stale when it arrives, and the
aid reports stale on /diagnostics when frames run that far ahead of the newest sample). /diagnostics
carries a ``scale`` status (OK once the estimator has observed the metric scale, WARN with the reason
otherwise) and, when the aid is on, a ``speed aid`` status.

Bad input never stops the node: a malformed observation is rejected whole (logged once, counted on
/diagnostics); a step the solver cannot make is replaced by a constant-velocity prediction and flagged;
nothing non-finite is ever published.

Stamps: an observation stamped more than ``max_future_s`` ahead of the node clock is rejected and counted
(accepted, it would make every later observation out of order). One not after the last accepted frame is
dropped and counted (/diagnostics WARN, logged once). When they keep coming older than the last accepted
one (``backward_reset_count`` in a row, or for ``backward_reset_s``: the clock jumped back, e.g. a bag was
restarted), the node logs it and resets the trajectory, which restarts at that observation.

Parameters (:data:`fixego_ros.pipeline.params.ESTIMATOR_NODE_PARAMS`) are checked at start and on
``ros2 param set``; the step acceptance thresholds, the lag/stamp bounds and the diagnostics period change
at run time, the rest is read-only.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Empty
from std_srvs.srv import Trigger

from fixego_ros.estimation.backend import make_backend
from fixego_ros.estimation.frames import FrameResult
from fixego_ros.estimation.live_smoother import LiveSmoother
from fixego_ros.estimation.scale_requests import Measurement, ScaleRequests, newest, vergence_measurement
from fixego_ros.estimation.status import StepStatus
from fixego_ros.geometry.frames import static_transforms
from fixego_ros.geometry.rig import SIDES, default_rig_path, load_rig
from fixego_ros.geometry.rotation import Pose, base_link_covariance, rig_pose_to_base_link
from fixego_ros.nodes.common import (
    ERROR,
    LATCHED_QOS,
    OK,
    RELIABLE_QOS,
    WARN,
    CameraInfoIntrinsics,
    CloudError,
    OnceLogger,
    cloud_to_table,
    declare_parameters,
    diagnostic_status,
    in_namespace,
    percentile_values,
    pose_to_msg,
    publish_diagnostics,
    queue_wait_s,
    run_node,
    set_timer_period,
    stamp_to_sec,
    tf_broadcaster,
    transform_msg,
)
from fixego_ros.pipeline.observation import ROW_DTYPE, ObservationError, rows_to_observation
from fixego_ros.pipeline.odometry import (
    OdometryError,
    SpeedInput,
    SpeedSettings,
    vergence_from_msg,
)
from fixego_ros.pipeline.params import ESTIMATOR_NODE_PARAMS, Getter, estimator_config

PARAMS = ESTIMATOR_NODE_PARAMS
# the parameters applied at run time: the back end reads these config fields at every step ...
LIVE_CONFIG = ('fixation_weight', 'velocity_prior', 'prior_sigma_rel', 'prior_sigma_min', 'max_step_translation',
               'max_speed', 'max_step_rotation_deg', 'reject_translation_std')
# ... and the node reads these per message (or sets the timer's period)
LIVE_NODE = ('max_lag_s', 'max_keyframe_lag_s', 'max_future_s', 'backward_reset_count', 'backward_reset_s',
             'diagnostics_period_s', 'vergence_request_rel_std', 'vergence_request_min_interval_s', 'scale_drift_per_s',
             'smoother_warn_behind_s')


def odom_covariance(cov_rig: np.ndarray, pose_rig: Pose, mount: Pose | None = None) -> list[float]:
    """Row-major 6x6 Odometry covariance (x, y, z, rot x, rot y, rot z; ``odom`` axes) of the estimator's
    covariance over [rotation, position] of ``pose_rig`` (rig frame at frame 0), through the rig's mount."""
    return [float(x) for x in base_link_covariance(cov_rig, pose_rig, mount).ravel()]


class AnswerWaiter:
    """Takes the smoother process's answers as they come, between frames: a thread waits on its pipe
    (:meth:`LiveSmoother.wait_for_answer`, bounded) and wakes the executor through a guard condition, whose callback
    (``take``, on the executor's thread like every other callback) takes them and revises the path. Taken on the next
    frame's path instead, an answer (the window's revised poses, the frames between them re-interpolated) cost that
    frame 4 ms on average in its slowest tenth, 7 ms beside two CPU-bound processes (a real-time replay of recorded
    run 4 through the live smoother; docs/results.md "Stop 50"). Ends when the child is gone or :meth:`stop` is
    called."""

    WAIT_S = 0.2        # each wait on the pipe, and on the executor taking an answer (the thread's shutdown latency)

    def __init__(self, node: Node, smoother: LiveSmoother, take: Callable[[], None]) -> None:
        self._smoother, self._take = smoother, take
        self._taken, self._stopped = threading.Event(), threading.Event()
        self._guard = node.create_guard_condition(self._on_guard)
        self._thread = threading.Thread(target=self._run, name='smoother-answers', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stopped.is_set() and self._smoother.alive:
            if self._smoother.wait_for_answer(self.WAIT_S) and not self._stopped.is_set():
                self._taken.clear()
                self._guard.trigger()
                self._taken.wait(self.WAIT_S)      # the pipe stays readable until the executor has taken it

    def _on_guard(self) -> None:
        try:
            self._take()
        finally:
            self._taken.set()

    def stop(self) -> None:
        """End the thread (bounded wait) before the smoother's pipe is closed."""
        self._stopped.set()
        self._taken.set()
        self._thread.join(2 * self.WAIT_S)


class EstimatorNode(Node):

    def __init__(self, **kwargs) -> None:
        super().__init__('estimator_node', **in_namespace(kwargs))
        self.params = g = declare_parameters(self, PARAMS)
        rig_notes: list[str] = []
        self.rig = load_rig(g('rig_file') or default_rig_path(), warnings=rig_notes)
        for note in rig_notes:
            self.get_logger().warning(note)
        self.intrinsics = CameraInfoIntrinsics(self, self.rig, SIDES)   # what the rig file lacks: camera_info
        self.intrinsics.wait(float(g('camera_info_wait_s')))
        self.rig = self.intrinsics.rig
        self.config = estimator_config(g, self.rig)
        self.estimator = make_backend(self.rig, self.config, live=True)
        self.odom_frame, self.base_frame = str(g('odom_frame')), str(g('base_frame'))
        self._set_stamp_bounds(g)
        self.once = OnceLogger(self)
        n_path = int(g('path_max_length'))
        self.path: deque[PoseStamped] = deque(maxlen=n_path)
        self.path_raw: deque[PoseStamped] = deque(maxlen=n_path)
        # paths: built from the stored messages at most once per period of observation time (a Path of n poses
        # costs O(n) to publish), and flushed by a steady-clock timer once the poses stop (a bag's /clock stops too)
        self.path_period = float(g('path_publish_period_s'))
        self._path_stamp: float | None = None       # observation stamp of the last Path published
        self._paths_pending = False                 # poses stored (or corrected) since then
        self._last_pose_wall = time.monotonic()
        self.pub_pose = self.create_publisher(PoseStamped, 'pose', RELIABLE_QOS)
        self.pub_path = self.create_publisher(Path, 'path', RELIABLE_QOS)
        self.pub_path_raw = self.create_publisher(Path, 'path_raw', RELIABLE_QOS)
        self.pub_odom = self.create_publisher(Odometry, 'odom', RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE_QOS)
        self.tf = self._make_tf_broadcaster(str(g('publish_tf')), str(g('speed_topic')))
        if bool(g('publish_static_tf')):
            self._send_static_tf()
        # with the middleware's message info: the receive time says how long an observation waited for this node
        self.create_subscription(PointCloud2, str(g('observation_topic')),
                                 lambda msg, info: self._on_observation(msg, info), RELIABLE_QOS)
        self.speed = SpeedInput(SpeedSettings.from_getter(g, self.base_frame), self.rig.mount)
        self.speed_topic = self.speed.settings.topic
        self.speed_stats: Counter[str] = Counter()
        self.speed_last: float | None = None       # stamp of the newest sample forwarded
        self.speed_rejected_recent, self.speed_error = 0, ''
        if self.speed_topic:
            self.create_subscription(Odometry, self.speed_topic, self._on_speed, RELIABLE_QOS)
        self.vergence_topic = str(g('vergence_topic'))
        if self.vergence_topic:
            self.create_subscription(PoseWithCovarianceStamped, self.vergence_topic, self._on_vergence, LATCHED_QOS)
        request_topic = str(g('vergence_request_topic'))
        self.pub_vergence_request = self.create_publisher(Empty, request_topic, RELIABLE_QOS) if request_topic else None
        self.scale_requests = ScaleRequests(float(g('vergence_request_rel_std')),
                                            float(g('vergence_request_min_interval_s')), float(g('scale_drift_per_s')))
        self.vergence_received: Measurement | None = None   # the newest one given to the estimator (scale_requests)
        self.create_service(Trigger, '~/reset', self._srv_reset)
        self.diag_timer = self.create_timer(float(g('diagnostics_period_s')), self._publish_diagnostics)
        if self.path_period > 0:
            self.create_timer(self.path_period, self._flush_paths, clock=Clock(clock_type=ClockType.STEADY_TIME))
        # the smoother process's results arrive between frames, and after the last
        self.answers = (AnswerWaiter(self, self.estimator, self._take_revisions)
                        if isinstance(self.estimator, LiveSmoother) else None)
        self.status_counts: Counter[str] = Counter()
        self.stats = {'observations': 0, 'malformed': 0, 'out_of_order': 0, 'future_rejected': 0,
                      'skipped_behind': 0, 'published': 0, 'paths_published': 0, 'resets': 0,
                      'clock_jump_resets': 0}
        self.recent: Counter[str] = Counter()      # stamp problems since the last diagnostics report
        self.stamp_problem = ''                    # the latest of them, in words
        self._backward: tuple[float, int] | None = None   # (monotonic start, count) of a run of older stamps
        self.solve_ms: deque[float] = deque(maxlen=300)
        self.queue_ms: deque[float] = deque(maxlen=300)     # receive -> callback, per observation
        # ms after the image stamp, on this node's clock: an observation at the callback, its pose published
        self.observation_in_ms: deque[float] = deque(maxlen=300)
        self.pose_out_ms: deque[float] = deque(maxlen=300)
        self.behind_s: deque[float] = deque(maxlen=300)     # the smoother process's lag behind each frame
        self.last: FrameResult | None = None
        self.last_error = ''
        self.params.start(self._apply_params, LIVE_CONFIG + LIVE_NODE)
        back_end = (f'fixed-lag smoother, lag {self.config.smoother.lag_s:g} s'
                    if self.config.refinement == 'smoother' else
                    f'local BA n={self.config.window} mode={self.config.mode}')
        self.get_logger().info(f'estimator: {back_end}, TF {"on" if self.tf else "off"}, speed aid '
                               f'{self.speed_topic or "off"}')

    def _make_tf_broadcaster(self, mode: str, speed_topic: str):
        """publish_tf 'auto' is on only without a speed source: a robot with wheel odometry (or
        robot_localization) usually broadcasts odom -> base_link itself, and two parents of one frame break TF."""
        if mode == 'false' or (mode == 'auto' and speed_topic):
            if mode == 'auto':
                self.get_logger().info(f'publish_tf auto: no TF {self.odom_frame} -> {self.base_frame}, a speed '
                                       f'source ({speed_topic}) is configured (set publish_tf true to force it)')
            return None
        tf = tf_broadcaster(self)
        if tf is None:
            self.get_logger().info(f'tf2_ros not importable: no TF {self.odom_frame} -> {self.base_frame} '
                                   '(topics carry the pose)')
        return tf

    def _send_static_tf(self) -> None:
        """base_frame -> rig (the mount) -> right_zero / left_zero, once (latched by tf2_ros)."""
        static = tf_broadcaster(self, static=True)
        if static is None:
            return
        stamp = self.get_clock().now().to_msg()
        static.sendTransform([transform_msg(parent, child, pose, stamp)
                              for parent, child, pose in static_transforms(self.rig, self.base_frame)])
        self._static_tf = static        # kept alive: its latched publisher serves late joiners

    def destroy_node(self) -> None:
        if self.answers is not None:
            self.answers.stop()
        close = getattr(self.estimator, 'close', None)     # the live smoother's child process (bounded stop)
        if close is not None:
            close()
        super().destroy_node()

    # -------------------------------------------------------------------------------------- input
    def _on_observation(self, msg: PointCloud2, info: Mapping[str, int] | None = None) -> None:
        self.stats['observations'] += 1
        waited = queue_wait_s(info)
        if waited is not None:
            self.queue_ms.append(waited * 1e3)
        stamp = stamp_to_sec(msg.header.stamp)
        try:
            obs = rows_to_observation(stamp, cloud_to_table(msg, ROW_DTYPE))
        except (CloudError, ObservationError) as e:
            self.stats['malformed'] += 1
            self.last_error = f'malformed observation: {e}'
            self.once.warn('malformed', f'{self.last_error} (rejected; further ones are only counted)')
            return
        self.once.clear('malformed', 'observations well-formed again')
        now_ns = self.get_clock().now().nanoseconds
        now = now_ns * 1e-9
        # ROS time before the first /clock message reads 0: nothing to compare with then
        if now_ns > 0:
            self.observation_in_ms.append(1e3 * (now - stamp))
        if now_ns > 0 and stamp - now > self.max_future_s:
            self._stamp_problem('future_rejected', f'observation stamped {stamp - now:.3f} s ahead of the node '
                                                   f'clock (max_future_s {self.max_future_s:g}): rejected')
            self.once.warn('future', f'{self.stamp_problem} (further ones are only counted on /diagnostics)')
            return
        self.once.clear('future', 'observation stamps no longer ahead of the clock')
        # a non-keyframe is skipped when this node is behind its input (it waited here), not when it came late: a
        # pose costs ~1 ms, and skipping what the flow delivered late only left frames without a pose (demo runs:
        # 0-133 of ~800, median 12). Without the receive time, its age on the clock decides, as before
        lag = now - stamp
        behind = lag if waited is None else waited
        if (obs.keyframe is False and behind > self.max_lag_s) or lag > self.max_keyframe_lag_s:
            self.stats['skipped_behind'] += 1
            why = (f'{behind * 1e3:.0f} ms in the queue' if waited is not None and lag <= self.max_keyframe_lag_s
                   else f'{lag * 1e3:.0f} ms behind the clock')
            self.get_logger().warning(f'{why}: skipping non-keyframe observations (count on /diagnostics)',
                                      throttle_duration_sec=10.0)
            return
        last = self.estimator.last_stamp
        t = time.perf_counter()
        res = self.estimator.update(obs)
        self.solve_ms.append((time.perf_counter() - t) * 1e3)
        if not res.placed:
            self._stamp_problem('out_of_order', f'observation ignored: {res.message}')
            if not (last is not None and stamp <= last and self._clock_jumped_back()):
                if last is None or stamp > last:
                    self._backward = None          # not older than the last frame: no clock jump in progress
                self.once.warn('order', f'{self.stamp_problem} (further ones are only counted on /diagnostics)')
                return
            self._reset_after_jump(stamp, last)
            t = time.perf_counter()
            res = self.estimator.update(obs)       # the first frame of the new trajectory
            self.solve_ms.append((time.perf_counter() - t) * 1e3)
        self._backward = None
        self.once.clear('order', 'observations in order again')
        if isinstance(self.estimator, LiveSmoother):
            self._watch_smoother(self.estimator.behind_s)
        self.status_counts[res.status.value] += 1
        if not res.status.usable and res.status is not StepStatus.INIT:
            self.get_logger().warning(f'step not solved ({res.status.value}): {res.message} (further ones are '
                                      'counted on /diagnostics)', throttle_duration_sec=10.0)
        self.last = res
        self._publish(msg.header.stamp, res)
        if self.pub_vergence_request is not None and self.scale_requests.due(
                res.stamp, self._scale_measurement(), self.estimator.speed_source_used):
            self.pub_vergence_request.publish(Empty())

    def _watch_smoother(self, behind: float) -> None:
        """Keep the smoother process's lag, and say once when it falls ``smoother_warn_behind_s`` behind (and once
        when it is back under half of that)."""
        self.behind_s.append(behind)
        limit = self.warn_behind_s
        if limit > 0.0 and behind > limit:
            self.once.warn('behind', f'the smoother is {behind:.1f} s behind the newest frame: this machine does not '
                                     'keep up, so the path is revised late and from keyframes alone (less accurate); '
                                     'fewer processes on the cores, or a faster machine, help')
        elif limit <= 0.0 or behind < 0.5 * limit:
            self.once.clear('behind', f'the smoother caught up ({behind:.1f} s behind the newest frame)')

    def _scale_measurement(self) -> Measurement | None:
        """The newest vergence measurement, received here or used by the back end (scale_requests' module docstring)."""
        return newest(self.estimator.scale_measurement, self.vergence_received)

    def _stamp_problem(self, key: str, text: str) -> None:
        self.stats[key] += 1
        self.recent[key] += 1
        self.stamp_problem = text

    def _clock_jumped_back(self) -> bool:
        """One more observation older than the last accepted frame: true once they have come
        ``backward_reset_count`` times in a row or for ``backward_reset_s`` (a jump, not a stray one)."""
        now = time.monotonic()
        since, n = self._backward if self._backward is not None else (now, 0)
        self._backward = (since, n + 1)
        return n + 1 >= self.backward_reset_count or now - since >= self.backward_reset_s

    def _reset_after_jump(self, stamp: float, last: float) -> None:
        n = self._backward[1] if self._backward is not None else 1
        self.stats['clock_jump_resets'] += 1
        self.recent['clock_jump_resets'] += 1
        self.stamp_problem = (f'clock jumped back: {n} observations in a row older than the last accepted frame '
                              f'({last:.3f} s; newest {stamp:.3f} s): trajectory reset')
        self.get_logger().warning(f'{self.stamp_problem}, odom restarts at this observation')
        self._reset_trajectory()
        self._backward = None

    def _on_speed(self, msg: Odometry) -> None:
        try:
            sample = self.speed.from_msg(msg, self.last.stamp if self.last is not None else None)
            self.estimator.add_velocity(sample.stamp, sample.v_rig, sample.cov_rig)
        except (OdometryError, ValueError) as e:     # ValueError: the estimator refused it (never expected)
            if not isinstance(e, OdometryError):
                e = OdometryError(f'estimator refused the sample: {e}', 'estimator')
            self.speed_stats[f'rejected_{e.kind}'] += 1
            self.speed_rejected_recent += 1
            self.speed_error = str(e)
            self.once.warn(f'speed:{e.kind}', f'speed sample on {self.speed_topic} dropped: {e} (further ones '
                                              'are only counted on /diagnostics)')
            return
        if self.speed.assumed_frame:
            self.once.warn('speed:no_frame', f'{self.speed_topic}: empty child_frame_id, twist taken as '
                                             f'{self.base_frame}')
        self.speed_stats['samples'] += 1
        self.speed_last = sample.stamp

    # -------------------------------------------------------------------------------------- output
    def _on_vergence(self, msg: PoseWithCovarianceStamped) -> None:
        """The right fixation point measured by the vergence step: a position prior on that landmark."""
        try:
            stamp, point, cov = vergence_from_msg(msg)
            self.estimator.add_fixation_point(stamp, 'right', point, cov)
        except ValueError as e:      # a bad message, or the estimator refused it
            self.stats['vergence_rejected'] = self.stats.get('vergence_rejected', 0) + 1
            self.once.warn('vergence', f'vergence measurement on {self.vergence_topic} dropped: {e}')
            return
        self.vergence_received = newest(self.vergence_received, vergence_measurement(stamp, point, cov))
        self.stats['vergence'] = self.stats.get('vergence', 0) + 1
        self.get_logger().info(f'vergence: right fixation point at {float(np.linalg.norm(point)):.3f} m given to '
                               'the estimator')

    def _rescale_paths(self, k: float) -> None:
        """The scale was just measured (constant-speed prior + vergence step): the published paths so far were
        built at the nominal speed, so their positions get the metric scale (the next Path messages show it)."""
        for path in (self.path, self.path_raw):
            for ps in path:
                p = ps.pose.position
                p.x, p.y, p.z = p.x * k, p.y * k, p.z * k
        self.get_logger().info(f'scale measured: the {len(self.path)} path poses so far rescaled by {k:.3f}')

    def _correct_last(self, stamp: float, pose: Pose, pose_raw: Pose) -> None:
        """A blind step (nothing seen across it) was re-estimated once the step after it was solved: the path's
        last pose, that frame's, is replaced (the pose and odometry published then stay as they were)."""
        mount = self.rig.mount
        pose, pose_raw = rig_pose_to_base_link(pose, mount), rig_pose_to_base_link(pose_raw, mount)
        if not (self.path and pose.is_finite() and pose_raw.is_finite()
                and abs(stamp_to_sec(self.path[-1].header.stamp) - stamp) <= 1e-6):
            return
        self.path[-1] = self._stamped(self.path[-1].header.stamp, pose)
        self.path_raw[-1] = self._stamped(self.path_raw[-1].header.stamp, pose_raw)
        self.stats['blind_steps_bridged'] = self.stats.get('blind_steps_bridged', 0) + 1

    def _revise(self, revised: tuple[tuple[float, Pose], ...]) -> None:
        """The smoother's newer estimates of recent frames replace their poses in the path (pose, odometry and TF
        published then stay as they were: the live pose is continuous, the path is the best estimate)."""
        newer = {round(s, 6): p for s, p in revised}
        if not newer:
            return
        changed, oldest = 0, min(s for s, _ in revised) - 1e-6
        for k in range(len(self.path) - 1, -1, -1):
            ps = self.path[k]
            t = stamp_to_sec(ps.header.stamp)
            if t < oldest:
                break
            p = newer.get(round(t, 6))
            if p is None:
                continue
            p = rig_pose_to_base_link(p, self.rig.mount)
            if p.is_finite():
                self.path[k] = self._stamped(ps.header.stamp, p)
                changed += 1
        self.stats['path_poses_revised'] = self.stats.get('path_poses_revised', 0) + changed

    def _take_revisions(self) -> None:
        """The smoother process's results that came in since the last frame go into the path (published at once
        when paths go out with every pose, by the flush timer once the poses have stopped otherwise)."""
        revised = self.estimator.drain(0.0)
        if not revised:
            return
        self._revise(revised)
        self._paths_pending = True
        if self.path_period == 0:
            self._publish_paths()

    def _publish(self, stamp, res: FrameResult) -> None:
        pose = rig_pose_to_base_link(res.pose, self.rig.mount)
        pose_raw = rig_pose_to_base_link(res.pose_raw, self.rig.mount)
        if not (pose.is_finite() and pose_raw.is_finite() and np.all(np.isfinite(res.pose_covariance))):
            self.once.error('nan', 'estimator produced a non-finite pose: not published (please report)')
            return
        if res.prefix_scale != 1.0 and math.isfinite(res.prefix_scale):
            self._rescale_paths(res.prefix_scale)
        if res.corrected is not None:
            self._correct_last(*res.corrected)
        self._revise(res.revised)
        live = pose if res.odom is None else rig_pose_to_base_link(res.odom, self.rig.mount)
        if not live.is_finite():
            live = pose
        self.pub_pose.publish(self._stamped(stamp, live))
        self.path.append(self._stamped(stamp, pose))
        self.path_raw.append(self._stamped(stamp, pose_raw))
        self._paths_pending = True
        self._last_pose_wall = time.monotonic()
        if self.path_period == 0 or self._path_stamp is None or res.stamp - self._path_stamp >= self.path_period - 1e-6:
            self._publish_paths()
        self.pub_odom.publish(self._odometry(stamp, live, res))
        if self.tf is not None:
            self._send_tf(stamp, live)
        self.stats['published'] += 1
        now_ns = self.get_clock().now().nanoseconds
        if now_ns > 0:          # 0: ROS time before the first /clock message
            self.pose_out_ms.append(1e3 * (now_ns * 1e-9 - stamp_to_sec(stamp)))

    def _publish_paths(self) -> None:
        """path and path_raw from the stored poses (corrections and rescaling already applied to them), stamped
        with the newest one."""
        if not self.path:
            return
        stamp = self.path[-1].header.stamp
        for pub, poses in ((self.pub_path, self.path), (self.pub_path_raw, self.path_raw)):
            path = Path()
            path.header.stamp = stamp
            path.header.frame_id = self.odom_frame
            path.poses = list(poses)
            pub.publish(path)
        self._path_stamp = stamp_to_sec(stamp)
        self._paths_pending = False
        self.stats['paths_published'] += 1

    def _flush_paths(self) -> None:
        """Steady-clock timer: once no pose has come for a period (the run ended, or stalled), publish the paths
        that are still unpublished, so the last Path holds the whole trajectory."""
        if self._paths_pending and time.monotonic() - self._last_pose_wall >= self.path_period:
            self._publish_paths()

    def _stamped(self, stamp, pose: Pose) -> PoseStamped:
        ps = PoseStamped()
        ps.header.stamp = stamp
        ps.header.frame_id = self.odom_frame
        pose_to_msg(pose, ps.pose)
        return ps

    def _odometry(self, stamp, pose: Pose, res: FrameResult) -> Odometry:
        od = Odometry()
        od.header.stamp = stamp
        od.header.frame_id = self.odom_frame
        od.child_frame_id = self.base_frame
        pose_to_msg(pose, od.pose.pose)
        od.pose.covariance = odom_covariance(res.pose_covariance, res.pose, self.rig.mount)
        dt = res.stamp - res.ref_stamp if res.ref_stamp is not None else 0.0
        if dt > 0 and res.status is not StepStatus.INIT:
            step = rig_pose_to_base_link(res.step, self.rig.mount)   # base_link at t in base_link at the keyframe
            v, w = step.R.T @ step.t / dt, step.rvec() / dt   # twist in the child frame (base_link at t)
            od.twist.twist.linear.x, od.twist.twist.linear.y, od.twist.twist.linear.z = (float(x) for x in v)
            od.twist.twist.angular.x, od.twist.twist.angular.y, od.twist.twist.angular.z = (float(x) for x in w)
            tw = odom_covariance(res.step_covariance, res.step, self.rig.mount)
            od.twist.covariance = [float(min(x / (dt * dt), 1e12)) for x in tw]
        else:
            od.twist.covariance = [0.0] * 36
            for i in range(6):
                od.twist.covariance[7 * i] = 1e6   # unknown velocity
        return od

    def _send_tf(self, stamp, pose: Pose) -> None:
        self.tf.sendTransform(transform_msg(self.odom_frame, self.base_frame, pose, stamp))

    # -------------------------------------------------------------------------------------- parameters
    def _set_stamp_bounds(self, g: Getter) -> None:
        self.max_lag_s = float(g('max_lag_s'))
        self.max_keyframe_lag_s = float(g('max_keyframe_lag_s'))
        self.max_future_s = float(g('max_future_s'))
        self.backward_reset_count = int(g('backward_reset_count'))
        self.backward_reset_s = float(g('backward_reset_s'))
        self.warn_behind_s = float(g('smoother_warn_behind_s'))

    def _apply_params(self, changes: dict[str, object], g: Getter) -> None:
        """``ros2 param set`` of run-time parameters: everything is built first (a combination the core
        refuses raises and changes nothing), then put in place; the estimator reads its config every step."""
        config = estimator_config(g, self.rig) if changes.keys() & set(LIVE_CONFIG) else None
        if config is not None:
            self.config = self.estimator.config = config
        self._set_stamp_bounds(g)
        r = self.scale_requests
        r.max_rel_std = float(g('vergence_request_rel_std'))
        r.min_interval_s = float(g('vergence_request_min_interval_s'))
        r.drift_per_s = float(g('scale_drift_per_s'))
        if 'diagnostics_period_s' in changes:
            set_timer_period(self.diag_timer, float(g('diagnostics_period_s')))

    # -------------------------------------------------------------------------------------- services
    def _reset_trajectory(self) -> None:
        self.estimator.reset()
        self.vergence_received = None
        self.speed.reset()
        self.path.clear()
        self.path_raw.clear()
        self._path_stamp, self._paths_pending = None, False
        self.last = None

    def _srv_reset(self, request, response):
        self._reset_trajectory()
        self.stats['resets'] += 1
        self.get_logger().info('trajectory reset: odom restarts at the next frame')
        response.success = True
        response.message = 'trajectory reset'
        return response

    # -------------------------------------------------------------------------------------- diagnostics
    def _publish_diagnostics(self) -> None:
        values: dict[str, object] = dict(self.stats)
        values['vergence_requests'] = self.scale_requests.count
        if self.last is not None:
            std = self.scale_requests.rel_std(self.last.stamp, self._scale_measurement())
            values['scale_rel_std'] = f'{std:.4f}' if math.isfinite(std) else 'unmeasured'
        values.update({f'steps_{k}': v for k, v in sorted(self.status_counts.items())})
        values.update(percentile_values('solve_ms', self.solve_ms or (0.0,)))
        if self.queue_ms:
            values.update(percentile_values('queue_ms', self.queue_ms))
        for name, q in (('observation_in_ms', self.observation_in_ms), ('pose_out_ms', self.pose_out_ms)):
            if q:
                values.update(percentile_values(name, q))
        level, message = OK, 'estimating'
        if not isinstance(self.estimator, LiveSmoother):     # the papers' local BA: its window and cost
            values.update({'window': self.config.window, 'mode': self.config.mode})
        else:
            values.update({'smoother_results': self.estimator.smoothed_results,
                           'smoother_skipped_frames': self.estimator.frames_skipped,
                           'smoother_behind_s': f'{self.estimator.behind_s:.2f}',
                           **percentile_values('smoother_behind_s', self.behind_s or (0.0,)),
                           **percentile_values('smoother_update_ms', self.estimator.update_ms or (0.0,)),
                           **{k: v for stage, ms in self.estimator.stage_ms.items() if ms
                              for k, v in percentile_values(f'smoother_{stage}_ms', ms).items()},
                           'smoother_restarts': self.estimator.restarts,
                           'smoother_repairs': self.estimator.repairs,
                           'smoother_dropped_landmarks': self.estimator.dropped,
                           'smoother_resections_rejected': self.estimator.resections_rejected,
                           'smoother_vergence_used': self.estimator.vergence_used})
        if self.last is None:
            level, message = WARN, 'no observation yet'
        else:
            std = np.sqrt(np.clip(np.diag(self.last.step_covariance)[3:], 0, None))
            values.update({'frame': self.last.index, 'last_status': self.last.status.value,
                           'last_message': self.last.message, 'step_translation_std_m': f'{np.max(std):.4g}'})
            if not self.last.status.usable and self.last.status is not StepStatus.INIT:
                level, message = WARN, f'last step {self.last.status.value}: {self.last.message}'
            elif self.last.status is StepStatus.WEAK:
                level, message = WARN, 'scale weakly observed (large translation covariance)'
        if self.once.active('behind'):
            level, message = WARN, (f'smoother {self.behind_s[-1]:.1f} s behind the newest frame: the path is '
                                    'revised late and from keyframes alone')
        if self.recent:      # stamp problems since the last report: out of order, from the future, clock jumps
            values.update({f'recent_{k}': v for k, v in sorted(self.recent.items())})
            level, message = WARN, (f'{", ".join(f"{v} {k}" for k, v in sorted(self.recent.items()))} since the '
                                    f'last report; latest: {self.stamp_problem}')
            self.recent.clear()
        if isinstance(self.estimator, LiveSmoother) and not self.estimator.alive:
            level, message = ERROR, 'the smoother process has ended: poses are two-frame only (please report)'
        if self.once.active('malformed'):
            level, message = ERROR, self.last_error
        statuses = [diagnostic_status('fixego estimator_node', 'estimator', level, message, values),
                    self._scale_status(), self.intrinsics.status('fixego estimator_node: intrinsics')]
        if self.speed_topic:
            statuses.append(self._speed_status())
        publish_diagnostics(self, self.pub_diag, statuses)

    def _scale_status(self):
        if self.last is None:
            return diagnostic_status('fixego estimator_node: scale', 'estimator', WARN, 'no frame yet')
        observed, note = bool(self.last.scale_observed), str(self.last.scale_note)
        message = note if observed or note.startswith('scale unobserved') else f'scale unobserved: {note}'
        return diagnostic_status('fixego estimator_node: scale', 'estimator', OK if observed else WARN, message,
                                 {'scale_observed': observed, 'scale_note': note})

    def _speed_status(self):
        n = self.speed_stats['samples']
        values: dict[str, object] = {'topic': self.speed_topic, 'samples': n,
                                     **{k: v for k, v in sorted(self.speed_stats.items()) if k != 'samples'}}
        if self.speed_last is None:
            return diagnostic_status('fixego estimator_node: speed aid', 'speed aid', WARN,
                                     f'no valid sample on {self.speed_topic} yet', values)
        age = self.get_clock().now().nanoseconds * 1e-9 - self.speed_last
        values['last_age_s'] = f'{age:.3f}'
        scale = getattr(self.estimator, 'speed_scale', None)    # the smoother's: the source's scale (wheel radius)
        if scale is not None:
            values['speed_scale'] = f'{scale:.4f}'
            values['speed_scale_estimated'] = bool(self.estimator.speed_scale_estimated)
        level, message = OK, f'receiving: {n} samples, last {age:.2f} s ago'
        behind = self.last.stamp - self.speed_last if self.last is not None else 0.0
        if behind > self.speed.max_age_s:
            level, message = WARN, (f'stale: newest sample {behind:.2f} s older than the newest frame '
                                    f'(speed_max_age_s {self.speed.max_age_s:g})')
        elif self.speed_rejected_recent:
            level, message = WARN, (f'{message}; {self.speed_rejected_recent} rejected since the last report '
                                    f'({self.speed_error})')
        self.speed_rejected_recent = 0
        return diagnostic_status('fixego estimator_node: speed aid', 'speed aid', level, message, values)


def main(args: list[str] | None = None) -> int:
    return run_node(EstimatorNode, 'estimator_node', args)


if __name__ == '__main__':
    sys.exit(main())
