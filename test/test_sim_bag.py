"""``fixego sim`` bags: read back with rosbags and mcap, deserialised with rclpy, ground truth, determinism."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip('rclpy')

from fixego_ros.cli import main as fixego
from fixego_ros.geometry.rig import load_rig
from fixego_ros.geometry.rotation import from_quat_xyzw, rig_pose_to_base_link
from fixego_ros.sim.bag_writer import topics
from fixego_ros.sim.run import EPOCH, SimSettings, build_trajectory

ARGS = ['--trajectory', 'paper', '--steps', '6', '--width', '160', '--height', '120', '--fps', '10',
        '--texel', '0.006', '--no-progress']


def _msg_class(msgtype: str):
    package, _, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


def _write(tmp: Path, name: str, *extra: str) -> Path:
    out = tmp / name
    assert fixego(['sim', *ARGS, '--out', str(out), *extra]) == 0
    return out


@pytest.fixture(scope='module')
def bag(tmp_path_factory) -> Path:
    return _write(tmp_path_factory.mktemp('simbag'), 'bag')


def _read_rosbags(path: Path) -> list[tuple[str, str, int, bytes]]:
    from rosbags.rosbag2 import Reader
    with Reader(path) as reader:
        return [(c.topic, c.msgtype, t, bytes(raw)) for c, t, raw in reader.messages()]


def test_bag_reads_back_with_rosbags_and_rclpy(bag):
    from rclpy.serialization import deserialize_message

    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['storage_identifier'] == 'mcap'
    listed = {t['topic_metadata']['name']: t for t in meta['topics_with_message_count']}
    assert set(listed) == set(topics())
    for name, t in listed.items():
        assert t['topic_metadata']['type'] == topics()[name]
        assert t['topic_metadata']['type_description_hash'].startswith('RIHS01_')
        assert t['topic_metadata']['offered_qos_profiles']  # ros2 bag play needs them
    msgs = _read_rosbags(bag)
    traj = build_trajectory(SimSettings(steps=6))
    n_frames = int(np.floor(traj.duration * 10 + 1e-9)) + 1
    assert len(msgs) == meta['message_count'] == n_frames * len(topics())
    rig = load_rig(bag / 'rig.yaml')
    assert (rig.right.width, rig.right.height) == (160, 120)
    assert rig.right.fx == pytest.approx(1727.0 / 4)  # angle of view kept when resizing
    from rosbags.typesys import Stores, get_typestore
    typestore = get_typestore(Stores.ROS2_JAZZY)
    stamps: dict[str, list[int]] = {}
    for topic, msgtype, t_ns, raw in msgs:
        msg = deserialize_message(raw, _msg_class(msgtype))
        typestore.deserialize_cdr(raw, msgtype)  # rosbags' strict decoder accepts it too
        stamp_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        assert stamp_ns == t_ns  # log time = header stamp (exposure time)
        stamps.setdefault(topic, []).append(stamp_ns)
        if topic.endswith('image_raw'):
            side = topic.split('/')[2]
            assert msg.header.frame_id == f'{side}_optical_frame'
            assert (msg.width, msg.height, msg.encoding, msg.step) == (160, 120, 'mono8', 160)
            img = np.frombuffer(bytes(msg.data), np.uint8)
            assert img.size == 160 * 120 and img.std() > 20  # textured, not blank
        elif topic.endswith('camera_info'):
            assert msg.distortion_model == 'plumb_bob'
            assert np.allclose(np.reshape(msg.k, (3, 3)), rig.camera(topic.split('/')[2]).K)
        elif topic.endswith('joint_states'):
            side = topic.split('/')[2]
            assert list(msg.name) == [f'{side}_pan', f'{side}_tilt']
            assert abs(msg.position[0]) < np.radians(100) and abs(msg.position[1]) < np.radians(25)
        elif topic.endswith('fixation'):
            # the servo keeps the true fixation point close to the image centre
            assert np.hypot(msg.point.x - 79.5, msg.point.y - 59.5) < 5.0
            assert msg.point.z == 0.0  # no re-selection in the first six steps
    first = {topic: s[0] for topic, s in stamps.items()}
    assert set(first.values()) == {round(EPOCH * 1e9)}
    assert all(s == stamps['/fixego/right/image_raw'] for s in stamps.values())  # one stamp per frame


def test_ground_truth_in_bag_matches_the_trajectory(bag):
    from rclpy.serialization import deserialize_message

    traj = build_trajectory(SimSettings(steps=6))
    p0inv = traj.pose_at(0.0).inverse()
    n = 0
    for topic, msgtype, t_ns, raw in _read_rosbags(bag):
        if topic != '/fixego/ground_truth/pose':
            continue
        msg = deserialize_message(raw, _msg_class(msgtype))
        assert msg.header.frame_id == 'odom'
        t = t_ns * 1e-9 - EPOCH
        want = rig_pose_to_base_link(p0inv @ traj.pose_at(t))
        p, q = msg.pose.position, msg.pose.orientation
        assert np.allclose([p.x, p.y, p.z], want.t, atol=1e-9)
        assert np.allclose(from_quat_xyzw(np.array([q.x, q.y, q.z, q.w])), want.R, atol=1e-9)
        if n == 0:
            assert np.allclose(want.matrix(), np.eye(4))
        n += 1
    assert n > 10
    # the rig drives forward (base_link x) along the first straight
    assert want.t[0] > 0.1 and abs(want.t[1]) < 1e-6


def test_bag_reads_back_with_mcap(bag):
    from mcap.reader import make_reader
    from rclpy.serialization import deserialize_message

    files = list(bag.glob('*.mcap'))
    assert len(files) == 1
    count = 0
    with files[0].open('rb') as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            assert channel.message_encoding == 'cdr' and schema.encoding == 'ros2msg'
            assert channel.topic in topics() and schema.name == topics()[channel.topic]
            msg = deserialize_message(message.data, _msg_class(schema.name))
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == message.log_time
            count += 1
    assert count == len(_read_rosbags(bag))


def test_same_seed_same_bytes_other_seed_other_images(bag, tmp_path):
    again = _write(tmp_path, 'again')
    a, b = _read_rosbags(bag), _read_rosbags(again)
    assert len(a) == len(b) and all(x == y for x, y in zip(a, b, strict=True))
    other = _write(tmp_path, 'other', '--seed', '1')
    c = _read_rosbags(other)
    imgs = [(x[3], y[3]) for x, y in zip(a, c, strict=True) if x[0].endswith('image_raw')]
    assert all(x != y for x, y in imgs)
    assert fixego(['sim', *ARGS, '--out', str(bag)]) == 2  # never overwrites


def test_vergence_std_adds_one_noisy_right_fixation_point(bag, tmp_path):
    """``--vergence-std`` writes a single start-up vergence measurement: the right camera's true fixation point
    at the first frame (rig frame), its distance off by a small relative error; nothing else changes."""
    from rclpy.serialization import deserialize_message

    from fixego_ros.sim.bag_writer import VERGENCE_TOPIC, write_bag
    from fixego_ros.sim.run import Simulation

    std = 0.01
    verg = _write(tmp_path, 'verg', '--vergence-std', str(std))
    a, b = _read_rosbags(bag), _read_rosbags(verg)
    assert VERGENCE_TOPIC not in {m[0] for m in a}                   # off by default
    assert [m for m in b if m[0] != VERGENCE_TOPIC] == a           # its own noise stream: the rest byte-identical
    assert set(topics(vergence=True)) == {m[0] for m in b}
    ours = [m for m in b if m[0] == VERGENCE_TOPIC]
    assert len(ours) == 1 and b[0][0] == VERGENCE_TOPIC               # one message, before the first images
    _, msgtype, t_ns, raw = ours[0]
    msg = deserialize_message(raw, _msg_class(msgtype))
    assert msgtype == 'geometry_msgs/msg/PoseWithCovarianceStamped' and msg.header.frame_id == 'rig'
    assert t_ns == round(EPOCH * 1e9) == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    # the truth, independently: the same simulation's first frame
    rig = load_rig(verg / 'rig.yaml')
    meta = yaml.safe_load((verg / 'sim.yaml').read_text())
    frame = next(Simulation(rig, SimSettings(**meta['simulator'])).frames())
    true_pt = frame.rig_pose.inverse().apply(frame.states['right'].point) - rig.center('right')
    p = msg.pose.pose.position
    got = np.array([p.x, p.y, p.z]) - rig.center('right')
    d_true, d = np.linalg.norm(true_pt), np.linalg.norm(got)
    assert 0.5 < d_true < 20 and 0 < abs(d / d_true - 1) < 4 * std              # noisy, by a few %
    assert np.linalg.norm(np.cross(got / d, true_pt / d_true)) < 1e-9           # on the true ray
    cov6 = np.array(msg.pose.covariance).reshape(6, 6)
    u = got / d
    assert u @ cov6[:3, :3] @ u == pytest.approx((std * d) ** 2)               # relative std along the ray
    assert np.allclose(np.sort(np.linalg.eigvalsh(cov6[:3, :3]))[:2], 1e-6)    # 1 mm across it
    assert np.all(np.diag(cov6)[3:] >= 1e6)                                     # orientation unused
    assert meta['vergence']['topic'] == VERGENCE_TOPIC and meta['vergence']['std_rel'] == std
    assert meta['vergence']['distance_true_m'] == pytest.approx(d_true)
    info = yaml.safe_load((verg / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['custom_data']['fixego_sim_vergence_std'] == str(std)
    qos = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles'][0]
           for t in info['topics_with_message_count']}
    assert qos[VERGENCE_TOPIC]['durability'] == 'transient_local'              # latched, as camera_node's
    # invalid values are refused, by the CLI and by write_bag
    assert fixego(['sim', *ARGS, '--out', str(tmp_path / 'bad'), '--vergence-std', '-0.1']) == 2
    with pytest.raises(ValueError, match='vergence std'):
        write_bag(tmp_path / 'bad', rig, vergence_std=float('nan'))
    assert not (tmp_path / 'bad').exists()
