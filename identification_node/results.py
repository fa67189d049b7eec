"""The estimate as a document (YAML/JSON) and as files: shared by the node and the CLI."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .fileio import atomic_write_text, atomic_write_yaml
from .pipeline import IdentificationPipeline
from .urdf_export import consistency_problems, identified_urdf

ESTIMATE_FILE = 'estimate.yaml'
URDF_FILE = 'identified.urdf'


def estimate_document(pipeline: IdentificationPipeline) -> dict:
    """Plain-data summary of the running estimate (names, values, stddev, covariance, health,
    and the closest full parameter set)."""
    est = pipeline.estimate()
    robot, base = pipeline.robot, pipeline.base
    phi = pipeline.standard_parameters()
    problems = consistency_problems(robot, phi)
    doc = {
        'robot': robot.name,
        'joints': list(robot.joint_names),
        'num_samples': est.num_samples,
        'time': None if np.isnan(est.stamp) else est.stamp,
        'base_parameters': [
            {'name': name, 'expression': expr, 'value': float(v), 'stddev': float(s)}
            for name, expr, v, s in zip(base.names, base.expressions, est.values, est.stddev)],
        'condition_number': float(est.condition_number),
        'residual_rms': {j: float(r) for j, r in zip(robot.joint_names, est.residual_rms)},
        'converged': est.converged,
        'frozen': est.frozen,
        'physically_consistent': not problems,
        'consistency_problems': problems,
        'standard_parameters': dict(zip(robot.param_names, map(float, phi))),
        'rejected': {k: v for k, v in pipeline.rejected.items() if v},
        'covariance': pipeline.covariance.tolist(),
    }
    return plain(doc)


def save_results(pipeline: IdentificationPipeline, directory: str | os.PathLike,
                 payload=None) -> list[Path]:
    """Write estimate.yaml and identified.urdf into ``directory`` atomically; return the paths.
    ``payload`` (payload.PayloadEstimate): carried as ``payload`` in estimate.yaml and as a
    fixed link in the URDF."""
    directory = Path(directory)
    doc = estimate_document(pipeline)
    if payload is not None:
        doc['payload'] = plain(payload.document())
    paths = [atomic_write_yaml(directory / ESTIMATE_FILE, doc)]
    if pipeline.robot.kind == 'urdf':
        note = ('identified by identification_node; ' + (
            'physically consistent' if doc['physically_consistent'] else
            'NOT physically consistent: ' + '; '.join(doc['consistency_problems'])))
        phi = np.array(list(doc['standard_parameters'].values()))  # in param_names order
        urdf = identified_urdf(pipeline.robot, phi, note)
        if payload is not None:
            from .payload import urdf_with_payload
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
