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
import textwrap
import sys

import numpy as np

from identification_node.cli import add_robot_arguments, add_settings_arguments, settings_from_args

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
                        'their statistics (offline/parallel.py; 0: one per core; default 1). '
                        'Not with --report, --payload, --start/--end')
    parser.add_argument('--save-inconsistent', action='store_true',
                        help='--save writes an estimate that is not physically consistent too '
                        '(refused by default)')
    parser.add_argument('--no-physical-consistency', action='store_true',
                        help='the unconstrained least-squares estimate only (config: '
                        'physical_consistency: false)')


def result_document(result, validations=(), training=None) -> dict:
    """The ``--json`` object of an identification (offline.Identification, or the
    replay.ReplayResult of the streaming pipeline), with the torque errors on the training
    bag and on the validation bags (validation.BagError) when given."""
    from identification_node.offline.identification import Identification, from_replay
    from identification_node.offline.results import parameters_document, plain
    from identification_node.model.urdf_export import consistency_problems

    ident = result if isinstance(result, Identification) else from_replay(result)
    robot, base = ident.robot, ident.base
    problems = ident.consistency_problems()
    unexcited = ident.unexcited
    # parameters in an unexcited direction: the data say nothing about them, so no estimate
    blind = {name for _, names in unexcited for name in names}
    params = parameters_document(robot, base, ident.theta, ident.stddev, ident.consistent,
                                 ident.covariance)
    doc = {
        'bag': ident.bag, 'robot': robot.name, 'joints': robot.joint_names,
        'method': ident.method, 'processing': ident.details,
        'num_samples': ident.num_samples, 'messages': ident.messages,
        'base_parameters': [
            {'name': n, 'expression': e, 'terms': t,
             'estimate': None if n in blind else float(v),
             'unconstrained_estimate': None if n in blind else float(u),
             'stddev': None if n in blind else float(s),
             'rel_stddev': None if n in blind else float(r), 'model': float(m),
             'excited': n not in blind}
            for n, e, t, v, u, s, r, m in zip(base.names, base.expressions, base.terms,
                                              ident.estimate, ident.theta, ident.stddev,
                                              ident.rel_stddev, ident.theta_model)],
        'estimate': ident.estimate.tolist(),
        'unconstrained_estimate': ident.theta.tolist(),
        'stddev': ident.stddev.tolist(),
        'consistency_solver': params['consistency_solver'],
        'links': params['links'],
        'standard_parameters': params['standard_parameters'],
        'relative_error': dict(zip(robot.joint_names, ident.relative_error(
            ident.estimate).tolist())),
        'unconstrained_relative_error': dict(zip(robot.joint_names,
                                                 ident.relative_error().tolist())),
        'model_relative_error': dict(zip(robot.joint_names, ident.relative_error(
            ident.theta_model).tolist())),
        'residual_rms': dict(zip(robot.joint_names, ident.residual_rms.tolist())),
        'noise_std': dict(zip(robot.joint_names, np.sqrt(ident.noise_variance).tolist())),
        'condition_number': ident.condition_number,
        'excited': not unexcited,
        'unexcited_directions': [text for text, _ in unexcited],
        'converged': ident.converged and not unexcited,
        'smoother_delay_samples': (ident.pipeline.smoother.half_window
                                   if ident.pipeline is not None
                                   and ident.pipeline.smoother is not None else None),
        'smoother': (ident.pipeline.smoother.document() if ident.pipeline is not None
                     and ident.pipeline.smoother is not None else None),
        'rejected': ident.rejected,
        'excluded_equations': ident.details.get('excluded_per_joint', {}),
        'warnings': list(ident.warnings),
        'physically_consistent': not problems, 'consistency_problems': problems,
        'errors': consistency_errors(params['consistency_solver'], problems),
        'model_consistency_problems': consistency_problems(robot, robot.phi_model),
        'convergence': [{'num_samples': c.num_samples, 'estimate': np.asarray(c.values).tolist(),
                         'stddev': np.asarray(c.stddev).tolist()} for c in ident.history],
    }
    if training is not None:
        doc['training_error'] = training.document()
    if validations:
        doc['validation'] = [v.document() for v in validations]
    return plain(doc)


def consistency_errors(solver: dict, problems: list[str]) -> list[str]:
    """The errors of a solve (results.solver_document) whose estimate is not physically
    consistent although asked to be: none when it is, or when consistency is disabled."""
    if solver['status'] == 'disabled' or not problems:
        return []
    tried = '; '.join(solver['attempts']) or solver['status']
    return [f'the physically consistent solve failed ({tried}): the estimate given is the '
            'unconstrained one, NOT physically consistent: ' + '; '.join(problems[:3])]


def saved_document(ident) -> dict:
    """estimate.yaml of an identification: what the node's ~/save writes."""
    from identification_node.offline.results import parameters_document, plain

    doc = parameters_document(ident.robot, ident.base, ident.theta, ident.stddev,
                              ident.consistent, ident.covariance)
    doc.update({'bag': ident.bag, 'method': ident.method, 'num_samples': ident.num_samples,
                'condition_number': ident.condition_number, 'converged': ident.converged,
                'residual_rms': dict(zip(ident.robot.joint_names,
                                         ident.residual_rms.tolist())),
                'rejected': ident.rejected})
    return plain(doc)


def format_report(doc: dict) -> str:
    lines = [f"{doc['robot']} from {doc['bag']}: {doc['num_samples']} samples used "
             f"({doc['messages']} messages)",
             f"method: {doc['method']} ({doc['processing'].get('processing', '')})"]
    if doc.get('smoother'):
        sm = doc['smoother']

        def known(v, scale=1.0):
            return '?' if v is None else f'{scale * v:.4g}'
        lines.append(f"smoother: cut-off {known(sm['cutoff_hz'])} Hz ({sm['source']}), half "
                     f"window {sm['half_window']} samples at {known(sm['rate_hz'])} Hz, delay "
                     f"{known(sm['delay_s'], 1e3)} ms")
    elif doc['processing'].get('cutoff_hz') is not None:
        lines.append(f"filter: cut-off {_number(doc['processing']['cutoff_hz'])} Hz "
                     f"({doc['processing'].get('cutoff_source', 'given')})")
    if doc['rejected']:
        lines.append('rejected: ' + ', '.join(f'{k} {v}' for k, v in doc['rejected'].items()))
    rows = [(b['name'], f"{b['estimate']:.6g}", f"{b['unconstrained_estimate']:.6g}",
             f"{b['stddev']:.3g}" if b['stddev'] is not None else 'inf',
             _relative(b['estimate'], b['stddev']), f"{b['model']:.6g}")
            if b['estimate'] is not None else
            (b['name'], 'not excited', '', '', '', f"{b['model']:.6g}")
            for b in doc['base_parameters']]
    lines += ['', 'base parameters (SI units):'] + _table(
        ('name', 'estimate', 'unconstrained', 'stddev', 'rel %', 'model'), rows) + [
        f'  rel %: stddev / |estimate|; - where the estimate is within {ABOUT_ZERO:g} stddev '
        'of zero']
    regrouped = [b for b in doc['base_parameters'] if b['expression'] != b['name']]
    if regrouped:
        lines += ['', 'regrouped base parameters (sums of standard parameters; `structure` '
                  'explains them):']
        for b in regrouped:
            lines += textwrap.wrap(f"{b['name']} = {b['expression']}", TEXT_WIDTH,
                                   initial_indent='  ', subsequent_indent='      ',
                                   break_on_hyphens=False)
        lines.append('')
    solver = doc['consistency_solver']
    lines.append(f"physically consistent solve: {solver['status']}" + (
        f" by {solver['method']}" if solver.get('method') else '') + (
        f" ({solver['solve_time']:.3f} s)" if solver['solve_time'] is not None else '')
        + ''.join(f'; {a} failed' for a in solver.get('attempts', [])))
    for n in solver['notes']:
        lines += textwrap.wrap(f'note: {n}', TEXT_WIDTH, initial_indent='  ',
                               subsequent_indent='    ')
    lines += [f'error: {e}' for e in doc.get('errors', [])]
    lines += textwrap.wrap('link masses, kg (ratio to the URDF): ' + ', '.join(
        f"{k} {v['mass']:.4g}"
        + ('' if v.get('mass_ratio') is None else f" ({v['mass_ratio']:.2f})")
        for k, v in doc['links'].items()), TEXT_WIDTH, subsequent_indent='  ')
    lines += ['']
    for what, e in ([('training bag', doc['training_error'])] if 'training_error' in doc
                    else []) + [(f"validation bag {v['bag']}", v)
                                for v in doc.get('validation', [])]:
        lines += _torque_errors(what, e)
    lines += [f"on the {doc['processing'].get('processing', '')} rows fitted, percent: "
              + _per_joint(doc['relative_error']),
              'with the model\'s own parameters: ' + _per_joint(doc['model_relative_error']),
              'excitation condition number: ' + _number(doc['condition_number'])
              + f"   converged: {'yes' if doc['converged'] else 'no'}"]
    if not doc['excited']:
        lines += [f"not excited: the motion does not determine {len(doc['unexcited_directions'])}"
                  ' direction(s) of the base parameters (no estimate for the parameters in '
                  'them; excite the arm more):'] + [
                      f'  {d}' for d in doc['unexcited_directions']]
    if not doc['physically_consistent']:
        lines.append('closest full parameter set is not physically consistent: '
                     + '; '.join(doc['consistency_problems']))
        if doc['model_consistency_problems']:
            lines.append('(the model\'s own parameters, which it stays closest to, are not '
                         'either: ' + '; '.join(doc['model_consistency_problems']) + ')')
    if any(doc['excluded_equations'].values()):
        lines.append('equations left out near velocity reversals (coulomb_exclusion_speed): '
                     + ', '.join(f'{j} {k}' for j, k in doc['excluded_equations'].items()))
    lines += [f'warning: {w}' for w in doc['warnings']]
    lines += ['', 'convergence (estimate change to final, in final standard deviations):']
    final = np.array([np.nan if b['estimate'] is None else b['estimate']
                      for b in doc['base_parameters']])
    sd = np.array([b['stddev'] if b['stddev'] else np.inf for b in doc['base_parameters']])
    picks = _spread(len(doc['convergence']), 8)
    rows = []
    for c in (doc['convergence'][k] for k in picks):
        dev = np.abs(np.array(c['estimate'], dtype=float) - final) / sd
        dev = dev[np.isfinite(dev)]   # not the unexcited parameters
        rows.append((str(c['num_samples']),
                     *(f'{f(dev):.2f}' if len(dev) else '-' for f in (np.max, np.median))))
    lines += _table(('samples', 'max', 'median'), rows)
    return '\n'.join(lines)


def _torque_errors(what: str, e: dict) -> list[str]:
    """The lines of one bag's torque errors (validation.BagError.document)."""
    window = e['window_s']
    span = '' if window is None else ' from {} to {}'.format(
        f"{window['start'] or 0:g} s", 'the end' if window['end'] is None
        else f"{window['end']:g} s")
    lines = [f"relative torque error on the {what}{span} ({e['num_samples']} samples, raw "
             'torque), percent:']
    for key, label in (('estimate', 'identified'), ('model', 'model')):
        lines.append(f"  {label}: stacked {_number(e[key]['stacked'], '.3f')}; "
                     + _per_joint(e[key]['per_joint']))
    s = e['smoothed_torque']['estimate']
    lines.append(f"  identified, against the smoothed torque: stacked "
                 f"{_number(s['stacked'], '.3f')}; " + _per_joint(s['per_joint']))
    return lines


def _number(value: float | None, spec: str = '.4g') -> str:
    """A JSON number of the document (None: inf or NaN)."""
    return 'inf' if value is None else format(value, spec)


def format_payload_changes(changes: list, warnings: list | None = None) -> str:
    """The payload segments as text: values with stddev, 'not excited' where unknown (with
    the fitted value and its stddev where finite but above payload.tolerance), each change's
    mass step; ``warnings`` first."""
    def show(v, sd, unit, fv=None, fsd=None):
        if v is not None:
            return f'{v:.4g} +- {sd:.2g} {unit}'
        if fv is not None and fsd is not None:
            return f'not excited ({fv:.4g} +- {fsd:.2g} {unit})'
        return 'not excited'
    lines = [f'warning: {w}' for w in warnings or ()]
    lines += [f'payload: {len(changes) - 1} change(s) detected (link frame; inertia about the '
              'centre of mass):']
    for c in changes:
        p = c['payload']
        when = (f"at {c['stamp']:.3f} s" + (f" (detected {c['detected']:.3f} s)"
                                            if c['detected'] is not None else ' (start)'))
        if p is None:
            lines.append(f'  {when}: no fit (too few samples)')
            continue
        sd = p['stddev']
        f = p.get('fitted') or {'mass': None, 'com': [None] * 3, 'inertia': [None] * 6,
                                'stddev': {'mass': None, 'com': [None] * 3,
                                           'inertia': [None] * 6}}
        fsd = f['stddev']
        step = ('' if c.get('mass_change') is None else
                f"; change {c['mass_change']:+.4g} +- {c['mass_change_std']:.2g} kg")
        lines.append(f"  {when}, {p['link']}: mass "
                     f"{show(p['mass'], sd['mass'], 'kg', f['mass'], fsd['mass'])}{step}")
        lines.append('    com ' + ', '.join(show(*a[:2], 'm', *a[2:]) for a in zip(
            p['com'], sd['com'], f['com'], fsd['com'])))
        lines.append('    inertia ' + ', '.join(show(*a[:2], 'kg m^2', *a[2:]) for a in zip(
            p['inertia'], sd['inertia'], f['inertia'], fsd['inertia'])))
    return '\n'.join(lines)


def _per_joint(errors: dict) -> str:
    return ', '.join(f'{j} {_number(e, ".2f")}' for j, e in errors.items())


def paper_table3(fit) -> str:
    """The first paper's Table 3 combinations: identified, model (Table 1) and paper values.
    ``fit``: an offline.Identification or an IdentificationPipeline."""
    from identification_node.offline.report import paper_table3_rows

    if hasattr(fit, 'rls'):
        theta, cov = fit.rls.theta, fit.covariance
    else:
        theta, cov = fit.theta, fit.covariance
    rows = [(r['combination'], f"{r['identified']:.4f}", f"{r['stddev']:.4f}",
             f"{r['model']:.4f}", f"{r['paper_cad']:.4f}", f"{r['paper_estimate']:.4f}")
            for r in paper_table3_rows(fit.base, theta, cov,
                                       fit.base.to_base(fit.robot.phi_model))]
    return '\n'.join(['', "An, Atkeson, Hollerbach (1986) Table 3 combinations:"] + _table(
        ('combination', 'identified', 'stddev', 'Table 1', 'paper CAD', 'paper est.'), rows))


ABOUT_ZERO = 3.0     # an estimate within this many stddev of zero has no relative stddev
TEXT_WIDTH = 100    # columns of the text output


def _relative(value: float, stddev: float | None) -> str:
    """stddev / |value| in percent, '-' where the value is about zero (or stddev unknown)."""
    if stddev is None or not np.isfinite(stddev) or abs(value) <= ABOUT_ZERO * stddev:
        return '-'
    return f'{100 * stddev / abs(value):.2f}'


def _spread(n: int, k: int) -> list[int]:
    return sorted({int(round(i)) for i in np.linspace(0, n - 1, min(n, k))}) if n else []


def _table(header: tuple, rows: list[tuple]) -> list[str]:
    widths = [max(len(str(r[i])) for r in [header] + rows) for i in range(len(header))]
    return ['  ' + '  '.join(f'{str(c):<{w}}' if i == 0 else
                             f'{str(c):>{w}}' for i, (c, w) in enumerate(zip(r, widths))).rstrip()
            for r in [header] + rows]


def _method(args: argparse.Namespace) -> str:
    from identification_node.errors import IdentificationError

    given = [f"--{o.replace('_', '-')}" for o in BATCH_OPTIONS if getattr(args, o) is not None]
    if args.method == 'rls' and given:
        raise IdentificationError(f"{', '.join(given)} only apply to --method batch")
    return args.method or ('batch' if given else 'rls')


def batch_options(args: argparse.Namespace, robot):
    """offline.BatchOptions from --period/--trajectory/--harmonics/--cutoff/--decimate."""
    from identification_node.errors import IdentificationError
    from identification_node.offline.identification import BatchOptions
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

    from identification_node.offline.identification import validate
    from identification_node.offline.predictions import PredictionsWriter

    with (PredictionsWriter(args.predictions, ident.robot.joint_names) if args.predictions
          else contextlib.nullcontext()) as writer:
        training = validate(ident, args.bag, settings, window, *topics, predictions=writer,
                            label='training', training=True)
        validations = [validate(ident, bag, settings, window, *topics, predictions=writer,
                                label=f'validation{k}')
                       for k, bag in enumerate(args.validate or [], 1)]
    return training, validations


def run(args: argparse.Namespace) -> int:
    from identification_node.errors import IdentificationError
    from identification_node.offline.identification import (check_same_robot, make_consistent,
                                                            offline_identify, replay_identify)
    from identification_node.offline.replay import (bag_robot, foreign_joints_warning,
                                                    locked_warning, mimic_warning, robot_for_bag)
    from identification_node.offline.windows import TimeWindow

    settings = settings_from_args(args)
    if args.workers < 0:
        raise IdentificationError(f'--workers must be >= 0 (0: one per core), got '
                                  f'{args.workers}')
    window = TimeWindow(args.start, args.end).validate()
    consistency = None if args.no_physical_consistency else settings.consistency_options()
    method = _method(args)
    if args.report:
        from identification_node.offline.report import check_writable
        check_writable(args.report)
    if args.save:
        from identification_node.fileio import writable_directory
        writable_directory(args.save, '--save')
    if args.predictions:
        from identification_node.offline.predictions import check_predictions
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
        from identification_node.offline.drive_gains import (identify_drive_gains,
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
        from identification_node.offline.parallel import default_workers, parallel_identify
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
    from identification_node.offline.effort_semantics import training_gravity_warning
    gravity = training_gravity_warning(ident, training)
    if gravity:
        ident.warnings.append(gravity)
    doc = result_document(ident, validations, training)
    if gains is not None:
        doc['drive_gains'] = [g.document() for g in gains]
        doc['warnings'] += [g.warning for g in gains if g.warning]
    if monitor is not None:
        from identification_node.payload.monitor import segments_document
        from identification_node.offline.results import plain
        doc['payload_changes'] = plain(segments_document(monitor.finish()))
        doc['payload_warnings'] = monitor.warnings()
        for w in doc['payload_warnings']:
            print(f'warning: {w}', file=sys.stderr)
    if args.save:
        from identification_node.offline.results import write_results
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
        from identification_node.offline.report import write_report
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


def format_outputs(doc: dict) -> str:
    """The files --save, --report and --predictions wrote, by name."""
    written = [('--save', doc.get('saved') or []),
               ('--report', list((doc.get('report') or {}).values())),
               ('--predictions', [doc['predictions']] if doc.get('predictions') else [])]
    lines = [f'  {option}: {path}' for option, paths in written for path in paths]
    return '\n'.join(['', 'files written:'] + lines) if lines else ''
