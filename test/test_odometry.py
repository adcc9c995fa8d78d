"""The external speed aid: Odometry -> rig-frame velocity samples, the simulator's wheel odometry, and
estimator_node forwarding samples received over real DDS (private domain)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from fixego_ros.geometry.rotation import RIG_TO_BASE
from fixego_ros.pipeline.odometry import (
    SPEED_PARAMS,
    OdometryError,
    SpeedInput,
    SpeedSettings,
    twist_to_rig,
    vergence_from_msg,
)

CONFIG = Path(__file__).resolve().parents[1] / 'config'


def cov6(lin: np.ndarray | None = None) -> list[float]:
    c = np.zeros((6, 6))
    if lin is not None:
        c[:3, :3] = lin
        c[3:, 3:] = np.eye(3) * 1e6
    return c.ravel().tolist()


# ---------------------------------------------------------------------------------------------- conversion
@pytest.mark.parametrize('v_base, v_rig', [((1, 0, 0), (0, 0, 1)),     # forward = rig z
                                           ((0, 1, 0), (-1, 0, 0)),    # left = rig -x
                                           ((0, 0, 1), (0, -1, 0))])   # up = rig -y
def test_axes_follow_rep105_and_the_rig_frame(v_base, v_rig):
    v, _ = twist_to_rig(v_base, cov6(np.eye(3) * 0.01), 0.1)
    np.testing.assert_allclose(v, v_rig, atol=1e-15)
    np.testing.assert_allclose(RIG_TO_BASE @ v, v_base, atol=1e-15)


def test_covariance_is_rotated_into_the_rig_frame():
    c_base = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.002], [0.0, 0.002, 0.16]])
    _, c_rig = twist_to_rig((0.3, 0.0, 0.0), cov6(c_base), 0.1)
    # variances: rig x = base y, rig y = base z, rig z = base x; covariances keep their sign through the flips
    np.testing.assert_allclose(np.diag(c_rig), [0.09, 0.16, 0.04])
    np.testing.assert_allclose(c_rig, RIG_TO_BASE.T @ c_base @ RIG_TO_BASE, atol=1e-15)
    assert c_rig[0, 2] == pytest.approx(-0.01)      # cov(rig x, rig z) = cov(-base y, base x)
    assert c_rig[0, 1] == pytest.approx(0.002)      # cov(-base y, -base z)
    # sampling check: rotating samples gives the same covariance
    rng = np.random.default_rng(0)
    samples = rng.multivariate_normal(np.zeros(3), c_base, 20000) @ RIG_TO_BASE   # rows: (R^T v)^T
    np.testing.assert_allclose(np.cov(samples.T), c_rig, atol=0.006)


def test_zero_covariance_means_unknown_and_uses_the_default_std():
    _, c = twist_to_rig((0.5, 0, 0), [0.0] * 36, 0.25)
    np.testing.assert_allclose(c, np.eye(3) * 0.0625)
    s = SpeedInput(SpeedSettings(default_std=0.3)).convert(1.0, 'base_link', (0.5, 0, 0), [0.0] * 36)
    np.testing.assert_allclose(s.cov_rig, np.eye(3) * 0.09)
    # an exactly-zero axis among known ones is floored (the estimator must be able to invert it)
    _, c = twist_to_rig((0.5, 0, 0), cov6(np.diag([0.01, 0.0, 0.0])), 0.25)
    assert np.all(np.linalg.eigvalsh(c) > 0) and c[2, 2] == pytest.approx(0.01)


@pytest.mark.parametrize('linear, cov, kind', [
    ((math.nan, 0, 0), cov6(np.eye(3)), 'velocity'),
    ((0, math.inf, 0), cov6(np.eye(3)), 'velocity'),
    ((0.1, 0, 0), cov6(np.diag([math.nan, 1, 1])), 'covariance'),
    ((0.1, 0, 0), cov6(np.diag([-0.01, 1, 1])), 'covariance'),
    ((0.1, 0, 0), cov6(np.array([[1.0, 2.0, 0], [2.0, 1.0, 0], [0, 0, 1]])), 'covariance'),   # not PSD
    ((0.1, 0, 0), [0.01] * 9, 'covariance'),                                               # not 6x6
])
def test_unusable_twists_are_rejected_with_the_reason(linear, cov, kind):
    with pytest.raises(OdometryError) as e:
        SpeedInput().convert(1.0, 'base_link', linear, cov)
    assert e.value.kind == kind and isinstance(e.value, ValueError) and str(e.value)


def test_frames_order_and_age():
    s = SpeedInput(SpeedSettings(max_age_s=0.2))
    with pytest.raises(OdometryError, match="'odom'") as e:
        s.convert(1.0, 'odom', (0.1, 0, 0), cov6(np.eye(3)))
    assert e.value.kind == 'frame'
    assert not s.assumed_frame
    first = s.convert(1.0, '', (0.1, 0, 0), cov6(np.eye(3)))    # empty child frame: taken as base_link
    assert s.assumed_frame and first.stamp == 1.0
    for t, kind in ((0.9, 'order'), (1.0, 'order'), (math.nan, 'stamp')):
        with pytest.raises(OdometryError) as e:
            s.convert(t, 'base_link', (0.1, 0, 0), cov6(np.eye(3)))
        assert e.value.kind == kind
    with pytest.raises(OdometryError) as e:      # older than speed_max_age_s relative to the newest frame
        s.convert(1.1, 'base_link', (0.1, 0, 0), cov6(np.eye(3)), frame_stamp=1.5)
    assert e.value.kind == 'stale'
    assert s.convert(1.1, 'base_link', (0.1, 0, 0), cov6(np.eye(3)), frame_stamp=1.25).stamp == 1.1
    s.reset()
    assert s.convert(0.5, 'base_link', (0.1, 0, 0), cov6(np.eye(3))).stamp == 0.5
    with pytest.raises(ValueError):
        SpeedSettings(default_std=0.0)
    with pytest.raises(ValueError):
        SpeedSettings(max_age_s=-1.0)


def test_from_an_rclpy_odometry_message():
    pytest.importorskip('rclpy')
    from nav_msgs.msg import Odometry

    from fixego_ros.nodes.common import sec_to_stamp
    msg = Odometry()
    msg.header.stamp = sec_to_stamp(12.5)
    msg.child_frame_id = 'base_link'
    msg.twist.twist.linear.x, msg.twist.twist.linear.y = 0.4, 0.1
    msg.twist.covariance = cov6(np.diag([0.01, 0.04, 0.09]))
    s = SpeedInput().from_msg(msg)
    assert s.stamp == 12.5
    np.testing.assert_allclose(s.v_rig, [-0.1, 0.0, 0.4])
    np.testing.assert_allclose(np.diag(s.cov_rig), [0.04, 0.09, 0.01])


def vergence_msg(point=(0.3, 0.0, 3.0), cov=None, stamp: float = 12.5, frame_id: str = 'rig'):
    """PoseWithCovarianceStamped as camera_node publishes a vergence measurement."""
    pytest.importorskip('rclpy')
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from fixego_ros.nodes.common import sec_to_stamp
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = sec_to_stamp(stamp)
    msg.header.frame_id = frame_id
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = point
    msg.pose.pose.orientation.w = 1.0
    msg.pose.covariance = cov6(np.diag([1e-6, 1e-6, 0.0036]) if cov is None else cov)
    return msg


def test_vergence_message_gives_the_point_and_its_position_covariance():
    stamp, point, cov = vergence_from_msg(vergence_msg())
    assert stamp == 12.5 and point.shape == (3,) and cov.shape == (3, 3)
    np.testing.assert_allclose(point, [0.3, 0.0, 3.0])
    np.testing.assert_allclose(cov, np.diag([1e-6, 1e-6, 0.0036]))      # the orientation block (1e6) is dropped
    assert vergence_from_msg(vergence_msg(stamp=0.0, frame_id=''))[0] == 0.0   # zero stamp, empty frame: fine


@pytest.mark.parametrize('kwargs, match', [
    ({'point': (0.3, math.nan, 3.0)}, 'point not finite'),
    ({'point': (math.inf, 0.0, 3.0)}, 'point not finite'),
    ({'cov': np.diag([1e-6, math.nan, 1e-2])}, 'covariance not finite'),
    ({'cov': np.diag([1e-6, -1e-2, 1e-2])}, 'not positive semi-definite'),
    ({'frame_id': 'right_optical_frame'}, "expected 'rig'"),
])
def test_unusable_vergence_messages_are_rejected_with_the_reason(kwargs, match):
    with pytest.raises(ValueError, match=match):
        vergence_from_msg(vergence_msg(**kwargs))


def test_config_file_lists_the_speed_parameters_with_their_defaults():
    params = yaml.safe_load((CONFIG / 'estimator_node.yaml').read_text())['/**']['ros__parameters']
    for name, (default, text) in SPEED_PARAMS.items():
        assert params[name] == default and text, name
    assert SPEED_PARAMS['speed_topic'][0] == ''        # off by default


# ---------------------------------------------------------------------------------------------- simulator
SIM_ARGS = ['--vergence', 'off', '--trajectory', 'paper', '--steps', '8', '--width', '160', '--height', '120',
            '--fps', '10', '--texel', '0.006', '--no-progress']


def _read(path: Path) -> list[tuple[str, str, int, bytes]]:
    from rosbags.rosbag2 import Reader
    with Reader(path) as reader:
        return [(c.topic, c.msgtype, t, bytes(raw)) for c, t, raw in reader.messages()]


def test_sim_wheel_odometry_is_the_true_twist_plus_seeded_noise(tmp_path):
    pytest.importorskip('rclpy')
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message

    from fixego_ros.cli import main as fixego
    from fixego_ros.pipeline.messages import msg_to_pose
    from fixego_ros.sim.bag_writer import WHEEL_ODOM_TOPIC, topics

    std = 0.02
    plain, wheel = tmp_path / 'plain', tmp_path / 'wheel'
    assert fixego(['sim', *SIM_ARGS, '--out', str(plain)]) == 0
    assert fixego(['sim', *SIM_ARGS, '--out', str(wheel), '--wheel-odom-std', str(std)]) == 0
    a, b = _read(plain), _read(wheel)
    # everything else is unchanged: the option only adds the topic
    assert [m for m in b if m[0] != WHEEL_ODOM_TOPIC] == a
    assert WHEEL_ODOM_TOPIC not in {m[0] for m in a} and set(topics(True)) == {m[0] for m in b}
    meta = yaml.safe_load((wheel / 'sim.yaml').read_text())
    assert meta['wheel_odometry'] == {'topic': WHEEL_ODOM_TOPIC, 'std_m_s': std}
    # written first in each frame, with the frame's stamp
    first_of_frame = {}
    for topic, _, t, _ in b:
        first_of_frame.setdefault(t, topic)
    assert set(first_of_frame.values()) == {WHEEL_ODOM_TOPIC}

    gt = [(t, msg_to_pose(deserialize_message(raw, PoseStamped).pose))
          for topic, _, t, raw in b if topic == '/fixego/ground_truth/pose']
    odo = [deserialize_message(raw, Odometry) for topic, _, _, raw in b if topic == WHEEL_ODOM_TOPIC]
    assert len(odo) == len(gt) > 20
    errs, speeds = [], []
    for k in range(1, len(gt) - 1):
        (t0, p0), (t1, p1), (t2, p2) = gt[k - 1], gt[k], gt[k + 1]
        v_fd = p1.R.T @ (p2.t - p0.t) / ((t2 - t0) * 1e-9)        # base_link velocity in base_link at frame k
        m = odo[k]
        assert m.header.frame_id == 'odom' and m.child_frame_id == 'base_link'
        assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == t1
        lin = m.twist.twist.linear
        errs.append(np.array([lin.x, lin.y, lin.z]) - v_fd)
        speeds.append(np.linalg.norm(v_fd))
        cov = np.array(m.twist.covariance).reshape(6, 6)
        np.testing.assert_allclose(np.diag(cov)[:3], std ** 2)
        assert np.all(np.diag(cov)[3:] >= 1e6) and np.count_nonzero(cov - np.diag(np.diag(cov))) == 0
    errs = np.array(errs)
    assert np.median(speeds) > 0.1                       # the rig moves forward along the first straight
    assert np.all(np.abs(errs.mean(axis=0)) < 4 * std / np.sqrt(len(errs)) + 0.005)   # unbiased
    assert 0.5 * std < errs.std() < 1.5 * std            # noise of the requested size
    # deterministic: same seed, same bytes
    again = tmp_path / 'again'
    assert fixego(['sim', *SIM_ARGS, '--out', str(again), '--wheel-odom-std', str(std)]) == 0
    assert _read(again) == b


def test_sim_wheel_odometry_at_its_own_rate_with_a_scale_bias(tmp_path):
    """``--wheel-odom-rate 20 --wheel-odom-bias 0.01``: samples every 50 ms, not at the frames, written in stamp
    order before the frame after them; their speed is the true one times 1.01 (the covariance does not show it),
    the images are unchanged."""
    pytest.importorskip('rclpy')
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message

    from fixego_ros.cli import main as fixego
    from fixego_ros.geometry.rig import load_rig
    from fixego_ros.sim.bag_writer import WHEEL_ODOM_TOPIC
    from fixego_ros.sim.run import SimSettings, Simulation

    plain, wheel, unbiased = tmp_path / 'plain', tmp_path / 'wheel', tmp_path / 'unbiased'
    assert fixego(['sim', *SIM_ARGS, '--out', str(plain)]) == 0
    common = ['--wheel-odom-std', '0.0', '--wheel-odom-rate', '20']
    assert fixego(['sim', *SIM_ARGS, '--out', str(wheel), *common, '--wheel-odom-bias', '0.01']) == 0
    assert fixego(['sim', *SIM_ARGS, '--out', str(unbiased), *common]) == 0
    a, b = _read(plain), _read(wheel)
    assert [m for m in b if m[0] != WHEEL_ODOM_TOPIC] == a
    assert [m[2] for m in b] == sorted(m[2] for m in b)               # log times in order
    odo = [(t, deserialize_message(raw, Odometry)) for topic, _, t, raw in b if topic == WHEEL_ODOM_TOPIC]
    flat = [deserialize_message(raw, Odometry) for topic, _, _, raw in _read(unbiased) if topic == WHEEL_ODOM_TOPIC]
    frames = sorted({t for topic, _, t, _ in a})
    span = (frames[-1] - frames[0]) * 1e-9
    assert abs(len(odo) - (span * 20 + 1)) <= 1
    stamps = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for _, m in odo])
    np.testing.assert_allclose(np.diff(stamps), 0.05, atol=1e-6)
    assert np.array_equal([t for t, _ in odo], np.round(stamps * 1e9).astype(np.int64))
    speed = np.array([np.hypot(m.twist.twist.linear.x, m.twist.twist.linear.y) for _, m in odo])
    true = np.array([np.hypot(m.twist.twist.linear.x, m.twist.twist.linear.y) for m in flat])
    moving = true > 0.05
    assert moving.sum() > 10
    np.testing.assert_allclose(speed[moving] / true[moving], 1.01, rtol=1e-9)
    # and the unbiased samples are the simulator's true velocity at their stamps
    settings = SimSettings(trajectory='paper', seed=0, fps=10.0, steps=8, vergence='off', texel=0.006)
    from fixego_ros.sim.run import resize_rig
    sim = Simulation(resize_rig(load_rig(plain / 'rig.yaml'), 160, 120), settings)
    v = sim.base_velocities(stamps - settings.epoch)
    np.testing.assert_allclose(true, np.hypot(v[:, 0], v[:, 1]), atol=1e-6)   # stamps: ns and float rounding


def test_sim_true_velocity_in_base_link():
    from fixego_ros.geometry.rig import default_rig_path, load_rig
    from fixego_ros.sim.run import SimSettings, Simulation, resize_rig
    sim = Simulation(resize_rig(load_rig(default_rig_path()), 64, 48), SimSettings(trajectory='straight', fps=5))
    v = sim.base_velocities()
    mid = v[len(v) // 2]
    # the straight trajectory drives forward (base_link +x) at 0.2 m/s once past the start ramp
    np.testing.assert_allclose(mid, [0.2, 0.0, 0.0], atol=1e-6)


# ---------------------------------------------------------------------------------------------- estimator_node
def test_estimator_node_forwards_speed_samples_over_dds(ros_context, monkeypatch, tmp_path):
    rclpy = pytest.importorskip('rclpy')
    from conftest import executor_for, spin_until
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from nav_msgs.msg import Odometry
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2

    from fixego_ros.experiments.point_scene import PRESETS, PointScene, random_motion_sequence
    from fixego_ros.nodes.common import RELIABLE_QOS, sec_to_stamp, table_to_cloud
    from fixego_ros.nodes.estimator_node import EstimatorNode
    from fixego_ros.pipeline.observation import observation_to_rows

    cfg = PRESETS['dense']
    rng = np.random.default_rng(3)
    scene = PointScene(cfg, rng)
    _, _, clean = scene.frames(random_motion_sequence(cfg, 2, rng))
    rig_file = tmp_path / 'rig.yaml'
    scene.rig.save(rig_file)
    node = EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter('rig_file', value=str(rig_file)), Parameter('speed_topic', value='/fixego/wheel/odom'),
        Parameter('speed_default_std', value=0.3), Parameter('max_lag_s', value=1e12),
        Parameter('max_keyframe_lag_s', value=1e12), Parameter('diagnostics_period_s', value=0.2)])
    got: list[tuple[float, np.ndarray, np.ndarray]] = []
    add_velocity = node.estimator.add_velocity

    def spy(t, v, c):
        got.append((t, v, c))
        add_velocity(t, v, c)
    monkeypatch.setattr(node.estimator, 'add_velocity', spy)
    probe = rclpy.create_node('probe', context=ros_context)
    ex = executor_for(ros_context, node, probe)
    diags: list[DiagnosticArray] = []
    probe.create_subscription(DiagnosticArray, '/diagnostics', diags.append, RELIABLE_QOS)
    pub = probe.create_publisher(Odometry, '/fixego/wheel/odom', RELIABLE_QOS)
    obs_pub = probe.create_publisher(PointCloud2, '/fixego/flow/observation', RELIABLE_QOS)
    assert spin_until(ex, lambda: pub.get_subscription_count() > 0 and obs_pub.get_subscription_count() > 0, 10.0)

    def odom(t: float, vx: float, frame: str = 'base_link', var: float = 0.0) -> Odometry:
        m = Odometry()
        m.header.stamp = sec_to_stamp(t)
        m.header.frame_id, m.child_frame_id = 'odom', frame
        m.twist.twist.linear.x = vx
        m.twist.covariance = cov6(np.eye(3) * var) if var else [0.0] * 36
        return m

    def speed_status():
        for d in reversed(diags):
            for s in d.status:
                if s.name.endswith('speed aid'):
                    return s
        return None

    try:
        pub.publish(odom(10.0, 0.5))                       # zero covariance: default std 0.3
        pub.publish(odom(10.1, math.nan))                  # dropped: NaN
        pub.publish(odom(10.2, 0.6, frame='odom'))         # dropped: twist in another frame
        pub.publish(odom(9.9, 0.6))                        # dropped: goes backwards
        pub.publish(odom(10.3, 0.7, var=0.01))
        assert spin_until(ex, lambda: len(got) >= 2 and sum(node.speed_stats.values()) >= 5, 10.0), \
            (got, node.speed_stats)
        assert [g[0] for g in got] == [10.0, 10.3]
        np.testing.assert_allclose(got[0][1], [0.0, 0.0, 0.5])
        np.testing.assert_allclose(got[0][2], np.eye(3) * 0.09)
        np.testing.assert_allclose(got[1][1], [0.0, 0.0, 0.7])
        np.testing.assert_allclose(got[1][2], np.eye(3) * 0.01)
        assert node.speed_stats == {'samples': 2, 'rejected_velocity': 1, 'rejected_frame': 1, 'rejected_order': 1}
        assert spin_until(ex, lambda: speed_status() is not None and 'receiving' in speed_status().message, 5.0)
        values = {kv.key: kv.value for kv in speed_status().values}
        assert values['samples'] == '2' and values['rejected_velocity'] == '1' and 'last_age_s' in values
        # the smoother's scale of the source: held at 1 until a vergence measurement is in its graph
        assert values['speed_scale'] == '1.0000' and values['speed_scale_estimated'] == 'False'
        # a frame: the scale status follows FrameResult.scale_observed / scale_note
        for k, o in enumerate(clean):
            o.prev_stamp = None
            obs_pub.publish(table_to_cloud(observation_to_rows(o), sec_to_stamp(10.4 + 0.1 * k), 'rig'))
        assert spin_until(ex, lambda: node.last is not None and node.last.index >= len(clean) - 1, 10.0)
        n = len(diags)
        assert spin_until(ex, lambda: len(diags) > n + 1, 5.0)
        scale = [s for s in diags[-1].status if s.name.endswith('scale')]
        assert len(scale) == 1
        values = {kv.key: kv.value for kv in scale[0].values}
        if values['scale_observed'] == 'True':
            assert scale[0].level == DiagnosticStatus.OK and scale[0].message == values['scale_note']
        else:
            assert scale[0].level == DiagnosticStatus.WARN and scale[0].message.startswith('scale unobserved: ')
        # a sample older than speed_max_age_s relative to the newest frame is not used
        pub.publish(odom(10.35, 0.7, var=0.01))
        assert spin_until(ex, lambda: node.speed_stats['rejected_stale'] == 1, 5.0)
        assert len(got) == 2
    finally:
        ex.shutdown()


def test_estimator_node_without_speed_topic_has_no_subscription(ros_context, tmp_path):
    pytest.importorskip('rclpy')
    from fixego_ros.nodes.estimator_node import EstimatorNode
    node = EstimatorNode(context=ros_context)
    try:
        assert node.speed_topic == ''
        assert not any(s.topic_name.endswith('odom') for s in node.subscriptions)
    finally:
        node.destroy_node()


def test_estimator_node_takes_a_latched_vergence_distance(ros_context, monkeypatch):
    """A vergence measurement published before the estimator starts (latched) reaches the estimator as a
    fixation point of the right camera; a NaN one is dropped and counted."""
    rclpy = pytest.importorskip('rclpy')
    from conftest import executor_for, spin_until
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.parameter import Parameter

    from fixego_ros.nodes.common import LATCHED_QOS, sec_to_stamp
    from fixego_ros.nodes.estimator_node import EstimatorNode

    probe = rclpy.create_node('probe', context=ros_context)
    pub = probe.create_publisher(PoseWithCovarianceStamped, '/fixego/vergence', LATCHED_QOS)
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = sec_to_stamp(12.5)
    msg.header.frame_id = 'rig'
    msg.pose.pose.position.x, msg.pose.pose.position.z = 0.3, 3.0
    msg.pose.covariance = cov6(np.eye(3) * 1e-4)
    pub.publish(msg)                                   # before the estimator exists: latched
    node = EstimatorNode(context=ros_context,
                         parameter_overrides=[Parameter('vergence_topic', value='/fixego/vergence')])
    got = []
    add = node.estimator.add_fixation_point

    def spy(stamp, side, point, cov):
        got.append((stamp, side, np.asarray(point), np.asarray(cov)))
        add(stamp, side, point, cov)
    monkeypatch.setattr(node.estimator, 'add_fixation_point', spy)
    ex = executor_for(ros_context, node, probe)
    try:
        assert spin_until(ex, lambda: len(got) == 1, 10.0)
        stamp, side, point, cov = got[0]
        assert stamp == pytest.approx(12.5) and side == 'right'
        assert np.allclose(point, [0.3, 0.0, 3.0]) and np.allclose(cov, np.eye(3) * 1e-4)
        msg.pose.pose.position.z = float('nan')
        pub.publish(msg)
        assert spin_until(ex, lambda: node.stats.get('vergence_rejected', 0) == 1, 10.0)
        assert node.stats['vergence'] == 1
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()
