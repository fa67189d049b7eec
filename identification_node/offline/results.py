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
    ok = consistent is not None and consistent.ok
    value = consistent.theta if ok else theta
    phi = consistent.phi if ok else base.closest_standard(theta, robot.phi_model)
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
