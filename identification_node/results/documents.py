"""The estimate as a document (YAML/JSON) and as files: shared by the node and the CLI."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import ConsistentEstimate
from identification_node.fileio import atomic_write_text, atomic_write_yaml
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.model.urdf_export import (consistency_problems, identified_urdf,
                                                   link_inertia)
from identification_node.pipeline import EstimateReport, IdentificationPipeline

__all__ = ['ESTIMATE_FILE', 'URDF_FILE', 'estimate_document', 'snapshot_document',
           'parameters_document', 'solver_document', 'save_results', 'write_results', 'plain',
           'result_document', 'consistency_errors', 'saved_document']

ESTIMATE_FILE = 'estimate.yaml'
URDF_FILE = 'identified.urdf'


def estimate_document(pipeline: IdentificationPipeline,
                      consistent: ConsistentEstimate | None = None) -> dict:
    """Plain-data summary of the running estimate (names, values, stddev, covariance, health,
    the full parameter set and its links); ``consistent``: the constrained solve's outcome on
    the pipeline's current information (None: physical consistency off)."""
    return snapshot_document(pipeline.robot, pipeline.base, pipeline.estimate(),
                             pipeline.covariance, pipeline.rejected, consistent)


def snapshot_document(robot: RobotModel, base: BaseParameters, est: EstimateReport,
                      covariance: np.ndarray, rejected: Mapping[str, int],
                      consistent: ConsistentEstimate | None = None) -> dict:
    """estimate_document of a snapshot taken earlier (the estimate, its covariance and the
    rejection counts of a pipeline at one time)."""
    doc = parameters_document(robot, base, est.values, est.stddev, consistent, covariance)
    doc.update({
        'num_samples': est.num_samples,
        'time': None if np.isnan(est.stamp) else est.stamp,
        'condition_number': float(est.condition_number),
        'residual_rms': {j: float(r) for j, r in zip(robot.joint_names, est.residual_rms)},
        'converged': est.converged,
        'frozen': est.frozen,
        'rejected': {k: v for k, v in rejected.items() if v},
    })
    return plain(doc)


def parameters_document(robot: RobotModel, base: BaseParameters, theta: np.ndarray,
                        stddev: np.ndarray, consistent: ConsistentEstimate | None,
                        covariance: np.ndarray) -> dict:
    """The estimate's part of estimate.yaml, shared by the node and ``identify --save``:
    base parameters (``value`` the published estimate: the consistent one when solved, else
    the unconstrained ``unconstrained``), the solver's status, the full standard parameters
    (the consistent ones, else the closest to the model's reproducing theta) and per link
    mass, centre of mass and inertia about it (link frame, SI)."""
    if consistent is not None and consistent.phi is not None and consistent.theta is not None:
        value, phi = consistent.theta, consistent.phi    # consistent.ok: both set
    else:
        value, phi = theta, base.closest_standard(theta, robot.phi_model)
    problems = consistency_problems(robot, phi)
    links = {}
    for i, link in enumerate(robot.link_names):
        m, c, Ic = link_inertia(phi[10 * i:10 * i + 10])
        m0 = float(robot.phi_model[10 * i])
        links[link] = {'mass': m, 'com': c.tolist(), 'inertia': Ic.tolist(), 'urdf_mass': m0,
                       'mass_ratio': m / m0 if m0 > 0 else None}
    return {
        'robot': robot.name,
        'joints': list(robot.joint_names),
        'base_parameters': [
            {'name': name, 'expression': expr, 'value': float(v), 'stddev': float(s),
             'unconstrained': float(u)}
            for name, expr, v, s, u in zip(base.names, base.expressions, value, stddev, theta)],
        'physically_consistent': not problems,
        'consistency_problems': problems,
        'consistency_solver': solver_document(consistent),
        'standard_parameters': dict(zip(robot.param_names, map(float, phi))),
        'links': links,
        'covariance': np.asarray(covariance).tolist(),
    }


def solver_document(consistent: ConsistentEstimate | None) -> dict:
    """Status of the constrained solve: status, solve time (s), notes, the path that gave
    the estimate (``method``: a solver, 'projection', '' when none), the failed ``attempts``
    before it, and the chi-square ``excess`` beyond the data's confidence region."""
    if consistent is None:
        return {'status': 'disabled', 'solve_time': None, 'notes': [], 'method': '',
                'attempts': [], 'excess': 0.0}
    return {'status': consistent.status, 'solve_time': consistent.solve_time,
            'notes': list(consistent.notes), 'method': consistent.method,
            'attempts': list(consistent.attempts), 'excess': consistent.excess}


def save_results(pipeline: IdentificationPipeline, directory: str | os.PathLike,
                 payload=None, consistent: ConsistentEstimate | None = None,
                 inconsistent: bool = False) -> list[Path]:
    """Write estimate.yaml and identified.urdf into ``directory`` atomically; return the paths.
    ``payload`` (payload.PayloadEstimate): carried as ``payload`` in estimate.yaml and as a
    fixed link in the URDF; ``consistent``: the constrained solve's outcome; ``inconsistent``:
    write a physically inconsistent estimate too (write_results)."""
    doc = estimate_document(pipeline, consistent)
    if payload is not None:
        doc['payload'] = plain(payload.document())
    return write_results(directory, doc, pipeline.robot, payload, inconsistent)


def write_results(directory: str | os.PathLike, doc: dict, robot: RobotModel,
                  payload=None, inconsistent: bool = False) -> list[Path]:
    """estimate.yaml (``doc``) and, for a URDF robot, identified.urdf with ``doc``'s standard
    parameters, written atomically into ``directory``; returns the paths. An estimate that is
    not physically consistent is refused (IdentificationError, nothing written) unless
    ``inconsistent``: a simulator or controller would load bodies no arm has."""
    if robot.kind == 'urdf' and not doc['physically_consistent'] and not inconsistent:
        raise IdentificationError(
            'not saved: the estimate is not physically consistent ('
            + '; '.join(doc['consistency_problems'][:3]) + '); identify --save-inconsistent '
            '(node: save_inconsistent) writes it anyway')
    directory = Path(directory)
    paths = [atomic_write_yaml(directory / ESTIMATE_FILE, doc)]
    if robot.kind == 'urdf':
        note = ('identified by identification_node; ' + (
            'physically consistent' if doc['physically_consistent'] else
            'NOT physically consistent: ' + '; '.join(doc['consistency_problems'])))
        phi = np.array(list(doc['standard_parameters'].values()))  # in param_names order
        urdf = identified_urdf(robot, phi, note)
        if payload is not None:
            from identification_node.payload.fit import urdf_with_payload
            urdf = urdf_with_payload(urdf, payload)
        paths.append(atomic_write_text(directory / URDF_FILE, urdf))
    return paths


def plain(x):
    """numpy scalars and non-finite floats made YAML/JSON-safe (inf/nan -> None)."""
    if isinstance(x, dict):
        return {k: plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def result_document(result, validations=(), training=None) -> dict:
    """The ``--json`` object of an identification (results.identification.Identification, or the
    replay.ReplayResult of the streaming pipeline), with the torque errors on the training
    bag and on the validation bags (validation.BagError) when given."""
    from identification_node.results.identification import Identification, from_replay
    from identification_node.results.documents import parameters_document, plain
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
    from identification_node.results.documents import parameters_document, plain

    doc = parameters_document(ident.robot, ident.base, ident.theta, ident.stddev,
                              ident.consistent, ident.covariance)
    doc.update({'bag': ident.bag, 'method': ident.method, 'num_samples': ident.num_samples,
                'condition_number': ident.condition_number, 'converged': ident.converged,
                'residual_rms': dict(zip(ident.robot.joint_names,
                                         ident.residual_rms.tolist())),
                'rejected': ident.rejected})
    return plain(doc)
