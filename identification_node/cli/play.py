"""``play BAG``: publish a bag's messages live with their recorded timing (ros2 bag play)."""
from __future__ import annotations

import argparse
import contextlib
import math
import sys
from typing import Any, Iterator

from identification_node.errors import IdentificationError

ROS_ARGS = True   # the CLI passes unparsed arguments on as args.ros_args


def add_ros_arguments(parser: argparse.ArgumentParser) -> None:
    """Document ``--ros-args ...`` (the CLI hands unparsed arguments over as args.ros_args)."""
    parser.epilog = ('ROS arguments go last, e.g. --ros-args -r /joint_states:=/arm/joint_states '
                     '-p use_sim_time:=true')


def ros_arguments(args: argparse.Namespace) -> list[str]:
    """The ``--ros-args ...`` part of the command line; other leftovers are an error."""
    rest = list(getattr(args, 'ros_args', None) or [])
    if rest and rest[0] != '--ros-args':
        cut = rest.index('--ros-args') if '--ros-args' in rest else len(rest)
        raise IdentificationError(f'unrecognized arguments: {" ".join(rest[:cut])}')
    return rest


def warn(text: str) -> None:
    print(f'warning: {text}', file=sys.stderr)


@contextlib.contextmanager
def ros_session(args: argparse.Namespace, node_name: str) -> Iterator[tuple[Any, Any]]:
    """(node, signals) for a verb: rclpy initialised with ``--ros-args`` and without its own
    signal handlers, so that SIGINT/SIGTERM only call ``signals.callback`` and the verb
    finishes cleanly (flushes, closes its bag); everything is torn down on exit."""
    import rclpy
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from identification_node.ros.spin import stop_signals

    ros_args = ros_arguments(args)
    node = None
    with stop_signals() as signals:
        try:
            rclpy.init(args=['identification_node', *ros_args],
                       signal_handler_options=SignalHandlerOptions.NO)
            node = Node(node_name, start_parameter_services=False)
            yield node, signals
        finally:
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', help='rosbag2 bag directory (or a lone .mcap/.db3 file)')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='playback speed factor (default 1: recorded timing)')
    parser.add_argument('--loop', action='store_true', help='play again and again until Ctrl-C')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC',
                        help='play only these topics (default: all)')
    parser.add_argument('--clock', nargs='?', type=float, const=40.0, default=0.0,
                        metavar='HZ', help='publish /clock with the bag time at HZ '
                        '(default 40 Hz when given without a value)')
    parser.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='S',
                        help='before playing, wait up to S seconds until every (non-latched) '
                        'topic has a subscriber')
    parser.add_argument('--wait-for-all-acked', type=float, default=0.0, metavar='S',
                        help='after playing, wait up to S seconds until reliable subscribers '
                        'acknowledged every message (FastDDS acknowledges on its heartbeat, '
                        'up to ~3 s; default: exit at once)')
    add_ros_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from identification_node.bags.reader import open_bag
    from identification_node.ros.player import BagPlayer, select_topics

    for name, value in (('--rate', args.rate), ('--clock', args.clock),
                        ('--wait-for-subscribers', args.wait_for_subscribers),
                        ('--wait-for-all-acked', args.wait_for_all_acked)):
        if not math.isfinite(value) or value < 0 or (name == '--rate' and value == 0):
            raise IdentificationError(f'{name} must be a positive number, got {value}')
    ros_arguments(args)
    reader = open_bag(args.bag)
    try:
        # before rclpy starts: a wrong bag or topic list fails fast with one line
        select_topics(reader, args.topics, args.clock > 0)
        with ros_session(args, 'bag_player') as (node, signals), BagPlayer(
                node, reader, rate=args.rate, topics=args.topics, loop=args.loop,
                clock=args.clock) as player:
            signals.callback = player.stop
            if args.wait_for_subscribers > 0:
                lonely = player.wait_for_subscribers(args.wait_for_subscribers)
                if lonely:
                    warn(f'no subscriber after {args.wait_for_subscribers:g} s on '
                         f'{", ".join(lonely)}; playing anyway')
            stats = player.play()
            if (args.wait_for_all_acked > 0 and not stats.interrupted
                    and not player.wait_for_acks(args.wait_for_all_acked)):
                warn('some reliable subscribers did not acknowledge every message')
            print(stats.summary(), flush=True)
    finally:
        reader.close()
    return 0
