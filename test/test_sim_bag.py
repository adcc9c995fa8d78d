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

BASE = ['--trajectory', 'paper', '--width', '160', '--height', '120', '--fps', '10', '--texel', '0.006',
        '--no-progress']
ARGS = [*BASE, '--steps', '6', '--vergence', 'off']   # the plain bag: no vergence step (default: physical, below)


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


@pytest.fixture(scope='module')
def physical_bag(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp('simbag') / 'physical'
    assert fixego(['sim', *BASE, '--steps', '8', '--out', str(out)]) == 0   # vergence physical is the default
    return out


def _decode(msgs, topic: str) -> list[tuple[int, object]]:
    from rclpy.serialization import deserialize_message
    return [(t, deserialize_message(raw, _msg_class(mt))) for top, mt, t, raw in msgs if top == topic]


def test_physical_vergence_bag(bag, physical_bag):
    """By default the left head verges on the right's point at start-up (its joint states show the slew and the
    return) and /fixego/vergence carries the measurement, stamped with a frame's stamp, before its images."""
    from fixego_ros.sim.bag_writer import VERGENCE_TOPIC

    msgs = _read_rosbags(physical_bag)
    assert {m[0] for m in msgs} == set(topics(vergence=True))
    meta = yaml.safe_load((physical_bag / 'sim.yaml').read_text())
    assert meta['simulator']['vergence'] == 'physical'
    verg = meta['vergence']
    assert verg['mode'] == 'physical' and verg['topic'] == VERGENCE_TOPIC
    [rec] = verg['measurements']                                       # start-up only in these 2.25 s
    [step] = verg['steps']
    assert step['outcome'] == 'measured' and 0.3 < step['slew_out_s'] < 1.5 and step['away_s'] < 2.5
    ours = _decode(msgs, VERGENCE_TOPIC)
    assert len(ours) == 1
    t_ns, msg = ours[0]
    image_stamps = [t for top, _, t, _ in msgs if top == '/fixego/right/image_raw']
    assert t_ns in image_stamps and t_ns == round(rec['stamp_s'] * 1e9)    # a frame's stamp
    assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == t_ns and msg.header.frame_id == 'rig'
    first_of_stamp = next(m[0] for m in msgs if m[2] == t_ns)
    assert first_of_stamp == VERGENCE_TOPIC                            # before that frame's images
    p = msg.pose.pose.position
    point = np.array([p.x, p.y, p.z])
    assert np.linalg.norm(point) == pytest.approx(rec['distance_m'])
    assert rec['error_m'] == pytest.approx(rec['distance_m'] - rec['distance_true_m'])
    assert abs(rec['error_m']) < 4 * rec['std_m'] and 1.0 < rec['distance_true_m'] < 5.0
    cov6 = np.array(msg.pose.covariance).reshape(6, 6)
    u = point / np.linalg.norm(point)
    assert u @ cov6[:3, :3] @ u == pytest.approx(rec['std_m'] ** 2)
    assert np.all(np.linalg.eigvalsh(cov6[:3, :3]) > 0) and np.all(np.diag(cov6)[3:] >= 1e6)
    info = yaml.safe_load((physical_bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    qos = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles'][0]
           for t in info['topics_with_message_count']}
    assert qos[VERGENCE_TOPIC]['durability'] == 'transient_local'      # latched, as camera_node's
    # the left joint states: out to the right's point (tens of degrees) and back to where it looked
    pan = np.degrees([m.position[0] for _, m in _decode(msgs, '/fixego/left/joint_states')])
    stamps = (np.array(image_stamps) - image_stamps[0]) * 1e-9
    k_held = int(np.argmax(pan))
    assert pan[k_held] - pan[0] > 30.0 and stamps[k_held] < 1.5
    assert abs(pan[-1] - pan[0]) < 5.0
    ids = [m.point.z for _, m in _decode(msgs, '/fixego/ground_truth/left/fixation')]
    assert ids[0] == 0 and ids[-1] == 2 and sorted(set(ids)) == [0, 1, 2]  # out: new id; back: new id again
    # the right camera is not disturbed: its images are the plain bag's (which ends two steps earlier)
    plain = [m for m in _read_rosbags(bag) if m[0] == '/fixego/right/image_raw']
    assert plain == [m for m in msgs if m[0] == '/fixego/right/image_raw'][:len(plain)]


def test_measurements_vergence_bag_only_adds_the_messages(bag, tmp_path):
    """``--vergence measurements``: the same images and everything else as ``off``, plus the measurements."""
    from fixego_ros.sim.bag_writer import VERGENCE_TOPIC

    out = _write(tmp_path, 'meas', '--vergence', 'measurements')
    a, b = _read_rosbags(bag), _read_rosbags(out)
    assert [m for m in b if m[0] != VERGENCE_TOPIC] == a
    ours = _decode(b, VERGENCE_TOPIC)
    assert len(ours) == 1 and ours[0][0] == round(EPOCH * 1e9) and b[0][0] == VERGENCE_TOPIC   # start-up
    meta = yaml.safe_load((out / 'sim.yaml').read_text())['vergence']
    assert meta['mode'] == 'measurements' and 'steps' not in meta
    assert abs(meta['measurements'][0]['error_m']) < 4 * meta['measurements'][0]['std_m']


def test_vergence_option_is_checked(bag, tmp_path, capsys):
    assert 'vergence' not in yaml.safe_load((bag / 'sim.yaml').read_text())      # off: the record of old
    assert 'vergence=' not in (bag / 'metadata.yaml').read_text()
    with pytest.raises(SystemExit) as e:                       # argparse's check, as one line (cli_options)
        fixego(['sim', *ARGS, '--out', str(tmp_path / 'bad'), '--vergence', 'sometimes'])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count('\n') == 1 and err.startswith('fixego sim: ') and 'sometimes' in err
    with pytest.raises(SystemExit) as e:                       # replaced by --vergence
        fixego(['sim', *ARGS, '--out', str(tmp_path / 'bad'), '--vergence-std', '0.01'])
    assert e.value.code == 2 and '--vergence-std' in capsys.readouterr().err
    assert not (tmp_path / 'bad').exists()
