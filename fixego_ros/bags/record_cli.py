"""``fixego record BAG_DIR [TOPIC ...]``: record live topics into a rosbag2/MCAP bag (``ros2 bag record``
is not available as a wheel). Runs :class:`~fixego_ros.nodes.bag_recorder.BagRecorderNode` in-process
until Ctrl-C, SIGTERM or ``--duration``, then closes the bag and prints one summary line on stdout.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path

from fixego_ros.cli_options import ROS_DOMAIN_IDS, OptionError, check_float, check_int, check_topic_name

DURATION_MAX = 1e7     # s (~4 months): a longer --duration is a typo for 'until Ctrl-C'
PROG = 'fixego record'


def register(subparsers) -> None:
    p = subparsers.add_parser(
        'record', help='record topics into a rosbag2/MCAP bag (like ros2 bag record)',
        description='Record live ROS 2 topics into a new rosbag2 (version 9) bag with zstd-compressed MCAP '
                    'storage, until Ctrl-C, SIGTERM or --duration. Subscriptions adapt their QoS to the '
                    'publishers; new topics are picked up as they appear. Prints one summary line at the end.')
    p.add_argument('bag', type=Path, metavar='BAG_DIR', help='bag directory to create (must not exist)')
    p.add_argument('topics', nargs='*', metavar='TOPIC', help='topics to record (default: every topic discovered)')
    p.add_argument('--duration', type=float, metavar='S', help='stop after S seconds (default: at Ctrl-C)')
    p.add_argument('--domain-id', type=int, metavar='N', help='ROS domain id (default: $ROS_DOMAIN_ID or 0)')
    p.add_argument('--include-hidden', action='store_true', help='without TOPIC: also record hidden topics')
    p.add_argument('--no-compression', action='store_true', help='do not zstd-compress the MCAP chunks')
    p.add_argument('--quiet', action='store_true', help='print only warnings and the summary line')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.bag.exists():
        print(f'{PROG}: {args.bag} exists already; give a new directory', file=sys.stderr)
        return 2
    try:
        if args.duration is not None:
            check_float(args.duration, '--duration', 0.0, DURATION_MAX, lo_open=True, unit='s',
                        note=' (leave it out to record until Ctrl-C)')
        if args.domain_id is not None:
            check_int(args.domain_id, '--domain-id', *ROS_DOMAIN_IDS)
        for t in args.topics:
            check_topic_name(t, 'TOPIC')
    except OptionError as e:
        print(f'{PROG}: {e}', file=sys.stderr)
        return 2

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.logging import LoggingSeverity
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from fixego_ros.bags.recorder import RecordError
    from fixego_ros.nodes.bag_recorder import BagRecorderNode

    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    context = rclpy.context.Context()
    node = None
    try:
        rclpy.init(context=context, domain_id=args.domain_id, signal_handler_options=SignalHandlerOptions.NO)
        # no /diagnostics from a terminal recorder: the summary line is its report (and it would record them)
        overrides = [Parameter('bag', value=str(args.bag)), Parameter('include_hidden', value=args.include_hidden),
                     Parameter('compression', value=not args.no_compression),
                     Parameter('diagnostics_period_s', value=0.0)]
        if args.topics:
            overrides.append(Parameter('topics', value=list(args.topics)))
        if args.quiet:       # the node logs what it records at INFO; warnings stay
            rclpy.logging.get_logger('bag_recorder').set_level(LoggingSeverity.WARN)
        try:
            node = BagRecorderNode(context=context, parameter_overrides=overrides)
        except RecordError as e:
            print(f'{PROG}: {e}', file=sys.stderr)       # BAG_DIR unusable (appeared meanwhile, no permission)
            return 2
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not stop.is_set() and context.ok() and (deadline is None or time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.1)
        summary = node.stop()
        executor.shutdown(timeout_sec=1.0)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
        for s, handler in previous.items():
            signal.signal(s, handler)
    print(f'{PROG}: {summary.line()}', flush=True)
    return 0 if summary.ok else 1
