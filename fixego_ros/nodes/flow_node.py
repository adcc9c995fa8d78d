"""flow_node: synchronised stereo frames in, one flow observation per frame out.

Subscribes each camera's ``image_raw`` (sensor-data QoS), ``joint_states`` and ``fixation`` (from
``camera_node``), matches them by stamp (:class:`~fixego_ros.pipeline.sync.StereoSync`, bounded waits),
keeps persistent point tracks in a window around each fixation point (pyramidal Lucas-Kanade frame to
frame from positions predicted by the pan/tilt readings and the rig's angular velocity, epipolar RANSAC)
and turns every point into rig-frame rays with the pan/tilt of its frame
(:class:`~fixego_ros.pipeline.frontend.StereoFrontEnd`). Publishes ``/fixego/flow/observation``
(sensor_msgs/PointCloud2 rows: cameras, flow pairs keyframe -> t, live tracks;
:mod:`fixego_ros.pipeline.observation`) and ``/diagnostics``. A frame with one camera only gives a
one-camera observation; dropped frames show up as a gap between the observation's ``t0`` and the
previous frame, which the estimator bridges.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np
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
    ImageError,
    OnceLogger,
    declare_parameters,
    diagnostic_status,
    publish_diagnostics,
    spin_node,
    stamp_to_sec,
    table_to_cloud,
)
from fixego_ros.pipeline.frontend import CameraSample, StereoFrontEnd
from fixego_ros.pipeline.messages import gray_for_camera, pan_tilt
from fixego_ros.pipeline.observation import observation_to_rows
from fixego_ros.pipeline.params import FLOW_PARAMS, flow_params, keyframe_policy, sync_params
from fixego_ros.pipeline.sync import StereoSync

PARAMS: dict[str, tuple[object, str]] = {
    'rig_file': ('', 'rig calibration YAML (DESIGN.md §4); empty = the package config/rig.yaml'),
    **FLOW_PARAMS,
    'observation_topic': ('/fixego/flow/observation', 'where observations are published'),
    'diagnostics_period_s': (1.0, 'diagnostics publishing period'),
}


class FlowNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__('flow_node', **kwargs)
        g = declare_parameters(self, PARAMS)
        self.rig = load_rig(g('rig_file') or default_rig_path())
        self.flow_params = flow_params(g)
        self.frontend = StereoFrontEnd(self.rig, self.flow_params, keyframe_policy(g))
        self.sync = StereoSync(sync_params(g))
        self.once = OnceLogger(self)
        self.pub_obs = self.create_publisher(PointCloud2, str(g('observation_topic')), RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE_QOS)
        for side in SIDES:
            ns = f'/fixego/{side}'
            self.create_subscription(Image, f'{ns}/image_raw', lambda m, s=side: self._on_image(s, m), SENSOR_QOS)
            self.create_subscription(JointState, f'{ns}/joint_states', lambda m, s=side: self._on_joints(s, m),
                                     RELIABLE_QOS)
            self.create_subscription(PointStamped, f'{ns}/fixation', lambda m, s=side: self._on_fixation(s, m),
                                     RELIABLE_QOS)
        self.create_timer(0.02, self._drain)
        self.create_timer(float(g('diagnostics_period_s')), self._publish_diagnostics)
        self.stats = {'images': 0, 'bad_images': 0, 'observations': 0, 'keyframes': 0, 'points_right': 0,
                      'points_left': 0, 'tracks_right': 0, 'tracks_left': 0}
        self.process_ms: deque[float] = deque(maxlen=300)
        self.last_problem = ''
        self.get_logger().info(f'flow: preset {self.flow_params.preset}, window {self.flow_params.window_px} px')

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    # -------------------------------------------------------------------------------------- input
    def _on_image(self, side: str, msg: Image) -> None:
        self.stats['images'] += 1
        try:
            gray = gray_for_camera(msg, self.rig.camera(side))
        except ImageError as e:
            self.stats['bad_images'] += 1
            self.last_problem = f'{side} image ignored: {e}'
            self.once.warn(f'image_{side}', self.last_problem)
            return
        self.once.clear(f'image_{side}', f'{side} images usable again')
        self.sync.add_image(side, stamp_to_sec(msg.header.stamp), (gray, msg.header.stamp), self._now())
        self._drain()

    def _on_joints(self, side: str, msg: JointState) -> None:
        try:
            pan, tilt = pan_tilt(msg, side)
        except ValueError as e:
            self.once.warn(f'joints_{side}', f'{e}: ignored')
            return
        if not self.sync.add_joints(side, stamp_to_sec(msg.header.stamp), pan, tilt):
            self.once.warn(f'joints_bad_{side}', f'{side} joint state non-finite or out of order: ignored')
        self._drain()

    def _on_fixation(self, side: str, msg: PointStamped) -> None:
        p = msg.point
        fid = round(p.z) if np.isfinite(p.z) else -1
        if not self.sync.add_fixation(side, stamp_to_sec(msg.header.stamp), (p.x, p.y), fid):
            self.once.warn(f'fixation_bad_{side}', f'{side} fixation non-finite or late: ignored')
        self._drain()

    # -------------------------------------------------------------------------------------- processing
    def _drain(self) -> None:
        for frame in self.sync.pop_ready(self._now()):
            t = time.perf_counter()
            samples: dict[str, CameraSample | None] = {
                side: None if c is None else CameraSample(c.image[0], c.pan, c.tilt, c.fixation_px, c.fixation_id)
                for side, c in frame.cameras.items()}
            base = frame.cameras['right'] or frame.cameras['left']     # the frame's stamp is the base camera's
            stamp_msg = base.image[1]
            obs = self.frontend.process(frame.stamp, samples)
            rows = observation_to_rows(obs)
            if len(rows) == 0:
                continue
            self.pub_obs.publish(table_to_cloud(rows, stamp_msg, 'rig'))
            self.process_ms.append((time.perf_counter() - t) * 1e3)
            self.stats['observations'] += 1
            self.stats['keyframes'] += int(bool(obs.keyframe))
            for side in SIDES:
                cam = obs.camera(side)
                self.stats[f'points_{side}'] = len(cam.flow_prev) if cam is not None else 0
                self.stats[f'tracks_{side}'] = len(cam.track_ids) if cam is not None else 0

    # -------------------------------------------------------------------------------------- diagnostics
    def _publish_diagnostics(self) -> None:
        s = self.sync.stats
        values: dict[str, object] = dict(self.stats)
        values.update({'frames': s.frames, 'stereo_frames': s.stereo_frames,
                       'single_camera_frames': s.single_camera_frames, 'late_images': s.late_images,
                       'overflow_images': s.overflow_images, 'no_joints': s.no_joints, 'no_fixation': s.no_fixation,
                       'rejected_inputs': s.rejected, 'preset': self.flow_params.preset})
        values.update(self.frontend.stats)     # each camera's last status, reason and point counts
        totals = self.frontend.totals           # which LK attempt the tracks came from, RANSAC runs
        values.update({f'{side}.{k}_total': totals[f'{side}.{k}'] for side in SIDES
                       for k in ('lk_predicted', 'lk_zero', 'lk_stereo', 'lk_retry', 'ransac', 'epipolar')})
        ms = np.array(self.process_ms) if self.process_ms else np.zeros(1)
        values.update({'process_ms_p50': f'{np.median(ms):.2f}', 'process_ms_p95': f'{np.percentile(ms, 95):.2f}'})
        level, message = OK, 'tracking flow'
        if self.stats['observations'] == 0:
            level, message = WARN, 'no synchronised frame yet (images, joint states, fixations?)'
        elif any(self.once.active(f'image_{side}') for side in SIDES):
            level, message = WARN, self.last_problem
        elif s.single_camera_frames > 0 and s.stereo_frames == 0:
            level, message = WARN, 'only one camera delivers frames'
        publish_diagnostics(self, self.pub_diag, [diagnostic_status('fixego flow_node', 'flow', level, message,
                                                                    values)])


def main(args: list[str] | None = None) -> None:
    spin_node(FlowNode, args)


if __name__ == '__main__':
    main()
