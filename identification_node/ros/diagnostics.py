"""Diagnostics values as text a controller or a dashboard parses: a number (integers as they
are, other numbers to 6 significant digits, SI units as the key says), ``true``/``false``,
a word or sentence, or the literal ``not determined`` (no value yet: no samples, not chosen,
not finite, not known with this middleware) or ``not excited`` (the motion did not excite
the quantity). Never Python syntax (None, lists, reprs).

``identification_status`` is the node's status: a pure function of the pipeline's status
snapshot (pipeline/status.py) and what the node itself counts (NodeStatus).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from numbers import Integral, Real
from typing import Any, Mapping, Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from identification_node.estimation.consistency import ConsistentEstimate
from identification_node.pipeline.rows import SmootherChoice
from identification_node.pipeline.status import PipelineStatus

__all__ = ['NOT_DETERMINED', 'NOT_EXCITED', 'SMOOTHER_SOURCES', 'NodeStatus',
           'identification_status', 'key_values', 'plain', 'robust_gate_text', 'smoother_plan',
           'smoother_text', 'smoother_values', 'vector']

NOT_DETERMINED = 'not determined'
NOT_EXCITED = 'not excited'
# SmootherChoice.source in words ('automatic' stays)
SMOOTHER_SOURCES = {'half_window': 'given half window', 'cutoff': 'given cut-off',
                    'automatic': 'automatic', 'fallback': 'fallback cut-off'}


def plain(value: Any) -> str:
    """One value as diagnostics text (see the module docstring)."""
    if value is None:
        return NOT_DETERMINED
    if isinstance(value, (bool, np.bool_)):
        return 'true' if value else 'false'
    if isinstance(value, Integral):
        return str(int(value))
    if isinstance(value, Real):
        return f'{float(value):.6g}' if math.isfinite(value) else NOT_DETERMINED
    if isinstance(value, str):
        return value
    raise TypeError(f'diagnostics value {value!r}: give a number, bool, str or None '
                    '(vectors as one key per element)')


def vector(key: str, names: Sequence[str], values: Sequence[Any] | np.ndarray,
           excited: Sequence[bool] | None = None) -> dict[str, Any]:
    """``key.<name>`` per element; ``not excited`` where ``excited`` is false."""
    flags = [True] * len(names) if excited is None else excited
    return {f'{key}.{n}': (v if ok else NOT_EXCITED)
            for n, v, ok in zip(names, values, flags)}


def key_values(values: Mapping[str, Any]) -> list[KeyValue]:
    """``values`` (key -> plain value) as diagnostic_msgs KeyValues, in order."""
    return [KeyValue(key=k, value=plain(v)) for k, v in values.items()]


def smoother_text(choice: SmootherChoice) -> str:
    """The smoother in use in words: cut-off, window, delay."""
    rate = f'{choice.rate:.6g} Hz' if choice.rate > 0 else 'a rate not known yet'
    delay = f'{1e3 * choice.delay:.1f} ms' if choice.rate > 0 else f'{choice.half_window} samples'
    cutoff = f'cut-off {choice.cutoff:.3g} Hz' if choice.rate > 0 else 'cut-off not known yet'
    source = SMOOTHER_SOURCES.get(choice.source, choice.source)
    return (f'{cutoff} ({source}), half window {choice.half_window} samples at {rate}, '
            f'delay of ~/predicted_effort {delay}')


def smoother_plan(choice: SmootherChoice | None, cutoff: float, auto_seconds: float) -> str:
    """The smoother at start-up in words: ``choice`` when made, else the given ``cutoff``
    (Hz, 0: none) or the ``auto_seconds`` of motion it is to be chosen from."""
    if choice is not None:
        return smoother_text(choice)
    return 'cut-off ' + (f'{cutoff:g} Hz' if cutoff > 0 else
                         f'to be chosen from the first {auto_seconds:g} s of motion')


def smoother_values(choice: SmootherChoice | None, holding: int) -> dict[str, Any]:
    """The diagnostics of the smoother (None while being chosen, ``holding`` samples held)."""
    if choice is None:
        return {'smoother': f'being chosen ({holding} samples held back)',
                'smoother_delay_samples': None}
    return {'smoother': SMOOTHER_SOURCES.get(choice.source, choice.source),
            'smoother_delay_samples': choice.half_window, 'smoother_delay_ms': 1e3 * choice.delay,
            'smoother_cutoff_hz': choice.cutoff, 'smoother_order': choice.order}


def robust_gate_text(status: PipelineStatus) -> str:
    """The robust gate's state in words."""
    if not status.gate_enabled:
        return 'off'
    if status.gate_suspended:
        return 'residual shift: not gating'
    return 'gating' if status.gate_armed else 'waiting for convergence'


@dataclass
class NodeStatus:
    """What the node knows besides the pipeline's status: its input rate (Hz of joint state
    messages received since the last diagnostics), failed callbacks, the constrained solve
    (``consistency_enabled``; the last ``consistent`` result, None before the first) and the
    identified URDF's ``consistency_problems``; per input topic the messages ``lost`` before
    the node took them (its queue overflowing while processing stalled, dropped packets; None:
    not known) and ``dropped`` beyond its queue's bound; incompatible QoS endpoints seen;
    ``extra``: further values (payload, drive gains), appended in order; the wall-clock
    ``processing_period`` in use (ros/node.py)."""
    input_rate_hz: float
    callback_errors: int
    consistency_enabled: bool
    consistent: ConsistentEstimate | None
    consistency_problems: list[str]
    lost: dict[str, int | None]
    dropped: dict[str, int]
    qos_incompatible: int
    extra: dict[str, Any] = field(default_factory=dict)
    processing_period: float | None = None   # s between processing runs now


def identification_status(name: str, hardware_id: str, joint_names: Sequence[str],
                          pipeline: PipelineStatus, node: NodeStatus) -> DiagnosticStatus:
    """The node's DiagnosticStatus ``name``: level and message from convergence and what is
    wrong, the values as diagnostics text (keys in a fixed order)."""
    est, offset, result = pipeline.estimate, pipeline.time_offset, node.consistent
    problems, missing = node.consistency_problems, pipeline.missing_joints
    terms = pipeline.model_term_warnings
    status = DiagnosticStatus(name=name, hardware_id=hardware_id)
    if est.converged:
        status.level, status.message = DiagnosticStatus.OK, 'converged'
    else:
        status.level, status.message = DiagnosticStatus.WARN, 'not converged'
    if pipeline.gate_suspended:
        status.level = DiagnosticStatus.WARN
        status.message += '; residual shift (payload change?)'
    if problems:
        status.level = DiagnosticStatus.WARN
        status.message += '; identified parameters not physically consistent'
    if missing:
        status.level = DiagnosticStatus.WARN
        status.message += f"; messages lack joint(s) {', '.join(missing)}"
    if terms:
        status.level = DiagnosticStatus.WARN
        status.message += '; missing model term?'
    values = {
        'input_rate_hz': node.input_rate_hz, 'processing_period_s': node.processing_period,
        'samples_received': pipeline.received,
        'samples_used': pipeline.used, 'samples_rejected': sum(pipeline.rejected.values()),
        'condition_number': est.condition_number,
        'min_information_eigenvalue': est.min_eigenvalue,
        'converged': est.converged, 'frozen': est.frozen, 'stream_restarts': pipeline.restarts,
        **smoother_values(pipeline.smoother, pipeline.holding),
        'physically_consistent': not problems,
        'robust_gate': robust_gate_text(pipeline), 'residual_shifts': pipeline.residual_shifts,
        'numerical_failures': pipeline.numerical_failures,
        'smoother_edge_samples': pipeline.smoother_edge,
        'layout_cache_bytes': pipeline.layout_cache_bytes,
        'callback_errors': node.callback_errors,
        'time_offset_s': None if offset is None else offset.offset,
    }
    values['consistency_status'] = ('disabled' if not node.consistency_enabled else
                                    'not solved yet' if result is None else result.status)
    if result is not None:
        values['consistency_solve_time_ms'] = 1e3 * result.solve_time
        values['consistency_method'] = result.method or 'none'
        if not result.ok:
            status.level = DiagnosticStatus.ERROR
            status.message += ('; consistent solve failed: unconstrained estimate '
                               'published, NOT physically consistent')
        if result.notes:
            values['consistency_notes'] = '; '.join(result.notes)
    values.update({f'lost_messages.{t}': n for t, n in node.lost.items()})
    values.update({f'dropped_messages.{t}': n for t, n in node.dropped.items()})
    values['qos_incompatible'] = node.qos_incompatible
    values.update({f'rejected.{k}': v for k, v in pipeline.rejected.items()})
    values.update(vector('residual_rms', joint_names, est.residual_rms))
    values.update({f'excluded_equations.{j}': int(k)
                   for j, k in zip(joint_names, pipeline.excluded_equations)})
    if missing:
        values['missing_joints'] = ', '.join(missing)
    if terms:
        values['model_term_warnings'] = '; '.join(terms)
    if problems:
        values['consistency_problems'] = '; '.join(problems)
    values.update(node.extra)
    if offset is not None and offset.level:   # time_offset.py: torque late or early
        status.level = max(status.level, (DiagnosticStatus.WARN, DiagnosticStatus.ERROR)[
            offset.level - 1])
        status.message += f'; torque {offset.offset:+.3f} s off the motion'
    status.values = key_values(values)
    return status
