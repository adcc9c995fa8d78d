"""``fixego record``: the storage core alone (threads, flushing, errors), the recorder node over real DDS
(private domain), and the command as a process stopped with Ctrl-C. Bags are read back with
:class:`fixego_ros.bags.reader.Bag` and checked message by message against what rclpy serialises."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from fixego_ros.bags.reader import Bag, BagError
from fixego_ros.bags.recorder import BagRecorder, RecordError

QOS_RELIABLE = {'history': 'unknown', 'depth': 0, 'reliability': 'reliable', 'durability': 'volatile',
                'deadline': {'sec': 0, 'nsec': 0}, 'lifespan': {'sec': 0, 'nsec': 0}, 'liveliness': 'automatic',
                'liveliness_lease_duration': {'sec': 0, 'nsec': 0}, 'avoid_ros_namespace_conventions': False}


def wait_for(predicate, timeout_s: float, step_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return bool(predicate())


def messages_in(path: Path) -> int:
    """Messages readable from ``path`` right now (0 while the file does not exist yet)."""
    try:
        return sum(1 for _ in Bag(path).messages())
    except BagError:
        return 0


@pytest.fixture(scope='module')
def store():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def string_cdr(store, text: str) -> bytes:
    return bytes(store.serialize_cdr(store.types['std_msgs/msg/String'](data=text), 'std_msgs/msg/String'))


def canonical(store, data: bytes, msgtype: str) -> bytes:
    """CDR re-encoded by rosbags: zeroed alignment padding, no trailing bytes (little-endian CDR only)."""
    assert data[:4] == b'\x00\x01\x00\x00'
    msgdef = store.get_msgdef(msgtype)
    fields, _ = msgdef.deserialize_cdr_le(bytes(data)[4:], 0, msgdef.cls, store)
    return bytes(store.serialize_cdr(fields, msgtype))


def same_bytes(recorded: bytes, sent: bytes) -> bool:
    """Byte-identical, allowing the zero padding to a 4-byte multiple DDS adds to a payload between processes."""
    extra = bytes(recorded[len(sent):])
    return bytes(recorded[:len(sent)]) == sent and len(extra) < 4 and extra == bytes(len(extra))


# ---------------------------------------------------------------------------------------------- BagRecorder
def test_recorder_is_ros_free(tmp_path):
    code = ('import sys\nfrom fixego_ros.bags.recorder import BagRecorder\n'
            f'r = BagRecorder({str(tmp_path / "bag")!r})\nr.add_topic("/a", "std_msgs/msg/String", [])\n'
            'r.put("/a", 1, bytes(12))\nassert r.close().ok\n'
            'assert "rclpy" not in sys.modules, "rclpy imported"')
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


def test_recorder_concurrent_puts_are_all_written(tmp_path, store):
    rec = BagRecorder(tmp_path / 'bag', flush_period_s=0.05)
    assert rec.add_topic('/a', 'std_msgs/msg/String', [QOS_RELIABLE]) == ''
    rec.add_topic('/b', 'std_msgs/msg/String', [dict(QOS_RELIABLE, reliability='best_effort')])
    n_threads, n = 4, 400
    payload = {(k, i): string_cdr(store, f'thread {k} message {i}') for k in range(n_threads) for i in range(n)}
    start = threading.Barrier(n_threads)

    def worker(k: int) -> None:
        start.wait()
        for i in range(n):
            rec.put('/a' if k % 2 == 0 else '/b', 1_000_000 + k * n + i, payload[(k, i)])

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(n_threads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    summary = rec.close()
    assert summary.ok, summary.line()
    assert (summary.received, summary.written, summary.dropped) == (n_threads * n, n_threads * n, 0)
    assert {k: (c.received, c.written) for k, c in summary.topics.items()} == {'/a': (2 * n, 2 * n),
                                                                                 '/b': (2 * n, 2 * n)}
    with pytest.raises(RecordError, match='closed'):
        rec.put('/a', 0, payload[(0, 0)])
    assert rec.close().written == n_threads * n          # idempotent

    bag = Bag(tmp_path / 'bag')
    assert {name: t.count for name, t in bag.topics.items()} == {'/a': 2 * n, '/b': 2 * n}
    assert bag.topics['/b'].qos[0]['reliability'] == 'best_effort'
    got = [(m.topic, m.log_time_ns, m.data) for m in bag.messages()]
    assert bag.report.lines() == []
    # every message exactly once, each thread's messages in the order it put them
    assert sorted(d for _, _, d in got) == sorted(payload.values())
    for k in range(n_threads):
        mine = [t for _, t, _ in got if 1_000_000 + k * n <= t < 1_000_000 + (k + 1) * n]
        assert mine == sorted(mine) and len(mine) == n
    assert bag.decode(next(iter(bag.messages(['/a'])))).data.startswith('thread ')


def test_recorder_flushes_a_readable_prefix_while_recording(tmp_path, store):
    """What a SIGKILLed recorder leaves: the .mcap file without summary, holding every flushed message."""
    rec = BagRecorder(tmp_path / 'bag', flush_period_s=0.1)
    rec.add_topic('/a', 'std_msgs/msg/String', [QOS_RELIABLE])
    for i in range(25):
        rec.put('/a', 1000 + i, string_cdr(store, f'm{i}'))
    mcap = tmp_path / 'bag' / 'bag.mcap'
    try:
        assert wait_for(lambda: messages_in(mcap) == 25, 10.0), rec.summary().line()
        assert not (tmp_path / 'bag' / 'metadata.yaml').exists()
        assert rec.summary().flushing
    finally:
        rec.close()
    assert messages_in(tmp_path / 'bag') == 25


def test_recorder_refuses_what_it_cannot_record(tmp_path, store):
    (tmp_path / 'old').mkdir()
    with pytest.raises(RecordError, match='exists already'):
        BagRecorder(tmp_path / 'old')
    rec = BagRecorder(tmp_path / 'bag')
    try:
        with pytest.raises(RecordError, match='unknown to the rosbags Jazzy type store'):
            rec.add_topic('/x', 'no_such_msgs/msg/Thing', [])
        with pytest.raises(RecordError, match='before add_topic'):
            rec.put('/x', 0, b'')
        rec.add_topic('/a', 'std_msgs/msg/String', [], type_hash='RIHS01_' + '0' * 64)   # a foreign hash: noted
        with pytest.raises(RecordError, match='twice'):
            rec.add_topic('/a', 'std_msgs/msg/String', [])
    finally:
        summary = rec.close()
    assert summary.ok and summary.written == 0
    assert Bag(tmp_path / 'bag').topics['/a'].type_hash == 'RIHS01_' + '0' * 64


# ---------------------------------------------------------------------------------------------- node over DDS
def received(node, topics) -> int:
    """Fewest messages the recorder node has received on any of ``topics``."""
    counts = node.recorder.summary().topics
    return min(counts[t].received if t in counts else 0 for t in topics)


def test_node_records_what_is_published(ros_context, tmp_path, store):
    rclpy = pytest.importorskip('rclpy')
    import numpy as np
    from conftest import executor_for, spin_until
    from diagnostic_msgs.msg import DiagnosticArray
    from mcap.reader import make_reader
    from rclpy.parameter import Parameter
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from fixego_ros.nodes.bag_recorder import BagRecorderNode
    from fixego_ros.nodes.common import RELIABLE_QOS, SENSOR_QOS, array_to_image, sec_to_stamp

    n = 30
    bag = tmp_path / 'bag'
    peer = rclpy.create_node('peer', context=ros_context)
    pub_img = peer.create_publisher(Image, '/test/image', SENSOR_QOS)
    pub_str = peer.create_publisher(String, '/test/chatter', RELIABLE_QOS)
    diags: list[DiagnosticArray] = []
    peer.create_subscription(DiagnosticArray, '/diagnostics', diags.append, RELIABLE_QOS)
    node = BagRecorderNode(context=ros_context, parameter_overrides=[     # no topic list: every topic
        Parameter('bag', value=str(bag)), Parameter('discovery_period_s', value=0.1),
        Parameter('diagnostics_period_s', value=0.2)])
    ex = executor_for(ros_context, node, peer)
    try:
        assert spin_until(ex, lambda: pub_img.get_subscription_count() and pub_str.get_subscription_count(), 10.0)
        sent: dict[str, list[bytes]] = {'/test/image': [], '/test/chatter': []}
        t0 = node.get_clock().now().nanoseconds
        rng = np.random.default_rng(0)
        for i in range(n):
            img = array_to_image(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8), sec_to_stamp(100 + i / 30), 'cam')
            text = String(data=f'hello {i}')
            pub_img.publish(img)
            pub_str.publish(text)
            sent['/test/image'].append(serialize_message(img))
            sent['/test/chatter'].append(serialize_message(text))
            # lock-step, so the best-effort images are not lost to a full queue
            assert spin_until(ex, lambda i=i: received(node, sent) > i, 5.0), f'message {i} not received'
        t1 = node.get_clock().now().nanoseconds
        assert spin_until(ex, lambda: any(kv.key == 'written' and int(kv.value) > 0
                                          for d in diags for s in d.status for kv in s.values), 5.0)
        summary = node.stop()
    finally:
        node.destroy_node()
        peer.destroy_node()
        ex.shutdown(timeout_sec=1.0)

    assert summary.ok, summary.line()
    for name in sent:
        c = summary.topics[name]
        assert (c.received, c.written, c.dropped) == (n, n, 0), name

    b = Bag(bag)
    got = {name: [m for m in b.messages([name])] for name in sent}
    assert b.report.lines() == []
    # String has no inner alignment padding: byte-identical. Image has some, which Fast-CDR leaves
    # uninitialised (serialize_message and the publisher fill it differently): identical up to those bytes.
    assert len(got['/test/chatter']) == n
    assert all(same_bytes(m.data, d) for m, d in zip(got['/test/chatter'], sent['/test/chatter'], strict=True))
    for name, msgtype in (('/test/image', 'sensor_msgs/msg/Image'), ('/test/chatter', 'std_msgs/msg/String')):
        assert [canonical(store, m.data, msgtype) for m in got[name]] == \
            [canonical(store, d, msgtype) for d in sent[name]], f'{name}: recorded bytes differ from rclpy\'s'
        assert [deserialize_message(m.data, Image if 'image' in name else String) for m in got[name]] == \
            [deserialize_message(d, Image if 'image' in name else String) for d in sent[name]]
    for name in sent:
        times = [m.log_time_ns for m in got[name]]
        assert times == sorted(times) and t0 <= times[0] and times[-1] <= t1   # receive time, node clock
    assert b.decode(got['/test/chatter'][7]).data == 'hello 7'
    assert b.decode(got['/test/image'][0]).encoding == 'rgb8'

    # offered QoS and type hashes of the publishers, counts in metadata.yaml
    assert b.topics['/test/chatter'].qos[0]['reliability'] == 'reliable'
    assert b.topics['/test/image'].qos[0]['reliability'] == 'best_effort'
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['storage_identifier'] == 'mcap'
    listed = {t['topic_metadata']['name']: t for t in meta['topics_with_message_count']}
    for name, msgtype in (('/test/image', 'sensor_msgs/msg/Image'), ('/test/chatter', 'std_msgs/msg/String')):
        assert listed[name]['message_count'] == n
        assert listed[name]['topic_metadata']['type'] == msgtype
        assert listed[name]['topic_metadata']['type_description_hash'].startswith('RIHS01_')
    with (bag / meta['relative_file_paths'][0]).open('rb') as f:
        assert make_reader(f).get_summary().chunk_indexes[0].compression == 'zstd'


# ---------------------------------------------------------------------------------------------- the command
def _cli(*args: str) -> list[str]:
    return [sys.executable, '-m', 'fixego_ros.cli', 'record', *args]


def test_cli_refuses_an_existing_bag_dir(tmp_path):
    proc = subprocess.run(_cli(str(tmp_path), '/x'), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and 'exists already' in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_cli_records_until_ctrl_c(ros_context, tmp_path):
    rclpy = pytest.importorskip('rclpy')
    from conftest import executor_for, private_domain_id, spin_until
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from fixego_ros.nodes.common import RELIABLE_QOS

    k = 20
    bag = tmp_path / 'bag'
    env = dict(os.environ, ROS_DOMAIN_ID=str(private_domain_id()), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    proc = subprocess.Popen(_cli(str(bag), '/test/cli', '--quiet'), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    peer = rclpy.create_node('cli_peer', context=ros_context)
    pub = peer.create_publisher(String, '/test/cli', RELIABLE_QOS)
    other = peer.create_publisher(String, '/test/not_recorded', RELIABLE_QOS)
    ex = executor_for(ros_context, peer)
    try:
        assert spin_until(ex, lambda: pub.get_subscription_count() > 0 or proc.poll() is not None, 30.0)
        assert proc.poll() is None, proc.communicate()
        sent = []
        for i in range(k):
            msg = String(data=f'cli {i}')
            pub.publish(msg)
            other.publish(msg)
            sent.append(serialize_message(msg))
        # the recorder flushes its chunk every second: wait until all k are on disk, then Ctrl-C
        assert spin_until(ex, lambda: messages_in(bag / 'bag.mcap') >= k, 15.0, step_s=0.1)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        peer.destroy_node()
        ex.shutdown(timeout_sec=1.0)

    assert proc.returncode == 0, err
    assert len(out.strip().splitlines()) == 1, out
    line = out.strip()
    m = re.search(r'received (\d+), written (\d+), dropped (\d+)', line)
    assert m is not None, line
    received, written, dropped = map(int, m.groups())
    assert (received, written, dropped) == (k, k, 0), line
    assert f'/test/cli {k}' in line and str(bag) in line and re.search(r'\d+(\.\d)? (B|KiB|MiB)', line)

    b = Bag(bag)
    assert list(b.topics) == ['/test/cli']
    got = [m.data for m in b.messages()]
    assert len(got) == k and all(same_bytes(r, s) for r, s in zip(got, sent, strict=True))
    assert b.report.lines() == [] and b.topics['/test/cli'].count == written


def test_cli_duration_in_process_with_nothing_to_record(tmp_path, capsys):
    pytest.importorskip('rclpy')
    from conftest import private_domain_id

    from fixego_ros.cli import main

    t = time.monotonic()
    assert main(['record', str(tmp_path / 'bag'), '/test/silent', '--duration', '0.5', '--quiet',
                 '--domain-id', str(private_domain_id())]) == 0
    assert time.monotonic() - t < 10
    line = capsys.readouterr().out.strip()
    assert 'received 0, written 0, dropped 0' in line and 'no topic recorded' in line
    b = Bag(tmp_path / 'bag')
    assert b.topics == {} and list(b.messages()) == []
