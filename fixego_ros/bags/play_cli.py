"""``fixego play``: play a bag on its recorded topics (the ``bag_player`` node, run in this process).

In-process rather than a child ``bag_player`` process: the settings go to the node as typed parameter
overrides (no YAML quoting of paths or topic names on a ``--ros-args`` command line) and Ctrl-C needs no
forwarding. The bag is opened once before ROS starts, so a wrong path fails fast with one line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fixego_ros.cli_options import ROS_DOMAIN_IDS, OptionError, check_float, check_int, check_topic_name

RATE_MIN = 1e-3          # slower than 1000x slow motion is a typo, not a playback (1e-300 never ended)
RATE_MAX = 1e6
OFFSET_MAX = 1e9         # s (~30 years): beyond it the nanosecond arithmetic overflows


def register(subparsers) -> None:
    p = subparsers.add_parser(
        'play', help='play a rosbag2/MCAP bag on its recorded topics (ros2 bag play without ros2cli)',
        description='Publish the messages of a rosbag2/MCAP bag as recorded (raw CDR, recorded QoS) at '
                    'their recorded pace, scaled by --rate. Damaged bags play what can be read. Exits 0 '
                    'when the bag has been played, 2 when it cannot be opened.')
    p.add_argument('bag', type=Path, metavar='BAG_DIR', help='rosbag2 directory or .mcap file')
    p.add_argument('--rate', type=float, default=1.0, help='speed factor (default 1; 0 = as fast as possible)')
    p.add_argument('--loop', action='store_true', help='replay from the start when the bag ends')
    p.add_argument('--topics', nargs='+', metavar='T', default=[], help='play only these topics')
    p.add_argument('--remap', nargs='+', metavar='FROM:=TO', default=[], help='publish topic FROM as TO')
    p.add_argument('--clock', action='store_true', help='publish /clock at each message\'s bag time')
    p.add_argument('--start-offset', type=float, default=0.0, metavar='S', help='skip the first S seconds')
    p.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: inherited)')
    p.add_argument('--delay', type=float, default=0.5, metavar='S',
                   help='wait S seconds for discovery before the first message (default 0.5)')
    p.set_defaults(func=run)


def check_args(args: argparse.Namespace) -> None:
    """Every option before the bag is opened (:class:`OptionError`): a rate that would make playback endless, an
    offset or delay that overflows, a domain id ROS refuses, a remap that is not FROM:=TO with valid names."""
    check_float(args.rate, '--rate', 0.0, RATE_MAX, note=' (0 = as fast as possible)')
    check_float(args.start_offset, '--start-offset', 0.0, OFFSET_MAX, unit='s')
    check_float(args.delay, '--delay', 0.0, OFFSET_MAX, unit='s')
    if args.rate != 0.0 and args.rate < RATE_MIN:
        raise OptionError(f'--rate must be 0 or at least {RATE_MIN:g} (slower playback would take ages), '
                          f'got {args.rate!r}')
    if args.domain_id is not None:
        check_int(args.domain_id, '--domain-id', *ROS_DOMAIN_IDS)
    for name in [*args.topics, *(part for r in args.remap for part in r.split(':=', 1))]:
        check_topic_name(name, '--topics/--remap')


def run(args: argparse.Namespace) -> int:
    from fixego_ros.bags.player import PlayError, Schedule
    from fixego_ros.bags.reader import Bag, BagError

    try:
        check_args(args)
        Schedule(Bag(args.bag), args.rate, start_offset_s=args.start_offset)   # fail before starting DDS
    except (BagError, PlayError, OptionError) as e:
        print(f'fixego play: {e}', file=sys.stderr)
        return 2

    from rclpy.parameter import Parameter

    from fixego_ros.nodes.bag_player import run as run_player

    overrides = [Parameter('bag', value=str(args.bag)), Parameter('rate', value=float(args.rate)),
                 Parameter('loop', value=bool(args.loop)), Parameter('publish_clock', value=bool(args.clock)),
                 Parameter('start_delay_s', value=float(args.delay)),
                 Parameter('start_offset_s', value=float(args.start_offset))]
    if args.topics:
        overrides.append(Parameter('topics', value=[str(t) for t in args.topics]))
    if args.remap:
        overrides.append(Parameter('remap', value=[str(r) for r in args.remap]))
    return run_player(args=[], overrides=overrides, domain_id=args.domain_id, prog='fixego play')
