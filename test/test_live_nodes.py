"""flow_node and estimator_node over real DDS (private domain) with synthetic publishers, and the
whole live pipeline as separate processes (``fixego demo``) on a short simulated run."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from conftest import executor_for, private_domain_id, spin_until  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile  # noqa: E402
from test_flow import sim_pair  # noqa: E402, F401  (fixture: two rendered frames with a known step)

from fixego_ros.estimation.coplanarity import RayPairs, sampson_residuals  # noqa: E402
from fixego_ros.geometry.rig import SIDES  # noqa: E402
from fixego_ros.geometry.rotation import rig_pose_to_base_link  # noqa: E402
from fixego_ros.pipeline.observation import ROW_DTYPE, observation_to_rows, rows_to_observation  # noqa: E402


# ---------------------------------------------------------------------------------------------- flow_node
def _flow_node_with_publishers(ros_context, sim_pair, tmp_path, *extra: Parameter):  # noqa: F811
    """A flow_node on the sim pair's rig (with ``extra`` parameters), a probe node that publishes each camera's
    image, joint state and fixation and collects the observations, and an executor spinning both (once every
    publisher is matched)."""
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import Image, JointState, PointCloud2

    from fixego_ros.nodes.common import RELIABLE_QOS, SENSOR_QOS
    from fixego_ros.nodes.flow_node import FlowNode

    rig = sim_pair[0]
    rig_file = tmp_path / 'rig.yaml'
    rig.save(rig_file)
    node = FlowNode(context=ros_context, parameter_overrides=[
        Parameter('rig_file', value=str(rig_file)), Parameter('keyframe_max_frames', value=1), *extra])
    probe = rclpy.create_node('probe', context=ros_context)
    ex = executor_for(ros_context, node, probe)
    got: list[PointCloud2] = []
    probe.create_subscription(PointCloud2, '/fixego/flow/observation', got.append, RELIABLE_QOS)
    pubs = {s: (probe.create_publisher(Image, f'/fixego/{s}/image_raw', SENSOR_QOS),
                probe.create_publisher(JointState, f'/fixego/{s}/joint_states', RELIABLE_QOS),
                probe.create_publisher(PointStamped, f'/fixego/{s}/fixation', RELIABLE_QOS)) for s in SIDES}
    assert spin_until(ex, lambda: all(p[0].get_subscription_count() and p[1].get_subscription_count()
                                      and p[2].get_subscription_count() for p in pubs.values()), 10.0)
    return node, ex, pubs, got


def _joint_state(side: str, t: float, pan: float, tilt: float):
    from sensor_msgs.msg import JointState

    from fixego_ros.nodes.common import sec_to_stamp
    msg = JointState(name=[f'{side}_pan', f'{side}_tilt'], position=[pan, tilt])
    msg.header.stamp = sec_to_stamp(t)
    return msg


def _publish_frame(pubs, frame, t: float) -> None:
    """One camera frame per side: its image, its joint state and its fixation, all stamped ``t``."""
    from geometry_msgs.msg import PointStamped

    from fixego_ros.nodes.common import array_to_image, sec_to_stamp
    stamp = sec_to_stamp(t)
    for side in SIDES:
        s = frame[side]
        img, js, fx = pubs[side]
        fix = PointStamped()
        fix.header.stamp = stamp
        fix.point.x, fix.point.y, fix.point.z = *s.fixation_px, float(s.fixation_id)
        img.publish(array_to_image(s.gray, stamp, f'{side}_optical_frame'))
        js.publish(_joint_state(side, t, s.pan, s.tilt))
        fx.publish(fix)


class _HeldFrontEnd:
    """Holds ``node``'s front end on each frame until :attr:`release` is set (bounded: ``timeout_s``);
    :attr:`started` once a frame reached it, :attr:`holding` while one waits."""

    def __init__(self, node, timeout_s: float) -> None:
        self.started, self.holding, self.release = threading.Event(), threading.Event(), threading.Event()
        process = node.frontend.process

        def held(*args, **kwargs):
            self.started.set()
            self.holding.set()
            self.release.wait(timeout_s)
            self.holding.clear()
            return process(*args, **kwargs)

        node.frontend.process = held


def _flow_status(node):
    """flow_node's own /diagnostics status, as it would publish it now."""
    sent: list = []
    publish, node.pub_diag.publish = node.pub_diag.publish, sent.append
    try:
        node._publish_diagnostics()
    finally:
        node.pub_diag.publish = publish
    return next(st for st in sent[0].status if st.name == 'fixego flow_node')


def test_flow_node_rays_fit_the_true_motion(ros_context, sim_pair, tmp_path):  # noqa: F811
    from fixego_ros.nodes.common import array_to_image, cloud_to_table, sec_to_stamp, stamp_to_sec

    rig, step, _, frames, _, _ = sim_pair
    node, ex, pubs, got = _flow_node_with_publishers(ros_context, sim_pair, tmp_path)
    stamps = [100.0, 100.0 + 1 / 30]
    try:
        # a wrong-size image first: ignored with a warning, nothing published, node alive
        pubs['right'][0].publish(array_to_image(np.zeros((10, 12), np.uint8), sec_to_stamp(99.0),
                                                'right_optical_frame'))
        for t, frame in zip(stamps, frames, strict=True):
            _publish_frame(pubs, frame, t)
            n_before = len(got)
            spin_until(ex, lambda n=n_before: len(got) > n, 5.0)
        assert spin_until(ex, lambda: len(got) >= 2, 5.0), f'{len(got)} observations'
    finally:
        ex.shutdown()
    assert node.stats['bad_images'] == 1
    obs = rows_to_observation(stamp_to_sec(got[1].header.stamp), cloud_to_table(got[1], ROW_DTYPE))
    assert obs.prev_stamp == pytest.approx(stamps[0]) and obs.stamp == pytest.approx(stamps[1])
    for side in SIDES:
        cam = obs.camera(side)
        assert cam.fixation_id == 7 and len(cam.flow_prev) >= 30
        pairs = RayPairs.build([(cam.flow_prev, cam.flow_curr, rig.center(side), 1.0)])
        res_px = np.abs(sampson_residuals(step.R, step.t, pairs)) * rig.camera(side).fx
        assert np.median(res_px) < 0.3, side
        wrong = np.abs(sampson_residuals(step.R, -step.t[[2, 0, 1]], pairs)) * rig.camera(side).fx
        assert np.median(wrong) > 5 * np.median(res_px)


def test_flow_node_takes_joint_states_while_a_frame_is_processed(ros_context, sim_pair, tmp_path):  # noqa: F811
    """The frames are processed off the executor: while the front end works on one (here held until released),
    the node still takes every joint state as it comes. With the processing in the image callbacks, rclpy's
    executor took one message per subscription per wake, the joint states queued behind the images, came later
    than the synchroniser's wait and whole frames were lost ("no joints")."""
    frames = sim_pair[3]
    node, ex, pubs, got = _flow_node_with_publishers(ros_context, sim_pair, tmp_path)
    hold = _HeldFrontEnd(node, 5.0)
    try:
        _publish_frame(pubs, frames[0], 100.0)
        assert spin_until(ex, hold.started.is_set, 10.0), 'the frame never reached the front end'
        later = [100.0 + k / 30 for k in range(1, 11)]
        for t in later:
            for side in SIDES:
                pubs[side][1].publish(_joint_state(side, t, frames[0][side].pan, frames[0][side].tilt))
        taken = spin_until(ex, lambda: len(node.joints_in_ms) >= 2 + 2 * len(later), 5.0)
        assert taken and hold.holding.is_set(), f'{len(node.joints_in_ms)} joint states taken while the frame was held'
        hold.release.set()
        assert spin_until(ex, lambda: len(got) >= 1, 10.0)
    finally:
        hold.release.set()
        ex.shutdown()
        node.destroy_node()
    assert node.stats['frame_errors'] == 0 and not node._worker.is_alive()


def test_flow_node_survives_a_frame_the_front_end_fails_on(ros_context, sim_pair, tmp_path):  # noqa: F811
    """A frame the front end raises on is counted and reported (WARN on /diagnostics), not fatal: the worker goes
    on with the next frame, and the warning clears."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from fixego_ros.nodes.common import stamp_to_sec

    frames = sim_pair[3]
    node, ex, pubs, got = _flow_node_with_publishers(ros_context, sim_pair, tmp_path)
    process, calls = node.frontend.process, []

    def broken_second(*args, **kwargs):
        calls.append(args[0])
        if len(calls) == 2:
            raise RuntimeError('a broken frame')
        return process(*args, **kwargs)

    node.frontend.process = broken_second
    stamps = [100.0 + k / 30 for k in range(3)]
    try:
        _publish_frame(pubs, frames[0], stamps[0])
        assert spin_until(ex, lambda: len(got) >= 1, 10.0)
        _publish_frame(pubs, frames[1], stamps[1])
        assert spin_until(ex, lambda: node.stats['frame_errors'] == 1, 10.0)
        during = _flow_status(node)
        _publish_frame(pubs, frames[1], stamps[2])
        assert spin_until(ex, lambda: len(got) >= 2, 10.0)
        after = _flow_status(node)
    finally:
        ex.shutdown()
        node.destroy_node()
    assert node.stats['frame_errors'] == 1 and not node._worker.is_alive()
    assert [stamp_to_sec(m.header.stamp) for m in got] == pytest.approx([stamps[0], stamps[2]])
    assert during.level == DiagnosticStatus.WARN and 'RuntimeError: a broken frame' in during.message
    assert after.level == DiagnosticStatus.OK


@pytest.mark.parametrize('max_lag_s', [0.1, 30.0])
def test_flow_node_behind_skips_frames_older_than_max_lag(ros_context, sim_pair, tmp_path, max_lag_s):  # noqa: F811
    """Frames that complete while the front end works on an earlier one, each about 1 s old: with ``max_lag_s``
    0.1 the newest is processed and the older ones are skipped and counted (they would only come out later still);
    with 30 s every one is processed in order."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from fixego_ros.nodes.common import stamp_to_sec

    frames = sim_pair[3]
    node, ex, pubs, got = _flow_node_with_publishers(ros_context, sim_pair, tmp_path,
                                                     Parameter('max_lag_s', value=max_lag_s))
    hold = _HeldFrontEnd(node, 10.0)
    t0 = node.get_clock().now().nanoseconds * 1e-9 - 1.0
    stamps = [t0 + k / 30 for k in range(1, 4)]
    try:
        _publish_frame(pubs, frames[0], t0)
        assert spin_until(ex, hold.started.is_set, 10.0)
        for t in stamps:
            _publish_frame(pubs, frames[1], t)
        n = 2 * (1 + len(stamps))
        assert spin_until(ex, lambda: min(node.stats['images'], node.stats['fixations'],
                                          len(node.joints_in_ms)) >= n, 5.0)
        hold.release.set()
        processed = [t0, stamps[-1]] if max_lag_s < 1.0 else [t0, *stamps]
        assert spin_until(ex, lambda: len(got) >= len(processed), 10.0)
        spin_until(ex, lambda: len(got) > len(processed), 0.5)       # nothing more comes
    finally:
        hold.release.set()
        ex.shutdown()
        node.destroy_node()
    assert [stamp_to_sec(m.header.stamp) for m in got] == pytest.approx(processed, abs=1e-6)
    assert node.stats['frames_skipped'] == len(stamps) + 1 - len(processed)
    # a run that skips more than 5 % of its frames says so on /diagnostics
    node.sync.stats.frames = 100
    flow = _flow_status(node)
    assert flow.level == DiagnosticStatus.OK, flow.message      # 2 or 0 of 100 skipped
    node.stats['frames_skipped'] = 6
    flow = _flow_status(node)
    assert flow.level == DiagnosticStatus.WARN and '6 of 100 frames skipped' in flow.message


# ---------------------------------------------------------------------------------------------- estimator_node
@pytest.fixture(scope='module')
def clean_sequence():
    from fixego_ros.experiments.point_scene import PRESETS, PointScene, random_motion_sequence
    cfg = PRESETS['dense']
    rng = np.random.default_rng(11)
    scene = PointScene(cfg, rng)
    poses, _, clean = scene.frames(random_motion_sequence(cfg, 8, rng))
    return scene.rig, poses, clean


def _cloud(obs, t: float):
    from fixego_ros.nodes.common import sec_to_stamp, table_to_cloud
    obs.prev_stamp = None
    return table_to_cloud(observation_to_rows(obs), sec_to_stamp(t), 'rig')


def _synthetic_estimator_node(ros_context, rig, tmp_path, *extra: Parameter):
    """estimator_node on ``rig`` with the bounds opened for synthetic data (long steps, old stamps), plus ``extra``."""
    from fixego_ros.nodes.estimator_node import EstimatorNode

    rig_file = tmp_path / 'rig.yaml'
    rig.save(rig_file)
    return EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter('rig_file', value=str(rig_file)), Parameter('max_step_translation', value=2.0),
        Parameter('max_speed', value=100.0), Parameter('max_lag_s', value=1e12),
        Parameter('max_keyframe_lag_s', value=1e12), *extra])


def test_estimator_node_publishes_trajectory_resets_and_survives_bad_input(ros_context, clean_sequence, tmp_path):
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry, Path
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Empty
    from std_srvs.srv import Trigger

    from fixego_ros.nodes.common import RELIABLE_QOS, msg_to_pose
    rig, poses, clean = clean_sequence
    # noise-free rays: the lever arm gives the lengths here, to the papers' method (the smoother keeps its scale
    # unobserved without an aid; test_bag_pipeline runs it through the nodes)
    node = _synthetic_estimator_node(ros_context, rig, tmp_path, Parameter('constant_speed', value=False),
                                     Parameter('refinement', value='local'))
    probe = rclpy.create_node('probe', context=ros_context)
    ex = executor_for(ros_context, node, probe)
    pose_msgs: list[PoseStamped] = []
    odoms: list[Odometry] = []
    paths: dict[str, list[Path]] = {'path': [], 'path_raw': []}
    probe.create_subscription(PoseStamped, '/fixego/pose', pose_msgs.append, RELIABLE_QOS)
    probe.create_subscription(Odometry, '/fixego/odom', odoms.append, RELIABLE_QOS)
    requests: list[Empty] = []
    probe.create_subscription(Empty, '/fixego/vergence_request', requests.append, RELIABLE_QOS)
    for k in paths:
        probe.create_subscription(Path, f'/fixego/{k}', paths[k].append, RELIABLE_QOS)
    pub = probe.create_publisher(PointCloud2, '/fixego/flow/observation', RELIABLE_QOS)
    reset = probe.create_client(Trigger, '/fixego/estimator_node/reset')
    assert spin_until(ex, lambda: pub.get_subscription_count() > 0, 10.0)
    try:
        n = len(clean)
        for k, obs in enumerate(clean):
            pub.publish(_cloud(obs, 50.0 + k))
            if k == 3:   # malformed: wrong layout, then NaN rays
                bad = _cloud(clean[4], 50.0 + k + 0.5)
                bad.fields = [PointField(name='x', offset=0, datatype=PointField.FLOAT32, count=1)]
                pub.publish(bad)
                rows = observation_to_rows(clean[4])
                rows['x1'][2] = math.nan
                from fixego_ros.nodes.common import sec_to_stamp, table_to_cloud
                pub.publish(table_to_cloud(rows, sec_to_stamp(50.0 + k + 0.6), 'rig'))
        assert spin_until(ex, lambda: len(pose_msgs) >= n and len(paths['path_raw']) >= n, 15.0), len(pose_msgs)
        assert node.stats['malformed'] == 2
        # no scale aid: the unmeasured scale asks the rig for vergence, once per 5 s of stamps (50 s and 55 s)
        assert spin_until(ex, lambda: len(requests) >= 2, 5.0) and node.scale_requests.count == 2
        # poses: base_link in odom, close to the truth (noise-free rays; scale through the lever arm)
        path_len = sum(np.linalg.norm(poses[i + 1].t - poses[i].t) for i in range(n - 1))
        for msg, truth in zip(pose_msgs, poses, strict=True):
            est = msg_to_pose(msg.pose)
            assert msg.header.frame_id == 'odom'
            assert np.linalg.norm(est.t - rig_pose_to_base_link(truth).t) < 0.1 * path_len
        assert len(paths['path'][-1].poses) == n and len(paths['path_raw'][-1].poses) == n
        od = odoms[-1]
        cov = np.array(od.pose.covariance).reshape(6, 6)
        assert od.child_frame_id == 'base_link' and np.all(np.isfinite(cov)) and np.allclose(cov, cov.T)
        assert np.all(np.diag(cov) >= 0) and np.all(np.diag(cov)[:3] > 0)
        for m in pose_msgs:
            p = m.pose.position
            assert all(math.isfinite(v) for v in (p.x, p.y, p.z))
        # reset: the trajectory restarts at the next frame (identity), the path starts over
        assert reset.wait_for_service(timeout_sec=5.0)
        fut = reset.call_async(Trigger.Request())
        assert spin_until(ex, fut.done, 5.0) and fut.result().success
        pose_msgs.clear()
        pub.publish(_cloud(clean[0], 200.0))
        pub.publish(_cloud(clean[1], 201.0))
        assert spin_until(ex, lambda: len(pose_msgs) >= 2 and len(paths['path'][-1].poses) == 2, 10.0)
        assert np.allclose(msg_to_pose(pose_msgs[0].pose).t, 0.0)
        np.testing.assert_allclose(msg_to_pose(pose_msgs[1].pose).t, rig_pose_to_base_link(poses[1]).t,
                                   atol=0.1 * path_len)
    finally:
        ex.shutdown()


def test_estimator_node_counts_a_vergence_measurement_from_its_arrival(ros_context, clean_sequence, tmp_path):
    """A measurement the node has received stops the "scale unmeasured" requests at once, before the back end has
    used it (the live smoother takes it seconds later), and a reset forgets it (stop 56)."""
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from fixego_ros.nodes.common import sec_to_stamp
    rig, _, _ = clean_sequence
    node = _synthetic_estimator_node(ros_context, rig, tmp_path, Parameter('refinement', value='local'))
    try:
        assert node._scale_measurement() is None
        msg = PoseWithCovarianceStamped()
        msg.header.stamp, msg.header.frame_id = sec_to_stamp(50.0), 'rig'
        msg.pose.pose.position.z = 3.0
        cov = np.zeros((6, 6))
        cov[:3, :3] = np.diag([1e-4, 1e-4, 0.03 ** 2])
        msg.pose.covariance = cov.ravel().tolist()
        node._on_vergence(msg)
        assert node.estimator.scale_measurement is None          # the local BA uses it with the frames to come
        stamp, rel = node._scale_measurement()
        assert stamp == 50.0 and rel == pytest.approx(0.01)
        assert not node.scale_requests.due(51.0, node._scale_measurement(), False)
        node._reset_trajectory()
        assert node._scale_measurement() is None
    finally:
        node.destroy_node()


def test_estimator_node_rejects_future_stamps_counts_disorder_and_resets_on_a_clock_jump(ros_context,
                                                                                        clean_sequence, tmp_path):
    """An observation an hour ahead is rejected (it used to be accepted, and every later one then dropped as out
    of order); a stray old one is dropped and counted with a WARN; a run of older ones (the clock jumped back, a
    bag restarted) resets the trajectory, which restarts at the observation that completed the run."""
    import time

    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import PointCloud2

    from fixego_ros.nodes.common import RELIABLE_QOS, msg_to_pose, stamp_to_sec
    rig, _, clean = clean_sequence
    node = _synthetic_estimator_node(ros_context, rig, tmp_path, Parameter('backward_reset_count', value=3),
                                     Parameter('backward_reset_s', value=60.0),
                                     Parameter('diagnostics_period_s', value=0.05))
    probe = rclpy.create_node('probe', context=ros_context)
    ex = executor_for(ros_context, node, probe)
    poses: list[PoseStamped] = []
    diags: list[DiagnosticStatus] = []
    probe.create_subscription(PoseStamped, '/fixego/pose', poses.append, RELIABLE_QOS)
    probe.create_subscription(DiagnosticArray, '/diagnostics',
                              lambda m: diags.extend(s for s in m.status if s.name == 'fixego estimator_node'),
                              RELIABLE_QOS)
    pub = probe.create_publisher(PointCloud2, '/fixego/flow/observation', RELIABLE_QOS)
    assert spin_until(ex, lambda: pub.get_subscription_count() > 0, 10.0)
    seen = 0

    def send(k: int, t: float) -> None:
        nonlocal seen
        pub.publish(_cloud(clean[k], t))
        seen += 1
        assert spin_until(ex, lambda: node.stats['observations'] >= seen, 5.0)

    def warned(key: str) -> bool:
        return any(d.level == DiagnosticStatus.WARN and any(kv.key == key for kv in d.values) for d in diags)

    try:
        send(0, time.time() + 3600.0)                   # an hour ahead of the node clock
        assert node.stats['future_rejected'] == 1 and node.last is None
        for k in range(4):
            send(k, 100.0 + k)
        assert spin_until(ex, lambda: len(poses) >= 4, 5.0), len(poses)
        assert [stamp_to_sec(p.header.stamp) for p in poses] == [100.0, 101.0, 102.0, 103.0]
        send(4, 50.0)                                   # one stray old observation: dropped, counted, no reset
        assert node.stats['out_of_order'] == 1 and node.stats['clock_jump_resets'] == 0
        send(4, 104.0)
        assert spin_until(ex, lambda: len(poses) >= 5, 5.0)
        assert spin_until(ex, lambda: warned('recent_future_rejected') and warned('recent_out_of_order'), 5.0)
        # the clock jumps back: the third older observation in a row resets the trajectory and starts it anew
        for k, t in ((0, 10.0), (1, 11.0), (2, 12.0)):
            send(k, t)
        assert node.stats['clock_jump_resets'] == 1 and node.stats['out_of_order'] == 4
        send(3, 13.0)
        assert spin_until(ex, lambda: len(poses) >= 7, 5.0), len(poses)
        assert [stamp_to_sec(p.header.stamp) for p in poses[5:]] == [12.0, 13.0]
        assert np.allclose(msg_to_pose(poses[5].pose).t, 0.0) and len(node.path) == 2
        assert spin_until(ex, lambda: warned('recent_clock_jump_resets'), 5.0)
        # the stamp WARN clears once the problem stops (reports count since the previous one)
        assert spin_until(ex, lambda: not any(kv.key.startswith('recent_') for kv in diags[-1].values), 5.0)
        for p in poses:
            assert all(math.isfinite(v) for v in (p.pose.position.x, p.pose.position.y, p.pose.position.z))
    finally:
        ex.shutdown()
        probe.destroy_node()
        node.destroy_node()     # its smoother process and answer thread


def test_message_info_gives_the_transport_and_the_queue_wait():
    """From the middleware's source and receive stamps (system clock, ns): the transport alone and the wait in this
    process since the arrival; None where the middleware leaves a stamp out (0 or missing)."""
    import time

    from fixego_ros.nodes.common import queue_wait_s, transport_s
    info = {'source_timestamp': 5_000_000_000, 'received_timestamp': 5_002_500_000}
    assert transport_s(info) == pytest.approx(2.5e-3)
    assert transport_s({'source_timestamp': 0, 'received_timestamp': 5}) is None and transport_s(None) is None
    before = time.time_ns()
    waited = queue_wait_s({'received_timestamp': before - 50_000_000})
    assert 0.05 <= waited <= 0.05 + (time.time_ns() - before) * 1e-9
    assert queue_wait_s({'received_timestamp': 0}) is None and queue_wait_s({}) is None


def test_estimator_node_skips_only_what_waited_in_its_own_queue(ros_context, clean_sequence, tmp_path):
    """A non-keyframe that waited in the node's queue longer than max_lag_s is skipped (the node is behind its
    input); one that arrived late from upstream but found the node idle is posed (a pose costs ~1 ms: skipping it
    only left a frame without a pose). Without the middleware's receive time the clock decides, as before."""
    import copy
    import time

    rig, _, clean = clean_sequence
    node = _synthetic_estimator_node(ros_context, rig, tmp_path, Parameter('max_lag_s', value=0.1))
    try:
        def feed(k: int, waited_s: float | None) -> None:
            obs = copy.copy(clean[1 + k % (len(clean) - 1)])     # the fixture's frames stay as they are
            obs.keyframe = k == 0
            info = None if waited_s is None else {'received_timestamp': time.time_ns() - int(waited_s * 1e9)}
            node._on_observation(_cloud(obs, 100.0 + 0.2 * k), info)     # stamped ~56 years behind the clock

        feed(0, 0.0)
        assert node.stats['published'] == 1                  # a keyframe: always
        feed(1, 0.001)
        feed(2, 0.02)
        assert node.stats['published'] == 3 and node.stats['skipped_behind'] == 0     # late, but the node idle
        feed(3, 0.3)
        assert node.stats['published'] == 3 and node.stats['skipped_behind'] == 1     # behind its own input
        feed(4, None)
        assert node.stats['skipped_behind'] == 2              # no receive time: behind the clock
        assert len(node.queue_ms) == 4 and max(node.queue_ms) >= 300.0
    finally:
        node.destroy_node()


class _PipeStandIn:
    """What :class:`AnswerWaiter` asks of the live smoother: an answer waiting (``pending``) and whether it lives."""

    def __init__(self) -> None:
        self.pending, self.alive, self.polls = 0, True, 0

    def wait_for_answer(self, timeout_s: float) -> bool:
        self.polls += 1
        if self.pending:
            return True
        time.sleep(min(timeout_s, 0.01))
        return False


def test_the_smoothers_answers_are_taken_between_frames_by_the_executor(ros_context):
    """The waiter wakes the executor once per answer (the guard condition's callback takes it, on the executor's
    thread), does not spin while an answer waits to be taken, and ends on stop() or when the smoother is gone."""
    from fixego_ros.nodes.estimator_node import AnswerWaiter

    node = rclpy.create_node('waiter_probe', context=ros_context)
    ex = executor_for(ros_context, node)
    pipe, taken = _PipeStandIn(), []

    def take() -> None:
        taken.append(threading.get_ident())
        pipe.pending = 0

    waiter = AnswerWaiter(node, pipe, take)
    try:
        assert not spin_until(ex, lambda: taken, 0.3)            # nothing sent: nothing taken
        pipe.pending = 1
        polls = pipe.polls
        time.sleep(0.5)                                           # not spinning: the answer waits, the thread too
        assert pipe.polls - polls <= 1 + 0.5 / AnswerWaiter.WAIT_S + 1
        assert spin_until(ex, lambda: taken, 5.0)
        assert taken == [threading.get_ident()]                  # on the executor's thread, once
        pipe.pending = 1
        assert spin_until(ex, lambda: len(taken) == 2, 5.0)
    finally:
        waiter.stop()
    assert not waiter._thread.is_alive()
    pipe.alive = False
    gone = AnswerWaiter(node, pipe, take)
    gone._thread.join(2 * AnswerWaiter.WAIT_S)
    assert not gone._thread.is_alive()                            # a dead smoother ends the thread by itself
    ex.shutdown()
    node.destroy_node()


def test_estimator_node_publishes_paths_at_the_period_and_bounded(ros_context, clean_sequence, tmp_path):
    """A long run: pose every frame, but path and path_raw at most once per path_publish_period_s of observation
    time, never longer than path_max_length, and once more when the poses stop, holding the newest poses."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path

    from fixego_ros.nodes.common import stamp_to_sec
    rig, _, clean = clean_sequence
    period, dt, n, cap = 2.0, 0.2, 120, 25
    node = _synthetic_estimator_node(ros_context, rig, tmp_path, Parameter('path_max_length', value=cap),
                                     Parameter('path_publish_period_s', value=period))
    probe = rclpy.create_node('probe', context=ros_context)
    ex = executor_for(ros_context, node, probe)
    paths: dict[str, list[Path]] = {'path': [], 'path_raw': []}
    poses: list[PoseStamped] = []
    for k in paths:
        probe.create_subscription(Path, f'/fixego/{k}', paths[k].append, QoSProfile(depth=200))
    probe.create_subscription(PoseStamped, '/fixego/pose', poses.append, QoSProfile(depth=200))
    assert spin_until(ex, lambda: node.pub_path.get_subscription_count() and node.pub_path_raw.get_subscription_count()
                      and node.pub_pose.get_subscription_count(), 10.0)
    stamps = [100.0 + dt * k for k in range(n)]
    try:
        # fed straight into the callback without spinning: no timer can run during the feed, so every path
        # message until the end is one of the period's (the steady-clock flush needs a pause of a period)
        for k, t in enumerate(stamps):
            node._on_observation(_cloud(clean[1 + k % (len(clean) - 1)], t))
        assert node.stats['published'] == n
        assert spin_until(ex, lambda: len(poses) >= n and paths['path_raw']
                          and stamp_to_sec(paths['path_raw'][-1].header.stamp) == pytest.approx(stamps[-1])
                          and len(paths['path']) == len(paths['path_raw']), 4 * period + 10.0)
    finally:
        ex.shutdown()
        probe.destroy_node()
        node.destroy_node()     # its smoother process and answer thread
    expected = [t for t in stamps if round((t - stamps[0]) / period, 6).is_integer()]    # 100, 102, ... 122
    for msgs in paths.values():
        got = [stamp_to_sec(m.header.stamp) for m in msgs]
        np.testing.assert_allclose(got, [*expected, stamps[-1]])          # the period's, then the flush
        assert all(len(m.poses) <= cap for m in msgs)
        np.testing.assert_allclose([stamp_to_sec(p.header.stamp) for p in msgs[-1].poses], stamps[-cap:])
        first = msgs[0]
        assert len(first.poses) == 1 and first.header.frame_id == 'odom'
    assert node.stats['paths_published'] == len(expected) + 1
    assert len(poses) == n                                                  # pose: every frame


def test_nodes_move_with_the_namespace_remap(ros_context):
    """estimator_node, flow_node and a passive camera_node started with ``-r __ns:=/robot1``: every topic they
    publish or subscribe and every service they offer is under /robot1, but the global ones."""
    from fixego_ros.nodes.camera_node import CameraNode
    from fixego_ros.nodes.estimator_node import EstimatorNode
    from fixego_ros.nodes.flow_node import FlowNode

    remap = ['--ros-args', '-r', '__ns:=/robot1']
    nodes = [EstimatorNode(context=ros_context, cli_args=remap,
                           parameter_overrides=[Parameter('speed_topic', value='wheel/odom')]),
             FlowNode(context=ros_context, cli_args=remap), CameraNode(context=ros_context, cli_args=remap)]
    probe = rclpy.create_node('probe', context=ros_context)
    ex = executor_for(ros_context, probe, *nodes)
    global_topics = {'/diagnostics', '/rosout', '/parameter_events', '/tf', '/tf_static'}

    def graph(node) -> tuple[set[str], set[str], set[str]]:
        name, ns = node.get_name(), node.get_namespace()
        return ({t for t, _ in probe.get_publisher_names_and_types_by_node(name, ns)},
                {t for t, _ in probe.get_subscriber_names_and_types_by_node(name, ns)},
                {s for s, _ in probe.get_service_names_and_types_by_node(name, ns)})

    try:
        assert [n.get_namespace() for n in nodes] == ['/robot1'] * 3
        expect = {'estimator_node': ('/robot1/pose', '/robot1/flow/observation', '/robot1/estimator_node/reset'),
                  'flow_node': ('/robot1/flow/observation', '/robot1/right/image_raw',
                                '/robot1/flow_node/set_parameters'),
                  'camera_node': ('/robot1/right/fixation', '/robot1/right/joint_states',
                                  '/robot1/camera_node/reselect')}
        assert spin_until(ex, lambda: all(all(x in set().union(*graph(n)) for x in expect[n.get_name()])
                                          for n in nodes), 10.0), [graph(n) for n in nodes]
        for n in nodes:
            pubs, subs, services = graph(n)
            for topic in pubs | subs:
                assert topic.startswith('/robot1/') or topic in global_topics, (n.get_name(), topic)
            assert '/diagnostics' in pubs
            assert services and all(s.startswith(f'/robot1/{n.get_name()}/') for s in services), services
        pubs, subs, _ = graph(nodes[0])
        assert {'/robot1/pose', '/robot1/path', '/robot1/path_raw', '/robot1/odom', '/robot1/vergence_request'} <= pubs
        assert {'/robot1/flow/observation', '/robot1/vergence', '/robot1/wheel/odom'} <= subs
        _, subs, _ = graph(nodes[1])
        assert {f'/robot1/{s}/{t}' for s in SIDES for t in ('image_raw', 'joint_states', 'fixation')} <= subs
    finally:
        ex.shutdown()


# ---------------------------------------------------------------------------------------------- processes
def test_demo_runs_every_node_as_a_process_and_writes_a_report(tmp_path):
    """``fixego demo`` on a 3 s straight start of the paper loop at 320x240: sim rig, two camera nodes
    over VISCA on ptys, flow and estimator as separate processes over DDS on a private domain."""
    out = tmp_path / 'demo'
    cmd = [sys.executable, '-m', 'fixego_ros.cli', 'demo', '--out', str(out), '--duration', '3', '--width', '320',
           '--height', '240', '--domain-id', str(private_domain_id() + 1), '--quiet', '--ready-timeout', '90']
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads((out / 'report.json').read_text())
    # how many of the 90 frames get a pose depends on the machine's speed (the estimator skips frames it is too
    # far behind for, and the report counts them); enough are estimated for the checks below
    frames = report['frames']
    assert frames['poses'] + frames['dropped'] <= frames['rendered'] and frames['poses'] >= 10, frames
    assert frames['poses_without_truth'] == 0, frames    # the recorder got every frame's truth (stop 90)
    from fixego_ros.evaluation.tum import read_tum
    stamps, est = read_tum(out / 'estimate.tum')
    _, truth = read_tum(out / 'ground_truth.tum')
    assert len(est) == report['frames']['poses'] and np.all(np.diff(stamps) > 0)
    raw_stamps, raw = read_tum(out / 'estimate.raw.tum')     # the last raw path (published at most once a
    assert len(raw) >= 10 and raw_stamps[-1] == pytest.approx(stamps[-1])   # second) holds the last pose
    assert all(p.is_finite() for p in est)
    # The rig drives ~0.5 m straight ahead. On a straight run the translation's length is not observable
    # (DESIGN.md §5; issue 7): measured over runs it came out anywhere from 0.02 to 1.3 m, so a distance
    # check would test luck. The heading is observable: the estimate must not turn.
    assert truth[-1].t[0] > 0.3
    yaw_deg = [abs(math.degrees(math.atan2(p.R[1, 0], p.R[0, 0]))) for p in est]
    assert max(yaw_deg) < 15.0, max(yaw_deg)
    assert (out / 'trajectory.png').stat().st_size > 10_000
    assert report['latency_image_to_pose_ms']['p50'] > 0
    # the latency breakdown: every stage the recorder sees, and the nodes' own, measured (no timing asserted)
    stages = report['latency_stages_ms']
    for name in ('joint_publish', 'joint_state', 'fixation', 'flow_image_in', 'flow_image_dds', 'flow_image_queue',
                 'flow_joints_in', 'flow_ready', 'flow_compute', 'observation', 'estimator_in', 'estimator_queue',
                 'estimator_solve', 'estimator_out', 'pose'):
        assert stages[name]['p50'] >= 0 and stages[name]['p95'] >= stages[name]['p50'], (name, stages[name])
    # the camera nodes' joint states against the simulator's true angles at the same image stamps
    for side in ('right', 'left'):
        je = report['joint_error_deg'][side]
        assert je['frames'] >= 10 and 0.0 <= je['p50_deg'] <= je['p95_deg'] <= je['max_deg'] < 5.0, (side, je)
    assert 'joint states against the true angles' in (out / 'report.txt').read_text()
    # each camera node's check of its predicted sigma at its readings (SigmaCalibration), and where the refined
    # trajectory's error came from
    for side in ('right', 'left'):
        cam = report['diagnostics'][f'fixego camera_node {side}']
        assert int(cam['joint_sigma_samples']) >= 0 and float(cam['joint_sigma_scale']) >= 1.0, cam
    track = report['refined']['position_error_m']['terminal_track']
    assert 'terminal along the path' in (out / 'report.txt').read_text() and set(track) == {'along_m', 'across_m'}
    # each vergence measurement against the true distance in the simulated room: the one asked for while the rig
    # stands (after the reset, so the recorder has the truth) is within a few tenths of a percent (stop 66: 0.1 %)
    v = report['vergence']
    acc = v['against_truth']
    assert acc['checked'] + acc['without_truth'] == v['measurements'], v
    assert all(abs(s['error_pct']) < 2.0 and s['std_cm'] > 0 for s in acc['steps']), acc
    # the demo waits (bounded) for the smoother process to finish the last frames, and says how long that took
    assert report['smoother_done_after_last_pose_s'] >= 0.0
    est_diag = report['diagnostics']['fixego estimator_node']
    assert est_diag['smoother_behind_s'] == '0.00' and float(est_diag['smoother_behind_s_p95']) >= 0.0
    assert 'after the last pose' in (out / 'report.txt').read_text()
    # how many of the vergence measurements the smoother used (the others it ignored with a note): at most all
    assert 0 <= int(est_diag['smoother_vergence_used']) <= int(est_diag.get('vergence', 0))
    assert 'vergence measurements used' in (out / 'report.txt').read_text()
    # resections the smoother placed at the two-frame step's rotation instead, counted and reported
    assert int(est_diag['smoother_resections_rejected']) >= 0
    assert 'resections rejected' in (out / 'report.txt').read_text()
    # how many frames the child smoothed and how many it left out (its gate, or behind), as the report says
    smoothed, left_out = int(est_diag['smoother_results']), int(est_diag['smoother_skipped_frames'])
    assert smoothed > 0
    expected = f'{smoothed} frames smoothed and {left_out} left out (one per 0.1 s goes in, fewer when behind)'
    assert expected in (out / 'report.txt').read_text()
    # and what each took in the child (its own time per frame)
    assert 0.0 < float(est_diag['smoother_update_ms_p50']) <= float(est_diag['smoother_update_ms_p95'])
    assert (f'p50 {est_diag["smoother_update_ms_p50"]} / p95 {est_diag["smoother_update_ms_p95"]} ms per frame '
            'smoothed') in (out / 'report.txt').read_text()
    # ... and where that time went, stage by stage (the elimination always runs)
    assert float(est_diag['smoother_eliminate_ms_p50']) > 0.0
    assert f'eliminate {est_diag["smoother_eliminate_ms_p50"]}' in (out / 'report.txt').read_text()
    # how each pose was made: every published frame counted once (carried, solved, predicted...)
    steps = report['fast_pose_steps']
    assert steps and sum(steps.values()) >= int(est_diag['published']) > 0, (steps, est_diag['published'])
    assert 'fast poses by step' in (out / 'report.txt').read_text()
    # where the cores went: every node process (and the estimator's smoother child) measured, and the sum
    cpu = report['cpu_percent_of_one_core']
    nodes = ('sim_rig_node', 'right_camera_node', 'left_camera_node', 'flow_node', 'estimator_node')
    assert all(cpu[n] > 0 for n in nodes), cpu
    assert any(v > 0 for k, v in cpu.items() if k.startswith('estimator_node/child')), cpu     # the smoother
    assert cpu['total'] == pytest.approx(sum(v for k, v in cpu.items() if k not in ('total', 'cores')), abs=0.5)
    assert 'CPU, % of one core' in (out / 'report.txt').read_text()
    for name in ('sim_rig_node', 'right_camera_node', 'left_camera_node', 'flow_node', 'estimator_node'):
        assert (out / 'logs' / f'{name}.log').exists()
    # the estimator's inputs from the reset on, a bag that replays the estimator alone (every observation it got
    # after the reset became a frame of the replay; the live node may have skipped some, the replay takes all)
    inputs = report['estimator_inputs']
    assert inputs['error'] == '' and inputs['bag'] == str(out / 'estimator_inputs'), inputs
    n_obs = inputs['messages']['/fixego/flow/observation']
    assert n_obs >= frames['poses'] - 5 and inputs['messages']['/fixego/ground_truth/pose'] >= frames['rendered']
    assert 'replay them: fixego replay' in (out / 'report.txt').read_text()
    replayed = subprocess.run([sys.executable, '-m', 'fixego_ros.cli', 'replay', str(out / 'estimator_inputs'),
                               '--out', str(tmp_path / 'est.tum'), '--no-progress', '--workers', '1'],
                              capture_output=True, text=True, timeout=240)
    assert replayed.returncode == 0, replayed.stderr[-3000:]
    assert f'{n_obs} observations (the estimator alone)' in replayed.stdout, replayed.stdout
    _, r_est = read_tum(tmp_path / 'est.tum')
    assert len(r_est) == n_obs and all(p.is_finite() for p in r_est)
    r_yaw = [abs(math.degrees(math.atan2(p.R[1, 0], p.R[0, 0]))) for p in r_est]
    assert max(r_yaw) < 15.0, max(r_yaw)
    # ... which hold the simulator's true head angles too: the run replayed with them (bench.demo_inputs), every
    # camera of every frame given its true angles but the flow of the first frames, which starts at the keyframe
    # before the reset (held for at most keyframe_max_frames, 10, frames; both cameras)
    from fixego_ros.bench.demo_inputs import HeadAngles, run_dir
    assert inputs['messages']['/fixego/ground_truth/right/joint_states'] >= frames['rendered']
    row = run_dir(out)
    assert row.missing <= 2 * 10 and all(np.isfinite(row.replayed + row.angles[HeadAngles.TRUE])), row
    assert row.live == pytest.approx((100 * report['refined']['position_error_m']['mean'],
                                      100 * report['refined']['position_error_m']['terminal']))


def test_estimator_node_warns_once_while_the_smoother_falls_behind(ros_context, clean_sequence, tmp_path):
    """On a machine that does not keep up, the smoother process falls seconds behind and the path is revised from
    keyframes alone (docs/results.md "Stop 66"): WARN on /diagnostics while it is more than
    ``smoother_warn_behind_s`` behind, until it is back under half of that (logged once each way by OnceLogger)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    from fixego_ros.nodes.common import RELIABLE_QOS
    rig, _, _ = clean_sequence
    node = _synthetic_estimator_node(ros_context, rig, tmp_path, Parameter('smoother_warn_behind_s', value=1.0),
                                     Parameter('diagnostics_period_s', value=0.05))
    probe = rclpy.create_node('probe', context=ros_context)
    ex = executor_for(ros_context, node, probe)
    diags: list[DiagnosticStatus] = []
    probe.create_subscription(DiagnosticArray, '/diagnostics',
                              lambda m: diags.extend(s for s in m.status if s.name == 'fixego estimator_node'),
                              RELIABLE_QOS)

    def latest_behind_warning() -> str | None:
        n = len(diags)
        assert spin_until(ex, lambda: len(diags) > n + 1, 5.0)
        d = diags[-1]
        return d.message if d.level == DiagnosticStatus.WARN and 'behind' in d.message else None

    try:
        for behind in (0.2, 0.9):                           # within the bound: nothing said
            node._watch_smoother(behind)
        assert not node.once.active('behind') and latest_behind_warning() is None
        for behind in (1.4, 2.5, 0.8):                      # 0.8: still above half the bound
            node._watch_smoother(behind)
        assert node.once.active('behind')                   # (OnceLogger: logged when it became active)
        assert latest_behind_warning() == ('smoother 0.8 s behind the newest frame: the path is revised late and '
                                           'from keyframes alone')
        node._watch_smoother(0.3)                           # caught up: the WARN goes
        assert not node.once.active('behind') and latest_behind_warning() is None
        assert list(node.behind_s)[-6:] == [0.2, 0.9, 1.4, 2.5, 0.8, 0.3]
    finally:
        ex.shutdown()
        probe.destroy_node()
        node.destroy_node()     # its smoother process and answer thread
