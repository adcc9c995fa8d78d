"""sim_rig_node: the simulated rig, live. Two VISCA cameras on pseudo-terminals plus rendered images.

The node moves the rig along a trajectory in (scaled) wall-clock time and, at the frame rate, renders
each camera's view from the rig pose and the *true* pan/tilt of that camera's VISCA emulator, so two
real ``camera_node``s driving the emulators over serial close the fixation loop exactly as on a rig.
It publishes images and camera_info for both cameras, the true pose on ``ground_truth/pose`` (relative
names, namespace ``/fixego`` by default; ``base_link`` in ``odom``, ``odom`` = base_link at the first frame),
each head's true pan/tilt at the image stamp on ``ground_truth/<side>/joint_states`` (what the camera nodes'
``<side>/joint_states`` estimate from the VISCA readings), and ``/diagnostics``. The pty paths are logged
and written as JSON ``{"right": ..., "left": ...}`` to ``pty_file``; with ``pty_link_dir`` the node also
makes ``<pty_link_dir>/right`` and ``.../left`` symlinks to them, so camera nodes started at the same time
can be given those paths as ports (``sim.launch.py``: a fresh directory per launch, so a link left by a killed
run can never send VISCA bytes to an unrelated terminal; the camera nodes retry until it appears).

When the trajectory ends it publishes a final diagnostics status and, with ``exit_at_end``, stops
(``main`` returns); otherwise it keeps rendering the final pose (or loops, with ``loop``).

Parameters (:data:`fixego_ros.pipeline.params.SIM_RIG_NODE_PARAMS`) are checked at start (one line and exit
code 2 for a bad one) and are all read-only: they shape the world and trajectory built at start.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_srvs.srv import Trigger

from fixego_ros.geometry.rig import default_rig_path, load_rig
from fixego_ros.geometry.rotation import Pose, rig_pose_to_base_link
from fixego_ros.nodes.common import (
    OK,
    RELIABLE_QOS,
    SENSOR_QOS,
    TRUTH_QOS,
    WARN,
    array_to_image,
    declare_parameters,
    diagnostic_status,
    events_executor,
    in_namespace,
    publish_diagnostics,
    run_node,
)
from fixego_ros.pipeline.params import SIM_RIG_NODE_PARAMS
from fixego_ros.sim.bag_writer import camera_info_msg, pose_msg
from fixego_ros.sim.render import Renderer
from fixego_ros.sim.run import resize_rig, rig_with_hfov
from fixego_ros.sim.trajectories import make_trajectory
from fixego_ros.sim.world import make_room

SIDES = ('right', 'left')
PARAMS = SIM_RIG_NODE_PARAMS


class SimRigNode(Node):
    """Renders the rig's two cameras from the trajectory and the emulated heads' true angles."""

    ACK_TIMEOUT_S = 1.0     # per reliable publisher, at the end of the trajectory

    def __init__(self, **kwargs) -> None:
        super().__init__('sim_rig_node', **in_namespace(kwargs))
        g = declare_parameters(self, PARAMS)
        g.start(lambda changes, getter: None, ())      # every parameter is read-only
        p = {name: g(name) for name in PARAMS}
        self.p = p

        rig_notes: list[str] = []
        rig = load_rig(p['rig_file'] or default_rig_path(), warnings=rig_notes)
        for note in rig_notes:
            self.get_logger().warning(note)
        rig.require_intrinsics('sim_rig_node')      # it renders the images: camera_info cannot stand in
        if p['width'] > 0 or p['height'] > 0:
            w = p['width'] or round(rig.right.width * p['height'] / rig.right.height)
            h = p['height'] or round(rig.right.height * p['width'] / rig.right.width)
            rig = resize_rig(rig, w, h)
        if p['hfov_deg'] > 0:
            rig = rig_with_hfov(rig, p['hfov_deg'])
        self.rig = rig
        self.trajectory = make_trajectory(p['trajectory'], speed=p['speed'] or None, seed=p['seed'],
                                          duration=p['duration'] or None).then_rest(p['rest_end_s'])
        t_build = time.monotonic()
        world = make_room(p['seed'], p['texel'])
        self.renderer = Renderer(world, rig, p['encoding'], p['noise_sigma'], p['seed'])
        self.get_logger().info(f'world ready in {time.monotonic() - t_build:.1f} s '
                               f'({world.memory_bytes() / 1e6:.0f} MB of texture)')
        self._inv0: Pose | None = None  # odom = base_link at the first published frame

        from fixego_ros.visca.emulator import ViscaEmulator
        self.emulators = {}
        self.ptys: dict[str, str] = {}
        for side in SIDES:
            emu = ViscaEmulator(profile=p['profile'], address=1, baud=p['baud'],
                                start_pan_deg=p[f'start_pan_deg_{side}'], start_tilt_deg=p['start_tilt_deg'])
            self.ptys[side] = emu.start()
            self.emulators[side] = emu
        self._write_pty_file()
        self._links = self._make_pty_links()
        self.get_logger().info(f'VISCA emulators: right {self.ptys["right"]}, left {self.ptys["left"]} '
                               f'(written to {p["pty_file"] or "-"})')

        self.pub_image = {s: self.create_publisher(Image, f'{s}/image_raw', SENSOR_QOS) for s in SIDES}
        self.pub_info = {s: self.create_publisher(CameraInfo, f'{s}/camera_info', SENSOR_QOS)
                         for s in SIDES}
        self._info = {s: camera_info_msg(self.rig, s, 0.0) for s in SIDES}   # constant but for the stamp
        self.pub_gt = self.create_publisher(PoseStamped, 'ground_truth/pose', TRUTH_QOS)
        # each head's true angles at the image stamp: what the camera nodes' joint_states estimate
        self.pub_gt_joints = {s: self.create_publisher(JointState, f'ground_truth/{s}/joint_states', TRUTH_QOS)
                              for s in SIDES}
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE_QOS)

        self.frames = 0
        self.finished = False
        self._ended = False
        self._render_ms: list[float] = []
        self._t0 = time.monotonic()
        self._loop_offset = 0.0
        self.started = not p['wait_for_start']
        self.create_service(Trigger, '~/start', self._srv_start)
        self.timer = self.create_timer(1.0 / p['fps'], self._tick)
        self.diag_timer = self.create_timer(1.0, self._diagnostics)

    # ------------------------------------------------------------------------------------------
    def _write_pty_file(self) -> None:
        path = self.p['pty_file']
        if not path:
            return
        path = Path(path)
        tmp = path.with_name(f'.{path.name}.{os.getpid()}')
        tmp.write_text(json.dumps(self.ptys))
        os.replace(tmp, path)

    def _make_pty_links(self) -> list[Path]:
        """``<pty_link_dir>/<side>`` -> the emulator's own stable link to its pty (replaced atomically)."""
        if not self.p['pty_link_dir']:
            return []
        directory = Path(self.p['pty_link_dir'])
        directory.mkdir(parents=True, exist_ok=True)
        links = []
        for side, emu in self.emulators.items():
            link, tmp = directory / side, directory / f'.{side}.{os.getpid()}'
            tmp.unlink(missing_ok=True)
            os.symlink(emu.link_path or self.ptys[side], tmp)
            os.replace(tmp, link)
            links.append(link)
        self.get_logger().info(f'pty links: {", ".join(map(str, links))}')
        return links

    def sim_time(self, now: float) -> float:
        """Trajectory time at monotonic time ``now`` (0 until started)."""
        if not self.started:
            return 0.0
        return (now - self._t0) * self.p['time_scale'] - self._loop_offset

    def _srv_start(self, request, response):
        if self.started:
            response.success, response.message = False, 'already started'
            return response
        self._t0 = time.monotonic()
        self.started = True
        self.get_logger().info(f'trajectory {self.p["trajectory"]!r} started')
        response.success, response.message = True, 'started'
        return response

    def _tick(self) -> None:
        try:
            self._frame()
        except Exception:
            if self.context.ok():
                raise
            # Ctrl-C shut the context down while we were publishing: not an error

    def _frame(self) -> None:
        now = time.monotonic()
        stamp = self.get_clock().now().to_msg()
        t = self.sim_time(now)
        if t > self.trajectory.duration and not self._ended:
            if self.p['loop'] and self.trajectory.duration > 0:
                self._loop_offset += self.trajectory.duration
                t -= self.trajectory.duration
            else:
                self._end()
                if self.finished:
                    return
        pose = self.trajectory.pose_at(t)
        t_render = time.perf_counter()
        for side in SIDES:
            pan, tilt = self.emulators[side].pan_tilt_rad(now)
            img = self.renderer.render(side, pose, pan, tilt)
            self.pub_image[side].publish(array_to_image(img, stamp, f'{side}_optical_frame', self.p['encoding']))
            self._info[side].header.stamp = stamp
            self.pub_info[side].publish(self._info[side])
            js = JointState(name=[f'{side}_pan', f'{side}_tilt'], position=[float(pan), float(tilt)])
            js.header.stamp = stamp
            self.pub_gt_joints[side].publish(js)
        self._render_ms.append((time.perf_counter() - t_render) * 1e3 / 2)
        if self._inv0 is None:
            self._inv0 = pose.inverse()
        gt = pose_msg(rig_pose_to_base_link(self._inv0 @ pose, self.rig.mount), 0.0)
        gt.header.stamp = stamp
        self.pub_gt.publish(gt)
        self.frames += 1

    def _end(self) -> None:
        self._ended = True
        publish_diagnostics(self, self.pub_diag, [self._status(OK, 'trajectory finished')])
        self.get_logger().info(f'trajectory {self.p["trajectory"]!r} finished after {self.frames} frames')
        if self.p['exit_at_end']:
            self.timer.cancel()
            self._wait_for_truth_acked()
            self.finished = True

    def _wait_for_truth_acked(self) -> None:
        """Before the process exits, let every reliable subscriber acknowledge the last frame's ground truth: a
        writer destroyed with samples unacknowledged loses the ones still to be resent, and a pose would then have
        no truth to be scored against (a precaution: the losses the demo's recorder showed at stop 90 were its own,
        at the start of the run). Bounded per publisher."""
        reliable = (self.pub_gt, *self.pub_gt_joints.values(), self.pub_diag)
        late = [pub.topic_name for pub in reliable
                if not pub.wait_for_all_acked(Duration(seconds=self.ACK_TIMEOUT_S))]
        if late:
            self.get_logger().warning(f'exiting with the last messages on {", ".join(late)} not acknowledged '
                                      f'within {self.ACK_TIMEOUT_S:.1f} s each')

    def _status(self, level, message: str):
        ms = np.array(self._render_ms[-100:]) if self._render_ms else np.zeros(1)
        return diagnostic_status('fixego: sim_rig', 'sim_rig_node', level, message, {
            'trajectory': self.p['trajectory'], 'frames': self.frames,
            'sim_time_s': f'{min(self.sim_time(time.monotonic()), self.trajectory.duration):.2f}',
            'duration_s': f'{self.trajectory.duration:.2f}', 'render_ms_per_camera': f'{np.median(ms):.2f}',
            'pty_right': self.ptys.get('right', ''), 'pty_left': self.ptys.get('left', '')})

    def _diagnostics(self) -> None:
        if self.finished:
            return
        late = len(self._render_ms) > 10 and np.median(self._render_ms[-30:]) * 2 > 1e3 / self.p['fps']
        level, msg = (WARN, 'rendering slower than the frame rate') if late else (OK, 'running')
        publish_diagnostics(self, self.pub_diag, [self._status(level, 'finished' if self._ended else msg)])

    def destroy_node(self) -> None:
        self.close()
        super().destroy_node()

    def close(self) -> None:
        """Stop the emulators and remove the pty file if it is still ours."""
        for emu in self.emulators.values():
            emu.stop()
        for link in getattr(self, '_links', []):
            link.unlink(missing_ok=True)
        path = self.p.get('pty_file')
        if path and os.path.exists(path):
            try:
                if json.loads(Path(path).read_text()) == self.ptys:
                    os.remove(path)
            except (OSError, ValueError):
                pass


def main(args: list[str] | None = None) -> int:
    return run_node(SimRigNode, 'sim_rig_node', args, finished=lambda n: n.finished, images=True,
                    executor=events_executor)


if __name__ == '__main__':
    sys.exit(main())
