"""flow_node: synchronised stereo frames in, one flow observation per frame out.

Topics are relative names in the node namespace (default ``/fixego``). Subscribes each camera's
``<side>/image_raw`` (sensor-data QoS), ``joint_states`` and ``fixation`` (from
``camera_node``: a pixel, or id -1 for "no valid fixation at this stamp"), matches them by stamp
(:class:`~fixego_ros.pipeline.sync.StereoSync`, bounded waits; an image whose fixation message never comes, as in
bags recorded before camera_node sent the id -1 message, waits ``max_wait_s``),
keeps persistent point tracks in a window around each fixation point (pyramidal Lucas-Kanade frame to
frame from positions predicted by the pan/tilt readings and the rig's angular velocity, epipolar RANSAC)
and turns every point into rig-frame rays with the pan/tilt of its frame
(:class:`~fixego_ros.pipeline.frontend.StereoFrontEnd`). Publishes ``flow/observation``
(sensor_msgs/PointCloud2 rows: cameras, flow pairs keyframe -> t, live tracks;
:mod:`fixego_ros.pipeline.observation`) and ``/diagnostics``. A frame with one camera only gives a
one-camera observation; dropped frames show up as a gap between the observation's ``t0`` and the
previous frame, which the estimator bridges. The frames are processed on a worker thread of the node's own
(:meth:`FlowNode._work`): the executor's callbacks only feed the synchroniser, so a slow frame never holds back
the joint states and fixations that complete the next ones; when it falls behind, a ready frame older than
``max_lag_s`` with a newer one ready is skipped (``frames_skipped``). A frame the front end fails on is logged
once, counted (``frame_errors``) and skipped; the node goes on.

Parameters (:data:`fixego_ros.pipeline.params.FLOW_NODE_PARAMS`) are checked at start and on ``ros2 param
set``; the tracking thresholds, keyframe policy, synchronisation bounds and diagnostics period change at
run time, the rest (preset, window sizes, LK pyramid, topics, rig) is read-only.
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time
from collections import deque
from collections.abc import Mapping

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from sensor_msgs.msg import Image, JointState, PointCloud2

from fixego_ros.geometry.rig import SIDES, default_rig_path, load_rig
from fixego_ros.nodes.common import (
    OK,
    RELIABLE_QOS,
    SENSOR_QOS,
    WARN,
    CameraInfoIntrinsics,
    ImageError,
    OnceLogger,
    declare_parameters,
    diagnostic_status,
    in_namespace,
    percentile_values,
    publish_diagnostics,
    queue_wait_s,
    run_node,
    set_timer_period,
    stamp_to_sec,
    table_to_cloud,
    transport_s,
)
from fixego_ros.pipeline.frontend import CameraSample, StereoFrontEnd
from fixego_ros.pipeline.messages import fixation_from_msg, gray_for_camera, joint_sigma, pan_tilt
from fixego_ros.pipeline.observation import observation_to_rows
from fixego_ros.pipeline.params import FLOW_NODE_PARAMS, Getter, flow_params, keyframe_policy, sync_params
from fixego_ros.pipeline.sync import StereoSync, SyncedFrame

PARAMS = FLOW_NODE_PARAMS
# applied at run time: the front end and the synchroniser read their params objects at every frame
LIVE_FLOW = ('min_eig', 'fb_max_px', 'ransac_px', 'register_period_s')
LIVE_KEYFRAMES = ('keyframe_max_frames', 'keyframe_min_parallax_px', 'keyframe_min_tracked_fraction',
                  'keyframe_max_rotation_deg')
LIVE_SYNC = ('slop_s', 'max_wait_s', 'joint_extrapolation_s')
# images lost on the way (a frame whose other image never came): warned about once this share of frames is lost
LOST_IMAGES_WARN_FRACTION, LOST_IMAGES_MIN_FRAMES = 0.05, 100
# frames skipped while behind (max_lag_s): WARN on /diagnostics once this share of the frames is skipped (same minimum)
SKIPPED_WARN_FRACTION = 0.05


class FlowNode(Node):
    WORK_PERIOD_S = 0.02        # the worker looks for expired synchroniser waits this often without new input
    JOIN_TIMEOUT_S = 2.0        # bound on waiting for the worker's frame in progress at shutdown

    def __init__(self, **kwargs) -> None:
        super().__init__('flow_node', **in_namespace(kwargs))
        self.params = g = declare_parameters(self, PARAMS)
        rig_notes: list[str] = []
        self.rig = load_rig(g('rig_file') or default_rig_path(), warnings=rig_notes)
        for note in rig_notes:
            self.get_logger().warning(note)
        # intrinsics the rig file leaves out come from camera_info; no image is used until both are known
        self.intrinsics = CameraInfoIntrinsics(self, self.rig, SIDES, self._on_rig)
        self.flow_params = flow_params(g)
        self.frontend = StereoFrontEnd(self.rig, self.flow_params, keyframe_policy(g))
        self.sync = StereoSync(sync_params(g))
        self.once = OnceLogger(self)
        self.pub_obs = self.create_publisher(PointCloud2, str(g('observation_topic')), RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE_QOS)
        for side in SIDES:
            ns = side
            self.create_subscription(Image, f'{ns}/image_raw', lambda m, info, s=side: self._on_image(s, m, info),
                                     SENSOR_QOS)     # with the message info: the image's transport and queue times
            self.create_subscription(JointState, f'{ns}/joint_states', lambda m, s=side: self._on_joints(s, m),
                                     RELIABLE_QOS)
            self.create_subscription(PointStamped, f'{ns}/fixation', lambda m, s=side: self._on_fixation(s, m),
                                     RELIABLE_QOS)
        self.diag_timer = self.create_timer(float(g('diagnostics_period_s')), self._publish_diagnostics)
        self.stats = {'images': 0, 'fixations': 0, 'bad_images': 0, 'observations': 0, 'keyframes': 0,
                      'points_right': 0, 'points_left': 0, 'tracks_right': 0, 'tracks_left': 0, 'frame_errors': 0,
                      'frames_skipped': 0}
        self.process_ms: deque[float] = deque(maxlen=300)
        # latency stages (ms from the image stamp): an image received here (DDS), a stereo frame complete (its
        # images, joint states and fixations in: the synchroniser's wait), as in the README's latency breakdown
        self.image_in_ms: deque[float] = deque(maxlen=300)
        self.image_dds_ms: deque[float] = deque(maxlen=300)      # published -> received (the middleware's stamps)
        self.image_queue_ms: deque[float] = deque(maxlen=300)    # received -> this callback
        self.ready_ms: deque[float] = deque(maxlen=300)
        self.joints_in_ms: deque[float] = deque(maxlen=300)     # a joint state received here (after its stamp)
        self.last_problem = ''
        self.max_lag_s = float(g('max_lag_s'))
        self.params.start(self._apply_params, LIVE_FLOW + LIVE_KEYFRAMES + LIVE_SYNC + ('diagnostics_period_s',
                                                                                        'max_lag_s'))
        # the frames are processed on a thread of their own: the executor's callbacks only feed the synchroniser
        self._lock = threading.Lock()           # the synchroniser: fed by the callbacks, emptied by the worker
        self._wake, self._stop = threading.Event(), threading.Event()
        self._worker = threading.Thread(target=self._work, name='flow-frames', daemon=True)
        self._worker.start()
        self.get_logger().info(f'flow: preset {self.flow_params.preset}, window {self.flow_params.window_px} px')

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    # -------------------------------------------------------------------------------------- input
    def _on_rig(self, rig) -> None:
        self.rig = self.frontend.rig = rig

    def _on_image(self, side: str, msg: Image, info: Mapping[str, int] | None = None) -> None:
        self.stats['images'] += 1
        transport = transport_s(info)
        if transport is not None:
            self.image_dds_ms.append(1e3 * transport)
        waited = queue_wait_s(info)
        if waited is not None:
            self.image_queue_ms.append(1e3 * waited)
        if not self.intrinsics.ready():
            self.stats['images_before_intrinsics'] = self.stats.get('images_before_intrinsics', 0) + 1
            self.once.warn('intrinsics', 'images ignored until both cameras have intrinsics (rig file or '
                                         'camera_info)')
            return
        try:
            gray = gray_for_camera(msg, self.rig.camera(side))
        except ImageError as e:
            self.stats['bad_images'] += 1
            self.last_problem = f'{side} image ignored: {e}'
            self.once.warn(f'image_{side}', self.last_problem)
            return
        self.once.clear(f'image_{side}', f'{side} images usable again')
        now, t = self._now(), stamp_to_sec(msg.header.stamp)
        self.image_in_ms.append(1e3 * (now - t))
        with self._lock:
            self.sync.add_image(side, t, (gray, msg.header.stamp), now)
        self._wake.set()

    def _on_joints(self, side: str, msg: JointState) -> None:
        try:
            pan, tilt = pan_tilt(msg, side)
        except ValueError as e:
            self.once.warn(f'joints_{side}', f'{e}: ignored')
            return
        t = stamp_to_sec(msg.header.stamp)
        self.joints_in_ms.append(1e3 * (self._now() - t))
        with self._lock:
            added = self.sync.add_joints(side, t, pan, tilt, joint_sigma(msg, side))
        if not added:
            self.once.warn(f'joints_bad_{side}', f'{side} joint state non-finite or out of order: ignored')
        self._wake.set()

    def _on_fixation(self, side: str, msg: PointStamped) -> None:
        """A fixation pixel, or the camera's "no valid fixation at this stamp" (id -1): either completes the
        camera's part of the frame, so the synchroniser does not wait for a fixation that will not come."""
        self.stats['fixations'] += 1
        try:
            pixel, fid = fixation_from_msg(msg)
        except ValueError as e:
            with self._lock:
                self.sync.stats.rejected += 1
            self.once.warn(f'fixation_bad_{side}', f'{side} fixation ignored: {e}')
            return
        with self._lock:
            added = self.sync.add_fixation(side, stamp_to_sec(msg.header.stamp), pixel, fid)
        if not added:
            self.once.warn(f'fixation_bad_{side}', f'{side} fixation non-finite or late: ignored')
        self._wake.set()

    # -------------------------------------------------------------------------------------- processing
    def _work(self) -> None:
        """The worker thread: process the frames the synchroniser has ready, woken by each input (and every
        ``WORK_PERIOD_S``, for the waits that expire). Why a thread: rclpy's executor takes one message per
        subscription per wake, so with the processing in the image callbacks (20-40 ms a frame on a loaded machine)
        the joint states and fixations queued up behind the images, arrived later than ``max_wait_s`` and cost whole
        frames ("no joints"): most demo runs of stop 82 lost 30-50 % of their frames that way, at p50 ~360 ms."""
        while not self._stop.is_set() and self.context.ok():
            self._wake.wait(self.WORK_PERIOD_S)
            self._wake.clear()
            self._drain()

    def destroy_node(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._worker is not threading.current_thread():
            self._worker.join(timeout=self.JOIN_TIMEOUT_S)
        super().destroy_node()

    def _drain(self) -> None:
        now = self._now()
        with self._lock:
            frames = self.sync.pop_ready(now)
        stale = [f for f in frames[:-1] if now - f.stamp > self.max_lag_s]
        if stale:
            # behind: a frame older than max_lag_s with a newer one ready is skipped. It would come out later
            # still, and the estimator leaves late observations out anyway; the front end tracks across the gap
            # as across a frame lost on the way
            self.stats['frames_skipped'] += len(stale)
            self.once.warn('behind', f'flow_node is behind its input by more than max_lag_s '
                                     f'({self.max_lag_s:g} s; the front end takes longer than a frame period on '
                                     f'this machine): the older waiting frames are skipped (frames_skipped on '
                                     f'/diagnostics)')
            frames = frames[len(stale):]
        for frame in frames:
            self.ready_ms.append(1e3 * (now - frame.stamp))
            try:
                self._process(frame)
            except Exception as e:     # a frame that breaks the front end must not stop the node
                self.stats['frame_errors'] += 1
                self.last_problem = f'frame not processed: {type(e).__name__}: {e}'
                self.once.error('frame_error', f'{self.last_problem} (further ones are counted on /diagnostics)')

    def _process(self, frame: SyncedFrame) -> None:
        """One synchronised frame through the front end; its observation published."""
        t = time.perf_counter()
        samples: dict[str, CameraSample | None] = {
            side: None if c is None else CameraSample(c.image[0], c.pan, c.tilt, c.fixation_px, c.fixation_id,
                                                      c.joint_sigma)
            for side, c in frame.cameras.items()}
        base = frame.cameras['right'] or frame.cameras['left']     # the frame's stamp is the base camera's
        stamp_msg = base.image[1]
        obs = self.frontend.process(frame.stamp, samples)
        rows = observation_to_rows(obs)
        if len(rows) == 0:
            return
        self.pub_obs.publish(table_to_cloud(rows, stamp_msg, 'rig'))
        self.process_ms.append((time.perf_counter() - t) * 1e3)
        self.once.clear('frame_error', 'frames processed again')
        self.stats['observations'] += 1
        self.stats['keyframes'] += int(bool(obs.keyframe))
        for side in SIDES:
            cam = obs.camera(side)
            self.stats[f'points_{side}'] = len(cam.flow_prev) if cam is not None else 0
            self.stats[f'tracks_{side}'] = len(cam.track_ids) if cam is not None else 0

    # -------------------------------------------------------------------------------------- parameters
    def _apply_params(self, changes: dict[str, object], g: Getter) -> None:
        """``ros2 param set``: build every new params object first (a combination the core refuses raises
        and changes nothing), then swap them in; they are read at the next frame."""
        new_flow = flow_params(g) if changes.keys() & set(LIVE_FLOW) else None
        new_keyframes = keyframe_policy(g) if changes.keys() & set(LIVE_KEYFRAMES) else None
        new_sync = sync_params(g) if changes.keys() & set(LIVE_SYNC) else None
        if new_flow is not None:
            self.flow_params = self.frontend.params = new_flow
        if new_keyframes is not None:
            self.frontend.keyframes = new_keyframes
        if new_sync is not None:    # keep the synchroniser's own fields (queue bounds) that are not parameters
            with self._lock:
                self.sync.params = dataclasses.replace(self.sync.params, slop_s=new_sync.slop_s,
                                                       max_wait_s=new_sync.max_wait_s,
                                                       joint_extrapolation_s=new_sync.joint_extrapolation_s)
        if 'diagnostics_period_s' in changes:
            set_timer_period(self.diag_timer, float(g('diagnostics_period_s')))
        if 'max_lag_s' in changes:
            self.max_lag_s = float(g('max_lag_s'))

    # -------------------------------------------------------------------------------------- diagnostics
    def _publish_diagnostics(self) -> None:
        s = self.sync.stats
        values: dict[str, object] = dict(self.stats)
        values.update({'frames': s.frames, 'stereo_frames': s.stereo_frames,
                       'single_camera_frames': s.single_camera_frames, 'late_images': s.late_images,
                       'overflow_images': s.overflow_images, 'no_joints': s.no_joints, 'no_fixation': s.no_fixation,
                       'fixation_skipped': s.fixation_skipped, 'fixation_timeouts': s.fixation_timeouts,
                       'partner_timeouts': s.partner_timeouts, 'partner_missing': s.partner_missing,
                       'rejected_inputs': s.rejected, 'preset': self.flow_params.preset,
                       'slop_s_used': f'{self.sync.slop_s:.4f}'})
        values.update(self.frontend.stats)     # each camera's last status, reason and point counts
        totals = self.frontend.totals           # which LK attempt the tracks came from, RANSAC runs
        values.update({f'{side}.{k}_total': totals[f'{side}.{k}'] for side in SIDES
                       for k in ('lk_predicted', 'lk_zero', 'lk_fixation', 'lk_stereo', 'lk_retry', 'ransac',
                                 'epipolar', 'unregistered')})
        for name, q in (('process_ms', self.process_ms), ('image_in_ms', self.image_in_ms),
                        ('image_dds_ms', self.image_dds_ms), ('image_queue_ms', self.image_queue_ms),
                        ('ready_ms', self.ready_ms), ('joints_in_ms', self.joints_in_ms)):
            values.update(percentile_values(name, q or (0.0,)))
        level, message = OK, 'tracking flow'
        if self.stats['observations'] == 0:
            level, message = WARN, 'no synchronised frame yet (images, joint states, fixations?)'
        elif any(self.once.active(f'image_{side}') for side in SIDES) or self.once.active('frame_error'):
            level, message = WARN, self.last_problem
        elif s.single_camera_frames > 0 and s.stereo_frames == 0:
            level, message = WARN, 'only one camera delivers frames'
        elif s.frames >= LOST_IMAGES_MIN_FRAMES and s.partner_missing > LOST_IMAGES_WARN_FRACTION * s.frames:
            level, message = WARN, (f'{s.partner_missing} of {s.frames} frames lost one camera\'s image on the way '
                                    f'(best-effort images dropped between publisher and flow_node; a Fast DDS '
                                    f'publisher needs a shared-memory segment of several images: README "Images '
                                    f'over DDS")')
            self.once.warn('images_lost', message)
        elif s.frames >= LOST_IMAGES_MIN_FRAMES and self.stats['frames_skipped'] > SKIPPED_WARN_FRACTION * s.frames:
            level, message = WARN, (f"{self.stats['frames_skipped']} of {s.frames} frames skipped: the front end "
                                    f"takes longer than a frame period here (process_ms), so those frames get no "
                                    f"pose; fewer processes on the cores, a faster machine or a lower frame rate "
                                    f"help")
        publish_diagnostics(self, self.pub_diag, [diagnostic_status('fixego flow_node', 'flow', level, message,
                                                                    values),
                                                  self.intrinsics.status('fixego flow_node: intrinsics')])


def main(args: list[str] | None = None) -> int:
    return run_node(FlowNode, 'flow_node', args)


if __name__ == '__main__':
    sys.exit(main())
