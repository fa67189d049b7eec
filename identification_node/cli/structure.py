"""``structure``: which inertial parameters a robot's joint torques can reveal.

Prints the three groups of standard parameters (identifiable alone, unidentifiable, identifiable
only in combinations) and the base parameters with their value from the robot description's own
inertials; ``--json`` prints the same as one JSON object.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import textwrap

from identification_node.cli import add_robot_arguments, robot_from_args

UNITS = {'m': 'kg', 'mx': 'kg m', 'my': 'kg m', 'mz': 'kg m', 'fv': 'N m s/rad', 'fc': 'N m',
         'fo': 'N m', 'Ia': 'kg m^2'}
MAX_REGRESSOR_BYTES = 1 << 28   # --samples: the rank tests' regressor stays within 256 MiB
PRISMATIC_UNITS = {'fv': 'N s/m', 'fc': 'N', 'fo': 'N', 'Ia': 'kg'}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_robot_arguments(parser)
    parser.add_argument('--json', action='store_true', help='print one JSON object')
    parser.add_argument('--samples', type=int, default=None,
                        help='random samples of (q, qd, qdd) for the rank tests '
                        '(default: 4 regressor rows per parameter, at least 100)')
    parser.add_argument('--seed', type=int, default=0, help='random seed of the samples')


def unit(name: str, prismatic_joints: set[str]) -> str:
    """SI unit of a standard parameter ``<link>.<kind>`` or ``<joint>.<extra>``."""
    owner, kind = name.rsplit('.', 1)
    if owner in prismatic_joints and kind in PRISMATIC_UNITS:
        return PRISMATIC_UNITS[kind]
    return UNITS.get(kind, 'kg m^2')


def _number(x: float) -> str:
    return '0' if abs(x) < 1e-12 else f'{x:.6g}'


def _group(title: str, names: list[str], width: int) -> list[str]:
    lines = [f'{title} ({len(names)}):']
    body = '  '.join(names) if names else '(none)'
    lines += textwrap.wrap(body, width=width, initial_indent='  ', subsequent_indent='  ',
                           break_on_hyphens=False) or ['  (none)']
    return lines


def _wrap_terms(expression: str, width: int) -> list[str]:
    """Split an expression into lines of at most ``width`` characters, between terms."""
    terms = re.split(r' (?=[+-] )', expression)
    lines = [terms[0]]
    for term in terms[1:]:
        if len(lines[-1]) + 1 + len(term) <= width:
            lines[-1] += ' ' + term
        else:
            lines.append('  ' + term)
    return lines


def format_report(base, robot) -> str:
    """The readable report: robot, groups, base parameter table."""
    width = max(60, min(120, shutil.get_terminal_size((100, 24)).columns))
    prismatic = {j for j, p in zip(robot.joint_names, robot.prismatic) if p}
    values = base.to_base(robot.phi_model)
    lines = [f'robot {robot.name}: {robot.dof} joints ({", ".join(robot.joint_names)})',
             f'{base.num_params} standard parameters, {base.num_base} base parameters', '']
    lines += _group('identifiable alone', base.identifiable, width)
    lines += _group('unidentifiable, no effect on the joint torques', base.unidentifiable,
                    width)
    lines += _group('identifiable only in linear combinations', base.combined, width)
    lines += ['', 'base parameters (value from the robot description):']
    rows = [(str(k + 1), name, _number(v), unit(base.param_names[j], prismatic), expr)
            for k, (name, v, j, expr) in enumerate(
                zip(base.names, values, base.base_index, base.expressions))]
    header = ('#', 'name', 'value', 'unit', 'expression')
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(4)]
    indent = sum(widths) + 10
    for r in [header] + rows:
        first, *more = _wrap_terms(r[4], max(30, width - indent))
        lines.append(f'  {r[0]:>{widths[0]}}  {r[1]:<{widths[1]}}  {r[2]:>{widths[2]}}  '
                     f'{r[3]:<{widths[3]}}  {first}'.rstrip())
        lines += [' ' * indent + m for m in more]
    return '\n'.join(lines)


def run(args: argparse.Namespace) -> int:
    from identification_node.errors import IdentificationError
    from identification_node.model.identifiability import BaseParameters

    if args.samples is not None and args.samples < 1:
        raise IdentificationError(f'--samples must be a positive count, got {args.samples}')
    robot = robot_from_args(args)
    if args.samples is not None:
        most = MAX_REGRESSOR_BYTES // (8 * robot.dof * robot.num_params)
        if args.samples > most:
            raise IdentificationError(
                f'--samples {args.samples}: at most {most} for {robot.name} (each sample is '
                f'{robot.dof} x {robot.num_params} regressor values; the default '
                f'{max(100, -(-4 * robot.num_params // robot.dof))} is enough)')
    base = BaseParameters.from_robot(robot, num_samples=args.samples, seed=args.seed)
    if args.json:
        print(json.dumps(base.to_dict(robot.phi_model), indent=2))
    else:
        print(format_report(base, robot))
    return 0
