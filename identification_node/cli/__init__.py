"""Command line: ``python -m identification_node VERB ...``.

Each verb lives in its own module of this package with ``add_arguments(parser)`` and
``run(args) -> int``; heavy imports happen inside ``run`` so ``--help`` stays fast.
User mistakes (IdentificationError) print one line and exit 2, never a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

from ..errors import IdentificationError

VERBS = {
    'structure': ('structure', 'identifiability: parameter groups and base parameters'),
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
                        'rotor inertia)')


def split_list(text: str | None) -> list[str]:
    return [s.strip() for s in (text or '').split(',') if s.strip()]


def robot_from_args(args: argparse.Namespace):
    """The RobotModel named by add_robot_arguments' options."""
    from ..robot import load_robot
    return load_robot(args.robot or args.urdf, split_list(args.joints) or None,
                      extras=split_list(args.extras))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='python -m identification_node',
        description='Identify the inertial parameters of a robot arm (ROS 2 Jazzy).')
    sub = parser.add_subparsers(dest='verb', metavar='VERB', required=True)
    for verb, (module, text) in VERBS.items():
        p = sub.add_parser(verb, help=text, description=text)
        importlib.import_module(f'{__name__}.{module}').add_arguments(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(importlib.import_module(f'{__name__}.{VERBS[args.verb][0]}').run(args) or 0)
    except IdentificationError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into head and the like
        sys.stderr.close()
        return 0
