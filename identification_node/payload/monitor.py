"""Payload identification with change detection on the pipeline's smoothed samples.

PayloadMonitor takes the pipeline's outputs (q, qd, qdd and the measured torque of each
sample, stamped), forms the residual of a fixed arm model r = tau - Y phi_arm and the
payload's regressor, and runs through segments of constant payload:

- *fitting*: after the start (or a change, once ``settle`` s have passed), ``fit_time`` s of
  samples are gathered and the payload fitted (payload.fit_payload); then
- *watching*: the residual of arm plus payload goes to the change detector
  (change_detection.WindowedGLR), and its samples, once older than the detector's window
  (so none from after a change), refine the segment's fit every ``refresh`` s. A detection
  ends the segment at the estimated onset and starts *fitting* again.

Events (PayloadEvent) report the segment starts, the detections and each fit. Stamps are
seconds (header stamps).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.model.robot import RobotModel
from identification_node.payload.change_detection import (DEFAULT_CONFIRM, DEFAULT_MIN_CHANGE,
                                                          DEFAULT_MIN_Z, DEFAULT_THRESHOLD,
                                                          DEFAULT_WINDOW, Detection, WindowedGLR)
from identification_node.payload.fit import (Attachment, PayloadEstimate, fit_payload,
                                             given_payload, payload_regressor)
from identification_node.pipeline.signals import smoothing_noise_gain

ARM_ESTIMATE = 'estimate'   # payload.arm: the node's running estimate, taken at each reset
NOISE_FLOOR = 1e-4   # N m: the smallest noise standard deviation a joint is weighted by
DETECTOR_COLUMNS = 4  # m, mx, my, mz


@dataclass
class MonitorConfig:
    """Settings of the payload monitor (node parameters ``payload.*``)."""
    fit_time: float = 1.0        # s of samples after a change for the first fit
    settle: float = 0.1          # s after a detection before samples are used (the pick)
    refresh: float = 5.0         # s between refits while the payload stays
    window: float = DEFAULT_WINDOW
    threshold: float = DEFAULT_THRESHOLD
    min_change: float = DEFAULT_MIN_CHANGE
    min_z: float = DEFAULT_MIN_Z
    confirm: float = DEFAULT_CONFIRM
    max_gap: float = 0.05
    batch: float = 0.02          # s of samples gathered per run (numpy calls cost per run)
    tolerance: Mapping[str, float] = field(default_factory=dict)

    def validate(self) -> None:
        for name in ('fit_time', 'settle', 'refresh', 'window', 'threshold', 'min_change',
                     'min_z', 'max_gap', 'batch', 'confirm'):
            value = getattr(self, name)
            zero_ok = name in ('settle', 'min_change', 'min_z', 'batch', 'confirm')
            ok = value >= 0 if zero_ok else value > 0
            if not (isinstance(value, (int, float)) and math.isfinite(value) and ok):
                raise IdentificationError(f'parameter payload.{name} = {value!r} must be a '
                                          f'finite number {">=" if zero_ok else ">"} 0')
        for key, value in self.tolerance.items():
            if key not in ('mass', 'com', 'inertia') or not (
                    isinstance(value, (int, float)) and value > 0):
                raise IdentificationError(f'parameter payload.tolerance.{key} = {value!r}: '
                                          'mass, com or inertia, > 0')


@dataclass
class PayloadEvent:
    """``kind``: 'start' (a segment's first fit: the initial payload, stamp = first sample),
    'change' (a detection: stamp = estimated onset, ``detected`` = when detected, no payload
    yet), 'estimate' (the first fit after a change) or 'refresh' (a refined fit)."""
    kind: str
    stamp: float
    detected: float | None = None
    payload: PayloadEstimate | None = None
    detection: Detection | None = None


@dataclass
class Segment:
    """A span of constant payload: from ``stamp`` (s), detected at ``detected`` (None for the
    first), with its latest fit."""
    stamp: float
    detected: float | None
    payload: PayloadEstimate | None = None


class PayloadMonitor:
    """See the module docstring. ``phi_arm``: the arm's standard parameters (payload.
    arm_parameters); ``half_window``/``order``: the pipeline's smoother (noise scaling):
    its half window, or a callable giving it (None while the pipeline chooses it), asked when
    the first samples come."""

    def __init__(self, robot: RobotModel, attach: Attachment, phi_arm: np.ndarray,
                 config: MonitorConfig | None = None,
                 half_window: int | Callable[[], int | None] = 10, order: int = 3):
        self.robot, self.attach = robot, attach
        self.phi_arm = np.asarray(phi_arm, dtype=float)
        if self.phi_arm.shape != (robot.num_params,) or not np.isfinite(self.phi_arm).all():
            raise IdentificationError(f'arm parameters must be {robot.num_params} finite values')
        self.config = config or MonitorConfig()
        self.config.validate()
        c = self.config
        self._order = int(order)
        self._half_window = half_window if callable(half_window) else None
        self._smoother(10 if callable(half_window) else int(half_window))
        self.detector = WindowedGLR(c.window, c.threshold, c.min_change, c.max_gap,
                                    min_z=c.min_z, noise_scale=self._white_scale,
                                    confirm=c.confirm)
        self.segments: list[Segment] = []
        self._queued: list[tuple] = []
        self._last_t = -math.inf
        self.changes = 0
        self.reset()

    def _smoother(self, half_window: int) -> None:
        if int(half_window) < 1:
            raise IdentificationError(f'the smoother half window must be >= 1, got '
                                      f'{half_window!r}')
        self._block = 4 * (2 * int(half_window) + 1)
        self._white_scale = 1.0 / smoothing_noise_gain(int(half_window), self._order)

    def _resolve_smoother(self) -> None:
        """The pipeline's half window, once it is chosen (before the first samples are used:
        the statistics started with a stand-in block length restart with the real one)."""
        L = self._half_window()
        if L is None:
            return
        self._half_window = None
        self._smoother(L)
        self.detector.noise_scale = self._white_scale
        if self._stats.count == 0:
            self._stats = ResidualStatistics(10, self.robot.dof, self._block)

    # -- state ------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the payload: a new segment (no change event) starts at the next sample."""
        self.current: PayloadEstimate | None = None
        self._noise: np.ndarray | None = None   # the segment's noise variance, (N m)^2
        self._given = False
        self._new_segment(None, None, 0.0)

    def set_payload(self, phi: np.ndarray, stamp: float | None = None) -> PayloadEstimate:
        """A payload known to the user (10 parameters, attachment frame): watched from now on,
        not refitted until a change is detected."""
        est = given_payload(self.attach.link, phi)
        self._new_segment(stamp, None, 0.0)
        self.current, self._given = est, True
        self.segments[-1].payload = est
        self._state = 'watching'
        return est

    def _new_segment(self, stamp: float | None, detected: float | None, settle: float) -> None:
        self._stats = ResidualStatistics(10, self.robot.dof, self._block)
        self._pending: list[tuple] = []
        self._state = 'fitting'
        self._given = False
        self._start = stamp            # None: the next sample's stamp
        self._settle_until = -math.inf if detected is None else detected + settle
        self._fit_due = math.nan       # set from the first sample used
        self.detector.reset()
        self.segments.append(Segment(math.nan if stamp is None else stamp, detected))

    @property
    def state(self) -> str:
        """'fitting' (gathering samples for the segment's first fit) or 'watching'."""
        return self._state

    # -- samples ----------------------------------------------------------------------------------
    def add(self, stamps_ns: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
            tau: np.ndarray) -> list[PayloadEvent]:
        """Samples in time order (the pipeline's outputs): the events they bring, once
        ``batch`` s of samples are gathered."""
        if len(stamps_ns) == 0:
            return []
        if self._half_window is not None:
            self._resolve_smoother()
        self._queued.append((stamps_ns, q, qd, qdd, tau))
        if (int(stamps_ns[-1]) - int(self._queued[0][0][0])) * 1e-9 < self.config.batch:
            return []
        parts, self._queued = self._queued, []
        return self._run(*(np.concatenate(a) for a in zip(*parts)) if len(parts) > 1
                         else parts[0])

    def _run(self, stamps_ns: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
             tau: np.ndarray) -> list[PayloadEvent]:
        t = np.asarray(stamps_ns, dtype=np.int64) * 1e-9
        if t[0] <= self._last_t:   # a restarted stream: keep the payload, restart the clocks
            self._settle_until = -math.inf
            if self._state == 'fitting':
                self._fit_due = math.nan
            self._next_refresh = float(t[0]) + self.config.refresh
        self._last_t = float(t[-1])
        Y = self.robot.regressor(q, qd, qdd, checked=True)
        r = np.asarray(tau, dtype=float) - Y @ self.phi_arm
        Yp = payload_regressor(self.attach, Y)
        events: list[PayloadEvent] = []
        i, N = 0, len(t)
        while i < N:
            if self._start is None:
                self._start = float(t[i])
                self.segments[-1].stamp = self._start
            if self._state == 'fitting':
                i = self._fitting(t, Yp, r, i, events)
            else:
                i = self._watching(t, Yp, r, i, events)
        return events

    def _fitting(self, t, Yp, r, i: int, events: list) -> int:
        use = i + int(np.searchsorted(t[i:], self._settle_until, side='left'))
        if use < len(t) and math.isnan(self._fit_due):
            self._fit_due = float(t[use]) + self.config.fit_time
        j = (len(t) if math.isnan(self._fit_due)
             else i + int(np.searchsorted(t[i:], self._fit_due, side='left')))
        j = max(j, use)
        if j > use:
            self._stats.add(Yp[use:j], r[use:j])
        if j >= len(t):
            return len(t)
        first = self.segments[-1].detected is None
        est = self._fit()
        events.append(PayloadEvent('start' if first else 'estimate', self.segments[-1].stamp,
                                   self.segments[-1].detected, est))
        self._state = 'watching'
        self._next_refresh = float(t[j]) + self.config.refresh
        return j

    def _watching(self, t, Yp, r, i: int, events: list) -> int:
        if self._noise is None:   # a given payload, and no noise level known yet
            return self._noise_level(t, Yp, r, i)
        e = r[i:] - Yp[i:] @ self.current.phi
        found = self.detector.push(t[i:], Yp[i:, :, :DETECTOR_COLUMNS], e, self._noise)
        stop = len(t) if found is None else i + int(np.searchsorted(t[i:], found.stamp,
                                                                    side='right'))
        self._pending.append((t[i:stop], Yp[i:stop], r[i:stop]))
        if found is not None:
            self._flush(found.onset, inclusive=False)
            self._close_segment()
            self.changes += 1
            events.append(PayloadEvent('change', found.onset, found.stamp, None, found))
            self.current, self._given = None, False
            self._new_segment(found.onset, found.stamp, self.config.settle)
            return stop
        self._flush(float(t[-1]) - self.config.window, inclusive=True)
        if float(t[-1]) >= self._next_refresh and not self._given:
            self._next_refresh = float(t[-1]) + self.config.refresh
            events.append(PayloadEvent('refresh', self.segments[-1].stamp,
                                       self.segments[-1].detected, self._fit()))
        return len(t)

    def _noise_level(self, t, Yp, r, i: int) -> int:
        """Gather ``fit_time`` s of samples for the noise level the detector weights by."""
        if math.isnan(self._fit_due):
            self._fit_due = float(t[i]) + self.config.fit_time
        j = i + int(np.searchsorted(t[i:], self._fit_due, side='left'))
        self._stats.add(Yp[i:j], r[i:j])
        if j < len(t):
            self._noise = self._noise_variance(self.current.phi)
            self._stats = ResidualStatistics(10, self.robot.dof, self._block)
        return j

    def _flush(self, before: float, inclusive: bool) -> None:
        """Pending samples stamped before ``before`` into the segment's statistics; with
        ``inclusive`` False the later ones are dropped (they follow a change)."""
        keep = []
        for t, Yp, r in self._pending:
            k = int(np.searchsorted(t, before, side='right'))
            if k:
                self._stats.add(Yp[:k], r[:k])
            if inclusive and k < len(t):
                keep.append((t[k:], Yp[k:], r[k:]))
        self._pending = keep

    def _noise_variance(self, phi: np.ndarray) -> np.ndarray:
        var = self._stats.noise_variance(phi, self._white_scale)
        return np.maximum(np.nan_to_num(var, nan=NOISE_FLOOR ** 2), NOISE_FLOOR ** 2)

    def _fit(self) -> PayloadEstimate:
        """Fit the segment's statistics: weights from the residual without payload, then from
        the first fit's long-run noise."""
        ne = self._stats.normal_equations()
        tol = self.config.tolerance
        est = fit_payload(ne, self._noise_variance(np.zeros(10)), self.attach.link, tol)
        var = self._noise_variance(est.phi)
        est = fit_payload(ne, var, self.attach.link, tol)
        self._noise = self._noise_variance(est.phi)
        self.current = est
        self.segments[-1].payload = est
        return est

    def _close_segment(self) -> None:
        if not self._given and self._stats.count:
            self._fit()

    def finish(self) -> list[Segment]:
        """At the end of the data: the last segment fitted with everything pending; the
        segments (with a payload where one could be fitted)."""
        if self._queued:
            parts, self._queued = self._queued, []
            self._run(*(np.concatenate(a) for a in zip(*parts)))
        if self._pending:
            self._flush(math.inf, inclusive=False)
        if self._stats.count and not self._given:
            self._fit()
        return [s for s in self.segments if not math.isnan(s.stamp)]


def segments_document(segments: list[Segment]) -> list[dict]:
    """The ``payload_changes`` of the JSON output: per segment its start ``stamp`` (s; the
    first at the data's start), when the change was ``detected`` (None for the first) and
    the payload fitted over it (payload.PayloadEstimate.document)."""
    return [{'stamp': s.stamp, 'detected': s.detected,
             'payload': None if s.payload is None else s.payload.document()}
            for s in segments]


def monitor_from_settings(settings, robot: RobotModel, half_window=None) -> PayloadMonitor:
    """The PayloadMonitor of the ``payload.*`` parameters (settings.Settings), for the
    pipeline's smoother: ``half_window`` (an int, or a callable giving the pipeline's once
    chosen, e.g. ``lambda: pipeline.row_builder.half_window``; default the settings' value,
    which must then be set); errors name the parameter."""
    from identification_node.payload.fit import arm_parameters, attachment
    v = settings.values
    config = MonitorConfig(**{k: v[f'payload.{k}'] for k in (
        'fit_time', 'settle', 'refresh', 'window', 'threshold', 'min_change', 'min_z',
        'confirm')},
        max_gap=v['smoother.max_gap'],
        tolerance={k: v[f'payload.tolerance.{k}'] for k in ('mass', 'com', 'inertia')})
    attach = attachment(robot, v['payload.link'])
    try:
        arm = v['payload.arm']
        phi_arm = arm_parameters(robot, '' if arm == ARM_ESTIMATE else arm)
    except IdentificationError as exc:
        raise IdentificationError(f'parameter payload.arm: {exc}') from None
    if half_window is None:
        half_window = v['smoother.half_window']
        if not half_window:
            raise IdentificationError('parameter smoother.half_window: the payload monitor '
                                      'needs the pipeline\'s smoother (0: give the pipeline\'s '
                                      'chosen half window)')
    return PayloadMonitor(robot, attach, phi_arm, config, half_window, v['smoother.order'])
