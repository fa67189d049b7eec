"""``forward_payload``: hand the identified payload to a controller's service.

``python -m identification_node forward_payload --ros-args -p preset:=franka
-r payload:=/identification_node/payload`` (ros/payload_forwarder.py); every argument after
the verb goes to ROS. Exits 2 on invalid parameters.
"""
from __future__ import annotations

import argparse

ROS_ARGS = True   # the CLI passes unparsed arguments on as args.ros_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = ('Arguments after the verb go to ROS, e.g. --ros-args -p preset:=ur '
                     '-r payload:=/identification_node/payload')


def run(args: argparse.Namespace) -> int:
    from identification_node.ros.payload_forwarder import main
    return main(['payload_forwarder', *getattr(args, 'ros_args', [])])
