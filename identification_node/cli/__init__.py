"""Command line: ``python -m identification_node VERB ...``.

Each verb lives in its own module of this package with ``add_arguments(parser)`` and
``run(args) -> int``; heavy imports happen inside ``run`` so ``--help`` stays fast.
User mistakes (IdentificationError) print one line and exit 2, never a traceback; so do
OS and input-file errors (error_lines.py says what is wrong with which file) and any other
failure (numerical ones on absurd data), unless IDENTIFICATION_DEBUG is set.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import Sequence

from identification_node.config import default as parameter_default
from identification_node.error_lines import error_line
from identification_node.errors import IdentificationError

VERBS = {
    'structure': ('structure', 'identifiability: parameter groups and base parameters'),
    'excite': ('excite', 'excitation trajectory design: optimised Fourier series'),
    'play': ('play', 'publish a bag live with its recorded timing (ros2 bag play)'),
    'record': ('record', 'record topics into a bag (ros2 bag record)'),
    'simulate': ('simulate', 'simulate an arm into a rosbag2 bag, with its true parameters'),
    'identify': ('identify', 'identify the base parameters from a bag (offline replay)'),
    'fleet': ('fleet', 'identify many bags of many robots on a Dask cluster, with drift flags'),
    'sim': ('sim', 'run the simulated arm node (real-time joint states and currents)'),
    'node': ('node', 'run the identification node'),
    'forward_payload': ('forward_payload', 'forward the identified payload to a controller '
                        'service (UR set_payload, Franka SetLoad, any Inertia-shaped request)'),
    'forward_parameters': ('forward_parameters', 'push identified quantities into another '
                           "node's parameters (admittance_controller's gravity compensation, "
                           'friction coefficients)'),
}


def add_robot_arguments(parser: argparse.ArgumentParser, required: bool = True) -> None:
    """--robot / --urdf / --joints / --extras, shared by the verbs that load a robot."""
    group = parser.add_mutually_exclusive_group(required=required)
    group.add_argument('--robot', help='bundled robot name (mit_dd_arm, crs_a465) or URDF path')
    group.add_argument('--urdf', help='URDF or MJCF file')
    parser.add_argument('--joints', help='comma-separated identified joints, in this order '
                        '(default: all movable joints; the others are locked)')
    parser.add_argument('--extras', default='',
                        help='comma-separated per-joint columns: fv,fc,fo,Ia (friction, offset, '
                        'rotor inertia); none: no column (identify\'s default: '
                        f'{",".join(parameter_default("extras"))})')


def split_list(text: str | None) -> list[str]:
    return [s.strip() for s in (text or '').split(',') if s.strip()]


def extras_list(text: str | None) -> list[str]:
    """--extras as a list; 'none' is the empty one."""
    given = split_list(text)
    return [] if given == ['none'] else given


def robot_from_args(args: argparse.Namespace):
    """The RobotModel named by add_robot_arguments' options."""
    from identification_node.model.robot import load_robot
    return load_robot(args.robot or args.urdf, split_list(args.joints) or None,
                      extras=extras_list(args.extras))


def add_settings_arguments(parser: argparse.ArgumentParser) -> None:
    """--config: a node parameter file (config/*.yaml) whose settings the verb uses."""
    parser.add_argument('--config', help='parameter YAML file, as for the node '
                        '(config/identification.yaml): robot, joints, torque sources, ...')


def settings_from_args(args: argparse.Namespace):
    """Settings from --config, overridden by --robot/--urdf/--joints/--extras when given."""
    from identification_node.settings import Settings, read_parameter_file
    values = read_parameter_file(args.config) if getattr(args, 'config', None) else {}
    if getattr(args, 'robot', None) or getattr(args, 'urdf', None):
        values['robot'] = args.robot or args.urdf
        values['robot_description'] = ''
    if getattr(args, 'joints', None):
        values['joints'] = split_list(args.joints)
    if getattr(args, 'extras', None):
        values['extras'] = extras_list(args.extras)
    return Settings.from_dict(values)


class _ParameterHelp(argparse.Action):
    """-h/--help of a verb running a ROS node: the usual help, then the node's parameters
    with defaults and descriptions (the table is loaded only when asked for)."""

    def __init__(self, option_strings, dest, table=None, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)
        self.table = table

    def __call__(self, parser, namespace, values, option_string=None):
        import textwrap
        table = self.table()
        lines = [parser.epilog or '', '', 'ROS parameters (-p NAME:=VALUE or --params-file FILE; '
                 'default in parentheses):']
        for name, (default, text) in table.items():
            lines.append(f'  {name} ({default!r})')
            lines += textwrap.wrap(text, 92, initial_indent=' ' * 6,
                                   subsequent_indent=' ' * 6)
        parser.formatter_class = argparse.RawDescriptionHelpFormatter
        parser.epilog = '\n'.join(lines)
        parser.print_help()
        parser.exit()


def add_parameter_help(parser: argparse.ArgumentParser, table) -> None:
    """Make -h/--help of ``parser`` list the ROS parameters of ``table()`` (name ->
    (default, description))."""
    parser.add_argument('-h', '--help', action=_ParameterHelp, table=table,
                        help='show this help message and the ROS parameters, and exit')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='python -m identification_node',
        description='Identify the inertial parameters of a robot arm (ROS 2 Jazzy).')
    sub = parser.add_subparsers(dest='verb', metavar='VERB', required=True)
    for verb, (module, text) in VERBS.items():
        p = sub.add_parser(verb, help=text, description=text, conflict_handler='resolve')
        importlib.import_module(f'{__name__}.{module}').add_arguments(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    return _run_verb(parser, args.verb, args, rest)


def run_program(verb: str, prog: str, argv: Sequence[str] | None = None) -> int:
    """One verb as a program of its own (an installed entry point, ``ros2 run``): its
    ``--help``, and every other argument (``--ros-args ...``) handed on as ``main`` does."""
    module, text = VERBS[verb]
    parser = argparse.ArgumentParser(prog=prog, description=text, conflict_handler='resolve')
    importlib.import_module(f'{__name__}.{module}').add_arguments(parser)
    args, rest = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    return _run_verb(parser, verb, args, rest)


def _run_verb(parser: argparse.ArgumentParser, verb: str, args: argparse.Namespace,
              rest: list[str]) -> int:
    args.verb = verb
    module = importlib.import_module(f'{__name__}.{VERBS[verb][0]}')
    if rest and not getattr(module, 'ROS_ARGS', False):
        parser.error(f'unrecognized arguments: {" ".join(rest)}')
    args.ros_args = rest   # verbs running a ROS node (ROS_ARGS = True) pass these to rclpy
    try:
        return int(module.run(args) or 0)
    except IdentificationError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into head and the like
        sys.stderr.close()
        return 0
    except Exception as exc:   # noqa: BLE001 - one line, exit 2
        if os.environ.get('IDENTIFICATION_DEBUG'):
            raise
        line = error_line(exc)   # OS, input-file, range and memory errors: what is wrong
        if line is None:   # a numerical failure or a bug
            line = (f'{args.verb} failed: {type(exc).__name__}: {" ".join(str(exc).split())} '
                    '(IDENTIFICATION_DEBUG=1 shows the traceback)')
        print(f'error: {line}', file=sys.stderr)
        return 2
