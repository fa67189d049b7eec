"""``identify BAG``: offline identification, without DDS (replay/identify.py does it).

The robot is --robot/--urdf, else the robot of --config, else the bag's /robot_description.
``--method rls`` (default) streams the bag through the node's own pipeline; ``--method batch``
processes the whole bag at once (batch/): periodic averaging with --period or a periodic
--trajectory, else zero-phase filtering (--cutoff) and decimation (--decimate), then weighted
least squares. Prints the base parameter estimate with standard deviations, the per-joint
relative torque error 100 ||tau_measured - tau_predicted|| / ||tau_measured|| on the training
bag and on each ``--validate`` bag against the raw torque (replay/validation.py), the
excitation condition number and how the estimate converged; ``--start``/``--end`` window every
bag (bags/windows.py), ``--predictions OUT`` writes measured and predicted torque per sample
(results/predictions.py), ``--report DIR`` writes report.md with figures, ``--json`` prints the
same as one object, ``--save DIR`` writes estimate.yaml and identified.urdf as the node's
``~/save`` does. The estimate is the physically consistent one (consistency.py) unless
``--no-physical-consistency`` (config ``physical_consistency: false``); the unconstrained one
is reported alongside. ``--back-emf`` and ``--known-payload-bag``/``--known-payload`` first
identify the drive gains (batch/drive_gains.py) and identify with them: ``drive_gains``.
"""
from __future__ import annotations

import argparse
import json
import sys

from identification_node.cli import add_robot_arguments, add_settings_arguments, settings_from_args


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
                        help='rls: stream the bag in N equal segments (cut at a 10 s grid) '
                        'in N processes and merge their statistics (replay/parallel.py; 0: one '
                        'per core; default 1). Not with --report, --payload, --start/--end')
    parser.add_argument('--save-inconsistent', action='store_true',
                        help='--save writes an estimate that is not physically consistent too '
                        '(refused by default)')
    parser.add_argument('--no-physical-consistency', action='store_true',
                        help='the unconstrained least-squares estimate only (config: '
                        'physical_consistency: false)')


def run(args: argparse.Namespace) -> int:
    from identification_node.replay.identify import IdentifyConfig, identify
    from identification_node.results.text import identify_text

    config = IdentifyConfig(
        settings_from_args(args), robot_given=bool(args.robot or args.urdf),
        method=args.method, period=args.period, trajectory=args.trajectory,
        trajectory_start=args.trajectory_start, harmonics=args.harmonics, cutoff=args.cutoff,
        decimate=args.decimate, joint_states=args.joint_states_topic,
        currents=args.currents_topic, voltages=args.voltages_topic,
        validation_bags=tuple(args.validate or ()), start=args.start, end=args.end,
        predictions=args.predictions, report=args.report, save=args.save,
        save_inconsistent=args.save_inconsistent, workers=args.workers,
        physical_consistency=not args.no_physical_consistency, payload=args.payload,
        payload_link=args.payload_link, arm=args.arm, arm_table=args.arm_table,
        back_emf=args.back_emf, known_payload_bag=args.known_payload_bag,
        known_payload=args.known_payload)
    result = identify(args.bag, config,
                      warn=lambda text: print(f'warning: {text}', file=sys.stderr))
    doc = result.doc
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        for block in identify_text(doc, result.ident, result.gains, args.arm_table,
                                   args.paper_tables):
            print(block)
    for error in doc['errors'] if args.json else ():   # the text report has them
        print(f'error: {error}', file=sys.stderr)
    return 1 if args.save and not doc['saved'] else 0
