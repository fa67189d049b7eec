"""``sim``: the simulated arm node (``simulated_arm``) in this process.

``python -m identification_node sim --ros-args -p robot:=crs_a465 -p trajectory:=table1 ...``;
every argument after the verb goes to ROS (parameters: ``sim --help``, from
identification_node.ros.sim_node.SIM_PARAMETERS). Exits 0 after ``duration``, 2 on invalid
parameters.
"""
from __future__ import annotations

import argparse

ROS_ARGS = True   # the CLI passes unparsed arguments on as args.ros_args


def _parameters() -> dict:
    from identification_node.ros.sim_node import SIM_PARAMETERS
    return SIM_PARAMETERS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from identification_node.cli import add_parameter_help
    parser.epilog = ('Arguments after the verb go to ROS, e.g. --ros-args -p rate:=1000.0 '
                     '-p duration:=10.0 -p publish_currents:=true -p torque_source:=[three_phase]')
    add_parameter_help(parser, _parameters)


def run(args: argparse.Namespace) -> int:
    from identification_node.ros.sim_node import main
    return main(['simulated_arm', *getattr(args, 'ros_args', [])])
