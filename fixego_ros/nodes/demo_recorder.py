"""The demo's own node: records what the pipeline publishes (and when), and starts the run.

It keeps the refined poses with their arrival latency (receipt time minus the image stamp they carry: the
simulated rig stamps images with the wall clock, so this is image -> pose through every process), the ground truth,
the rig's vergence measurements, the last raw path (subscribed without deserialising each one), and the fixation and
diagnostics traffic the console progress line shows. For the latency breakdown it also notes when each joint state,
fixation and flow observation arrives, minus its (image) stamp; the observations are not deserialised (the stamp is
read from the message's first bytes). Names are relative in the default namespace /fixego, like the pipeline's nodes.

From :meth:`Recorder.start_inputs` on (the demo calls it when it resets the estimator) it also writes the estimator's
inputs, the serialised observations and vergence measurements with the ground truth (pose and head angles), to a bag
that ``fixego replay`` runs the estimator alone on (``replay.run.ReplayInput.OBSERVATIONS``): a live run's estimate
can be reproduced offline, its failures replayed, without recording the images (and ``bench.demo_inputs`` replays it
with the true head angles too). The bag is created beforehand (:meth:`Recorder.open_inputs`): that takes ~0.4 s, 2 s
on a loaded machine, and done after the reset it kept the node from spinning while its readers' queues overflowed,
losing the run's first ground truth (a pose without its truth in the report, cameras without true angles in the bag).
"""

from __future__ import annotations

import math
import struct
import time
from collections import Counter, deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState, PointCloud2
from std_srvs.srv import Trigger

from fixego_ros.bags.recorder import BagRecorder, RecordSummary
from fixego_ros.geometry.rig import SIDES
from fixego_ros.geometry.rotation import Pose
from fixego_ros.nodes.bag_recorder import qos_dict
from fixego_ros.nodes.common import LATCHED_QOS, RELIABLE_QOS, TRUTH_QOS, in_namespace, msg_to_pose, stamp_to_sec


def cdr_stamp(data: bytes) -> float | None:
    """The header stamp (s) of a serialised message that starts with a std_msgs/Header (CDR: 4 bytes of
    encapsulation, then int32 sec, uint32 nanosec); None when too short."""
    if len(data) < 12:
        return None
    sec, nsec = struct.unpack('<iI' if data[1] == 1 else '>iI', data[4:12])
    return sec + 1e-9 * nsec


# the stages the recorder sees arrive (s after the image stamp); see fixego_ros.demo.report.latency_stages
PATHS = ('path', 'path_raw')
STAGES = ('joint_state_right', 'joint_state_left', 'fixation_right', 'fixation_left', 'observation')
# what the inputs bag holds: relative topic -> (type, the publishers' QoS)
INPUTS = {'flow/observation': ('sensor_msgs/msg/PointCloud2', RELIABLE_QOS),
          'vergence': ('geometry_msgs/msg/PoseWithCovarianceStamped', LATCHED_QOS),
          'ground_truth/pose': ('geometry_msgs/msg/PoseStamped', TRUTH_QOS),
          **{f'ground_truth/{side}/joint_states': ('sensor_msgs/msg/JointState', TRUTH_QOS) for side in SIDES}}


class Recorder(Node):
    # ground truth received before the reset, put in the inputs bag when it starts: the observations the estimator
    # takes after the reset include frames stamped before it (the pipeline's backlog, up to ~2.5 s on a loaded
    # machine), whose truth came before the reset
    TRUTH_BEFORE_S = 5.0

    def __init__(self, **kwargs) -> None:
        super().__init__('fixego_demo', **in_namespace(kwargs))
        self.poses: list[tuple[float, Pose]] = []
        self.latency_s: list[float] = []
        self.stage_s: dict[str, list[float]] = {k: [] for k in STAGES}
        self.truth: list[tuple[float, Pose]] = []
        # (stamp -> pan, tilt in rad) per side: the camera nodes' joint states and the simulator's true angles
        self.joints: dict[str, dict[float, tuple[float, float]]] = {s: {} for s in SIDES}
        self.true_joints: dict[str, dict[float, tuple[float, float]]] = {s: {} for s in SIDES}
        # (stamp -> pan, tilt 1-sigma in rad) the camera nodes stated in ``effort``, where they did
        self.joint_sigmas: dict[str, dict[float, tuple[float, float]]] = {s: {} for s in SIDES}
        self.fixations: Counter[str] = Counter()
        # (stamp -> whether the message had a valid fixation) per side: frames where neither camera fixates
        self.fixation_valid: dict[str, dict[float, bool]] = {s: {} for s in SIDES}
        # the rig's vergence measurements: (stamp, right fixation point in the rig frame, its 3x3 covariance); kept
        # by clear(), so the report counts those before the run too
        self.vergence: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.statuses: dict[str, dict[str, str]] = {}
        self.status_times: dict[str, float] = {}     # when each status last came (monotonic)
        self.smoother_catch_up_s: float | None = None   # how long the smoother took to finish after the last pose
        # the last path / path_raw received (bytes: deserialised only when asked for, then cached with its bytes)
        self._paths: dict[str, bytes | None] = dict.fromkeys(PATHS)
        self._parsed: dict[str, tuple[bytes, Path]] = {}
        self._inputs: BagRecorder | None = None     # the estimator's inputs (open_inputs) ...
        self._writing_inputs = False                # ... written from start_inputs() on
        self._truth_before: deque[tuple[str, int, bytes]] = deque()   # (topic, receive ns, message) till then
        self._input_names = {topic: self.resolve_topic_name(topic) for topic in INPUTS}   # relative -> absolute
        self.create_subscription(PoseStamped, 'pose', self._on_pose, RELIABLE_QOS)
        self.create_subscription(PoseStamped, 'ground_truth/pose', self._on_truth, TRUTH_QOS, raw=True)
        for name in PATHS:
            self.create_subscription(Path, name, lambda data, n=name: self._paths.__setitem__(n, data), RELIABLE_QOS,
                                     raw=True)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, RELIABLE_QOS)
        for side in SIDES:
            self.create_subscription(PointStamped, f'{side}/fixation',
                                     lambda m, s=side: self._on_fixation(s, m), RELIABLE_QOS)
            self.create_subscription(JointState, f'{side}/joint_states',
                                     lambda m, s=side: self._on_joints(s, m), RELIABLE_QOS)
            self.create_subscription(JointState, f'ground_truth/{side}/joint_states',
                                     lambda data, s=side: self._on_true_joints(s, data), TRUTH_QOS, raw=True)
        self.create_subscription(PointCloud2, 'flow/observation', self._on_observation, RELIABLE_QOS, raw=True)
        self.create_subscription(PoseWithCovarianceStamped, 'vergence', self._on_vergence, LATCHED_QOS, raw=True)
        self.reset_client = self.create_client(Trigger, 'estimator_node/reset')
        self.start_client = self.create_client(Trigger, 'sim_rig_node/start')

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _arrived(self, stage: str, stamp) -> None:
        self.stage_s[stage].append(self._now() - stamp_to_sec(stamp))

    @staticmethod
    def _keep_joints(into: dict[float, tuple[float, float]], msg: JointState) -> None:
        if len(msg.position) >= 2:
            into[stamp_to_sec(msg.header.stamp)] = (float(msg.position[0]), float(msg.position[1]))

    def _on_joints(self, side: str, msg: JointState) -> None:
        self._arrived(f'joint_state_{side}', msg.header.stamp)
        self._keep_joints(self.joints[side], msg)
        sigma = [float(v) for v in msg.effort[:2]]
        if len(sigma) == 2 and all(math.isfinite(v) and v >= 0.0 for v in sigma):
            self.joint_sigmas[side][stamp_to_sec(msg.header.stamp)] = (sigma[0], sigma[1])

    def _on_true_joints(self, side: str, data: bytes) -> None:
        self._keep_input(f'ground_truth/{side}/joint_states', data)
        self._keep_joints(self.true_joints[side], deserialize_message(data, JointState))

    def _on_fixation(self, side: str, msg: PointStamped) -> None:
        """Counts valid fixations only (the demo waits for both); the arrival time of every message, the "no valid
        fixation" ones (z < 0) too: each is what lets flow_node complete a frame."""
        if msg.point.z >= 0:
            self.fixations.update([side])
        self.fixation_valid[side][stamp_to_sec(msg.header.stamp)] = msg.point.z >= 0
        self._arrived(f'fixation_{side}', msg.header.stamp)

    def open_inputs(self, bag) -> None:
        """Create the new bag directory ``bag`` for the estimator's inputs, written from :meth:`start_inputs` on
        (:class:`~fixego_ros.bags.recorder.RecordError` when it cannot be created)."""
        recorder = BagRecorder(bag)
        for topic, (msgtype, qos) in INPUTS.items():
            recorder.add_topic(self._input_names[topic], msgtype, [qos_dict(qos)])
        self._inputs, self._writing_inputs = recorder, False

    def start_inputs(self) -> None:
        """Write every observation, vergence measurement, true pose and true head angle received from now on to the
        bag :meth:`open_inputs` created (nothing when none was), after the ground truth of the last
        :attr:`TRUTH_BEFORE_S` seconds."""
        if self._inputs is None:
            return
        for topic, ns, data in self._truth_before:
            self._inputs.put(self._input_names[topic], ns, data)
        self._truth_before.clear()
        self._writing_inputs = True

    def close_inputs(self) -> RecordSummary | None:
        """Finish the inputs bag (bounded); its summary, None when none was opened."""
        recorder, self._inputs, self._writing_inputs = self._inputs, None, False
        return None if recorder is None else recorder.close()

    def _keep_input(self, topic: str, data: bytes) -> None:
        """Into the inputs bag while it is written; before that, the ground truth into the last
        :attr:`TRUTH_BEFORE_S` seconds (also while the bag is being created: the reset's backlog can be older)."""
        now = self.get_clock().now().nanoseconds
        if self._writing_inputs and self._inputs is not None:
            self._inputs.put(self._input_names[topic], now, data)
        elif topic.startswith('ground_truth/'):
            self._truth_before.append((topic, now, data))
            while self._truth_before and now - self._truth_before[0][1] > self.TRUTH_BEFORE_S * 1e9:
                self._truth_before.popleft()

    def _on_observation(self, data: bytes) -> None:
        self._keep_input('flow/observation', data)
        t = cdr_stamp(data)
        if t is not None:
            self.stage_s['observation'].append(self._now() - t)

    def _on_vergence(self, data: bytes) -> None:
        self._keep_input('vergence', data)
        msg = deserialize_message(data, PoseWithCovarianceStamped)
        p = msg.pose.pose.position
        cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)[:3, :3].copy()
        self.vergence.append((stamp_to_sec(msg.header.stamp), np.array([p.x, p.y, p.z]), cov))

    def _on_pose(self, msg: PoseStamped) -> None:
        t = stamp_to_sec(msg.header.stamp)
        self.latency_s.append(self._now() - t)
        self.poses.append((t, msg_to_pose(msg.pose)))

    def _on_truth(self, data: bytes) -> None:
        self._keep_input('ground_truth/pose', data)
        msg = deserialize_message(data, PoseStamped)
        self.truth.append((stamp_to_sec(msg.header.stamp), msg_to_pose(msg.pose)))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for st in msg.status:
            self.statuses[st.name] = {'message': st.message, **{kv.key: kv.value for kv in st.values}}
            self.status_times[st.name] = time.monotonic()

    def _last_path(self, name: str) -> Path | None:
        data = self._paths[name]
        if data is None:
            return None
        if name not in self._parsed or self._parsed[name][0] is not data:
            self._parsed[name] = (data, deserialize_message(data, Path))
        return self._parsed[name][1]

    def path_stamp(self, name: str) -> float | None:
        """Stamp of the last ``name`` Path received (its newest pose); None before the first. The estimator
        publishes paths at most once per path_publish_period_s, and once more when the poses stop."""
        path = self._last_path(name)
        return None if path is None else stamp_to_sec(path.header.stamp)

    def path_poses(self, name: str) -> list[tuple[float, Pose]]:
        """The last ``name`` Path received: ``path`` (the smoother's refined trajectory) or ``path_raw``."""
        path = self._last_path(name)
        if path is None:
            return []
        return [(stamp_to_sec(p.header.stamp), msg_to_pose(p.pose)) for p in path.poses]

    def call(self, client, executor, timeout_s: float) -> tuple[bool, str]:
        """Call a Trigger service with bounded waits (for the server, then for the answer)."""
        if not client.wait_for_service(timeout_sec=timeout_s):
            return False, f'service {client.srv_name} not available after {timeout_s:.0f} s'
        future = client.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=timeout_s)
        if not future.done() or future.result() is None:
            return False, f'service {client.srv_name} did not answer within {timeout_s:.0f} s'
        res = future.result()
        return bool(res.success), str(res.message)

    def clear(self) -> None:
        """Forget everything recorded so far (the run starts now)."""
        self.poses.clear()
        self.latency_s.clear()
        for v in self.stage_s.values():
            v.clear()
        self.truth.clear()
        for d in (*self.joints.values(), *self.true_joints.values(), *self.joint_sigmas.values()):
            d.clear()
        self._paths = dict.fromkeys(PATHS)
        self._parsed.clear()
