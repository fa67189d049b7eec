"""``identify BAG``: offline identification, without DDS.

The robot is --robot/--urdf, else the robot of --config, else the bag's /robot_description.
``--method rls`` (default) streams the bag through the node's own pipeline; ``--method batch``
processes the whole bag at once (offline.py): periodic averaging with --period or a periodic
--trajectory, else zero-phase filtering (--cutoff) and decimation (--decimate), then weighted
least squares. Prints the base parameter estimate with standard deviations, the per-joint
relative torque error 100 ||tau_measured - tau_predicted|| / ||tau_measured|| on the training
bag and on each ``--validate`` bag against the raw torque (offline/validation.py), the
excitation condition number and how the estimate converged; ``--start``/``--end`` window every
bag (offline/windows.py), ``--predictions OUT`` writes measured and predicted torque per sample
(offline/predictions.py), ``--report DIR`` writes report.md with figures, ``--json`` prints the
same as one object, ``--save DIR`` writes estimate.yaml and identified.urdf as the node's
``~/save`` does. The estimate is the physically consistent one (consistency.py) unless
``--no-physical-consistency`` (config ``physical_consistency: false``); the unconstrained one
is reported alongside. ``--back-emf`` and ``--known-payload-bag``/``--known-payload`` first
identify the drive gains (offline/drive_gains.py) and identify with them: ``drive_gains``.
"""
from __future__ import annotations

import argparse
import json
import sys


from identification_node.cli import add_robot_arguments, add_settings_arguments, settings_from_args
from identification_node.results.documents import result_document, saved_document
from identification_node.results.text import (format_outputs, format_payload_changes,
                                              format_report, paper_table3)
from identification_node.replay.validation import bag_error

BATCH_OPTIONS = ('period', 'trajectory', 'harmonics', 'cutoff', 'decimate',
                 'trajectory_start')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', help='rosbag2 bag directory (mcap or sqlite3)')
    add_robot_arguments(parser, required=False)
    add_settings_arguments(parser)
    parser.add_argument('--json', action='store_true', help='print one JSON object')
    parser.add_argument('--joint-states-topic', default='/joint_states')
    parser.add_argument('--currents-topic', default='/motor_currents')
    parser.add_argument('--paper-tables', action='store_true',
                        help="MIT arm: compare with the first paper's Table 3")
    parser.add_argument('--method', choices=('rls', 'batch'),
                        help='rls: the node\'s streaming pipeline (default); batch: the whole '
                        'bag at once (default when a batch option below is given)')
    batch = parser.add_argument_group('batch processing')
    batch.add_argument('--period', type=float, metavar='S',
                       help='periodic motion of this period (s): average over whole periods')
    batch.add_argument('--trajectory', metavar='FILE',
                       help='the periodic (Fourier .yaml) trajectory the bag followed: its '
                       'period, and its harmonics at least in the position fit; of a framed '
                       'one (excite\'s output) only the periodic part between the ramps is used')
    batch.add_argument('--trajectory-start', type=float, metavar='S',
                       help='s after the bag\'s first sample at which the framed --trajectory '
                       'started (default 0)')
    batch.add_argument('--harmonics', type=int, metavar='H',
                       help='harmonics of the Fourier fit to the averaged positions '
                       '(default: chosen from the data, up to cutoff x period)')
    batch.add_argument('--cutoff', type=float, metavar='HZ',
                       help='zero-phase low-pass cutoff (default: smoother.cutoff, or when '
                       'that is 0 the smoother\'s cut-off chosen from the first '
                       'smoother.auto_seconds of motion)')
    batch.add_argument('--decimate', type=int, metavar='K',
                       help='keep every K-th filtered sample (default: rate / (2 cutoff))')
    parser.add_argument('--validate', metavar='BAG', nargs='+',
                        help='held-out bags of the same robot: relative torque error of the '
                        'estimate on each, against the raw torque')
    parser.add_argument('--start', type=float, metavar='S',
                        help='use the messages recorded from S seconds after the first of '
                        'each bag (training and validation)')
    parser.add_argument('--end', type=float, metavar='S',
                        help='use the messages recorded up to S seconds after the first of '
                        'each bag (training and validation)')
    parser.add_argument('--predictions', metavar='OUT',
                        help='write measured and predicted torque per sample of every bag: '
                        'OUT an mcap bag (topics /training/measured_effort, '
                        '/training/predicted_effort, /validation1/...) and OUT.csv; OUT ending '
                        'in .csv: the CSV alone')
    payload = parser.add_argument_group('payload')
    payload.add_argument('--payload', action='store_true',
                         help='identify the payload and detect its changes: payload_changes')
    payload.add_argument('--payload-link', metavar='L',
                         help='link or fixed frame carrying the payload (default: the last '
                         'identified link)')
    payload.add_argument('--arm', metavar='ESTIMATE_YAML',
                         help="the arm's parameters without payload (estimate.yaml, ~/save); "
                         "default: the model's own")
    payload.add_argument('--arm-table', action='store_true',
                         help="with --payload, print the arm's identification too (the "
                         'payload changes alone otherwise)')
    drive = parser.add_argument_group(
        'drive gains (N m/A at the joint = kt x gear_ratio, identified in situ; the torques '
        'then use them)')
    drive.add_argument('--back-emf', action='store_true',
                       help='back-EMF method: fit V = R i + L di/dt + K_E omega per joint from '
                       'the motor voltages (needs motor speed)')
    drive.add_argument('--voltages-topic', default='/motor_voltages')
    drive.add_argument('--known-payload-bag', metavar='LOADED_BAG',
                       help='known-payload method: the same arm moving with --known-payload '
                       '(its gravity and inertia excited)')
    drive.add_argument('--known-payload', metavar='PAYLOAD_YAML',
                       help='the payload of --known-payload-bag: mass, com, inertia, link (the '
                       'fields of --payload-events entries)')
    parser.add_argument('--report', metavar='DIR',
                        help='write report.md and PNG figures into DIR')
    parser.add_argument('--save', metavar='DIR',
                        help="write estimate.yaml and identified.urdf into DIR (the node's "
                        '~/save)')
    parser.add_argument('--workers', type=int, default=1, metavar='N',
                        help='rls: stream the bag\'s 60 s segments in N processes and merge '
                        'their statistics (replay/parallel.py; 0: one per core; default 1). '
                        'Not with --report, --payload, --start/--end')
    parser.add_argument('--save-inconsistent', action='store_true',
                        help='--save writes an estimate that is not physically consistent too '
                        '(refused by default)')
    parser.add_argument('--no-physical-consistency', action='store_true',
                        help='the unconstrained least-squares estimate only (config: '
                        'physical_consistency: false)')


def _method(args: argparse.Namespace) -> str:
    from identification_node.errors import IdentificationError

    given = [f"--{o.replace('_', '-')}" for o in BATCH_OPTIONS if getattr(args, o) is not None]
    if args.method == 'rls' and given:
        raise IdentificationError(f"{', '.join(given)} only apply to --method batch")
    return args.method or ('batch' if given else 'rls')


def batch_options(args: argparse.Namespace, robot):
    """offline.BatchOptions from --period/--trajectory/--harmonics/--cutoff/--decimate."""
    from identification_node.errors import IdentificationError
    from identification_node.batch.rows import BatchOptions
    from identification_node.excitation.trajectories import FramedTrajectory, load_trajectory

    period, least, window = args.period, 1, None
    if args.trajectory_start is not None and not args.trajectory:
        raise IdentificationError('--trajectory-start needs a framed --trajectory')
    if args.trajectory:
        traj = load_trajectory(args.trajectory, robot)
        if isinstance(traj, FramedTrajectory):
            offset = args.trajectory_start or 0.0
            if not (offset >= 0 and offset < float('inf')):
                raise IdentificationError(f'--trajectory-start must be >= 0 s, got {offset}')
            window = tuple(offset + t for t in traj.periodic_window)
            traj = traj.periodic
        elif args.trajectory_start is not None:
            raise IdentificationError(f'--trajectory-start needs a framed --trajectory; '
                                      f'{args.trajectory} has no ramps')
        if traj.period is None:
            raise IdentificationError(f'trajectory {args.trajectory} is not periodic: batch '
                                      'processing uses it for its period')
        if period is not None and abs(period - traj.period) > 1e-9 * traj.period:
            raise IdentificationError(f'--period {period} s differs from the period '
                                      f'{traj.period} s of {args.trajectory}')
        period, least = traj.period, getattr(traj, 'harmonics', 1)
    if period is None and args.harmonics is not None:
        raise IdentificationError('--harmonics needs --period or a periodic --trajectory')
    options = BatchOptions(period=period, window=window, harmonics=args.harmonics,
                           min_harmonics=least,
                           cutoff=args.cutoff,
                           decimation=args.decimate)
    options.validate()
    return options


def payload_monitor(args: argparse.Namespace, settings, robot, method: str):
    """The PayloadMonitor of --payload (None without it)."""
    from identification_node.errors import IdentificationError
    if not args.payload:
        if args.payload_link or args.arm or args.arm_table:
            raise IdentificationError('--payload-link, --arm and --arm-table need --payload')
        return None
    if method != 'rls':
        raise IdentificationError('--payload streams the bag: not with --method batch')
    from identification_node.payload.monitor import monitor_from_settings
    from identification_node.settings import Settings
    values = dict(settings.values)
    values.update({'payload.link': args.payload_link or values['payload.link'],
                   'payload.arm': args.arm or values['payload.arm']})
    return monitor_from_settings(Settings(values, settings.given), robot)


def evaluate_bags(ident, args: argparse.Namespace, settings, window, topics):
    """The torque errors on the training bag and on each --validate bag (validation.py),
    with --predictions written as they are computed."""
    import contextlib

    from identification_node.results.predictions import PredictionsWriter

    with (PredictionsWriter(args.predictions, ident.robot.joint_names) if args.predictions
          else contextlib.nullcontext()) as writer:
        training = bag_error(ident, args.bag, settings, window, *topics, predictions=writer,
                             label='training', training=True)
        validations = [bag_error(ident, bag, settings, window, *topics, predictions=writer,
                                 label=f'validation{k}')
                       for k, bag in enumerate(args.validate or [], 1)]
    return training, validations


def run(args: argparse.Namespace) -> int:
    from identification_node.errors import IdentificationError
    from identification_node.batch.solve import offline_identify
    from identification_node.replay.stream import replay_identify
    from identification_node.replay.validation import check_same_robot
    from identification_node.results.identification import make_consistent
    from identification_node.replay.stream import (bag_robot, foreign_joints_warning,
                                                   locked_warning, mimic_warning, robot_for_bag)
    from identification_node.bags.windows import TimeWindow

    settings = settings_from_args(args)
    if args.workers < 0:
        raise IdentificationError(f'--workers must be >= 0 (0: one per core), got '
                                  f'{args.workers}')
    window = TimeWindow(args.start, args.end).validate()
    consistency = None if args.no_physical_consistency else settings.consistency_options()
    method = _method(args)
    if args.report:
        from identification_node.results.report import check_writable
        check_writable(args.report)
    if args.save:
        from identification_node.fileio import writable_directory
        writable_directory(args.save, '--save')
    if args.predictions:
        from identification_node.results.predictions import check_predictions
        check_predictions(args.predictions)
    robot = (settings.load_robot() if args.robot or args.urdf or settings.given_robot
             else bag_robot(args.bag, settings))
    robot, settings, locked = robot_for_bag(robot, settings, args.bag, args.joint_states_topic)
    check_same_robot(args.bag, robot, 'training')
    foreign = foreign_joints_warning(robot, args.bag, args.joint_states_topic)
    if foreign:
        print(f'warning: {foreign}', file=sys.stderr)
    from identification_node.bags.reader import open_bag
    from identification_node.estimation.prior import safe_prior
    for note in safe_prior(robot)[1]:
        print(f'warning: {note}', file=sys.stderr)
    for bag in [args.bag] + (args.validate or []):
        with open_bag(bag) as reader:   # its chunk CRCs verified
            if reader.unverified_chunks:
                print(f'warning: bag {bag}: {reader.unverified_chunks} mcap chunk(s) carry no '
                      'CRC, so corruption in them cannot be detected', file=sys.stderr)
    topics = (args.joint_states_topic, args.currents_topic)
    gains = None
    if args.back_emf or args.known_payload_bag or args.known_payload:
        from identification_node.batch.drive_gains import (identify_drive_gains,
                                                           settings_with_gains, used_gains)
        gains = identify_drive_gains(args.bag, settings, robot, *topics,
                                     args.voltages_topic if args.back_emf else None,
                                     args.known_payload_bag, args.known_payload)
        settings = settings_with_gains(settings, robot, used_gains(gains))
    options = None
    pipeline = settings.build(robot) if method == 'rls' else None
    monitor = payload_monitor(args, settings, robot, method)
    ident = None
    if method == 'rls' and args.workers != 1 and monitor is None and not args.report \
            and args.start is None and args.end is None:
        from identification_node.replay.parallel import default_workers, parallel_identify
        ident = parallel_identify(args.bag, settings, robot, args.workers or default_workers(),
                                  *topics)
    if ident is None and method == 'rls':
        ident = replay_identify(args.bag, settings, robot, *topics, on_output=None if (
            monitor is None) else monitor.add_output, window=window, pipeline=pipeline)
    elif ident is None:
        options = batch_options(args, robot)
        ident = offline_identify(args.bag, settings, robot, options, *topics, window=window)
    offset = ident.time_offset   # the torque against the motion (pipeline/time_offset.py)
    if offset is not None and offset.level == 2:
        raise IdentificationError(f'bag {args.bag}: {offset.describe()}; not identified '
                                  '(time_offset.warn: 0 in --config skips the check)')
    if locked:
        ident.warnings.insert(0, locked_warning(robot, locked, args.joint_states_topic))
    mimics = mimic_warning(robot, args.bag, args.joint_states_topic)
    if mimics:
        ident.warnings.insert(0, mimics)
    if foreign:
        ident.warnings.insert(0, foreign)
    make_consistent(ident, consistency)
    training, validations = evaluate_bags(ident, args, settings, window, topics)
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
            print(f'warning: {w}', file=sys.stderr)
    if args.save:
        from identification_node.results.documents import write_results
        saved = saved_document(ident)
        if gains is not None:
            saved['drive_gains'] = doc['drive_gains']
        try:
            doc['saved'] = [str(p) for p in write_results(
                args.save, saved, robot, inconsistent=args.save_inconsistent)]
        except IdentificationError as exc:   # the report is printed, then the exit status 1
            doc['errors'].append(str(exc))
            doc['saved'] = []
    if args.report:
        from identification_node.results.report import write_report
        report = write_report(args.report, ident, validations, training)
        doc['report'] = {k: str(p) for k, p in report.files.items()}
    if args.predictions:
        doc['predictions'] = str(args.predictions)
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        payload = 'payload_changes' in doc
        if payload:   # the payload first; the arm's table when asked
            print(format_payload_changes(doc['payload_changes'], doc['payload_warnings']))
        if not payload or args.arm_table:
            print(('\n' if payload else '') + format_report(doc))
        if args.paper_tables:
            print(paper_table3(ident))
        if gains is not None:
            from identification_node.estimation.drive_gains import gains_text
            print('\n'.join(gains_text(gains)))
        print(format_outputs(doc))
    for error in doc['errors'] if args.json else ():   # the text report has them
        print(f'error: {error}', file=sys.stderr)
    return 1 if args.save and not doc['saved'] else 0
