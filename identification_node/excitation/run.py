"""The ``excite`` use case: design an excitation for a robot and write its files.

excite(config) loads the robot, its limits (with the margin), the collision checker and the
torque models, runs optimize_excitation and writes, all atomically: the YAML (Fourier
coefficients, framing, criteria, limits and assumptions), beside it the samples (``.csv``,
ramps included, at ``rate`` Hz) and the plot (``.png``), and optionally a bag with a
trajectory_msgs/JointTrajectory on TOPIC. excite_text gives the summary a user reads.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from identification_node.config import Excitation
from identification_node.errors import IdentificationError

if TYPE_CHECKING:   # the heavy imports happen in the functions: the CLI's --help imports this
    from identification_node.excitation.collision import CollisionChecker
    from identification_node.excitation.limits import ExcitationLimits
    from identification_node.excitation.result import ExcitationResult
    from identification_node.excitation.trajectories import FourierTrajectory
    from identification_node.model.robot import RobotModel

__all__ = ['CONFIG_KEYS', 'TOPIC', 'ExciteConfig', 'Excited', 'excite', 'excite_text']

TOPIC = '/excitation_trajectory'
CONFIG_KEYS = ('limits', 'margin', 'start', 'periods', 'min_distance', 'srdf',
               'package_dirs', 'floor', 'boxes')


@dataclass(frozen=True)
class ExciteConfig:
    """What excite designs and writes (the ``excite`` verb's options). robot: bundled name or
    URDF path; start, noise_std: comma-separated rad and N m as given; period s, rate Hz,
    min_distance m, time_limit s; None: the default (or the --config file's, or the initial
    trajectory file's harmonics and period)."""
    robot: str
    out: str
    joints: tuple[str, ...] | None = None
    extras: tuple[str, ...] = ()
    config: str | None = None
    harmonics: int | None = None
    period: float | None = None
    periods: int | None = None
    start: str | None = None
    criterion: str = 'cond'
    limits: str | None = None
    margin: float | None = None
    no_effort: bool = False
    estimate: str | None = None
    package_dirs: tuple[str, ...] | None = None
    srdf: str | None = None
    min_distance: float | None = None
    no_collision: bool = False
    noise_std: str | None = None
    initial: str = 'lsq'
    seed: int = 0
    maxiter: int | None = None
    time_limit: float | None = None
    samples: int | None = None
    rate: float = Excitation.rate
    bag: str | None = None
    storage: str = 'mcap'
    overwrite: bool = False


@dataclass
class Excited:
    """excite's outcome: the robot, the optimisation result, the limits (without margin) and
    the margin, the collision checker (None: not checked), the criterion of Table I (CRS A465
    only, else None), the initial trajectory's label, the period (s) and the files written
    (YAML, CSV, PNG, then the bag when asked for); collision_asked: False with no_collision."""
    robot: RobotModel
    result: ExcitationResult
    limits: ExcitationLimits
    margin: float
    checker: CollisionChecker | None
    baseline: float | None
    label: str
    period: float
    files: list[Path]
    collision_asked: bool = True


def _initial(config: ExciteConfig, robot: RobotModel
             ) -> tuple[str | FourierTrajectory, int, float]:
    """(initial spec for optimize_excitation, harmonics, period)."""
    from identification_node.excitation.initial_guess import DEFAULT_HARMONICS, DEFAULT_PERIOD
    from identification_node.excitation.trajectories import (FourierTrajectory, FramedTrajectory,
                                                             load_trajectory)

    spec = config.initial.strip()
    if spec in ('lsq', 'table1'):
        return spec, (DEFAULT_HARMONICS if config.harmonics is None else config.harmonics), \
            (DEFAULT_PERIOD if config.period is None else config.period)
    if Path(spec).suffix.lower() not in ('.yaml', '.yml'):
        raise IdentificationError(f"unknown --initial {spec!r}: use 'lsq', 'table1' or a "
                                  '.yaml file of Fourier coefficients')
    traj = load_trajectory(spec, robot)
    if isinstance(traj, FramedTrajectory):
        traj = traj.periodic
    if not isinstance(traj, FourierTrajectory):
        raise IdentificationError(f'--initial {spec} is not a Fourier trajectory')
    harmonics = traj.harmonics if config.harmonics is None else config.harmonics
    period = traj.period if config.period is None else config.period
    return traj, harmonics, period


def _numbers(text: str | None, option: str) -> list[float] | None:
    """Comma-separated numbers (None when not given)."""
    if not text:
        return None
    try:
        return [float(v) for v in (s.strip() for s in text.split(',')) if v]
    except ValueError:
        raise IdentificationError(f'{option} must be numbers, got {text!r}') from None


def _noise(config: ExciteConfig, n: int) -> list[float] | None:
    values = _numbers(config.noise_std, '--noise-std')
    if values is not None and len(values) == 1:
        values *= n
    return values


def _settings(config: ExciteConfig) -> dict:
    """The --config file's settings, overridden by the command line's."""
    from identification_node.safe_yaml import read_yaml
    conf: dict = {}
    if config.config:
        conf = read_yaml(config.config, f'--config {config.config}') or {}
        if not isinstance(conf, dict):
            raise IdentificationError(f'--config {config.config} must be a mapping of '
                                      f'{", ".join(CONFIG_KEYS)}')
        unknown = sorted(set(map(str, conf)) - set(CONFIG_KEYS))
        if unknown:
            raise IdentificationError(f'--config {config.config}: unknown keys {unknown}; use '
                                      f'{", ".join(CONFIG_KEYS)}')
        if isinstance(conf.get('package_dirs'), str):
            conf['package_dirs'] = [conf['package_dirs']]
    given = {'margin': config.margin, 'periods': config.periods, 'srdf': config.srdf,
             'min_distance': config.min_distance,
             'package_dirs': None if config.package_dirs is None else list(config.package_dirs),
             'start': _numbers(config.start, '--start')}
    conf.update({k: v for k, v in given.items() if v is not None})
    return conf


def _outputs(config: ExciteConfig) -> tuple[Path, Path, Path, Path | None]:
    """(YAML, CSV, PNG, bag or None), checked writable."""
    out = Path(config.out)
    if out.suffix.lower() not in ('.yaml', '.yml'):
        raise IdentificationError(f'--out {config.out} must end in .yaml or .yml')
    csv, png = out.with_suffix('.csv'), out.with_suffix('.png')
    bag = Path(config.bag) if config.bag else None
    if not config.overwrite:
        existing = [str(p) for p in (out, csv, png, bag) if p is not None and p.exists()]
        if existing:
            raise IdentificationError(f'{", ".join(existing)} exist(s); pass --overwrite to '
                                      'replace')
    if bag is not None:
        from identification_node.bags.writer import check_replaceable
        check_replaceable(bag, '--bag')
    if not (config.rate > 0 and config.rate < float('inf')):
        raise IdentificationError(f'--rate must be a finite number > 0, got {config.rate}')
    return out, csv, png, bag


def _limits(config: ExciteConfig, conf: dict, robot: RobotModel) -> ExcitationLimits:
    from identification_node.excitation.limits import ExcitationLimits, load_limits
    limits = (load_limits(config.limits, robot, effort=not config.no_effort) if config.limits
              else ExcitationLimits.from_robot(robot, effort=not config.no_effort))
    if 'limits' in conf:
        limits = limits.updated(conf['limits'], f'--config {config.config} limits')
    return limits


def _checker(config: ExciteConfig, conf: dict, robot: RobotModel) -> CollisionChecker | None:
    """The CollisionChecker for a robot with collision geometry (None without, or with
    no_collision)."""
    from identification_node.excitation.collision import (DEFAULT_MIN_DISTANCE, CollisionChecker,
                                                          has_collision_geometry)
    wanted = any(k in conf for k in ('srdf', 'package_dirs', 'floor', 'boxes'))
    if config.no_collision:
        return None
    if not has_collision_geometry(robot):
        if wanted:
            raise IdentificationError(f'robot {robot.name} has no collision geometry: '
                                      '--srdf, --package-dir, floor and boxes need it')
        return None
    return CollisionChecker(robot, conf.get('package_dirs') or (), conf.get('srdf'),
                            conf.get('min_distance', DEFAULT_MIN_DISTANCE), conf.get('floor'),
                            conf.get('boxes') or ())


def excite(config: ExciteConfig, report: Callable[[str], None] = lambda line: None
           ) -> Excited:
    """Design the excitation ``config`` asks for and write its files (the module doc);
    ``report`` sees the problem's size first, then the optimiser's progress lines."""
    from identification_node.bags.writer import BagWriter
    from identification_node.excitation.criteria import DEFAULT_SAMPLES, criterion_value
    from identification_node.excitation.design import DEFAULT_MAXITER, optimize_excitation
    from identification_node.excitation.export import (plot_excitation, sample_times,
                                                       trajectory_to_joint_trajectory)
    from identification_node.excitation.framing import DEFAULT_PERIODS
    from identification_node.excitation.initial_guess import table1_trajectory
    from identification_node.excitation.limits import estimate_parameters
    from identification_node.excitation.result import DEFAULT_LIMIT_MARGIN
    from identification_node.excitation.sampled import write_motion_csv
    from identification_node.excitation.trajectories import TABLE1_PERIOD
    from identification_node.fileio import atomic_write_yaml
    from identification_node.model.identifiability import BaseParameters
    from identification_node.model.robot import load_robot

    out, csv, png, bag = _outputs(config)
    conf = _settings(config)
    robot = load_robot(config.robot, None if config.joints is None else list(config.joints),
                       extras=list(config.extras))
    limits = _limits(config, conf, robot)
    checker = _checker(config, conf, robot)
    phis = None
    if config.estimate:
        phis = [robot.phi_model, estimate_parameters(config.estimate, robot)]
    initial, harmonics, period = _initial(config, robot)
    noise = _noise(config, robot.dof)
    samples = DEFAULT_SAMPLES if config.samples is None else config.samples
    margin = conf.get('margin', DEFAULT_LIMIT_MARGIN)
    base = BaseParameters.from_robot(robot)
    report(f'robot {robot.name}: {robot.dof} joints, {base.num_base} base parameters; '
           f'{harmonics} harmonics, period {period:g} s, {samples} criterion samples'
           + (f', {checker.num_pairs} collision pairs' if checker is not None else ''))
    result = optimize_excitation(
        robot, harmonics, period, config.criterion, limits, seed=config.seed,
        maxiter=DEFAULT_MAXITER if config.maxiter is None else config.maxiter,
        num_samples=samples, initial=initial, base=base, noise_std=noise, margin=margin,
        start=conf.get('start'), periods=conf.get('periods', DEFAULT_PERIODS), phis=phis,
        checker=checker, progress=report, time_limit=config.time_limit)
    framed = result.framed
    assert framed is not None   # optimize_excitation's result is framed

    baseline = None
    if robot.name == 'crs_a465' and robot.dof == 6 and harmonics >= 5:
        baseline = criterion_value(robot, table1_trajectory(robot, harmonics, TABLE1_PERIOD),
                                   config.criterion, base, samples, noise)

    t = sample_times(framed, config.rate)
    write_motion_csv(csv, t, *framed.sample(t), robot.joint_names)
    plot_excitation(framed, limits, png, margin, config.rate,
                    f'{robot.name}: excitation ({config.criterion} {result.value:.4g})')
    if bag is not None:
        with BagWriter(bag, config.storage, overwrite=config.overwrite) as writer:
            writer.write(TOPIC, 0, trajectory_to_joint_trajectory(framed, config.rate))
    label = initial if isinstance(initial, str) else config.initial
    doc: dict[str, Any] = {
        **framed.to_dict(), 'robot': robot.name, 'joints': list(robot.joint_names),
        'harmonics': harmonics, 'initial': label, **result.summary(),
        'limits': limits.to_dict(), 'assumed_limits': limits.assumed,
        'torque_models': ['robot model'] + (['estimate ' + config.estimate]
                                            if config.estimate else []),
        'samples_csv': csv.name, 'plot': png.name}
    if baseline is not None:
        doc['criterion']['table1'] = baseline
    if bag is not None:
        doc['bag'] = {'path': str(bag), 'topic': TOPIC, 'rate': config.rate}
    atomic_write_yaml(out, doc)
    return Excited(robot, result, limits, margin, checker, baseline, label, period,
                   [out, csv, png] + ([bag] if bag is not None else []),
                   not config.no_collision)


def _ratio_line(result: ExcitationResult) -> str:
    names = result.trajectory.joint_names or []
    parts = [f'{k} {result.ratios[k]:.3f} ({names[result.ratios["worst_joint"][k]]})'
             for k in ('position', 'velocity', 'acceleration', 'effort')]
    return 'worst limit ratios (1 = at the limit): ' + ', '.join(parts)


def excite_text(excited: Excited) -> list[str]:
    """The summary lines of an excitation: criterion, optimiser, durations, limit ratios,
    assumed limits and collision clearance (or why collisions were not checked)."""
    result, robot, checker = excited.result, excited.robot, excited.checker
    framed = result.framed
    assert framed is not None   # excite's result is framed
    lines = []
    line = (f'criterion {result.criterion}: {result.initial_value:.6g} (initial '
            f'{excited.label}' + ('' if result.initial_feasible else ', infeasible')
            + f') -> {result.value:.6g}')
    if excited.baseline is not None:
        line += f' (Table I: {excited.baseline:.6g})'
    lines.append(line)
    lines.append(f'SLSQP: {result.iterations} iterations, {result.evaluations} evaluations, '
                 f'{result.runtime:.1f} s ({result.message})')
    parts = framed.parts()
    lines.append(f'durations: ramp in {parts["ramp_in"]:.1f} s, periodic '
                 f'{parts["periodic"]:.1f} s ({framed.periods} x {excited.period:g} s, the '
                 f'part to identify from), ramp out {parts["ramp_out"]:.1f} s, total '
                 f'{parts["total"]:.1f} s; start and end at rest at ['
                 + ', '.join(f'{v:.4g}' for v in framed.start) + '] rad')
    lines.append(_ratio_line(result) + f'; margin {100 * excited.margin:g} %')
    if excited.limits.assumed:
        lines.append('limits not in the robot description, assumed: '
                     + '; '.join(excited.limits.assumed_list()))
    if checker is not None:
        c = result.clearance
        line = f'collision: {checker.num_pairs} pairs checked'
        line += f' ({checker.srdf_removed} disabled by the SRDF)'
        if c is not None:
            line += (f', smallest distance {c["distance"]:.4g} m ({c["pair"][0]} - '
                     f'{c["pair"][1]}), minimum {checker.min_distance:g} m')
        lines.append(line)
    elif excited.collision_asked:
        lines.append(f'collision: not checked (the description of {robot.name} has no '
                     'collision geometry)')
    return lines
