"""bag_player: play a rosbag2/MCAP bag on its recorded topics, without ``ros2 bag`` (not in the PyPI ROS).

Messages are published as the CDR bytes stored in the bag (no decode/encode), each topic with the QoS
its publishers offered when recorded (:func:`~fixego_ros.bags.player.qos_from_profiles`), at the times
of :class:`~fixego_ros.bags.player.Schedule` (rate, loop, start offset, out-of-order stamps). A dedicated
thread publishes, waiting on an event in bounded steps so shutdown stops it at once; the executor only
runs the diagnostics timer. With ``publish_clock`` every message is preceded by a rosgraph_msgs/Clock on
``/clock`` carrying its bag time, so other nodes can run with ``use_sim_time``.

Damaged bags play what can be read (:mod:`fixego_ros.bags.reader`); topics whose message package is not
installed are skipped with one warning. At the end (not looping) the node logs one summary line, publishes
a final ``/diagnostics`` status, and ``main`` returns 0. A bag that cannot be opened or a bad parameter
(:data:`fixego_ros.pipeline.params.BAG_PLAYER_PARAMS`: checked at start, all read-only) gives one error
line on stderr and exit code 2.
"""

from __future__ import annotations

import importlib
import itertools
import sys
import threading
import time
from collections import Counter

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from fixego_ros.bags.player import PlayError, PlayItem, PlayQos, Schedule, play, qos_from_profiles
from fixego_ros.bags.reader import Bag, BagError
from fixego_ros.nodes.common import (
    ERROR,
    OK,
    RELIABLE_QOS,
    SETUP_ERRORS,
    WARN,
    OnceLogger,
    declare_parameters,
    diagnostic_status,
    publish_diagnostics,
    spin_node,
)
from fixego_ros.pipeline.params import BAG_PLAYER_PARAMS

PARAMS = BAG_PLAYER_PARAMS

# rosbag2's ClockQoS: the newest time only, best effort (matches rclpy's and rclcpp's /clock subscriptions)
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)


def to_qos_profile(q: PlayQos) -> QoSProfile:
    """rclpy profile of the neutral :class:`PlayQos`."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=q.depth,
                      reliability=ReliabilityPolicy.RELIABLE if q.reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if q.transient_local else DurabilityPolicy.VOLATILE)


def message_class(msgtype: str) -> type:
    """Python class of 'pkg/msg/Name'; ImportError or ValueError when it cannot be had."""
    parts = msgtype.split('/')
    if len(parts) != 3 or not all(parts):
        raise ValueError(f'malformed message type {msgtype!r}')
    module = importlib.import_module(f'{parts[0]}.{parts[1]}')
    try:
        return getattr(module, parts[2])
    except AttributeError:
        raise ImportError(f'{parts[0]}.{parts[1]} has no {parts[2]}') from None


def parse_remaps(rules: list[str]) -> dict[str, str]:
    out = {}
    for rule in rules:
        src, sep, dst = rule.partition(':=')
        if not sep or not src.strip() or not dst.strip():
            raise PlayError(f"remap rule {rule!r} is not 'FROM:=TO'")
        out[src.strip()] = dst.strip()
    return out


class BagPlayer(Node):
    """Publishes a bag's messages on their topics at their recorded pace."""

    def __init__(self, **kwargs) -> None:
        super().__init__('bag_player', **kwargs)
        g = declare_parameters(self, PARAMS)
        g.start(lambda changes, getter: None, ())      # every parameter is read-only: one playback per node

        def array(name: str) -> list[str]:
            return [str(x) for x in g(name) or []]

        if not str(g('bag')):
            raise PlayError('no bag given (parameter bag:=PATH)')
        self.bag = Bag(str(g('bag')))
        self.topics = [t for t in array('topics') if t]
        self.remap = parse_remaps(array('remap'))
        self.schedule = Schedule(self.bag, float(g('rate')), self.topics or None, bool(g('loop')),
                                 float(g('start_offset_s')))
        self.start_delay_s = float(g('start_delay_s'))
        self.ack_timeout_s = float(g('ack_timeout_s'))
        self.once = OnceLogger(self)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE_QOS)
        self.pub_clock = self.create_publisher(Clock, '/clock', CLOCK_QOS) if g('publish_clock') else None
        self.publishers_by_topic: dict[str, object] = {}
        self.skipped_topics: dict[str, str] = {}      # topic -> why it is not played
        self.played: Counter[str] = Counter()
        self.skipped: Counter[str] = Counter()
        self.max_late_s = 0.0
        self.finished = False                         # set by the playback thread when it is done
        self._ended = False                           # the final status is out: no more periodic ones
        self.exit_code = 0
        self.summary = ''
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._t_start = 0.0                           # monotonic time of due_s = 0, set when the thread starts

        # Read up to the first played message, so that every channel recorded before it (with rosbag2
        # and rosbags writers: all of them) is known even in a bag without summary, and create all the
        # publishers now: subscribers then have start_delay_s to discover them before the first message.
        self._items = iter(self.schedule)
        first = next(self._items, None)
        for name in list(self.bag.topics):
            if self.topics and name not in self.topics:
                continue
            self._publisher(name)
        missing = [t for t in self.topics if self.bag.topics and t not in self.bag.topics]
        if missing:
            self.get_logger().warning(f'not in the bag (yet): {", ".join(missing)}')
        if first is not None:
            self._items = itertools.chain([first], self._items)
        self.create_timer(float(g('diagnostics_period_s')), self._publish_diagnostics)
        self.get_logger().info(
            f'playing {self.bag.path} ({len(self.publishers_by_topic)} topics, rate '
            f'{"max" if self.schedule.as_fast_as_possible else f"{self.schedule.rate:g}"}'
            f'{", loop" if self.schedule.loop else ""}{", /clock" if self.pub_clock else ""}) '
            f'in {self.start_delay_s:g} s')
        self._thread = threading.Thread(target=self._run, name='bag_player', daemon=True)
        self._t_start = time.monotonic() + self.start_delay_s
        self._thread.start()

    # -------------------------------------------------------------------------------------- publishers
    def _publisher(self, topic: str):
        """The topic's publisher, created on first use; None (after one warning) when it cannot be played."""
        with self._lock:
            if topic in self.publishers_by_topic:
                return self.publishers_by_topic[topic]
            if topic in self.skipped_topics:
                return None
            info = self.bag.topics.get(topic)
            why = ''
            if info is None:
                why = 'unknown channel'
            elif info.serialization != 'cdr':
                why = f'serialization {info.serialization!r}, not cdr'
            else:
                try:
                    cls = message_class(info.msgtype)
                except (ImportError, ValueError) as e:
                    why = f'{info.msgtype} not available in Python ({e})'
            if why:
                self.skipped_topics[topic] = why
                self.once.warn(f'skip {topic}', f'{topic}: not played: {why}')
                return None
            pub = self.create_publisher(cls, self.remap.get(topic, topic), to_qos_profile(qos_from_profiles(info.qos)))
            self.publishers_by_topic[topic] = pub
            return pub

    # -------------------------------------------------------------------------------------- playback
    def _publish(self, item: PlayItem) -> None:
        m = item.msg
        pub = self._publisher(m.topic)
        if pub is None:
            self.skipped[m.topic] += 1
            return
        self.max_late_s = max(self.max_late_s, time.monotonic() - self._t_start - item.due_s)
        if self.pub_clock is not None:
            clock = Clock()
            clock.clock.sec, clock.clock.nanosec = divmod(item.clock_ns, 1_000_000_000)
            self.pub_clock.publish(clock)
        pub.publish(m.data if isinstance(m.data, bytes) else bytes(m.data))
        self.played[m.topic] += 1

    def _run(self) -> None:
        """Playback thread: publish everything at its due time, then wait for acks and summarise."""
        try:
            if not play(self._items, self._publish, self._t_start, time.monotonic, self._stop.wait):
                return
            self._wait_for_acks()
            self._finish()
        except Exception as e:  # the thread must end in a state main() can report
            if self._stop.is_set() or not self.context.ok():
                return                                    # shut down while publishing: not an error
            self.summary = f'playback failed: {type(e).__name__}: {e}'
            self.get_logger().error(self.summary)
            self.exit_code = 1
            self._ended = True
            publish_diagnostics(self, self.pub_diag, [self._status(ERROR, self.summary)])
        finally:
            self.finished = True

    def _wait_for_acks(self) -> None:
        """Reliable subscribers get the last messages before we exit (bounded by ack_timeout_s in total)."""
        deadline = time.monotonic() + self.ack_timeout_s
        for pub in list(self.publishers_by_topic.values()):
            left = deadline - time.monotonic()
            if left <= 0 or self._stop.is_set():
                break
            if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                self.once.warn('acks', f'{pub.topic_name}: not every subscriber acknowledged within '
                                       f'{self.ack_timeout_s:g} s')

    def _summary_line(self) -> str:
        st = self.schedule.stats
        wall = max(0.0, time.monotonic() - self._t_start)
        per_topic = ', '.join(f'{t} {n}' for t, n in sorted(self.played.items())) or 'none'
        parts = [f'played {sum(self.played.values())} messages in {wall:.1f} s ({per_topic})']
        if self.skipped:
            parts.append('skipped ' + ', '.join(f'{t} {n} ({self.skipped_topics.get(t, "?")})'
                                                for t, n in sorted(self.skipped.items())))
        parts.append(f'non-monotonic log times {st.non_monotonic}')
        if st.loops_completed:
            parts.append(f'loops {st.loops_completed}')
        if st.before_offset:
            parts.append(f'{st.before_offset} before the start offset')
        parts += self.bag.report.lines()
        return '; '.join(parts)

    def _finish(self) -> None:
        self._ended = True
        self.summary = self._summary_line()
        self.get_logger().info(self.summary)
        report = self.bag.report
        if report.corrupt:
            self.get_logger().error(report.corrupt_line())
            self.exit_code = 2           # played what was intact, but the recording is damaged: say so on exit
        problems = (['bag corrupt'] if report.corrupt else ['bag truncated'] if report.truncated else []) + \
            (['topics skipped'] if self.skipped else [])
        level, text = (WARN, f'finished ({", ".join(problems)})') if problems else (OK, 'finished')
        publish_diagnostics(self, self.pub_diag, [self._status(level, text)])

    # -------------------------------------------------------------------------------------- diagnostics
    def _status(self, level, message: str):
        # runs in the executor while the playback thread adds keys: iterate C-level copies only
        st = self.schedule.stats
        topics = dict(self.bag.topics)
        counts = [t.count for name, t in topics.items() if not self.topics or name in self.topics]
        expected = sum(counts) if counts and all(c is not None for c in counts) else None
        values: dict[str, object] = {
            'bag': str(self.bag.path), 'played': sum(dict(self.played).values()),
            'skipped': sum(dict(self.skipped).values()),
            'expected_per_pass': expected if expected is not None else 'unknown',
            'non_monotonic': st.non_monotonic, 'loops_completed': st.loops_completed,
            'bag_time_s': f'{st.bag_time_ns * 1e-9:.3f}' if st.bag_time_ns is not None else '-',
            'max_late_ms': f'{self.max_late_s * 1e3:.1f}',
            'skipped_topics': ', '.join(sorted(dict(self.skipped_topics))),
            'truncated': self.bag.report.truncated or 'no', 'corrupt': self.bag.report.corrupt or 'no'}
        return diagnostic_status('fixego bag_player', 'bag_player', level, message, values)

    def _publish_diagnostics(self) -> None:
        if self._ended:
            return
        skipped = sorted(dict(self.skipped_topics))
        if time.monotonic() < self._t_start:
            level, text = OK, 'waiting for the start delay'
        elif skipped:
            level, text = WARN, f'playing; not played: {", ".join(skipped)}'
        else:
            level, text = OK, 'playing'
        publish_diagnostics(self, self.pub_diag, [self._status(level, text)])

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop playback and join the thread (bounded)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def destroy_node(self) -> None:
        self.stop()
        super().destroy_node()


def run(args: list[str] | None = None, overrides: list[Parameter] | None = None, domain_id: int | None = None,
        prog: str = 'bag_player') -> int:
    """Init rclpy, play until the bag ends (or Ctrl-C), shut down; the exit code (0, 1 failure, 2 setup)."""
    try:
        node = spin_node(lambda: BagPlayer(parameter_overrides=overrides or []), args,
                         finished=lambda n: n.finished, domain_id=domain_id, images=True)
    except (BagError, PlayError, *SETUP_ERRORS) as e:
        print(f'{prog}: {e}', file=sys.stderr)
        return 2
    return node.exit_code if node is not None else 0


def main(args: list[str] | None = None) -> int:
    return run(args)


if __name__ == '__main__':
    sys.exit(main())
