"""``excite``: design an excitation trajectory a real arm can run, for identification.

Optimises a finite Fourier series per joint (Radkhah, Kulic and Croft, II.C-D) for the
condition number or the d-optimality of the stacked base regressor under the joint limits with
a margin (position, velocity, acceleration, torque) and, for a URDF with collision geometry,
self-collision and environment constraints; frames ``--periods`` periods of it with ramps
from and back to a start configuration at rest. Writes, all atomically and only when a
feasible trajectory was found:

- ``--out`` (YAML): the Fourier coefficients, the framing (start, ramp durations, periods; a
  trajectory file for ``simulate`` and ``identify``), criteria, limits and assumptions;
- beside it, same stem: ``.csv`` with ``t,<joint>.position,...,<joint>.velocity,...,
  <joint>.acceleration,...`` at ``--rate``, ramps included, and ``.png``, the plot;
- optionally (``--bag``) a trajectory_msgs/JointTrajectory on /excitation_trajectory.

``--config`` reads an excitation YAML file with any of: ``limits`` (as ``--limits``),
``margin``, ``start``, ``periods``, ``min_distance``, ``srdf``, ``package_dirs``, ``floor``
(height in m, or ``{height: z}``) and ``boxes`` (``[{size: [x, y, z], xyz: [...], rpy:
[...]}]``, world frame); options given on the command line win.
"""
from __future__ import annotations

import argparse
import sys

from identification_node.cli import add_robot_arguments, extras_list, split_list
from identification_node.config import Excitation
from identification_node.excitation.run import CONFIG_KEYS, TOPIC


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_robot_arguments(parser)
    parser.add_argument('--config', help='excitation YAML: ' + ', '.join(CONFIG_KEYS))
    parser.add_argument('--harmonics', type=int, default=None,
                        help=f'harmonics per joint (default {Excitation.harmonics}, or the '
                        '--initial file\'s)')
    parser.add_argument('--period', type=float, default=None,
                        help=f'period of the series in s (default {Excitation.period:g}, or '
                        'the --initial file\'s)')
    parser.add_argument('--periods', type=int, default=None,
                        help=f'periods between the ramps (default {Excitation.periods})')
    parser.add_argument('--start', help='comma-separated start (and end) configuration, rad '
                        '(default: the offset of the series)')
    parser.add_argument('--criterion', choices=('cond', 'dopt'), default='cond',
                        help='cond: condition number of the stacked base regressor (the '
                        'paper\'s); dopt: -log det of the information matrix (default cond)')
    parser.add_argument('--limits', help='YAML file of per-joint limits overriding the '
                        "robot's: joint: {position: [lo, hi], velocity, acceleration, effort}")
    parser.add_argument('--margin', type=float, default=None,
                        help=f'fraction of every limit kept free (default '
                        f'{Excitation.margin:g})')
    parser.add_argument('--no-effort', action='store_true',
                        help='ignore the torque (effort) limits of the robot description')
    parser.add_argument('--estimate', metavar='FILE',
                        help='estimate.yaml: torque limits hold under its parameters too')
    collision = parser.add_argument_group('collision (URDF collision geometry)')
    collision.add_argument('--package-dir', action='append', default=None, metavar='DIR',
                           help='directory resolving package:// meshes (repeatable)')
    collision.add_argument('--srdf', help='MoveIt SRDF: its disabled pairs are not checked')
    collision.add_argument('--min-distance', type=float, default=None,
                           help='minimum distance between checked pairs, m (default '
                           f'{Excitation.min_distance:g})')
    collision.add_argument('--no-collision', action='store_true',
                           help='do not check collisions')
    parser.add_argument('--noise-std', help='comma-separated torque noise standard deviations '
                        'per joint (N m): weights of the regressor rows')
    parser.add_argument('--initial', default='lsq',
                        help="starting point: 'lsq' (the paper's least-squares guess from "
                        "random velocities, default), 'table1' (the paper's Table I, CRS "
                        'A465) or a YAML file of Fourier coefficients')
    parser.add_argument('--seed', type=int, default=0, help='seed of the initial guess')
    parser.add_argument('--maxiter', type=int, default=None,
                        help=f'SLSQP iterations (default {Excitation.maxiter})')
    parser.add_argument('--time-limit', type=float, default=None, metavar='S',
                        help='stop optimising after S seconds and keep the best feasible '
                        'design found by then (default: none)')
    parser.add_argument('--samples', type=int, default=None,
                        help=f'criterion samples over one period (default {Excitation.samples})')
    parser.add_argument('--rate', type=float, default=Excitation.rate,
                        help='sample rate of the CSV, the plot and the bag, Hz (default '
                        f'{Excitation.rate:g})')
    parser.add_argument('--out', required=True,
                        help='output YAML file (.yaml/.yml); the CSV and PNG go beside it')
    parser.add_argument('--bag', help=f'also write a JointTrajectory on {TOPIC} to this bag')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='bag storage (default mcap)')
    parser.add_argument('--overwrite', action='store_true', help='replace existing outputs')


def run(args: argparse.Namespace) -> int:
    from identification_node.excitation.run import ExciteConfig, excite, excite_text

    config = ExciteConfig(
        robot=args.robot or args.urdf, out=args.out,
        joints=tuple(split_list(args.joints)) or None, extras=tuple(extras_list(args.extras)),
        config=args.config, harmonics=args.harmonics, period=args.period,
        periods=args.periods, start=args.start, criterion=args.criterion, limits=args.limits,
        margin=args.margin, no_effort=args.no_effort, estimate=args.estimate,
        package_dirs=None if args.package_dir is None else tuple(args.package_dir),
        srdf=args.srdf, min_distance=args.min_distance, no_collision=args.no_collision,
        noise_std=args.noise_std, initial=args.initial, seed=args.seed, maxiter=args.maxiter,
        time_limit=args.time_limit, samples=args.samples, rate=args.rate, bag=args.bag,
        storage=args.storage, overwrite=args.overwrite)
    excited = excite(config, report=lambda line: print(line, flush=True))
    for line in excite_text(excited):
        print(line)
    for w in excited.result.warnings:
        print(f'warning: {w}', file=sys.stderr)
    print('wrote ' + ', '.join(str(p) for p in excited.files))
    return 0
