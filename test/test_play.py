"""``fixego play`` / ``bag_player``: the playback schedule without ROS (fake clock), then real DDS playback
of a small rosbags-written bag (intact and cut), and the CLI's exit codes as a subprocess."""

from __future__ import annotations

import itertools
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import executor_for, private_domain_id, spin_until

from fixego_ros.bags.player import PlayError, PlayItem, PlayQos, Schedule, play, qos_from_profiles
from fixego_ros.bags.reader import Bag, BagMessage

NS = 1_000_000_000


# ---------------------------------------------------------------------------------------------- ROS-free
class FakeBag:
    """Yields the given (topic, log time in s) pairs as messages, like Bag.messages()."""

    def __init__(self, pairs: list[tuple[str, float]]) -> None:
        self.msgs = [BagMessage(t, 'std_msgs/msg/String', round(s * NS), f'{t}@{s}'.encode()) for t, s in pairs]

    def messages(self, topics=None):
        yield from self.msgs


class FakeClock:
    """Monotonic time that only moves when playback waits."""

    def __init__(self, t: float = 100.0, stop_after: int | None = None) -> None:
        self.t, self.waits, self.stop_after = t, [], stop_after

    def now(self) -> float:
        return self.t

    def wait(self, s: float) -> bool:
        self.waits.append(s)
        self.t += s
        return self.stop_after is not None and len(self.waits) >= self.stop_after


def _due(schedule) -> list[float]:
    return [round(i.due_s, 9) for i in schedule]


def test_schedule_follows_log_times_scaled_by_rate():
    bag = FakeBag([('/a', 10.0), ('/b', 10.1), ('/a', 10.4), ('/b', 11.0)])
    assert _due(Schedule(bag, 1.0)) == [0.0, 0.1, 0.4, 1.0]
    assert _due(Schedule(bag, 2.0)) == [0.0, 0.05, 0.2, 0.5]           # rate 2 halves every gap
    assert _due(Schedule(bag, 0.5)) == [0.0, 0.2, 0.8, 2.0]
    for fast in (0.0, math.inf):                                       # as fast as possible: no waits at all
        s = Schedule(bag, fast)
        assert s.as_fast_as_possible and _due(s) == [0.0] * 4
    assert [i.clock_ns for i in Schedule(bag)] == [m.log_time_ns for m in bag.msgs]
    for bad in (-1.0, math.nan):
        with pytest.raises(PlayError):
            Schedule(bag, bad)
    with pytest.raises(PlayError):
        Schedule(bag, 1.0, start_offset_s=-1)


def test_schedule_topic_filter_and_start_offset():
    bag = FakeBag([('/b', 0.0), ('/a', 0.5), ('/b', 1.0), ('/a', 1.5), ('/a', 2.0)])
    s = Schedule(bag, 1.0, topics=['/a'])
    items = list(s)
    assert [i.msg.topic for i in items] == ['/a'] * 3
    assert [round(i.due_s, 9) for i in items] == [0.0, 1.0, 1.5]     # time origin = first played message
    assert s.stats.filtered_out == 2
    s = Schedule(bag, 1.0, start_offset_s=1.2)                      # offset from the first message of the bag
    assert [m.msg.log_time_ns for m in s] == [round(1.5 * NS), 2 * NS] and s.stats.before_offset == 3
    assert list(Schedule(bag, topics=['/nothing'])) == []


def test_schedule_plays_out_of_order_log_times_in_file_order_without_waiting_backwards():
    bag = FakeBag([('/a', 0.0), ('/a', 0.2), ('/b', 0.1), ('/a', 0.3)])
    s = Schedule(bag, 1.0)
    items = list(s)
    assert [i.msg.log_time_ns for i in items] == [m.log_time_ns for m in bag.msgs]   # file order kept
    assert [round(i.due_s, 9) for i in items] == [0.0, 0.2, 0.2, 0.3]             # the late one goes at once
    assert [i.clock_ns for i in items] == [0, round(0.2 * NS), round(0.2 * NS), round(0.3 * NS)]  # never back
    assert s.stats.non_monotonic == 1


def test_schedule_loop_carries_time_and_clock_on():
    bag = FakeBag([('/a', 5.0), ('/a', 5.1), ('/a', 5.3)])
    s = Schedule(bag, 1.0, loop=True)
    items = list(itertools.islice(s, 7))
    period = 0.3 + 0.15                                              # played span + mean gap
    assert s.stats.period_ns == round(period * NS) and s.stats.loops_completed == 2
    assert [i.loop for i in items] == [0, 0, 0, 1, 1, 1, 2]
    np.testing.assert_allclose([i.due_s for i in items], [0, 0.1, 0.3, 0.45, 0.55, 0.75, 0.9], atol=1e-9)
    assert [i.clock_ns for i in items] == [m.log_time_ns + k * s.stats.period_ns
                                           for k, m in zip([0, 0, 0, 1, 1, 1, 2], bag.msgs * 3, strict=False)]
    assert all(b.clock_ns > a.clock_ns for a, b in itertools.pairwise(items))
    # a single stamp loops on a 1 s period; a filter matching nothing ends instead of spinning
    one = Schedule(FakeBag([('/a', 1.0)]), 1.0, loop=True)
    assert [i.due_s for i in itertools.islice(one, 3)] == [0.0, 1.0, 2.0]
    assert list(Schedule(bag, 1.0, topics=['/x'], loop=True)) == []


def test_play_publishes_at_due_times_on_a_fake_clock_and_stops_promptly():
    bag = FakeBag([('/a', 0.0), ('/a', 0.25), ('/a', 1.0), ('/a', 1.0)])
    clock, at = FakeClock(100.0), []
    assert play(Schedule(bag, 2.0), lambda item: at.append(clock.now()), 100.0, clock.now, clock.wait, 0.1)
    np.testing.assert_allclose(at, [100.0, 100.125, 100.5, 100.5])
    assert max(clock.waits) <= 0.1 + 1e-12                          # bounded waits only
    # a stop request (wait returning True) ends playback without publishing more
    clock, at = FakeClock(100.0, stop_after=3), []
    assert not play(Schedule(bag, 1.0), lambda item: at.append(item), 100.0, clock.now, clock.wait, 0.1)
    assert len(at) == 1
    # a late start publishes everything at once, nothing dropped
    clock, at = FakeClock(200.0), []
    assert play(Schedule(bag, 1.0), at.append, 100.0, clock.now, clock.wait)
    assert len(at) == 4 and clock.t == 200.0
    assert isinstance(at[0], PlayItem)


def test_player_core_and_cli_import_without_rclpy():
    """The schedule is ROS-free, and `fixego play --help` / a bad path must not pay for rclpy."""
    code = ('import sys, fixego_ros.bags.player, fixego_ros.bags.play_cli\n'
            'assert "rclpy" not in sys.modules')
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


def _profile(reliability, durability='volatile', history='keep_last', depth=10) -> dict:
    return {'history': history, 'depth': depth, 'reliability': reliability, 'durability': durability,
            'deadline': {'sec': 0, 'nsec': 0}, 'avoid_ros_namespace_conventions': False}


def test_qos_mapping_from_recorded_profiles():
    assert qos_from_profiles([]) == qos_from_profiles(None) == PlayQos(True, False, 10)
    assert qos_from_profiles([{}]) == PlayQos(True, False, 10)                 # missing keys -> defaults
    assert qos_from_profiles([_profile('reliable', depth=5)]) == PlayQos(True, False, 5)
    assert qos_from_profiles([_profile('best_effort')]) == PlayQos(False, False, 10)
    assert qos_from_profiles([_profile('reliable', 'transient_local', depth=1)]) == PlayQos(True, True, 1)
    assert qos_from_profiles([_profile('system_default', 'unknown', 'system_default', 0)]) == PlayQos()
    # Humble-era metadata stores rmw enum values: 1 reliable / 2 best effort; 1 transient local / 2 volatile
    assert qos_from_profiles([_profile(2, 1, 1, 7)]) == PlayQos(False, True, 7)
    # several publishers: best effort if any was, transient local only if all were, the deepest keep-last
    mixed = [_profile('reliable', 'transient_local', depth=3), _profile('best_effort', 'volatile', depth=20)]
    assert qos_from_profiles(mixed) == PlayQos(False, False, 20)
    both_tl = [_profile('reliable', 'transient_local'), _profile('reliable', 'transient_local', 'keep_all', 0)]
    assert qos_from_profiles(both_tl) == PlayQos(True, True, 10)


# ---------------------------------------------------------------------------------------------- a real bag
CHAT, IMAGE = '/fixego_test/chat', '/fixego_test/image'
FRAMES, DT, T0 = 20, 0.1, 1000.0


@pytest.fixture(scope='module')
def bag_dir(tmp_path_factory) -> Path:
    """20 x (a 512x256 mono8 Image, best effort; a String, reliable), 0.1 s apart: ~2.7 MB in 3 MCAP chunks."""
    pytest.importorskip('rclpy')
    from rosbags.typesys import Stores, get_typestore
    from std_msgs.msg import String

    from fixego_ros.bags.mcap_storage import bag_writer
    from fixego_ros.nodes.common import array_to_image, sec_to_stamp
    from fixego_ros.sim.bag_writer import _qos, canonical_cdr

    store = get_typestore(Stores.ROS2_JAZZY)
    out = tmp_path_factory.mktemp('play') / 'bag'
    rng = np.random.default_rng(0)
    with bag_writer(out, compression=False) as w:     # uncompressed chunks, with CRCs, as the recorder writes
        image = w.add_connection(IMAGE, 'sensor_msgs/msg/Image', typestore=store, offered_qos_profiles=[_qos(True)])
        chat = w.add_connection(CHAT, 'std_msgs/msg/String', typestore=store, offered_qos_profiles=[_qos(False)])
        for i in range(FRAMES):
            t = T0 + i * DT
            img = array_to_image(rng.integers(0, 256, (256, 512), dtype=np.uint8), sec_to_stamp(t), 'cam')
            w.write(image, round(t * NS), canonical_cdr(img, 'sensor_msgs/msg/Image', store))
            w.write(chat, round(t * NS) + 1000, canonical_cdr(String(data=f'message {i}'), 'std_msgs/msg/String',
                                                               store))
    return out


def _cut_copy(bag_dir: Path, dest: Path, fraction: float = 0.6) -> Path:
    """The bag as power loss leaves it: .mcap cut short, no metadata.yaml."""
    dest.mkdir()
    (mcap,) = bag_dir.glob('*.mcap')
    data = mcap.read_bytes()
    (dest / mcap.name).write_bytes(data[: int(len(data) * fraction)])
    return dest


class Listener:
    """A node recording raw CDR and receipt time of the test topics, /clock and /diagnostics."""

    def __init__(self, context) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import Image
        from std_msgs.msg import String

        self.node = Node('play_listener', context=context)
        self.chat: list[tuple[float, bytes]] = []
        self.images: list[bytes] = []
        self.clock: list[int] = []
        self.diag: list[str] = []
        best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.node.create_subscription(String, CHAT, lambda b: self.chat.append((time.monotonic(), b)),
                                      QoSProfile(depth=100), raw=True)
        self.node.create_subscription(Image, IMAGE, self.images.append, best_effort, raw=True)
        self.node.create_subscription(Clock, '/clock', lambda m: self.clock.append(m.clock.sec * NS + m.clock.nanosec),
                                      best_effort)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: self.diag.extend(
            s.message for s in m.status if s.name == 'fixego bag_player'), QoSProfile(depth=50))


def _player(context, **params):
    from rclpy.parameter import Parameter

    from fixego_ros.nodes.bag_player import BagPlayer
    return BagPlayer(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])


@pytest.mark.ros
def test_player_publishes_the_bag_over_dds(ros_context, bag_dir):
    expected = [m.data for m in Bag(bag_dir).messages() if m.topic == CHAT]
    listener = Listener(ros_context)
    rate = 2.0
    player = _player(ros_context, bag=str(bag_dir), rate=rate, publish_clock=True, start_delay_s=1.0)
    ex = executor_for(ros_context, listener.node, player)
    try:
        assert spin_until(ex, lambda: player.finished, 30.0), 'playback did not end'
        last_ns = round((T0 + (FRAMES - 1) * DT) * NS) + 1000
        assert spin_until(ex, lambda: len(listener.chat) >= FRAMES and 'finished' in listener.diag
                          and last_ns in listener.clock, 5.0)    # callbacks of different topics run in any order
        assert player.exit_code == 0, player.summary
        # every reliable message arrives, byte-identical, in order
        assert [b for _, b in listener.chat] == expected
        # paced by the stamps: first to last ~ (19 x 0.1 s) / rate, within a generous band
        span = listener.chat[-1][0] - listener.chat[0][0]
        nominal = (FRAMES - 1) * DT / rate
        assert 0.5 * nominal <= span <= 3.0 * nominal, (span, nominal)
        # best-effort images: published all; received (not guaranteed) ones are intact
        assert player.played == {CHAT: FRAMES, IMAGE: FRAMES}
        assert listener.images and all(len(b) > 512 * 256 for b in listener.images)
        # /clock carries the bag time, never backwards, up to the last message
        assert listener.clock and listener.clock == sorted(listener.clock)
        assert listener.clock[-1] == last_ns
        assert f'{CHAT} {FRAMES}' in player.summary and 'non-monotonic log times 0' in player.summary
    finally:
        ex.shutdown()
        player.destroy_node()
        listener.node.destroy_node()


@pytest.mark.ros
def test_player_plays_the_readable_prefix_of_a_cut_bag(ros_context, bag_dir, tmp_path):
    cut = _cut_copy(bag_dir, tmp_path / 'cut')
    reference = Bag(cut)
    expected = [m.data for m in reference.messages() if m.topic == CHAT]
    assert reference.report.truncated and 0 < len(expected) < FRAMES
    listener = Listener(ros_context)
    player = _player(ros_context, bag=str(cut), rate=0.0, topics=[CHAT], start_delay_s=1.0)
    ex = executor_for(ros_context, listener.node, player)
    try:
        assert spin_until(ex, lambda: player.finished, 30.0), 'playback did not end'
        assert spin_until(ex, lambda: len(listener.chat) >= len(expected), 5.0)
        assert player.exit_code == 0, player.summary
        assert [b for _, b in listener.chat] == expected
        assert player.played == {CHAT: len(expected)} and not listener.images     # the topic filter held
        assert 'truncated' in player.summary and 'no metadata.yaml' in player.summary
        assert spin_until(ex, lambda: any('bag truncated' in d for d in listener.diag), 3.0)
    finally:
        ex.shutdown()
        player.destroy_node()
        listener.node.destroy_node()


@pytest.mark.ros
def test_player_skips_types_without_python_package_and_remaps(ros_context, tmp_path):
    from rclpy.qos import QoSProfile
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    from std_msgs.msg import String

    from fixego_ros.nodes.bag_player import parse_remaps
    from fixego_ros.sim.bag_writer import _qos, canonical_cdr

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg('int32 value', 'fixego_missing_msgs/msg/Thing'))
    thing_type = 'fixego_missing_msgs/msg/Thing'
    thing_cls = store.types[thing_type]
    path = tmp_path / 'bag'
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        chat = w.add_connection(CHAT, 'std_msgs/msg/String', typestore=store, offered_qos_profiles=[_qos(False)])
        thing = w.add_connection('/thing', thing_type, typestore=store)
        for i in range(3):
            w.write(thing, (i + 1) * NS, bytes(store.serialize_cdr(thing_cls(value=i), thing_type)))
            w.write(chat, (i + 1) * NS, canonical_cdr(String(data=f'm{i}'), 'std_msgs/msg/String', store))
    from rclpy.node import Node
    got: list[str] = []
    sub = Node('remap_listener', context=ros_context)
    sub.create_subscription(String, '/renamed', lambda m: got.append(m.data), QoSProfile(depth=10))
    player = _player(ros_context, bag=str(path), rate=0.0, remap=[f'{CHAT}:=/renamed'], start_delay_s=0.5)
    ex = executor_for(ros_context, sub, player)
    try:
        assert spin_until(ex, lambda: player.finished and len(got) == 3, 15.0), (player.summary, got)
        assert got == ['m0', 'm1', 'm2'] and player.exit_code == 0
        assert player.played == {CHAT: 3} and player.skipped == {'/thing': 3}
        assert 'skipped /thing 3' in player.summary and 'fixego_missing_msgs' in player.summary
    finally:
        ex.shutdown()
        player.destroy_node()
        sub.destroy_node()
    assert parse_remaps(['/a:=/b', ' /c := /d ']) == {'/a': '/b', '/c': '/d'}
    with pytest.raises(PlayError):
        parse_remaps(['/a'])


# ---------------------------------------------------------------------------------------------- CLI process
def _cli(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return subprocess.run([sys.executable, '-m', 'fixego_ros.cli', 'play', *args], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=Path(__file__).resolve().parents[1])


@pytest.mark.ros
def test_cli_exit_codes(bag_dir, tmp_path):
    proc = _cli(str(tmp_path / 'no_such_bag'))
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and 'no such bag' in lines[0] and 'Traceback' not in proc.stderr, proc.stderr
    not_a_bag = tmp_path / 'empty'
    not_a_bag.mkdir()
    proc = _cli(str(not_a_bag))
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    # a good bag plays to its end and the process exits 0 by itself
    copy = shutil.copytree(bag_dir, tmp_path / 'bag')
    proc = _cli(str(copy), '--rate', '0', '--delay', '0.1', '--clock', '--domain-id', str(private_domain_id() + 2))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f'played {2 * FRAMES} messages' in proc.stdout + proc.stderr


@pytest.mark.ros
def test_cli_plays_the_intact_part_of_a_corrupt_bag_and_exits_2(bag_dir, tmp_path):
    """A flipped bit inside a chunk (the recorder writes chunk CRCs): what precedes it is played, the process
    says the bag is corrupt and exits 2 instead of 0."""
    copy = shutil.copytree(bag_dir, tmp_path / 'bag')
    mcap = next(copy.glob('*.mcap'))
    data = bytearray(mcap.read_bytes())
    data[len(data) * 2 // 5] ^= 0x10
    mcap.write_bytes(bytes(data))
    damaged = Bag(copy)
    assert len(list(damaged.messages())) < 2 * FRAMES and damaged.report.corrupt
    proc = _cli(str(copy), '--rate', '0', '--delay', '0.1', '--domain-id', str(private_domain_id() + 3))
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert 'corrupt' in proc.stdout + proc.stderr and 'Traceback' not in proc.stderr
