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
from pathlib import Path

from identification_node.cli import add_robot_arguments, robot_from_args, split_list
from identification_node.config import Excitation

TOPIC = '/excitation_trajectory'
CONFIG_KEYS = ('limits', 'margin', 'start', 'periods', 'min_distance', 'srdf',
               'package_dirs', 'floor', 'boxes')


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


def _initial(args: argparse.Namespace, robot):
    """(initial spec for optimize_excitation, harmonics, period)."""
    from identification_node.excitation.design import DEFAULT_HARMONICS, DEFAULT_PERIOD
    from identification_node.errors import IdentificationError
    from identification_node.excitation.trajectories import (FourierTrajectory, FramedTrajectory,
                                                             load_trajectory)

    spec = args.initial.strip()
    if spec in ('lsq', 'table1'):
        return spec, (DEFAULT_HARMONICS if args.harmonics is None else args.harmonics), \
            (DEFAULT_PERIOD if args.period is None else args.period)
    if Path(spec).suffix.lower() not in ('.yaml', '.yml'):
        raise IdentificationError(f"unknown --initial {spec!r}: use 'lsq', 'table1' or a "
                                  '.yaml file of Fourier coefficients')
    traj = load_trajectory(spec, robot)
    if isinstance(traj, FramedTrajectory):
        traj = traj.periodic
    if not isinstance(traj, FourierTrajectory):
        raise IdentificationError(f'--initial {spec} is not a Fourier trajectory')
    harmonics = traj.harmonics if args.harmonics is None else args.harmonics
    period = traj.period if args.period is None else args.period
    return traj, harmonics, period


def _numbers(text: str | None, option: str) -> list[float] | None:
    from identification_node.errors import IdentificationError
    if not text:
        return None
    try:
        return [float(v) for v in split_list(text)]
    except ValueError:
        raise IdentificationError(f'{option} must be numbers, got {text!r}') from None


def _noise(args: argparse.Namespace, n: int) -> list[float] | None:
    values = _numbers(args.noise_std, '--noise-std')
    if values is not None and len(values) == 1:
        values *= n
    return values


def _config(args: argparse.Namespace) -> dict:
    """The --config file's settings, overridden by the command line's."""
    from identification_node.errors import IdentificationError
    from identification_node.safe_yaml import read_yaml
    conf: dict = {}
    if args.config:
        conf = read_yaml(args.config, f'--config {args.config}') or {}
        if not isinstance(conf, dict):
            raise IdentificationError(f'--config {args.config} must be a mapping of '
                                      f'{", ".join(CONFIG_KEYS)}')
        unknown = sorted(set(map(str, conf)) - set(CONFIG_KEYS))
        if unknown:
            raise IdentificationError(f'--config {args.config}: unknown keys {unknown}; use '
                                      f'{", ".join(CONFIG_KEYS)}')
        if isinstance(conf.get('package_dirs'), str):
            conf['package_dirs'] = [conf['package_dirs']]
    given = {'margin': args.margin, 'periods': args.periods, 'srdf': args.srdf,
             'min_distance': args.min_distance, 'package_dirs': args.package_dir,
             'start': _numbers(args.start, '--start')}
    conf.update({k: v for k, v in given.items() if v is not None})
    return conf


def _outputs(args: argparse.Namespace) -> tuple[Path, Path, Path, Path | None]:
    from identification_node.errors import IdentificationError
    out = Path(args.out)
    if out.suffix.lower() not in ('.yaml', '.yml'):
        raise IdentificationError(f'--out {args.out} must end in .yaml or .yml')
    csv, png = out.with_suffix('.csv'), out.with_suffix('.png')
    bag = Path(args.bag) if args.bag else None
    if not args.overwrite:
        existing = [str(p) for p in (out, csv, png, bag) if p is not None and p.exists()]
        if existing:
            raise IdentificationError(f'{", ".join(existing)} exist(s); pass --overwrite to '
                                      'replace')
    if bag is not None:
        from identification_node.bags.writer import check_replaceable
        check_replaceable(bag, '--bag')
    if not (args.rate > 0 and args.rate < float('inf')):
        raise IdentificationError(f'--rate must be a finite number > 0, got {args.rate}')
    return out, csv, png, bag


def _limits(args: argparse.Namespace, conf: dict, robot):
    from identification_node.excitation.limits import ExcitationLimits, load_limits
    limits = (load_limits(args.limits, robot, effort=not args.no_effort) if args.limits
              else ExcitationLimits.from_robot(robot, effort=not args.no_effort))
    if 'limits' in conf:
        limits = limits.updated(conf['limits'], f'--config {args.config} limits')
    return limits


def _checker(args: argparse.Namespace, conf: dict, robot):
    """The CollisionChecker for a robot with collision geometry (None without, or with
    --no-collision)."""
    from identification_node.excitation.collision import (DEFAULT_MIN_DISTANCE, CollisionChecker,
                                                          has_collision_geometry)
    from identification_node.errors import IdentificationError
    wanted = any(k in conf for k in ('srdf', 'package_dirs', 'floor', 'boxes'))
    if args.no_collision:
        return None
    if not has_collision_geometry(robot):
        if wanted:
            raise IdentificationError(f'robot {robot.name} has no collision geometry: '
                                      '--srdf, --package-dir, floor and boxes need it')
        return None
    return CollisionChecker(robot, conf.get('package_dirs') or (), conf.get('srdf'),
                            conf.get('min_distance', DEFAULT_MIN_DISTANCE), conf.get('floor'),
                            conf.get('boxes') or ())


def _ratio_line(result) -> str:
    names = result.trajectory.joint_names
    parts = [f'{k} {result.ratios[k]:.3f} ({names[result.ratios["worst_joint"][k]]})'
             for k in ('position', 'velocity', 'acceleration', 'effort')]
    return 'worst limit ratios (1 = at the limit): ' + ', '.join(parts)


def run(args: argparse.Namespace) -> int:
    from identification_node.bags.writer import BagWriter
    from identification_node.excitation.criteria import DEFAULT_SAMPLES, criterion_value
    from identification_node.excitation.design import (DEFAULT_LIMIT_MARGIN, DEFAULT_MAXITER,
                                                       DEFAULT_PERIODS, TABLE1_PERIOD,
                                                       optimize_excitation, plot_excitation,
                                                       sample_times, table1_trajectory,
                                                       trajectory_to_joint_trajectory)
    from identification_node.excitation.limits import estimate_parameters
    from identification_node.fileio import atomic_write_yaml
    from identification_node.model.identifiability import BaseParameters
    from identification_node.excitation.trajectories import write_motion_csv

    out, csv, png, bag = _outputs(args)
    conf = _config(args)
    robot = robot_from_args(args)
    limits = _limits(args, conf, robot)
    checker = _checker(args, conf, robot)
    phis = None
    if args.estimate:
        phis = [robot.phi_model, estimate_parameters(args.estimate, robot)]
    initial, harmonics, period = _initial(args, robot)
    noise = _noise(args, robot.dof)
    samples = DEFAULT_SAMPLES if args.samples is None else args.samples
    margin = conf.get('margin', DEFAULT_LIMIT_MARGIN)
    base = BaseParameters.from_robot(robot)
    print(f'robot {robot.name}: {robot.dof} joints, {base.num_base} base parameters; '
          f'{harmonics} harmonics, period {period:g} s, {samples} criterion samples'
          + (f', {checker.num_pairs} collision pairs' if checker is not None else ''),
          flush=True)
    result = optimize_excitation(
        robot, harmonics, period, args.criterion, limits, seed=args.seed,
        maxiter=DEFAULT_MAXITER if args.maxiter is None else args.maxiter,
        num_samples=samples, initial=initial, base=base, noise_std=noise, margin=margin,
        start=conf.get('start'), periods=conf.get('periods', DEFAULT_PERIODS), phis=phis,
        checker=checker, progress=lambda line: print(line, flush=True),
        time_limit=args.time_limit)
    framed = result.framed
    assert framed is not None   # optimize_excitation's result is framed

    baseline = None
    if robot.name == 'crs_a465' and robot.dof == 6 and harmonics >= 5:
        baseline = criterion_value(robot, table1_trajectory(robot, harmonics, TABLE1_PERIOD),
                                   args.criterion, base, samples, noise)

    t = sample_times(framed, args.rate)
    write_motion_csv(csv, t, *framed.sample(t), robot.joint_names)
    plot_excitation(framed, limits, png, margin, args.rate,
                    f'{robot.name}: excitation ({args.criterion} {result.value:.4g})')
    if bag is not None:
        with BagWriter(bag, args.storage, overwrite=args.overwrite) as writer:
            writer.write(TOPIC, 0, trajectory_to_joint_trajectory(framed, args.rate))
    label = initial if isinstance(initial, str) else args.initial
    doc = {**framed.to_dict(), 'robot': robot.name, 'joints': list(robot.joint_names),
           'harmonics': harmonics, 'initial': label, **result.summary(),
           'limits': limits.to_dict(), 'assumed_limits': limits.assumed,
           'torque_models': ['robot model'] + (['estimate ' + args.estimate]
                                               if args.estimate else []),
           'samples_csv': csv.name, 'plot': png.name}
    if baseline is not None:
        doc['criterion']['table1'] = baseline
    if bag is not None:
        doc['bag'] = {'path': str(bag), 'topic': TOPIC, 'rate': args.rate}
    atomic_write_yaml(out, doc)

    line = (f'criterion {args.criterion}: {result.initial_value:.6g} (initial {label}'
            + ('' if result.initial_feasible else ', infeasible') + f') -> {result.value:.6g}')
    if baseline is not None:
        line += f' (Table I: {baseline:.6g})'
    print(line)
    print(f'SLSQP: {result.iterations} iterations, {result.evaluations} evaluations, '
          f'{result.runtime:.1f} s ({result.message})')
    parts = framed.parts()
    print(f'durations: ramp in {parts["ramp_in"]:.1f} s, periodic {parts["periodic"]:.1f} s '
          f'({framed.periods} x {period:g} s, the part to identify from), ramp out '
          f'{parts["ramp_out"]:.1f} s, total {parts["total"]:.1f} s; start and end at rest at '
          '[' + ', '.join(f'{v:.4g}' for v in framed.start) + '] rad')
    print(_ratio_line(result) + f'; margin {100 * margin:g} %')
    if limits.assumed:
        print('limits not in the robot description, assumed: '
              + '; '.join(limits.assumed_list()))
    if checker is not None:
        c = result.clearance
        line = f'collision: {checker.num_pairs} pairs checked'
        line += f' ({checker.srdf_removed} disabled by the SRDF)'
        if c is not None:
            line += (f', smallest distance {c["distance"]:.4g} m ({c["pair"][0]} - '
                     f'{c["pair"][1]}), minimum {checker.min_distance:g} m')
        print(line)
    elif not args.no_collision:
        print(f'collision: not checked (the description of {robot.name} has no collision '
              'geometry)')
    for w in result.warnings:
        print(f'warning: {w}', file=sys.stderr)
    print(f'wrote {out}, {csv}, {png}' + (f', {bag}' if bag is not None else ''))
    return 0
