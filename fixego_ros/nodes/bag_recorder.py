"""bag_recorder: record topics into a rosbag2/MCAP bag, the way ``ros2 bag record`` does (ros2cli and
rosbag2 are not available as wheels).

Every ``discovery_period_s`` the graph is scanned; each wanted topic (``topics``, or every topic when
empty, hidden ones only with ``include_hidden``) is subscribed once a publisher is known, *raw* (the CDR
bytes are written untouched), with a QoS adapted to the publishers like rosbag2: reliable only if every
publisher is reliable, transient-local only if every publisher is. The publishers' offered QoS profiles
and RIHS01 type hash go into the bag. The log time of a message is its receive time on the node clock.
Storage is :class:`fixego_ros.bags.recorder.BagRecorder` (a writer thread, so callbacks never wait on
the disk). Publishes nothing but ``/diagnostics`` (received / written / dropped counts). Parameters
(:data:`fixego_ros.pipeline.params.BAG_RECORDER_PARAMS`) are checked at start and all read-only.
"""

from __future__ import annotations

import importlib
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.expand_topic_name import expand_topic_name
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.topic_or_service_is_hidden import topic_or_service_is_hidden

from fixego_ros.bags.recorder import BagRecorder, RecordError, RecordSummary
from fixego_ros.nodes.common import (
    ERROR,
    OK,
    RELIABLE_QOS,
    WARN,
    OnceLogger,
    declare_parameters,
    diagnostic_status,
    publish_diagnostics,
    run_node,
)
from fixego_ros.pipeline.params import BAG_RECORDER_PARAMS

PARAMS = BAG_RECORDER_PARAMS


def _duration_dict(d) -> dict[str, int]:
    ns = int(d.nanoseconds)
    return {'sec': ns // 1_000_000_000, 'nsec': ns % 1_000_000_000}


def qos_dict(q: QoSProfile) -> dict:
    """A publisher's offered QoS as rosbag2 (bag version 9) writes it in ``offered_qos_profiles``."""
    return {'history': q.history.name.lower(), 'depth': int(q.depth), 'reliability': q.reliability.name.lower(),
            'durability': q.durability.name.lower(), 'deadline': _duration_dict(q.deadline),
            'lifespan': _duration_dict(q.lifespan), 'liveliness': q.liveliness.name.lower(),
            'liveliness_lease_duration': _duration_dict(q.liveliness_lease_duration),
            'avoid_ros_namespace_conventions': bool(q.avoid_ros_namespace_conventions)}


def adapted_qos(offered: list[QoSProfile], depth: int) -> QoSProfile:
    """Subscription QoS compatible with every publisher (rosbag2's rule), keep-last ``depth``."""
    reliable = bool(offered) and all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = bool(offered) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def message_class(msgtype: str):
    """Python class of 'pkg/msg/Name'; ImportError / AttributeError / ValueError when unavailable."""
    pkg, kind, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{pkg}.{kind}'), name)


class BagRecorderNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__('bag_recorder', **kwargs)
        g = declare_parameters(self, PARAMS)
        g.start(lambda changes, getter: None, ())      # every parameter is read-only: one recording per node
        wanted = [str(t) for t in g('topics') or [] if str(t)]
        self.wanted = {expand_topic_name(t, self.get_name(), self.get_namespace()) for t in wanted}
        self.include_hidden = bool(g('include_hidden'))
        self.depth = int(g('depth'))
        bag = str(g('bag')) or time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S')
        self.recorder = BagRecorder(bag, compression=bool(g('compression')),
                                    flush_period_s=float(g('flush_period_s')))
        self.once = OnceLogger(self)
        self.subs: dict[str, object] = {}
        self.reliable: dict[str, bool] = {}     # topic -> subscribed reliably
        self.skipped: set[str] = set()           # topics we will never record (type unavailable)
        self._summary: RecordSummary | None = None
        self._timers = [self.create_timer(float(g('discovery_period_s')), self.scan)]
        period = float(g('diagnostics_period_s'))
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE_QOS) if period > 0 else None
        if period > 0:
            self._timers.append(self.create_timer(period, self._publish_diagnostics))
        what = ', '.join(sorted(self.wanted)) if self.wanted else 'every topic'
        self.get_logger().info(f'recording {what} to {self.recorder.path}')
        self.scan()

    # -------------------------------------------------------------------------------------- discovery
    def scan(self) -> None:
        """Subscribe to wanted topics that have a publisher now; warn about publishers we cannot hear."""
        if self._summary is not None:
            return
        for name, types in self.get_topic_names_and_types():
            if name in self.skipped:
                continue
            if name in self.subs:
                self._check_late_publishers(name)
                continue
            if self.wanted and name not in self.wanted:
                continue
            if not self.wanted and not self.include_hidden and topic_or_service_is_hidden(name):
                continue
            if len(types) != 1:
                self.once.warn(f'types:{name}', f'{name}: published with several types {types}; not recorded '
                                                f'until only one is left')
                continue
            infos = self.get_publishers_info_by_topic(name)
            if infos:                       # no publisher yet: its QoS decides ours, wait for one
                self._subscribe(name, types[0], infos)

    def _subscribe(self, name: str, msgtype: str, infos) -> None:
        try:
            cls = message_class(msgtype)
        except (ImportError, AttributeError, ValueError) as e:
            self.skipped.add(name)
            self.once.warn(f'type:{msgtype}', f'{msgtype}: no Python message package ({type(e).__name__}); '
                                              f'topics of this type are not recorded (first: {name})')
            return
        hashes = {str(i.topic_type_hash) for i in infos} - {'INVALID'}
        try:
            note = self.recorder.add_topic(name, msgtype, [qos_dict(i.qos_profile) for i in infos],
                                           hashes.pop() if len(hashes) == 1 else '')
        except RecordError as e:
            self.skipped.add(name)
            self.once.warn(f'topic:{name}', str(e))
            return
        if note:
            self.once.warn(f'hash:{name}', note)
        qos = adapted_qos([i.qos_profile for i in infos], self.depth)
        self.reliable[name] = qos.reliability == ReliabilityPolicy.RELIABLE
        self.subs[name] = self.create_subscription(cls, name, lambda data, t=name: self._on_message(t, data), qos,
                                                   raw=True)
        self.get_logger().info(f'recording {name} [{msgtype}, {qos.reliability.name.lower()}, '
                               f'{qos.durability.name.lower()}]')

    def _check_late_publishers(self, name: str) -> None:
        """A best-effort publisher joining a topic we subscribed reliably is not heard: say so, once."""
        if not self.reliable.get(name):
            return
        infos = self.get_publishers_info_by_topic(name)
        if any(i.qos_profile.reliability != ReliabilityPolicy.RELIABLE for i in infos):
            self.once.warn(f'late:{name}', f'{name}: a best-effort publisher joined after the topic was subscribed '
                                           f'reliably; its messages are not recorded')

    # -------------------------------------------------------------------------------------- messages
    def _on_message(self, topic: str, data: bytes) -> None:
        try:
            self.recorder.put(topic, self.get_clock().now().nanoseconds, data)
        except RecordError as e:
            self.once.error('put', f'message not recorded: {e}')

    # -------------------------------------------------------------------------------------- end
    def stop(self) -> RecordSummary:
        """Stop subscribing and close the bag (idempotent); the final counts."""
        if self._summary is None:
            for timer in self._timers:
                self.destroy_timer(timer)
            for sub in self.subs.values():
                self.destroy_subscription(sub)
            self._summary = self.recorder.close()
            if self._summary.error:
                self.get_logger().error(f'bag {self._summary.path}: {self._summary.error}')
        return self._summary

    def destroy_node(self) -> None:
        self.stop()
        super().destroy_node()

    def _publish_diagnostics(self) -> None:
        s = self.recorder.summary()
        level, message = OK, f'recording {len(s.topics)} topics'
        if s.error:
            level, message = ERROR, s.error
        elif not s.topics:
            level, message = WARN, 'no topic to record yet'
        values = {'bag': str(s.path), 'topics': len(s.topics), 'received': s.received, 'written': s.written,
                  'dropped': s.dropped - s.pending, 'pending': s.pending, 'bytes': s.bytes}
        values.update({f'written {k}': v.written for k, v in sorted(s.topics.items())})
        publish_diagnostics(self, self.pub_diag, [diagnostic_status('fixego bag_recorder', 'bag_recorder', level,
                                                                    message, values)])


def main(args: list[str] | None = None) -> int:
    return run_node(BagRecorderNode, 'bag_recorder', args)


if __name__ == '__main__':
    sys.exit(main())
