"""``record OUT --topics ...``: record live topics into a rosbag2 bag (ros2 bag record)."""
from __future__ import annotations

import argparse
import math

from identification_node.errors import IdentificationError
from identification_node.cli.play import add_ros_arguments, ros_session

ROS_ARGS = True   # the CLI passes unparsed arguments on as args.ros_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('out', help='bag directory to create (appears when recording ends)')
    parser.add_argument('--topics', nargs='+', required=True, metavar='TOPIC',
                        help='topics to record (types and QoS come from their publishers)')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='storage format (default mcap)')
    parser.add_argument('--duration', type=float, metavar='S',
                        help='stop after S seconds (default: until Ctrl-C or SIGTERM)')
    parser.add_argument('--discovery-timeout', type=float, default=10.0, metavar='S',
                        help='fail if none of the topics has a publisher after S seconds '
                        '(default 10)')
    parser.add_argument('--overwrite', action='store_true', help='replace an existing OUT')
    add_ros_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from identification_node.ros.spin import make_executor
    from identification_node.ros.recorder import BagRecorder

    for name, value in (('--duration', args.duration),
                        ('--discovery-timeout', args.discovery_timeout)):
        if value is not None and (not math.isfinite(value) or value <= 0):
            raise IdentificationError(f'{name} must be a positive number, got {value}')
    if args.overwrite:   # before recording: only a bag is replaced
        from identification_node.bags.writer import check_replaceable
        check_replaceable(args.out, 'OUT')
    with ros_session(args, 'bag_recorder') as (node, signals):
        with BagRecorder(node, args.out, args.topics, args.storage,
                         overwrite=args.overwrite) as recorder:
            signals.callback = recorder.stop
            executor = make_executor()
            executor.add_node(node)
            try:
                recorder.spin(executor, args.duration, args.discovery_timeout)
            finally:
                executor.shutdown()
        print(recorder.summary(), flush=True)
    return 0
