"""camera_node: one per camera (``side:=right|left``). Tracks a fixation point and servoes the VISCA
pan/tilt head to keep it at the image centre; publishes joint states at image stamps and the fixation.

Topics (namespace /fixego, see README): subscribes ``<side>/image_raw`` (unless ``video_device``),
in passive mode also ``<side>/joint_states``; publishes ``<side>/joint_states`` (active mode),
``<side>/fixation`` (geometry_msgs/PointStamped, exactly one per processed image, stamp = the image's: x, y = pixel,
z = fixation id >= 0; for a frame without a valid fixation - the tracker lost it, or a vergence step drives the
left head - x = y = 0 and z = -1, so flow_node completes the frame at once instead of waiting for a fixation that
will not come) and ``/diagnostics``. Services ``~/reselect``, ``~/home``.

Joint states (active mode): one per image, stamped with the image stamp. ``joint_mode`` ``predict`` (default)
publishes at once: interpolated between the PosInq readings around the stamp when the one after it is in, else
predicted from the last reading and the servo's own commands
(:class:`~fixego_ros.tracking.joint_prediction.JointPredictor`, at most ``joint_predict_max_s`` ahead); ``wait``
publishes only once a reading after the stamp exists (25-50 ms at 9600 baud). Either way, a stamp with nothing to
go on is dropped after ``joint_max_wait_s``. JointState has no covariance: ``effort`` carries the 1-sigma of each
position in rad (reading quantisation when interpolated; growing with the extrapolation time and the commanded
rate when predicted), a use of ``effort`` this package's consumers know about (a pan/tilt head reports no torque).

Limits: near a pan/tilt limit the head swings back (``limit_margin_deg``, ``limit_swing_deg``) and publishes no
fixation while it turns. Each node follows the other camera's ``<side>/fixation`` and holds a due swing while that
camera has no fixation, up to ``limit_hold_max_s`` (:class:`~fixego_ros.tracking.fixation.SwingStagger`), so the
two cameras are never both without a fixation (the estimator has no rays for such a frame).

Vergence steps (the rig's own scale aid, on by default: ``vergence_enabled``; the *left* node in active mode
runs them, the right node needs no change): the left node drives its head so the right fixation ray's epipolar
curve is in view, finds the right fixation point in its image
(:func:`fixego_ros.tracking.vergence.find_partner_point`), fixates it with its own tracker and servo, and once
both fixations have settled triangulates it from the two heads' joint readings over ``vergence_frames`` image
stamps (:func:`~fixego_ros.tracking.vergence.average_samples`). Each step publishes one ``/fixego/vergence``
(geometry_msgs/PoseWithCovarianceStamped, frame ``rig``, transient local, depth 20), then the head goes back and
selects its own point again. When (:class:`~fixego_ros.tracking.vergence.VergenceScheduler`): at start-up, on each
new right fixation id (``/fixego/right/fixation``), on ``/fixego/vergence_request`` (std_msgs/Empty; the
estimator asks when its scale has grown uncertain), every ``vergence_period_s`` if > 0; never within
``vergence_min_interval_s`` of the previous step; a failure is retried at the next trigger or after
``vergence_retry_s`` (doubling). Every phase is bounded; the counts are a ``vergence`` status on ``/diagnostics``.

Parameters (:data:`fixego_ros.pipeline.params.CAMERA_NODE_PARAMS`) are checked at start and on ``ros2 param
set``; the tracker thresholds, servo gains, limit re-selection, joint mode and waits, diagnostics period and
vergence schedule (period, min interval, retry) change at run time, the rest (side, port, profile, rig, template
size, the vergence step itself) is read-only.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections import deque

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Empty
from std_srvs.srv import Trigger

from fixego_ros.geometry.frames import optical_transform
from fixego_ros.geometry.rig import default_rig_path, load_rig
from fixego_ros.nodes.common import (
    ERROR,
    LATCHED_QOS,
    OK,
    RELIABLE_QOS,
    SENSOR_QOS,
    WARN,
    CameraInfoIntrinsics,
    ImageError,
    OnceLogger,
    array_to_image,
    declare_parameters,
    diagnostic_status,
    events_executor,
    image_to_gray,
    in_namespace,
    percentile_values,
    publish_diagnostics,
    run_node,
    sec_to_stamp,
    set_timer_period,
    stamp_to_sec,
    tf_broadcaster,
    transform_msg,
    vergence_to_msg,
)
from fixego_ros.pipeline.messages import fixation_from_msg, pan_tilt
from fixego_ros.pipeline.params import CAMERA_NODE_PARAMS, FIXATION_PARAMS, Getter, ParamsError, fixation_params
from fixego_ros.tracking.fixation import NO_FIXATION_ID, FixationTracker, LimitCheck, SwingStagger
from fixego_ros.tracking.joint_prediction import JointSource
from fixego_ros.tracking.servo import FixationServo, JointHistory, ServoLoop, ServoParams, Target
from fixego_ros.tracking.vergence import (
    VergenceParams,
    VergenceResult,
    VergenceSchedule,
    VergenceScheduler,
    VergenceStep,
)
from fixego_ros.visca.driver import ModelCheck, ViscaCamera, check_model
from fixego_ros.visca.profiles import get_profile

PARAMS = CAMERA_NODE_PARAMS
# applied at run time: the tracker, the servo (and its loop thread) and the limit check read them per frame
LIVE_TRACKER = tuple(name for name, spec in FIXATION_PARAMS.items() if not spec.read_only)
LIVE_SERVO = ('servo_gain', 'servo_deadband_px', 'servo_move_time_s', 'servo_max_command_rate_hz',
              'servo_feedforward')
LIVE_NODE = ('limit_margin_deg', 'limit_swing_deg', 'limit_hold_max_s', 'joint_max_wait_s', 'joint_mode',
             'joint_predict_max_s', 'diagnostics_period_s')
# when vergence steps run (the scheduler's limits); the step itself is read-only
LIVE_VERGENCE = ('vergence_period_s', 'vergence_min_interval_s', 'vergence_retry_s')
MODEL_CHECK_TRIES = 3   # CAM_VersionInq attempts per connection before a silent camera counts as not answering


def servo_params(g: Getter) -> ServoParams:
    return ServoParams(gain=float(g('servo_gain')), deadband_px=float(g('servo_deadband_px')),
                       move_time_s=float(g('servo_move_time_s')),
                       max_command_rate_hz=float(g('servo_max_command_rate_hz')),
                       feedforward=bool(g('servo_feedforward')))


class CameraNode(Node):
    SWING_TOLERANCE_DEG = 1.0    # a swing back from a limit has arrived within this of its aim ...
    SWING_TIMEOUT_S = 3.0        # ... or ends after this long (EVI-D30: 200 deg in ~2.5 s)

    def __init__(self, **kwargs) -> None:
        super().__init__('camera_node', **in_namespace(kwargs))
        self.params = g = declare_parameters(self, PARAMS)
        self.side = str(g('side'))
        if float(g('vergence_min_depth_m')) >= float(g('vergence_max_depth_m')):
            raise ParamsError(f"parameters vergence_min_depth_m ({g('vergence_min_depth_m')}) and vergence_max_depth_m "
                              f"({g('vergence_max_depth_m')}): the nearest depth must be below the farthest")
        rig_notes: list[str] = []
        rig = load_rig(g('rig_file') or default_rig_path(), warnings=rig_notes)
        for note in rig_notes:
            self.get_logger().warning(note)
        # the left node's vergence steps also use the right camera; what the rig file lacks comes from camera_info
        verging = self.side == 'left' and bool(g('vergence_enabled')) and bool(str(g('port'))) and not bool(
            g('passive'))
        self.intrinsics = CameraInfoIntrinsics(self, rig, (self.side, 'right') if verging else (self.side,))
        self.intrinsics.wait(float(g('camera_info_wait_s')))
        rig = self.intrinsics.rig
        self.rig = rig
        self.camera = rig.camera(self.side)
        self.calibration = rig.calibration(self.side)
        try:
            self.profile = get_profile(str(g('profile')))
        except (ValueError, OSError) as e:
            raise ParamsError(f'parameter profile: {e}') from None
        self.frame_id = f'{self.side}_optical_frame'
        self.once = OnceLogger(self)
        self.tracker = FixationTracker(self.camera, fixation_params(g))
        pr = self.profile
        self.limits = LimitCheck((pr.pan_rad(pr.pan_min), pr.pan_rad(pr.pan_max)),
                                 (pr.tilt_rad(pr.tilt_min), pr.tilt_rad(pr.tilt_max)),
                                 math.radians(float(g('limit_margin_deg'))), math.radians(float(g('limit_swing_deg'))))
        self._swing: tuple[tuple[float, float], float] | None = None     # (aim, start) while swinging back
        # the left waits for the right's message of the same frame: both reaching a limit at once, one swings
        self.stagger = SwingStagger(float(g('limit_hold_max_s')), wait_for_partner_frame=self.side == 'left')
        self.partner = 'right' if self.side == 'left' else 'left'
        self._last_image_t: float | None = None
        self._frame_s = 0.0          # the last image interval (the stagger's "same frame")
        self.servo_params = servo_params(g)
        self.joint_max_wait_s = float(g('joint_max_wait_s'))
        self.joint_mode = str(g('joint_mode'))
        port = str(g('port'))
        self.passive = bool(g('passive')) or not port
        self.driver: ViscaCamera | None = None
        self.require_model_match = bool(g('require_model_match'))
        self.model_check: ModelCheck | None = None
        self._model_checked: int | None = None      # the driver connection (reconnect count) last checked
        self._model_tries = (-1, 0)                 # (connection, attempts) of the check under way
        self.loop: ServoLoop | None = None
        self.servo = FixationServo(self.camera, self.profile, self.servo_params, self.calibration)
        ns = self.side
        self.joint_names = [f'{self.side}_pan', f'{self.side}_tilt']
        self.pub_fix = self.create_publisher(PointStamped, f'{ns}/fixation', RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE_QOS)
        self.pub_joint = None
        self.tf = tf_broadcaster(self)       # <side>_zero -> <side>_optical_frame from the joint readings
        if self.passive:
            self.history = JointHistory()
            self.create_subscription(JointState, f'{ns}/joint_states', self._on_joint_state, RELIABLE_QOS)
        else:
            self.driver = ViscaCamera(port, baud=int(g('baud')), address=int(g('address')), profile=self.profile,
                                      timeout_s=float(g('serial_timeout_s')))
            try:
                self.driver.open()
            except Exception as e:
                self.get_logger().error(f'cannot open {port}: {e}; retrying in the background')
            self._check_model()         # before the servo loop owns the line
            self.loop = ServoLoop(self.driver, self.servo_params, clock=self._now)
            self.history = self.loop.history
            self._set_horizon(float(g('joint_predict_max_s')))
            self.pub_joint = self.create_publisher(JointState, f'{ns}/joint_states', RELIABLE_QOS)
            self.loop.start()
            self.create_timer(0.02, self._flush_joints)
            self.create_timer(0.5, self._check_model)    # a port opened later, or re-opened: check again
            # the other camera's fixations: a swing back waits for the other head's (and drives the vergence steps)
            self.create_subscription(PointStamped, f'{self.partner}/fixation', self._on_partner_fixation,
                                     RELIABLE_QOS)
        self._pending: deque = deque(maxlen=200)
        self.video = None
        self.pub_image = None
        vdev = str(g('video_device'))
        if vdev:
            import cv2
            self.video = cv2.VideoCapture(int(vdev) if vdev.isdigit() else vdev)
            if not self.video.isOpened():
                self.get_logger().error(f'cannot open video device {vdev!r}')
            self.pub_image = self.create_publisher(Image, f'{ns}/image_raw', SENSOR_QOS)
            self.create_timer(1.0 / max(1.0, float(g('video_fps'))), self._poll_video)
        else:
            self.create_subscription(Image, f'{ns}/image_raw', self._on_image, SENSOR_QOS)
        self.create_service(Trigger, '~/reselect', self._srv_reselect)
        self.create_service(Trigger, '~/home', self._srv_home)
        self.diag_timer = self.create_timer(float(g('diagnostics_period_s')), self._publish_diagnostics)
        self.stats = {'frames': 0, 'frames_without_fixation': 0, 'limit_swings': 0, 'limit_swings_held': 0,
                      'joint_states': 0,
                      'joint_states_dropped': 0, 'joint_states_predicted': 0}
        self.joint_latency_ms: deque[float] = deque(maxlen=300)     # image stamp -> joint state published
        self._setup_vergence(g)
        self.params.start(self._apply_params, LIVE_TRACKER + LIVE_SERVO + LIVE_NODE + LIVE_VERGENCE)
        self.get_logger().info(
            f'{self.side} camera: {"passive" if self.passive else f"VISCA on {port}"}, profile {self.profile.name}'
            + ('' if self.profile.verified else ' (UNVERIFIED numbers: run `fixego ptz calibrate`)'))

    # ---------------------------------------------------------------------------------------- time
    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    # ---------------------------------------------------------------------------------------- camera model
    def _check_model(self) -> None:
        """CAM_VersionInq once per serial connection (:func:`~fixego_ros.visca.driver.check_model`): a match is
        logged once, a mismatch is one error line (fatal with ``require_model_match``), no answer a warning. Silence
        or garbled bytes (e.g. just after a reconnect) are retried at the next ticks, MODEL_CHECK_TRIES in all."""
        d = self.driver
        if d is None or not d.connected or self._model_checked == d.stats['reconnects']:
            return
        key = d.stats['reconnects']
        tries = self._model_tries[1] + 1 if self._model_tries[0] == key else 1
        self._model_tries = (key, tries)
        c = check_model(d)
        if c.outcome == 'no_answer' and not c.final and tries < MODEL_CHECK_TRIES:
            return
        self._model_checked = key
        before, self.model_check = self.model_check, c
        if c.outcome == 'mismatch' and self.require_model_match:
            if self.loop is not None:
                self.loop.stop()
            d.close()
            raise ParamsError(f'parameter require_model_match is true and {c.message}')
        if before is not None and (before.outcome, before.version) == (c.outcome, c.version):
            return                                  # the same camera after a reconnect: said already
        if c.outcome == 'mismatch':
            self.get_logger().error(c.message + ' (require_model_match is false: carrying on)')
        elif c.outcome == 'no_answer':
            self.get_logger().warning(c.message)
        else:
            self.get_logger().info(c.message)

    def _model_status(self):
        c, pr = self.model_check, self.profile
        values: dict[str, object] = {'profile': pr.name, 'require_model_match': self.require_model_match,
                                     'expected_models': ' '.join(f'{m:#06x}' for m in pr.model_ids) or 'none'}
        if c is None:
            level, message = OK, 'not checked yet'
        else:
            level = {'mismatch': ERROR, 'no_answer': WARN}.get(c.outcome, OK)
            message = {'match': f'model matches profile {pr.name}',
                       'unchecked': f'profile {pr.name} lists no model id: not checked',
                       'no_answer': 'no answer to CAM_VersionInq: model not checked',
                       'mismatch': f'camera model mismatch with profile {pr.name}'}[c.outcome]
            values['check'] = c.outcome
            if c.version is not None:
                values.update({f'camera_{k}': f'{v:#06x}' for k, v in c.version.items() if k != 'max_socket'})
        return diagnostic_status(f'fixego camera_node {self.side}: camera model', self.driver.port, level, message,
                                 values)

    # ---------------------------------------------------------------------------------------- input
    def _on_joint_state(self, msg: JointState) -> None:
        try:
            pan, tilt = pan_tilt(msg, self.side)
        except ValueError as e:
            self.once.warn('joint_names', f'{e}: ignored')
            return
        if not (math.isfinite(pan) and math.isfinite(tilt)):
            self.once.warn('joint_nan', 'non-finite pan/tilt in joint_states: ignored')
            return
        self.history.add(stamp_to_sec(msg.header.stamp), pan, tilt)
        self._send_optical_tf(msg.header.stamp, pan, tilt)

    def _poll_video(self) -> None:
        if self.video is None:
            return
        ok, frame = self.video.read()
        if not ok:
            self.once.warn('video', 'video device returned no frame')
            return
        self.once.clear('video', 'video device delivers frames again')
        msg = array_to_image(frame, sec_to_stamp(self._now()), self.frame_id, encoding='bgr8')
        if self.pub_image is not None:
            self.pub_image.publish(msg)
        self._on_image(msg)

    def _on_image(self, msg: Image) -> None:
        try:
            gray = image_to_gray(msg)
        except ImageError as e:
            self.once.warn('image', f'image ignored: {e}')
            return
        if gray.shape != (self.camera.height, self.camera.width):
            self.once.warn('size', f'image is {gray.shape[1]}x{gray.shape[0]} but the rig file says '
                                   f'{self.camera.width}x{self.camera.height}: ignored')
            return
        self.once.clear('image')
        self.once.clear('size')
        self.stats['frames'] += 1
        t = stamp_to_sec(msg.header.stamp)
        if self._last_image_t is not None and t > self._last_image_t:
            self._frame_s = t - self._last_image_t
        self._last_image_t = t
        if not self.passive:
            self._pending.append(msg.header.stamp)
            self._flush_joints()
        joints = self.history.at(t, max_extrapolation_s=0.1)
        act, step = None, self.vergence
        if self._swinging(t, msg.header.stamp, joints, step):
            return
        if step is not None and not step.finished:
            self._vergence_stamps[t] = msg.header.stamp
            act = step.on_left_image(t, gray, self._now(), right_fixated=self.stagger.partner_fixated)
            self._vergence_tick()
            if act.kind == 'hold':     # the step drives the head: no tracking, "no valid fixation" published
                self._publish_fixation(msg.header.stamp, None, NO_FIXATION_ID)
                if self.loop is not None and act.aim is not None:
                    self.loop.set_target(self._aim_target(act.aim))
                return
            if act.reselect:
                self.tracker.request_reselect('vergence_end')
        if act is not None and act.select is not None:
            st = self.tracker.select_at(gray, act.select, t, 'vergence')
        else:
            st = self.tracker.update(gray, t)
        if step is not None and step is self.vergence:
            step.on_left_fixation(t, st.pixel, st.fixation_id, st.reselected)
            self._vergence_tick()
        if st.reselected:
            self.servo.reset(act.rate if act is not None else (0.0, 0.0))
            self.get_logger().info(f'fixation {st.fixation_id} selected at ({st.pixel[0]:.1f}, '
                                   f'{st.pixel[1]:.1f}): {st.reason}')
        if not st.valid:
            self.stats['frames_without_fixation'] += 1
            self.once.warn('fixation', f'no valid fixation point ({st.reason})')
            self._publish_fixation(msg.header.stamp, None, NO_FIXATION_ID)
            if self.loop is not None:
                self.loop.set_target(None)
            return
        self.once.clear('fixation', 'fixation point valid again')
        self._publish_fixation(msg.header.stamp, st.pixel, st.fixation_id)
        if self.loop is not None:
            if joints is None:
                self.once.warn('joints', 'no recent pan/tilt reading: not servoing')
                return
            self.once.clear('joints')
            self.loop.set_target(self.servo.target(st.pixel, joints, t, self._now()))

    def _swinging(self, t: float, stamp, joints: tuple[float, float] | None, step: VergenceStep | None) -> bool:
        """Near a pan/tilt limit the head swings back (:class:`LimitCheck`); while it turns, the frame publishes no
        fixation and is not tracked. Once it is there (or after ``SWING_TIMEOUT_S``) a new point is selected at the
        centre. Not while a vergence step has left the own fixation (it drives the head then)."""
        if self.loop is None or joints is None or (step is not None and not step.finished
                                                   and step.phase not in ('waiting', 'ended')):
            return False
        if self._swing is None:
            if self.limits.due(*joints) and self.stagger.hold(t, self._frame_s):
                if self.stagger.holds > self.stats['limit_swings_held']:
                    self.stats['limit_swings_held'] = self.stagger.holds
                    self.get_logger().info(f'pan/tilt near a limit: the swing back waits (up to '
                                           f'{self.stagger.max_hold_s:g} s) while the {self.partner} camera has no '
                                           'fixation (counted on /diagnostics)', throttle_duration_sec=10.0)
                return False
            self.stagger.reset()
            aim = self.limits.check(*joints)
            if aim is None:
                return False
            self._swing = (aim, t)
            self.stats['limit_swings'] += 1
            self.get_logger().info(f'pan/tilt near a limit: swinging back to pan {math.degrees(aim[0]):.1f}, tilt '
                                   f'{math.degrees(aim[1]):.1f} deg (counted on /diagnostics)',
                                   throttle_duration_sec=10.0)
        aim, t0 = self._swing
        tol = math.radians(self.SWING_TOLERANCE_DEG)
        if (abs(joints[0] - aim[0]) <= tol and abs(joints[1] - aim[1]) <= tol) or t - t0 > self.SWING_TIMEOUT_S:
            self._swing = None
            self.tracker.request_reselect('limit')
            return False
        self.loop.set_target(self._aim_target(aim))
        self._publish_fixation(stamp, None, NO_FIXATION_ID)
        if step is not None and not step.finished:
            step.on_left_fixation(t, None, NO_FIXATION_ID, False)      # waiting: the own point is not settled
        return True

    def _publish_fixation(self, stamp, pixel: tuple[float, float] | None, fixation_id: int) -> None:
        """One message per processed image, so flow_node never waits for one that will not come: the pixel and
        id, or for no valid fixation x = y = 0, z = NO_FIXATION_ID (-1; never NaN)."""
        out = PointStamped()
        out.header.stamp = stamp
        out.header.frame_id = self.frame_id
        if pixel is None:
            out.point.x, out.point.y, out.point.z = 0.0, 0.0, float(NO_FIXATION_ID)
        else:
            out.point.x, out.point.y, out.point.z = float(pixel[0]), float(pixel[1]), float(fixation_id)
        self.pub_fix.publish(out)

    def _set_horizon(self, seconds: float) -> None:
        pred = self.loop.predictor
        pred.params = dataclasses.replace(pred.params, max_horizon_s=seconds)

    def _flush_joints(self) -> None:
        """Publish joint states for the pending image stamps, in order: interpolated once a reading after the
        stamp exists; in predict mode at once from the prediction; dropped after joint_max_wait_s."""
        latest = self.history.latest()
        now = self._now()
        predictor = self.loop.predictor
        while self._pending:
            stamp = self._pending[0]
            t = stamp_to_sec(stamp)
            after = latest is not None and latest[0] >= t       # a reading after the stamp: interpolation
            est = predictor.estimate(t) if after or self.joint_mode == 'predict' else None
            if est is None and not after and now - t <= self.joint_max_wait_s:
                return          # wait mode, or too far past the last reading to predict: wait (bounded)
            self._pending.popleft()
            if est is None:
                self.stats['joint_states_dropped'] += 1
                self.once.warn('joint_drop', 'no PosInq readings around an image stamp: joint state dropped')
                continue
            self.once.clear('joint_drop')
            js = JointState()
            js.header.stamp = stamp
            js.header.frame_id = ''
            js.name = list(self.joint_names)
            js.position = [float(est.pan), float(est.tilt)]
            js.effort = [float(est.pan_sigma), float(est.tilt_sigma)]      # 1-sigma (rad): see the module docstring
            self.pub_joint.publish(js)
            self.stats['joint_states'] += 1
            self.stats['joint_states_predicted'] += est.source is JointSource.PREDICTED
            self.joint_latency_ms.append(1e3 * (self._now() - t))
            self._send_optical_tf(stamp, float(est.pan), float(est.tilt))

    def _send_optical_tf(self, stamp, pan: float, tilt: float) -> None:
        """The optical frame turns with the head: one transform per joint state (tf2_ros importable only)."""
        if self.tf is not None:
            self.tf.sendTransform(transform_msg(*optical_transform(self.rig, self.side, pan, tilt), stamp))

    # ---------------------------------------------------------------------------------------- parameters
    def _apply_params(self, changes: dict[str, object], g: Getter) -> None:
        """``ros2 param set``: new params objects are swapped in whole (the servo loop thread then reads
        either the old or the new one, never a mix); they take effect at the next frame or command."""
        if changes.keys() & set(LIVE_TRACKER):
            self.tracker.params = fixation_params(g)
        if changes.keys() & set(LIVE_SERVO):
            new = servo_params(g)
            self.servo_params = self.servo.params = new
            if self.loop is not None:
                self.loop.params = new
        self.limits.margin_rad = math.radians(float(g('limit_margin_deg')))
        self.limits.swing_rad = math.radians(float(g('limit_swing_deg')))
        self.stagger.max_hold_s = float(g('limit_hold_max_s'))
        self.joint_max_wait_s = float(g('joint_max_wait_s'))
        self.joint_mode = str(g('joint_mode'))
        if 'joint_predict_max_s' in changes and self.loop is not None:
            self._set_horizon(float(g('joint_predict_max_s')))
        if 'diagnostics_period_s' in changes:
            set_timer_period(self.diag_timer, float(g('diagnostics_period_s')))
        if changes.keys() & set(LIVE_VERGENCE) and self.scheduler is not None:
            self.scheduler.p = self._vergence_schedule(g)

    # ---------------------------------------------------------------------------------------- services
    def _srv_reselect(self, request, response):
        self.tracker.request_reselect('manual')
        response.success = True
        response.message = 'a new fixation point will be selected on the next frame'
        return response

    def _srv_home(self, request, response):
        if self.loop is None:
            response.success = False
            response.message = 'passive mode: no serial port'
            return response
        self.loop.request_home()
        self.tracker.request_reselect('home')
        response.success = True
        response.message = 'homing'
        return response

    # ---------------------------------------------------------------------------------------- vergence
    def _vergence_params(self, g: Getter, prior_depth_m: float | None = None) -> VergenceParams:
        return VergenceParams(min_depth_m=float(g('vergence_min_depth_m')),
                              max_depth_m=float(g('vergence_max_depth_m')), prior_depth_m=prior_depth_m,
                              ncc_min=float(g('vergence_ncc_min')),
                              match_ncc_min=float(g('vergence_match_ncc_min')),
                              margin_min=float(g('vergence_margin_min')),
                              max_rel_std=float(g('vergence_max_rel_std')),
                              pixel_sigma_px=float(g('vergence_pixel_sigma_px')),
                              joint_sigma_deg=float(g('vergence_joint_sigma_deg')),
                              timing_sigma_s=1e-3 * float(g('vergence_timing_sigma_ms')),
                              timing_bias_s=1e-3 * float(g('vergence_timing_bias_ms')),
                              settle_px=float(g('vergence_settle_px')), frames=int(g('vergence_frames')),
                              max_rate_deg_s=float(g('vergence_max_rate_deg_s')),
                              max_interruption_s=float(g('vergence_max_interruption_s')),
                              timeout_s=float(g('vergence_timeout_s')), wait_timeout_s=float(g('vergence_wait_s')),
                              slew_deg_s=get_profile(str(g('profile'))).fastest_deg_s)

    @staticmethod
    def _vergence_schedule(g: Getter) -> VergenceSchedule:
        return VergenceSchedule(period_s=float(g('vergence_period_s')), retry_s=float(g('vergence_retry_s')),
                                min_interval_s=float(g('vergence_min_interval_s')))

    def _setup_vergence(self, g: Getter) -> None:
        """Left node in active mode only: the scheduler, the right camera's topics (kept: a step needs the right's
        recent fixations, images and joints when it starts), the request topic and the publisher."""
        self.vergence: VergenceStep | None = None          # the step running now
        self.scheduler: VergenceScheduler | None = None
        self.vergence_state = 'off'
        self.vergence_last: VergenceResult | None = None   # the last measurement
        self.vergence_failure = ''                         # the last failure's reason
        self.vergence_time = {'last_interrupted_s': 0.0, 'max_interrupted_s': 0.0, 'total_interrupted_s': 0.0,
                              'last_away_s': 0.0, 'max_away_s': 0.0}
        self._vergence_stamps: dict[float, object] = {}     # left image stamps of the running step
        self._vergence_published = False
        self.vergence_timeline = ''                        # the last step's phases and events (s from leaving)
        self.pub_vergence = None
        if not bool(g('vergence_enabled')):
            self.vergence_state = 'off (vergence_enabled is false)'
            return
        if self.side != 'left':
            self.vergence_state = 'off (the left camera node runs the vergence steps)'
            return
        if self.loop is None:
            self.vergence_state = 'off (passive mode: no head to move)'
            self.get_logger().info('vergence steps off in passive mode (no serial port to move the head)')
            return
        self.right_history = JointHistory()
        self.scheduler = VergenceScheduler(self._vergence_schedule(g), self._now())
        self.vergence_state = 'idle'
        self.pub_vergence = self.create_publisher(PoseWithCovarianceStamped, 'vergence', LATCHED_QOS)
        # raw: a right image is decoded only while a step wants it (most frames it is not looked at)
        self.create_subscription(Image, 'right/image_raw', self._on_right_image, SENSOR_QOS, raw=True)
        self.create_subscription(JointState, 'right/joint_states', self._on_right_joints, RELIABLE_QOS)
        self.create_subscription(Empty, 'vergence_request', self._on_vergence_request, RELIABLE_QOS)
        self._vergence_timer = self.create_timer(0.05, self._vergence_tick)
        period = float(g('vergence_period_s'))
        self.get_logger().info('vergence steps armed: at start-up, on each new right fixation point, on '
                               'vergence_request' + (f', every {period:g} s' if period > 0 else '')
                               + f'; at least {float(g("vergence_min_interval_s")):g} s apart')

    def _on_right_image(self, data: bytes) -> None:
        if self.vergence is None or not self.vergence.wants_right_images:
            return
        try:
            msg = deserialize_message(data, Image)
            gray = image_to_gray(msg)
        except (ImageError, RuntimeError):     # RuntimeError: bytes that do not deserialize as an Image
            return
        if gray.shape == (self.rig.right.height, self.rig.right.width):
            self.vergence.add_right_image(stamp_to_sec(msg.header.stamp), gray)

    def _on_partner_fixation(self, msg: PointStamped) -> None:
        """The other camera's fixation: whether it has one (:class:`SwingStagger`); on the left node a right pixel
        may also trigger a vergence step (a new id), and a running step uses it. "No valid fixation" (id -1) is
        neither a new fixation point nor a pixel for the vergence step."""
        try:
            pixel, fid = fixation_from_msg(msg)
        except ValueError:
            return
        self.stagger.on_partner(stamp_to_sec(msg.header.stamp), pixel is not None)
        if pixel is None:
            return
        if self.scheduler is not None:
            self.scheduler.on_right_fixation(fid, self._now())
        if self.vergence is not None:
            self.vergence.add_right_fixation(stamp_to_sec(msg.header.stamp), pixel, fid)

    def _on_right_joints(self, msg: JointState) -> None:
        try:
            pan, tilt = pan_tilt(msg, 'right')
        except ValueError:
            return
        if math.isfinite(pan) and math.isfinite(tilt):
            self.right_history.add(stamp_to_sec(msg.header.stamp), pan, tilt)

    def _on_vergence_request(self, msg: Empty) -> None:
        if self.scheduler is not None:
            self.scheduler.trigger('request', self._now())

    def _head_range(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """Readings (rad) the head can reach, a VISCA unit inside its limits."""
        pr = self.profile
        return ((pr.pan_rad(pr.pan_min + 1), pr.pan_rad(pr.pan_max - 1)),
                (pr.tilt_rad(pr.tilt_min + 1), pr.tilt_rad(pr.tilt_max - 1)))

    def _aim_target(self, aim: tuple[float, float]) -> Target:
        pr = self.profile
        pan_u, tilt_u = pr.clamp(pr.pan_units(math.degrees(aim[0])), pr.tilt_units(math.degrees(aim[1])))
        return Target(pan_u, tilt_u, pr.pan_speed_max, pr.tilt_speed_max)

    def _vergence_tick(self) -> None:
        """Start a step when the scheduler says so; poll the running one (timeouts, the measurement) and
        publish its result once; close it when the head is back. Never blocks."""
        s = self.scheduler
        if s is None:
            return
        now = self._now()
        v = self.vergence
        if v is not None:
            v.poll(now)
            if v.result is not None and not self._vergence_published:
                self._vergence_published = True
                self._publish_vergence(v.result)
            if not v.finished:
                self.vergence_state = v.status
                if len(self._vergence_stamps) > 400:
                    for k in sorted(self._vergence_stamps)[:200]:
                        del self._vergence_stamps[k]
                return
            self._end_vergence(v, now)
        reason = s.due(now)
        if reason is None:
            return
        s.started(reason, now)
        prior = self.vergence_last.distance_m if self.vergence_last is not None else None
        self.vergence = VergenceStep(self.rig, self.history, self._vergence_params(self.params, prior),
                                     self.right_history, self._head_range(), self._joints_between_readings)
        self._vergence_published = False
        self.vergence_state = f'running: waiting ({reason})'

    def _joints_between_readings(self, t: float) -> tuple[float, float] | None:
        """The head's angles at ``t`` once a reading after it exists: the servo's commanded motion replayed between
        the readings (what ``joint_states`` publishes then), not a straight line, which cuts the corners of a
        head that starts, stops or turns back between two readings."""
        latest = self.history.latest()
        est = self.loop.predictor.estimate(t) if latest is not None and latest[0] >= t else None
        return None if est is None else (float(est.pan), float(est.tilt))

    def _end_vergence(self, v: VergenceStep, now: float) -> None:
        self.vergence = None
        self._vergence_stamps.clear()
        if v.needs_reselect:
            self.tracker.request_reselect('vergence_end')
        ok = v.succeeded
        self.scheduler.finished(ok, now, left_own_point=v.t_left is not None,
                                measured_at=v.result.stamp if v.result is not None else None)
        t = self.vergence_time
        t['last_interrupted_s'], t['last_away_s'] = v.interrupted_s, v.away_s
        t['max_interrupted_s'] = max(t['max_interrupted_s'], v.interrupted_s)
        t['max_away_s'] = max(t['max_away_s'], v.away_s)
        t['total_interrupted_s'] += v.interrupted_s
        t0 = v.timeline[0][1] if v.timeline else now
        self.vergence_timeline = ', '.join(f'{what} {when - t0:.2f}' for what, when in v.timeline)
        if ok:
            self.vergence_state = 'idle (last step done)'
            self.once.clear('vergence', 'vergence steps succeed again')
            return
        self.vergence_failure = v.reason
        self.vergence_state = f'idle (last step failed: {v.reason})'
        self.once.warn('vergence', f'vergence step failed: {v.reason}; independent fixation goes on, retried at the '
                                   f'next trigger or in {self.scheduler.t_retry - now:.0f} s (further failures are '
                                   f'counted on /diagnostics, not logged)')

    def _publish_vergence(self, res: VergenceResult) -> None:
        self.vergence_last = res
        stamp = self._vergence_stamps.get(res.stamp)
        self.pub_vergence.publish(vergence_to_msg(stamp if stamp is not None else sec_to_stamp(res.stamp),
                                                  res.point_rig, res.cov_rig))
        self.get_logger().info(
            f'vergence: right fixation point at {res.distance_m:.3f} m (std {res.std_m:.3f} m from {res.frames} '
            f'frames, vergence {math.degrees(res.angle_rad):.2f} deg, NCC {res.match.ncc:.2f}) after '
            f'{res.duration_s:.1f} s')

    def _vergence_status(self):
        s, r = self.scheduler, self.vergence_last
        values: dict[str, object] = {'state': self.vergence_state}
        level, message = OK, self.vergence_state
        if s is not None:
            values.update({'attempts': s.attempts, 'successes': s.successes, 'failures': s.failures,
                           'ignored_triggers': s.ignored, 'requests_answered_by_running_step': s.answered,
                           'last_trigger': s.last_trigger,
                           'last_failure': self.vergence_failure, 'last_timeline': self.vergence_timeline,
                           **{f'triggers_{k}': n for k, n in s.triggers.items()},
                           **{k: f'{x:.3f}' for k, x in self.vergence_time.items()}})
            message = f'{s.successes}/{s.attempts} steps done; {self.vergence_state}'
            if s.failures_in_a_row:
                level = WARN
        if r is not None:
            values.update({'last_stamp': f'{r.stamp:.3f}', 'last_distance_m': f'{r.distance_m:.4f}',
                           'last_std_m': f'{r.std_m:.4f}', 'last_frames': r.frames,
                           'last_vergence_deg': f'{math.degrees(r.angle_rad):.3f}', 'last_ncc': f'{r.match.ncc:.3f}',
                           'last_duration_s': f'{r.duration_s:.2f}'})
        return diagnostic_status(f'fixego camera_node {self.side}: vergence', 'vergence', level, message, values)

    # ---------------------------------------------------------------------------------------- diagnostics
    def _publish_diagnostics(self) -> None:
        st = self.tracker.last
        values: dict[str, object] = dict(self.stats)
        values.update({
            'mode': 'passive' if self.passive else 'active',
            'fixation_id': st.fixation_id if st else -1,
            'fixation_valid': bool(st and st.valid),
            'fixation_age_s': round(st.age_s, 3) if st else 0.0,
            'tracking_quality': round(st.quality, 3) if st else 0.0,
            'last_reason': st.reason if st else '',
            'reselections': len(self.tracker.reselections),
        })
        level, message = OK, 'tracking'
        if not (st and st.valid):
            level, message = WARN, f'no valid fixation ({st.reason if st else "no image yet"})'
        if self.driver is not None and self.loop is not None:
            values.update({f'serial_{k}': v for k, v in self.driver.stats.items()})
            values.update({'serial_state': self.driver.state, 'serial_comm_errors': self.driver.comm_errors,
                           'serial_last_error': self.driver.last_error,
                           'servo_loop_hz': round(self.loop.loop_rate_hz(), 2), 'joint_mode': self.joint_mode,
                           **(percentile_values('joint_latency_ms', self.joint_latency_ms)
                              if self.joint_latency_ms else {}),
                           'servo_commands': self.loop.stats['commands'],
                           # PosInq replies the host read too late to date them by their window (dated by the motion)
                           'servo_late_readings': self.loop.stats['late_readings'],
                           # the predictions' errors at the new readings over their sigmas, and the scale the
                           # sigmas take from it (>= 1: SigmaCalibration)
                           'joint_sigma_measured': round(self.loop.predictor.calibration.measured, 3),
                           'joint_sigma_scale': round(self.loop.predictor.calibration.scale, 3),
                           'joint_sigma_samples': self.loop.predictor.calibration.samples})
            if not self.driver.connected:
                level, message = ERROR, f'serial port {self.driver.state}: {self.driver.last_error}'
        publish_diagnostics(self, self.pub_diag, [diagnostic_status(
            f'fixego camera_node {self.side}', self.driver.port if self.driver else 'passive', level, message,
            values), self._vergence_status(), *([self._model_status()] if self.driver is not None else []),
            self.intrinsics.status(f'fixego camera_node {self.side}: intrinsics')])

    def destroy_node(self) -> None:
        if self.loop is not None:
            self.loop.stop()
        if self.driver is not None:
            self.driver.close()
        if self.video is not None:
            self.video.release()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(CameraNode, 'camera_node', args, images=True, executor=events_executor)


if __name__ == '__main__':
    sys.exit(main())
