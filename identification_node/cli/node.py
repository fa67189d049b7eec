"""``node``: the identification node in this process.

``python -m identification_node node --ros-args --params-file config/identification.yaml``;
every argument after the verb goes to ROS (parameters: ``node --help``, from
config.PARAMETERS). Exits 2 on invalid parameters.
"""
from __future__ import annotations

import argparse

ROS_ARGS = True   # the CLI passes unparsed arguments on as args.ros_args


def _parameters() -> dict:
    from identification_node.config import PARAMETERS
    return PARAMETERS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from identification_node.cli import add_parameter_help
    parser.epilog = ('Arguments after the verb go to ROS, e.g. --ros-args --params-file FILE '
                     '-p forgetting_factor:=0.9999')
    add_parameter_help(parser, _parameters)


def run(args: argparse.Namespace) -> int:
    from identification_node.ros.node import main
    return main(['identification_node', *getattr(args, 'ros_args', [])])
