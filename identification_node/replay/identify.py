"""identify(bag, config): the offline identification of one bag, the use case of ``identify``.

The robot is the configured one (``robot_given``, or the settings' robot), else the bag's
/robot_description. ``method`` 'rls' (default) streams the bag through the node's own
pipeline (stream.replay_identify, or replay/parallel.py with ``workers``); 'batch' processes
the whole bag at once (batch/): periodic averaging with ``period`` or a periodic
``trajectory``, else zero-phase filtering (``cutoff``) and decimation (``decimate``), then
weighted least squares. The estimate is the physically consistent one
(results.identification.make_consistent) unless ``physical_consistency`` is False; the torque
errors on the training bag and on each validation bag are those of validation.bag_error, on
the messages of [start, end) s of each bag. ``back_emf`` and ``known_payload_bag``/
``known_payload`` first identify the drive gains (batch/drive_gains.py) and identify with them;
``payload`` identifies the payload and its changes (payload/monitor.py). Writes ``save``
(estimate.yaml, identified.urdf), ``report`` (report.md and figures) and ``predictions``.
Returns the result document (results.documents.result_document) with what was added.
"""
from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from typing import Callable

from identification_node.bags.feed import JOINT_STATES, MOTOR_CURRENTS
from identification_node.bags.windows import TimeWindow
from identification_node.batch.rows import BatchOptions
from identification_node.errors import IdentificationError
from identification_node.model.robot import RobotModel
from identification_node.replay.stream import (bag_robot, foreign_joints_warning,
                                               locked_warning, mimic_warning, replay_identify,
                                               robot_for_bag)
from identification_node.replay.validation import bag_error, check_same_robot
from identification_node.results.documents import result_document, saved_document
from identification_node.results.identification import Identification, make_consistent
from identification_node.settings import Settings

__all__ = ['BATCH_OPTIONS', 'IdentifyConfig', 'Identified', 'identify', 'identify_method',
           'batch_options']

# the options of batch processing (IdentifyConfig fields): any given selects method 'batch'
BATCH_OPTIONS = ('period', 'trajectory', 'harmonics', 'cutoff', 'decimate',
                 'trajectory_start')


@dataclass(frozen=True)
class IdentifyConfig:
    """What identify does with a bag (the ``identify`` verb's options; times s after each
    bag's first message, period s, cutoff Hz; paths as given)."""
    settings: Settings
    robot_given: bool = False              # the robot of ``settings``, not the bag's
    method: str | None = None              # 'rls', 'batch'; None: batch when a batch option
    period: float | None = None
    trajectory: str | None = None
    trajectory_start: float | None = None
    harmonics: int | None = None
    cutoff: float | None = None
    decimate: int | None = None
    joint_states: str = JOINT_STATES
    currents: str = MOTOR_CURRENTS
    voltages: str = '/motor_voltages'
    validation_bags: tuple[str, ...] = ()
    start: float | None = None
    end: float | None = None
    predictions: str | None = None
    report: str | None = None
    save: str | None = None
    save_inconsistent: bool = False
    workers: int = 1
    physical_consistency: bool = True
    payload: bool = False
    payload_link: str | None = None
    arm: str | None = None
    arm_table: bool = False
    back_emf: bool = False
    known_payload_bag: str | None = None
    known_payload: str | None = None


@dataclass
class Identified:
    """identify's outcome: the Identification, its document (with drive_gains,
    payload_changes, saved, report, predictions when done) and the drive gains (or None)."""
    ident: Identification
    doc: dict
    gains: list | None = None


def identify_method(config: IdentifyConfig) -> str:
    """'rls' or 'batch': the configured method, else batch when a batch option is given."""
    given = [f"--{o.replace('_', '-')}" for o in BATCH_OPTIONS
             if getattr(config, o) is not None]
    if config.method == 'rls' and given:
        raise IdentificationError(f"{', '.join(given)} only apply to --method batch")
    return config.method or ('batch' if given else 'rls')


def batch_options(config: IdentifyConfig, robot: RobotModel) -> BatchOptions:
    """BatchOptions from period, trajectory (its period and harmonics; of a framed one the
    periodic window, from trajectory_start), harmonics, cutoff and decimate."""
    from identification_node.excitation.trajectories import FramedTrajectory, load_trajectory

    period, least, window = config.period, 1, None
    if config.trajectory_start is not None and not config.trajectory:
        raise IdentificationError('--trajectory-start needs a framed --trajectory')
    if config.trajectory:
        traj = load_trajectory(config.trajectory, robot)
        if isinstance(traj, FramedTrajectory):
            offset = config.trajectory_start or 0.0
            if not (offset >= 0 and offset < float('inf')):
                raise IdentificationError(f'--trajectory-start must be >= 0 s, got {offset}')
            t0, t1 = traj.periodic_window
            window = (offset + t0, offset + t1)
            traj = traj.periodic
        elif config.trajectory_start is not None:
            raise IdentificationError(f'--trajectory-start needs a framed --trajectory; '
                                      f'{config.trajectory} has no ramps')
        if traj.period is None:
            raise IdentificationError(f'trajectory {config.trajectory} is not periodic: batch '
                                      'processing uses it for its period')
        if period is not None and abs(period - traj.period) > 1e-9 * traj.period:
            raise IdentificationError(f'--period {period} s differs from the period '
                                      f'{traj.period} s of {config.trajectory}')
        period, least = traj.period, getattr(traj, 'harmonics', 1)
    if period is None and config.harmonics is not None:
        raise IdentificationError('--harmonics needs --period or a periodic --trajectory')
    options = BatchOptions(period=period, window=window, harmonics=config.harmonics,
                           min_harmonics=least,
                           cutoff=config.cutoff,
                           decimation=config.decimate)
    options.validate()
    return options


def _payload_monitor(config: IdentifyConfig, settings: Settings, robot: RobotModel,
                     method: str):
    """The PayloadMonitor of ``payload`` (None without it)."""
    if not config.payload:
        if config.payload_link or config.arm or config.arm_table:
            raise IdentificationError('--payload-link, --arm and --arm-table need --payload')
        return None
    if method != 'rls':
        raise IdentificationError('--payload streams the bag: not with --method batch')
    from identification_node.payload.monitor import monitor_from_settings
    values = dict(settings.values)
    values.update({'payload.link': config.payload_link or values['payload.link'],
                   'payload.arm': config.arm or values['payload.arm']})
    return monitor_from_settings(Settings(values, settings.given), robot)


def _check_outputs(config: IdentifyConfig) -> None:
    """IdentificationError now, before any work, when an output cannot be written."""
    if config.report:
        from identification_node.results.report import check_writable
        check_writable(config.report)
    if config.save:
        from identification_node.fileio import writable_directory
        writable_directory(config.save, '--save')
    if config.predictions:
        from identification_node.results.predictions import check_predictions
        check_predictions(config.predictions)


def _warn_unverified(bags: list, warn: Callable[[str], None]) -> None:
    from identification_node.bags.reader import open_bag

    for bag in bags:
        with open_bag(bag) as reader:   # its chunk CRCs verified
            if reader.unverified_chunks:
                warn(f'bag {bag}: {reader.unverified_chunks} mcap chunk(s) carry no CRC, so '
                     'corruption in them cannot be detected')


def _evaluate_bags(ident: Identification, bag: str | os.PathLike, config: IdentifyConfig,
                   settings: Settings, window: TimeWindow, topics: tuple[str, str]):
    """The torque errors on the training bag and on each validation bag (validation.py),
    with the predictions written as they are computed."""
    from identification_node.results.predictions import PredictionsWriter

    with (PredictionsWriter(config.predictions, ident.robot.joint_names)
          if config.predictions else contextlib.nullcontext()) as writer:
        training = bag_error(ident, bag, settings, window, *topics, predictions=writer,
                             label='training', training=True)
        validations = [bag_error(ident, other, settings, window, *topics, predictions=writer,
                                 label=f'validation{k}')
                       for k, other in enumerate(config.validation_bags, 1)]
    return training, validations


def identify(bag: str | os.PathLike, config: IdentifyConfig,
             warn: Callable[[str], None] = lambda text: None) -> Identified:
    """The identification of ``bag`` as ``config`` says (the module doc); ``warn`` sees each
    warning for the user as soon as it is known (the document's warnings have them too)."""
    settings = config.settings
    if config.workers < 0:
        raise IdentificationError(f'--workers must be >= 0 (0: one per core), got '
                                  f'{config.workers}')
    window = TimeWindow(config.start, config.end).validate()
    consistency = None if not config.physical_consistency else settings.consistency_options()
    method = identify_method(config)
    _check_outputs(config)
    robot = (settings.load_robot() if config.robot_given or settings.given_robot
             else bag_robot(bag, settings))
    robot, settings, locked = robot_for_bag(robot, settings, bag, config.joint_states)
    check_same_robot(bag, robot, 'training')
    foreign = foreign_joints_warning(robot, bag, config.joint_states)
    if foreign:
        warn(foreign)
    from identification_node.estimation.prior import safe_prior
    for note in safe_prior(robot)[1]:
        warn(note)
    _warn_unverified([bag] + list(config.validation_bags), warn)
    topics = (config.joint_states, config.currents)
    gains = None
    if config.back_emf or config.known_payload_bag or config.known_payload:
        from identification_node.batch.drive_gains import (identify_drive_gains,
                                                           settings_with_gains, used_gains)
        gains = identify_drive_gains(bag, settings, robot, *topics,
                                     config.voltages if config.back_emf else None,
                                     config.known_payload_bag, config.known_payload)
        settings = settings_with_gains(settings, robot, used_gains(gains))
    pipeline = settings.build(robot) if method == 'rls' else None
    monitor = _payload_monitor(config, settings, robot, method)
    ident = None
    if method == 'rls' and config.workers != 1 and monitor is None and not config.report \
            and config.start is None and config.end is None:
        from identification_node.replay.parallel import default_workers, parallel_identify
        ident = parallel_identify(bag, settings, robot, config.workers or default_workers(),
                                  *topics)
    if ident is None and method == 'rls':
        ident = replay_identify(bag, settings, robot, *topics, on_output=None if (
            monitor is None) else monitor.add_output, window=window, pipeline=pipeline)
    elif ident is None:
        from identification_node.batch.solve import offline_identify
        options = batch_options(config, robot)
        ident = offline_identify(bag, settings, robot, options, *topics, window=window)
    offset = ident.time_offset   # the torque against the motion (pipeline/time_offset.py)
    if offset is not None and offset.level == 2:
        raise IdentificationError(f'bag {bag}: {offset.describe()}; not identified '
                                  '(time_offset.warn: 0 in --config skips the check)')
    if locked:
        ident.warnings.insert(0, locked_warning(robot, locked, config.joint_states))
    mimics = mimic_warning(robot, bag, config.joint_states)
    if mimics:
        ident.warnings.insert(0, mimics)
    if foreign:
        ident.warnings.insert(0, foreign)
    make_consistent(ident, consistency)
    training, validations = _evaluate_bags(ident, bag, config, settings, window, topics)
    from identification_node.results.effort_semantics import training_gravity_warning
    gravity = training_gravity_warning(ident, training)
    if gravity:
        ident.warnings.append(gravity)
    doc = result_document(ident, validations, training)
    if gains is not None:
        doc['drive_gains'] = [g.document() for g in gains]
        doc['warnings'] += [g.warning for g in gains if g.warning]
    if monitor is not None:
        from identification_node.payload.monitor import segments_document
        from identification_node.results.documents import plain
        doc['payload_changes'] = plain(segments_document(monitor.finish()))
        doc['payload_warnings'] = monitor.warnings()
        for w in doc['payload_warnings']:
            warn(w)
    _write_outputs(ident, robot, doc, config, gains, training, validations)
    return Identified(ident, doc, gains)


def _write_outputs(ident: Identification, robot: RobotModel, doc: dict,
                   config: IdentifyConfig, gains, training, validations) -> None:
    """save, report and predictions, named in ``doc`` (a failed save: in its errors)."""
    if config.save:
        from identification_node.results.documents import write_results
        saved = saved_document(ident)
        if gains is not None:
            saved['drive_gains'] = doc['drive_gains']
        try:
            doc['saved'] = [str(p) for p in write_results(
                config.save, saved, robot, inconsistent=config.save_inconsistent)]
        except IdentificationError as exc:   # the report is printed, then the exit status 1
            doc['errors'].append(str(exc))
            doc['saved'] = []
    if config.report:
        from identification_node.results.report import write_report
        report = write_report(config.report, ident, validations, training)
        doc['report'] = {k: str(p) for k, p in report.files.items()}
    if config.predictions:
        doc['predictions'] = str(config.predictions)
