"""``excite``: design an excitation trajectory for identification.

Optimises a finite Fourier series per joint (Radkhah, Kulic and Croft, II.C-D) for the
condition number or the d-optimality of the stacked base regressor under the joint limits, and
writes the coefficients as YAML (``--out``, loadable as a trajectory file), the samples of one
period as CSV beside it (same stem, ``.csv``: t and one column per joint) and optionally a
trajectory_msgs/JointTrajectory on /excitation_trajectory in a bag (``--bag``).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from . import add_robot_arguments, robot_from_args, split_list

TOPIC = '/excitation_trajectory'


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_robot_arguments(parser)
    parser.add_argument('--harmonics', type=int, default=None,
                        help='harmonics per joint (default 5, or the --initial file\'s)')
    parser.add_argument('--period', type=float, default=None,
                        help='period of the series in s (default 10, or the --initial file\'s)')
    parser.add_argument('--criterion', choices=('cond', 'dopt'), default='cond',
                        help='cond: condition number of the stacked base regressor (the '
                        'paper\'s); dopt: -log det of the information matrix (default cond)')
    parser.add_argument('--limits', help='YAML file of per-joint limits overriding the '
                        "robot's: joint: {position: [lo, hi], velocity, acceleration, effort}")
    parser.add_argument('--no-effort', action='store_true',
                        help='ignore the torque (effort) limits of the robot description')
    parser.add_argument('--noise-std', help='comma-separated torque noise standard deviations '
                        'per joint (N m): weights of the regressor rows')
    parser.add_argument('--initial', default='lsq',
                        help="starting point: 'lsq' (the paper's least-squares guess from "
                        "random velocities, default), 'table1' (the paper's Table I, CRS "
                        'A465) or a YAML file of Fourier coefficients')
    parser.add_argument('--seed', type=int, default=0, help='seed of the initial guess')
    parser.add_argument('--maxiter', type=int, default=None,
                        help='SLSQP iterations (default 200)')
    parser.add_argument('--samples', type=int, default=None,
                        help='criterion samples over one period (default 100)')
    parser.add_argument('--rate', type=float, default=100.0,
                        help='sample rate of the CSV and the bag, Hz (default 100)')
    parser.add_argument('--out', required=True,
                        help='output YAML file (.yaml/.yml); the CSV goes beside it')
    parser.add_argument('--bag', help=f'also write a JointTrajectory on {TOPIC} to this bag')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='bag storage (default mcap)')
    parser.add_argument('--overwrite', action='store_true', help='replace existing outputs')


def _initial(args: argparse.Namespace, robot):
    """(initial spec for optimize_excitation, harmonics, period)."""
    from ..excitation import DEFAULT_HARMONICS, DEFAULT_PERIOD
    from ..errors import IdentificationError
    from ..trajectories import FourierTrajectory, load_trajectory

    spec = args.initial.strip()
    if spec in ('lsq', 'table1'):
        return spec, (DEFAULT_HARMONICS if args.harmonics is None else args.harmonics), \
            (DEFAULT_PERIOD if args.period is None else args.period)
    if Path(spec).suffix.lower() not in ('.yaml', '.yml'):
        raise IdentificationError(f"unknown --initial {spec!r}: use 'lsq', 'table1' or a "
                                  '.yaml file of Fourier coefficients')
    traj = load_trajectory(spec, robot)
    if not isinstance(traj, FourierTrajectory):
        raise IdentificationError(f'--initial {spec} is not a Fourier trajectory')
    harmonics = traj.harmonics if args.harmonics is None else args.harmonics
    period = traj.period if args.period is None else args.period
    return traj, harmonics, period


def _noise(args: argparse.Namespace, n: int) -> list[float] | None:
    from ..errors import IdentificationError
    if not args.noise_std:
        return None
    try:
        values = [float(v) for v in split_list(args.noise_std)]
    except ValueError:
        raise IdentificationError(f'--noise-std must be numbers, got {args.noise_std!r}') \
            from None
    if len(values) == 1:
        values *= n
    return values


def _outputs(args: argparse.Namespace) -> tuple[Path, Path, Path | None]:
    from ..errors import IdentificationError
    out = Path(args.out)
    if out.suffix.lower() not in ('.yaml', '.yml'):
        raise IdentificationError(f'--out {args.out} must end in .yaml or .yml')
    csv = out.with_suffix('.csv')
    bag = Path(args.bag) if args.bag else None
    if not args.overwrite:
        existing = [str(p) for p in (out, csv, bag) if p is not None and p.exists()]
        if existing:
            raise IdentificationError(f'{", ".join(existing)} exist(s); pass --overwrite to '
                                      'replace')
    if bag is not None and bag.exists() and not (bag / 'metadata.yaml').is_file():
        raise IdentificationError(f'--bag {bag} exists and is not a bag; not replacing it')
    if not (args.rate > 0 and args.rate < float('inf')):
        raise IdentificationError(f'--rate must be a finite number > 0, got {args.rate}')
    return out, csv, bag


def _ratio_line(result) -> str:
    names = result.trajectory.joint_names
    parts = [f'{k} {result.ratios[k]:.3f} ({names[result.ratios["worst_joint"][k]]})'
             for k in ('position', 'velocity', 'acceleration', 'effort')]
    return 'worst limit ratios: ' + ', '.join(parts)


def run(args: argparse.Namespace) -> int:
    from ..bagio import BagWriter
    from ..excitation import (DEFAULT_MAXITER, DEFAULT_SAMPLES, TABLE1_PERIOD,
                              ExcitationLimits, criterion_value, load_limits,
                              optimize_excitation, sample_times, table1_trajectory,
                              trajectory_to_joint_trajectory)
    from ..fileio import atomic_write_yaml
    from ..identifiability import BaseParameters
    from ..trajectories import SampledTrajectory

    out, csv, bag = _outputs(args)
    robot = robot_from_args(args)
    limits = (load_limits(args.limits, robot, effort=not args.no_effort) if args.limits
              else ExcitationLimits.from_robot(robot, effort=not args.no_effort))
    initial, harmonics, period = _initial(args, robot)
    noise = _noise(args, robot.dof)
    samples = DEFAULT_SAMPLES if args.samples is None else args.samples
    base = BaseParameters.from_robot(robot)
    result = optimize_excitation(
        robot, harmonics, period, args.criterion, limits, seed=args.seed,
        maxiter=DEFAULT_MAXITER if args.maxiter is None else args.maxiter,
        num_samples=samples, initial=initial, base=base, noise_std=noise)
    traj = result.trajectory

    baseline = None
    if robot.name == 'crs_a465' and robot.dof == 6 and harmonics >= 5:
        baseline = criterion_value(robot, table1_trajectory(robot, harmonics, TABLE1_PERIOD),
                                   args.criterion, base, samples, noise)

    t = sample_times(traj, args.rate)
    q = traj.sample(t)[0]
    if bag is not None:
        with BagWriter(bag, args.storage, overwrite=args.overwrite) as writer:
            writer.write(TOPIC, 0, trajectory_to_joint_trajectory(traj, args.rate))
    SampledTrajectory(t, q, robot.joint_names).to_csv(csv)
    label = initial if isinstance(initial, str) else args.initial
    doc = {**traj.to_dict(), 'robot': robot.name, 'joints': list(robot.joint_names),
           'harmonics': harmonics, 'initial': label, **result.summary(),
           'limits': limits.to_dict(), 'samples_csv': csv.name}
    if baseline is not None:
        doc['criterion']['table1'] = baseline
    if bag is not None:
        doc['bag'] = {'path': str(bag), 'topic': TOPIC, 'rate': args.rate}
    atomic_write_yaml(out, doc)

    print(f'robot {robot.name}: {robot.dof} joints, {base.num_base} base parameters; '
          f'{harmonics} harmonics, period {period:g} s, {samples} criterion samples')
    line = (f'criterion {args.criterion}: {result.initial_value:.6g} (initial {label}) -> '
            f'{result.value:.6g}')
    if baseline is not None:
        line += f' (Table I: {baseline:.6g})'
    print(line)
    print(f'SLSQP: {result.iterations} iterations, {result.evaluations} evaluations, '
          f'{result.runtime:.1f} s ({result.message})'
          + ('' if result.improved else '; no improvement, kept the initial trajectory'))
    print(_ratio_line(result))
    print(f'wrote {out}, {csv}' + (f', {bag}' if bag is not None else ''))
    return 0
