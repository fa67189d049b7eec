"""``forward_parameters``: push identified quantities into another node's parameters.

``python -m identification_node forward_parameters --ros-args -p preset:=admittance``
(ros/parameter_forwarder.py); every argument after the verb goes to ROS. Exits 2 on invalid
parameters.
"""
from __future__ import annotations

import argparse

ROS_ARGS = True   # the CLI passes unparsed arguments on as args.ros_args


def _parameters() -> dict:
    from identification_node.ros.parameter_forwarder import PARAMETERS
    return PARAMETERS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from identification_node.cli import add_parameter_help
    parser.epilog = ('Arguments after the verb go to ROS, e.g. --ros-args -p preset:=admittance '
                     '-p target:=/my_admittance_controller')
    add_parameter_help(parser, _parameters)


def run(args: argparse.Namespace) -> int:
    from identification_node.ros.parameter_forwarder import main
    return main(['parameter_forwarder', *getattr(args, 'ros_args', [])])
