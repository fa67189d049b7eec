"""``identify BAG``: offline identification through the node's own pipeline, without DDS.

The robot is --robot/--urdf, else the robot of --config, else the bag's /robot_description.
Prints the base parameter estimate with standard deviations, the per-joint relative torque
error 100 ||tau_measured - tau_predicted|| / ||tau_measured||, the excitation condition number
and how the estimate converged; ``--json`` prints the same as one object.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from . import add_robot_arguments, add_settings_arguments, settings_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', help='rosbag2 bag directory (mcap or sqlite3)')
    add_robot_arguments(parser, required=False)
    add_settings_arguments(parser)
    parser.add_argument('--json', action='store_true', help='print one JSON object')
    parser.add_argument('--joint-states-topic', default='/joint_states')
    parser.add_argument('--currents-topic', default='/motor_currents')
    parser.add_argument('--paper-tables', action='store_true',
                        help="MIT arm: compare with the first paper's Table 3")


def result_document(result, base_values: np.ndarray | None = None) -> dict:
    """The ``--json`` object of an identification (replay.ReplayResult)."""
    from ..results import plain
    from ..urdf_export import consistency_problems

    p = result.pipeline
    robot, base = p.robot, p.base
    est = p.estimate()
    model = base.to_base(robot.phi_model)
    with np.errstate(divide='ignore', invalid='ignore'):
        rel = 100 * est.stddev / np.abs(est.values)
    problems = consistency_problems(robot, p.standard_parameters())
    return plain({
        'bag': result.bag, 'robot': robot.name, 'joints': robot.joint_names,
        'num_samples': est.num_samples, 'messages': result.messages,
        'base_parameters': [
            {'name': n, 'expression': e, 'terms': t, 'estimate': float(v), 'stddev': float(s),
             'rel_stddev': float(r), 'model': float(m)}
            for n, e, t, v, s, r, m in zip(base.names, base.expressions, base.terms,
                                           est.values, est.stddev, rel, model)],
        'relative_error': dict(zip(robot.joint_names, p.relative_error().tolist())),
        'residual_rms': dict(zip(robot.joint_names, est.residual_rms.tolist())),
        'condition_number': est.condition_number,
        'converged': est.converged,
        'smoother_delay_samples': int(p.delay),
        'rejected': {k: v for k, v in p.rejected.items() if v},
        'physically_consistent': not problems, 'consistency_problems': problems,
        'convergence': [{'num_samples': c.num_samples, 'estimate': c.values.tolist(),
                         'stddev': c.stddev.tolist()} for c in result.history],
    })


def format_report(doc: dict, pipeline) -> str:
    lines = [f"{doc['robot']} from {doc['bag']}: {doc['num_samples']} samples used "
             f"({doc['messages']} messages)"]
    if doc['rejected']:
        lines.append('rejected: ' + ', '.join(f'{k} {v}' for k, v in doc['rejected'].items()))
    rows = [(b['name'], f"{b['estimate']:.6g}", f"{b['stddev']:.3g}" if b['stddev'] is not None
             else 'inf', f"{b['rel_stddev']:.2f}" if b['rel_stddev'] is not None else 'inf',
             f"{b['model']:.6g}", b['expression']) for b in doc['base_parameters']]
    lines += ['', 'base parameters (SI units):'] + _table(
        ('name', 'estimate', 'stddev', 'rel %', 'model', 'expression'), rows)
    lines += ['', 'relative torque error, percent: ' + ', '.join(
        f'{j} {e:.2f}' for j, e in doc['relative_error'].items()),
        f"excitation condition number: {doc['condition_number']:.4g}"
        f"   converged: {'yes' if doc['converged'] else 'no'}"]
    if not doc['physically_consistent']:
        lines.append('closest full parameter set is not physically consistent: '
                     + '; '.join(doc['consistency_problems']))
    lines += ['', 'convergence (estimate change to final, in final standard deviations):']
    final = np.array([b['estimate'] for b in doc['base_parameters']])
    sd = np.array([b['stddev'] if b['stddev'] else np.inf for b in doc['base_parameters']])
    picks = _spread(len(doc['convergence']), 8)
    rows = []
    for c in (doc['convergence'][k] for k in picks):
        dev = np.abs(np.array(c['estimate'], dtype=float) - final) / sd
        rows.append((str(c['num_samples']), f'{np.max(dev):.2f}', f'{np.median(dev):.2f}'))
    lines += _table(('samples', 'max', 'median'), rows)
    return '\n'.join(lines)


def paper_table3(pipeline) -> str:
    """The first paper's Table 3 combinations: identified, model (Table 1) and paper values."""
    from ..errors import IdentificationError
    from ..identifiability import format_expression
    from ..papers import MIT_TABLE3

    base, robot = pipeline.base, pipeline.robot
    theta, cov = pipeline.rls.theta, pipeline.covariance
    model = base.to_base(robot.phi_model)
    rows = []
    for terms, paper_est, paper_cad in MIT_TABLE3:
        try:
            w = base.combination(terms)
        except IdentificationError:
            continue
        rows.append((format_expression(terms), f'{w @ theta:.4f}',
                     f'{np.sqrt(w @ cov @ w):.4f}', f'{w @ model:.4f}', f'{paper_cad:.4f}',
                     f'{paper_est:.4f}'))
    return '\n'.join(['', "An, Atkeson, Hollerbach (1986) Table 3 combinations:"] + _table(
        ('combination', 'identified', 'stddev', 'Table 1', 'paper CAD', 'paper est.'), rows))


def _spread(n: int, k: int) -> list[int]:
    return sorted({int(round(i)) for i in np.linspace(0, n - 1, min(n, k))}) if n else []


def _table(header: tuple, rows: list[tuple]) -> list[str]:
    widths = [max(len(str(r[i])) for r in [header] + rows) for i in range(len(header))]
    return ['  ' + '  '.join(f'{str(c):<{w}}' if i in (0, len(header) - 1) else
                             f'{str(c):>{w}}' for i, (c, w) in enumerate(zip(r, widths))).rstrip()
            for r in [header] + rows]


def run(args: argparse.Namespace) -> int:
    from ..replay import bag_robot, identify_bag

    settings = settings_from_args(args)
    robot = (settings.load_robot() if args.robot or args.urdf or settings.given_robot
             else bag_robot(args.bag, settings))
    result = identify_bag(args.bag, settings, robot, args.joint_states_topic,
                          args.currents_topic)
    doc = result_document(result)
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print(format_report(doc, result.pipeline))
        if args.paper_tables:
            print(paper_table3(result.pipeline))
    return 0
