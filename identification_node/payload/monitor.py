"""Payload identification with change detection, on samples smoothed by the monitor itself.

PayloadMonitor takes the validated samples as they enter the pipeline (q, qd where measured
and the joint torque, stamped; PipelineOutput.inputs), smooths them with a short fixed-lag
smoother of its own (signals.FixedLagSmoother, cut-off ``cutoff`` Hz: the same local cubic
fit as the estimator's, but with a short delay of its own, whatever window the estimator's
automatic smoother picks and however long it holds samples to pick it), forms the residual
of the arm's model r = tau - Y phi_arm and the payload's regressor (with the arm's base
columns beside it where the arm comes with its uncertainty: payload.fit.ArmPrior), and runs
through segments of constant payload:

- *fitting*: after the start (or a change, once ``settle`` s have passed), ``fit_time`` s of
  samples are gathered and the payload fitted (payload.fit_payload); then
- *watching*: the residual of arm plus payload goes to the change detector
  (change_detection.WindowedGLR), and its samples, once older than the latest a change
  is declared after its onset (2 ``window`` + ``confirm``: so none from after a change),
  refine the segment's fit every ``refresh`` s. A detection
  ends the segment a ``window`` before the estimated onset and starts *fitting* again.

With an ArmPrior, each segment's fit corrects the arm's base parameters within that prior,
and a segment's end adds what it told of the arm (its payload eliminated) to the prior the
next segments are fitted with: the arm is refined by every segment, and the payloads'
covariances include what remains of its uncertainty.

The torque noise is measured too (raw torque minus its smoothed value, at the window
centres): a fit whose residual is many times that noise means the arm's model does not
explain the torque (``arm_residual_ratio``, ``warnings``).

Events (PayloadEvent) report the segment starts, the detections and each fit. Stamps are
seconds (header stamps).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from identification_node.config import Payload, Smoother
from identification_node.errors import IdentificationError
from identification_node.estimation.residuals import MIN_BLOCKS, ResidualStatistics
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.payload.change_detection import (DEFAULT_CONFIRM, DEFAULT_MIN_CHANGE,
                                                          DEFAULT_MIN_Z, DEFAULT_THRESHOLD,
                                                          DEFAULT_WINDOW, Detection, WindowedGLR)
from identification_node.payload.fit import (ArmPrior, Attachment, PayloadEstimate,
                                             arm_information, fit_payload, given_payload,
                                             payload_regressor)
from identification_node.pipeline.signals import (FixedLagSmoother, half_window_for_cutoff,
                                                  smoothing_noise_gain)

ARM_ESTIMATE = 'estimate'   # payload.arm: the node's running estimate, taken at each reset
NOISE_FLOOR = 1e-4   # N m: the smallest noise standard deviation a joint is weighted by
DETECTOR_COLUMNS = 4  # m, mx, my, mz
DEFAULT_CUTOFF = Payload.cutoff   # Hz: the monitor's smoother (delay ~ 0.7 / cutoff s)
DERIVATIVE_BAND = 4.0  # the derivatives' smoother's cut-off over the low-pass's
ARM_RESIDUAL_RATIO = 4.0   # a fit's residual this many times the noise: the arm is not known


@dataclass
class MonitorConfig:
    """Settings of the payload monitor (node parameters ``payload.*``)."""
    fit_time: float = Payload.fit_time   # s of samples after a change for the first fit
    settle: float = Payload.settle       # s after a detection before samples are used
    refresh: float = Payload.refresh     # s between refits while the payload stays
    window: float = DEFAULT_WINDOW
    threshold: float = DEFAULT_THRESHOLD
    min_change: float = DEFAULT_MIN_CHANGE
    min_z: float = DEFAULT_MIN_Z
    confirm: float = DEFAULT_CONFIRM
    max_gap: float = Smoother.max_gap
    batch: float = 0.02          # s of samples gathered per run (numpy calls cost per run)
    cutoff: float = DEFAULT_CUTOFF   # Hz, -3 dB cut-off of the monitor's own smoother
    order: int = 3               # its polynomial order
    tolerance: Mapping[str, float] = field(default_factory=dict)

    def validate(self) -> None:
        if self.order not in (2, 3, 4):
            raise IdentificationError(f'payload smoother order {self.order!r}: 2, 3 or 4')
        for name in ('fit_time', 'settle', 'refresh', 'window', 'threshold', 'min_change',
                     'min_z', 'max_gap', 'batch', 'confirm', 'cutoff'):
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
    yet), 'estimate' (the first fit after a change) or 'refresh' (a refined fit).
    ``mass_change``: of an 'estimate', the fitted mass minus the previous segment's (kg) and
    its standard deviation ``mass_change_std`` (NaN where either is not known)."""
    kind: str
    stamp: float
    detected: float | None = None
    payload: PayloadEstimate | None = None
    detection: Detection | None = None
    mass_change: float = math.nan
    mass_change_std: float = math.nan


@dataclass
class Segment:
    """A span of constant payload: from ``stamp`` (s), detected at ``detected`` (None for the
    first), with its latest fit."""
    stamp: float
    detected: float | None
    payload: PayloadEstimate | None = None


class PayloadMonitor:
    """See the module docstring. ``phi_arm``: the arm's standard parameters (payload.fit.
    read_arm); ``arm_base``: the arm's base parameters when its uncertainty is to be
    taken into account (the base columns are then filtered and gathered beside the payload's),
    with the prior ``arm_prior`` (None: the arm is taken as exact until set_arm gives one).
    Its smoother is made from the first samples' rate."""

    def __init__(self, robot: RobotModel, attach: Attachment, phi_arm: np.ndarray,
                 config: MonitorConfig | None = None, arm_base: BaseParameters | None = None,
                 arm_prior: ArmPrior | None = None):
        self.robot, self.attach = robot, attach
        self.arm_base = arm_base if arm_base is not None else (
            None if arm_prior is None else arm_prior.base)
        self.columns = 10 + (0 if self.arm_base is None else self.arm_base.num_base)
        self.phi_arm = np.zeros(robot.num_params)
        self._arm_prior: ArmPrior | None = None
        self.set_arm(phi_arm, arm_prior, reset=False)
        self.config = config or MonitorConfig()
        self.config.validate()
        c = self.config
        self.smoother: FixedLagSmoother | None = None   # made from the first samples
        self.rate = math.nan      # Hz, of the first samples
        self._block = 1
        self._white_scale = 1.0
        self._derivative_gain = 0.0
        self.derivatives: FixedLagSmoother | None = None
        self.detector = WindowedGLR(c.window, c.threshold, c.min_change, c.max_gap,
                                    min_z=c.min_z, confirm=c.confirm)
        self.segments: list[Segment] = []
        self._queued: list[tuple] = []
        self._last_t = -math.inf
        self._epoch_ns: int | None = None
        self._last_ns: int | None = None
        self._tail = (np.empty(0), np.empty((0, robot.dof)))   # raw (t, tau) not yet centred
        self._hf = np.zeros(robot.dof)   # sum of (raw - smoothed torque)^2 at the centres
        self._hf_count = 0
        self.arm_residual_ratio = math.nan
        self.burst_samples = 0
        self.changes = 0
        self.reset()

    def set_arm(self, phi_arm: np.ndarray, prior: ArmPrior | None = None,
                reset: bool = True) -> None:
        """The arm's standard parameters and what is known of their error (None: exact);
        the payload is forgotten (``reset``)."""
        phi = np.asarray(phi_arm, dtype=float)
        if phi.shape != (self.robot.num_params,) or not np.isfinite(phi).all():
            raise IdentificationError(
                f'arm parameters must be {self.robot.num_params} finite values')
        if prior is not None and (self.arm_base is None
                                  or prior.base.num_base != self.arm_base.num_base):
            raise IdentificationError("the arm's prior is not of the monitor's base parameters")
        self.phi_arm, self._arm_prior = phi, prior
        if reset:
            self.reset()

    @property
    def detector_delay(self) -> float:
        """s: how far the detector's samples lag the newest input (the smoother's half
        window; NaN before the first samples). A change is declared ``confirm`` s and a
        fraction of ``window`` after that."""
        if self.smoother is None or self.derivatives is None:   # made together
            return math.nan
        return self.smoother.delay(self.rate) + self.derivatives.delay(self.rate)

    def torque_noise(self) -> np.ndarray:
        """Per joint the standard deviation (N m) of the white torque noise: the raw torque
        minus its smoothed value at the window centres, over 1 - the smoother's noise gain
        (NaN before any sample)."""
        if not self._hf_count:
            return np.full(self.robot.dof, math.nan)
        return np.sqrt(self._hf / self._hf_count / max(1.0 - self._derivative_gain, 1e-9))

    def warnings(self, hint: str = 'pass --arm') -> list[str]:
        """What the user must know: an arm model that does not explain the torque (``hint``:
        how to give the identified arm)."""
        r = self.arm_residual_ratio
        if math.isfinite(r) and r > ARM_RESIDUAL_RATIO:
            return [f"the arm's residual is {r:.0f} times the noise: identify the arm first "
                    f'and {hint}']
        return []

    # -- state ------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the payload and what the segments told of the arm: a new segment (no change
        event) starts at the next sample."""
        self.prior = self._arm_prior
        self.current: PayloadEstimate | None = None
        self._theta = np.zeros(self.columns)   # the current payload, then arm correction
        self._noise: np.ndarray | None = None   # the segment's noise variance, (N m)^2
        self._given = False
        self._new_segment(None, None, 0.0)

    def set_payload(self, phi: np.ndarray, stamp: float | None = None) -> PayloadEstimate:
        """A payload known to the user (10 parameters, attachment frame): watched from now on,
        not refitted until a change is detected."""
        est = given_payload(self.attach.link, phi)
        self._new_segment(stamp, None, 0.0)
        self.current, self._given = est, True
        self._theta = np.zeros(self.columns)
        self._theta[:10] = est.phi
        if self.prior is not None:
            self._theta[10:] = self.prior.mean()
        self.segments[-1].payload = est
        self._state = 'watching'
        return est

    def _new_segment(self, stamp: float | None, detected: float | None, settle: float) -> None:
        self._stats = ResidualStatistics(self.columns, self.robot.dof, self._block)
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
    def add_output(self, out) -> list[PayloadEvent]:
        """``add`` of a PipelineOutput's input samples."""
        inp = getattr(out, 'inputs', None)
        return [] if inp is None else self.add(inp.stamps_ns, inp.q, inp.tau)

    def add(self, stamps_ns: np.ndarray, q: np.ndarray, tau: np.ndarray
            ) -> list[PayloadEvent]:
        """Validated samples in time order (header stamps int64 ns; q and the joint torque
        (N, n)): the events they bring, once ``batch`` s of samples are gathered. Velocities
        and accelerations are the smoother's derivatives of q: over a short window a
        measured velocity's noise, differentiated, would swamp the payload's torque, where
        an encoder's is orders of magnitude below it."""
        if len(stamps_ns) == 0:
            return []
        self._queued.append((np.asarray(stamps_ns, dtype=np.int64), q, tau))
        span = (int(stamps_ns[-1]) - int(self._queued[0][0][0])) * 1e-9
        if span < self.config.batch or (self.smoother is None and span <= 0):
            return []
        return self._smooth(*self._take())

    def _take(self) -> tuple:
        parts, self._queued = self._queued, []
        return tuple(np.concatenate(a) for a in zip(*parts)) if len(parts) > 1 else parts[0]

    def _smooth(self, ns: np.ndarray, q: np.ndarray, tau: np.ndarray) -> list[PayloadEvent]:
        """_filter on each run of increasing stamps (a stream restarts where they fall)."""
        cuts = [0, *(np.flatnonzero(np.diff(ns) <= 0) + 1).tolist(), len(ns)]
        events: list[PayloadEvent] = []
        for a, b in zip(cuts[:-1], cuts[1:]):
            events += self._filter(ns[a:b], q[a:b], tau[a:b])
        return events

    def _filter(self, ns: np.ndarray, q: np.ndarray, tau: np.ndarray) -> list[PayloadEvent]:
        """Parallel filtering of raw samples: the derivatives (wide smoother), the residual
        and payload regressor at its window centres from the raw torque, then the same
        low-pass (narrow smoother) on both; _run on its window centres."""
        if self._epoch_ns is None:
            self._epoch_ns = int(ns[0])
        if self.smoother is None:
            self._make_smoother(ns)
        elif self._last_ns is not None and int(ns[0]) <= self._last_ns:   # a restarted stream
            assert self.derivatives is not None   # made with the smoother
            self.smoother.reset()
            self.derivatives.reset()
            self._tail = (np.empty(0), np.empty((0, self.robot.dof)))
        else:
            ns, q, tau = self._drop_bursts(ns, q, tau)
            if len(ns) == 0:
                return []
        self._last_ns = int(ns[-1])
        assert self.smoother is not None and self.derivatives is not None   # made above
        t = (ns - self._epoch_ns) * 1e-9
        n = self.robot.dof
        tc, x, xd, xdd = self.derivatives.push_checked(t, np.hstack([q, tau]))
        raw_t, raw_tau = (np.concatenate([self._tail[0], t]),
                          np.concatenate([self._tail[1], tau]))
        keep = max(len(raw_t) - 2 * self.derivatives.half_window - 2, 0)
        self._tail = raw_t[keep:], raw_tau[keep:]
        if len(tc) == 0:
            return []
        at = np.clip(np.searchsorted(raw_t, tc - 1e-10), 0, len(raw_t) - 1)
        if not np.all(np.abs(raw_t[at] - tc) < 1e-9):
            raise IdentificationError('payload monitor: a window centre without its sample')
        tau_c = raw_tau[at]
        self._hf += ((tau_c - x[:, n:]) ** 2).sum(axis=0)
        self._hf_count += len(tc)
        Y = self.robot.regressor(x[:, :n], xd[:, :n], xdd[:, :n], checked=True)
        r = tau_c - Y @ self.phi_arm
        A = payload_regressor(self.attach, Y)
        if self.arm_base is not None:
            A = np.concatenate([A, Y[:, :, self.arm_base.base_index]], axis=2)
        tf, z, _, _ = self.smoother.push_checked(tc, np.hstack([A.reshape(len(tc), -1), r]))
        if len(tf) == 0:
            return []
        stamps = (self._epoch_ns + np.round(tf * 1e9).astype(np.int64))
        c = self.columns
        return self._run(stamps, z[:, :c * n].reshape(len(tf), n, c), z[:, c * n:])

    def _drop_bursts(self, ns: np.ndarray, q: np.ndarray, tau: np.ndarray) -> tuple:
        """Samples stamped closer than half the sampling period to the one before, and the
        sample before each run of them, dropped (counted in ``burst_samples``): a stalled
        stream's held samples sent at once with compressed stamps, whose first carries the
        end of the stall; their stamps are not their times. The smoother fits across the
        hole (or restarts, past max_gap)."""
        step = np.diff(np.concatenate([[self._last_ns], ns]))
        bad = step < 0.5e9 / self.rate
        if not bad.any():
            return ns, q, tau
        starts = np.flatnonzero(bad & ~np.concatenate([[False], bad[:-1]]))
        drop = bad.copy()
        drop[starts[starts > 0] - 1] = True
        self.burst_samples += int(drop.sum())
        return ns[~drop], q[~drop], tau[~drop]

    def _make_smoother(self, ns: np.ndarray) -> None:
        """The two smoothers, for the first samples' rate: ``derivatives`` (cut-off
        DERIVATIVE_BAND times ``cutoff``: little distortion of the motion) and ``smoother``
        (``cutoff``: it takes out most of the noise the derivatives bring)."""
        c = self.config
        self.rate = 1e9 / float(np.median(np.diff(ns)))
        n = self.robot.dof
        Ld = half_window_for_cutoff(DERIVATIVE_BAND * c.cutoff, self.rate, c.order)
        self.derivatives = FixedLagSmoother(2 * n, Ld, c.order, c.max_gap)
        L = half_window_for_cutoff(c.cutoff, self.rate, c.order)
        self.smoother = FixedLagSmoother((self.columns + 1) * n, L, c.order, c.max_gap)
        self._block = 2 * L + 1
        self._white_scale = 1.0 / smoothing_noise_gain(L, c.order)
        self._derivative_gain = smoothing_noise_gain(Ld, c.order)
        self.detector.noise_scale = self._white_scale
        self._stats = ResidualStatistics(self.columns, n, self._block)

    def _run(self, stamps_ns: np.ndarray, Yp: np.ndarray, r: np.ndarray
             ) -> list[PayloadEvent]:
        """Filtered payload regressor (N, n, 10; then the arm's base columns) and arm
        residual (N, n) at stamps (ns)."""
        t = np.asarray(stamps_ns, dtype=np.int64) * 1e-9
        if t[0] <= self._last_t:   # a restarted stream: keep the payload, restart the clocks
            self._settle_until = -math.inf
            if self._state == 'fitting':
                self._fit_due = math.nan
            self._next_refresh = float(t[0]) + self.config.refresh
        self._last_t = float(t[-1])
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
        event = PayloadEvent('start' if first else 'estimate', self.segments[-1].stamp,
                             self.segments[-1].detected, est)
        before = self.segments[-2].payload if len(self.segments) > 1 else None
        if not first and before is not None:
            sd = math.hypot(before.stddev['mass'], est.stddev['mass'])
            if math.isfinite(sd):
                event.mass_change, event.mass_change_std = est.mass - before.mass, sd
        events.append(event)
        self._state = 'watching'
        self._refresh_step = self.config.fit_time
        self._next_refresh = float(t[j]) + self._refresh_step
        return j

    def _watching(self, t, Yp, r, i: int, events: list) -> int:
        assert self.current is not None   # watching: the segment's payload is known
        if self._noise is None:   # a given payload, and no noise level known yet
            return self._noise_level(t, Yp, r, i)
        e = r[i:] - Yp[i:] @ self._theta
        found = self.detector.push(t[i:], Yp[i:, :, :DETECTOR_COLUMNS], e, self._noise)
        stop = len(t) if found is None else i + int(np.searchsorted(t[i:], found.stamp,
                                                                    side='right'))
        self._pending.append((t[i:stop], Yp[i:stop], r[i:stop]))
        if found is not None:
            # the onset is known to within a window, and the low-pass spreads the change
            # half its window earlier: no sample after the change may join the segment it ends
            self._flush(found.onset - self.config.window, inclusive=False)
            self._close_segment()
            self.changes += 1
            events.append(PayloadEvent('change', found.onset, found.stamp, None, found))
            self.current, self._given = None, False
            self._new_segment(found.onset, found.stamp, self.config.settle)
            return stop
        # a change is declared up to about window + confirm after its onset (later when
        # small or noisy): samples join the fit only once older than twice that window
        self._flush(float(t[-1]) - 2.0 * self.config.window - self.config.confirm,
                    inclusive=True)
        if float(t[-1]) >= self._next_refresh and not self._given:
            # refits come at doubling intervals up to ``refresh``: a first fit from a short
            # motion may leave directions unexcited that the next seconds determine
            self._refresh_step = min(2.0 * self._refresh_step, self.config.refresh)
            self._next_refresh = float(t[-1]) + self._refresh_step
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
            assert self.current is not None   # the given payload (called while watching)
            self._set_noise(self._theta)
            self._stats = ResidualStatistics(self.columns, self.robot.dof, self._block)
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
        """Per joint the variance (N m)^2 of the residual of ``phi`` (the columns' parameters:
        payload, then arm correction) noise a sum over the segment
        averages: its long-run variance once MIN_BLOCKS blocks are in (the smoothed torque
        noise, and model errors at the motion's frequencies; not the noise the derivatives
        bring into the regressor, which is high-frequency), else the white noise that
        explains the residual's variance."""
        s = self._stats
        return _floored(s.long_run_variance(phi) if s.blocks >= MIN_BLOCKS
                        else s.variance(phi) * self._white_scale)

    def _fit_variance(self, phi: np.ndarray) -> np.ndarray:
        """Per joint the noise variance (N m)^2 the fits weight by and a segment's information
        on the arm is counted with: the estimator's rule (ResidualStatistics.noise_variance),
        the larger of the long-run variance and the white noise that explains the residual's
        variance. The long-run variance alone is blind to the derivatives' noise in the
        regressor: each segment would tell the arm's prior more than it knows."""
        return _floored(self._stats.noise_variance(phi, self._white_scale))

    def _set_noise(self, phi: np.ndarray) -> None:
        """The detector's noise: the segment's long-run variance, and per joint its ratio to
        the residual's variance per sample (how the detector scales a window's)."""
        self._noise = self._noise_variance(phi)
        with np.errstate(divide='ignore', invalid='ignore'):
            scale = self._noise / self._stats.variance(phi)
        self.detector.noise_scale = np.clip(np.nan_to_num(scale, nan=self._white_scale), 1.0,
                                            self._white_scale)

    def _fit(self) -> PayloadEstimate:
        """Fit the segment's statistics: weights from the residual without payload, then from
        the first fit's noise (``_fit_variance``)."""
        ne = self._stats.normal_equations()
        tol = self.config.tolerance
        est = fit_payload(ne, self._noise_variance(np.zeros(self.columns)), self.attach.link,
                          tol, prior=self.prior)
        est = fit_payload(ne, self._fit_variance(self._parameters(est)), self.attach.link, tol,
                          prior=self.prior)
        self._theta = self._parameters(est)
        self._set_noise(self._theta)
        assert self._noise is not None   # set just now
        noise = self.torque_noise() ** 2
        ok = np.isfinite(noise) & (noise > 0)
        if ok.any():
            self.arm_residual_ratio = float(np.sqrt((self._noise[ok] / noise[ok]).max()))
        self.current = est
        self.segments[-1].payload = est
        return est

    def _parameters(self, est: PayloadEstimate) -> np.ndarray:
        """The columns' parameters of a fit: its payload, then its arm correction (0 where
        the arm is taken as exact)."""
        theta = np.zeros(self.columns)
        theta[:10] = est.phi
        theta[10:10 + est.arm_correction.size] = est.arm_correction
        return theta

    def _close_segment(self) -> None:
        """The ending segment's final fit; what it told of the arm joins the prior."""
        if not self._given and self._stats.count:
            self._fit()
            if self.prior is not None and self._noise is not None:
                self.prior = self.prior.updated(*arm_information(
                    self._stats.normal_equations(), self._fit_variance(self._theta)))

    def finish(self) -> list[Segment]:
        """At the end of the data: the last segment fitted with everything pending; the
        segments (with a payload where one could be fitted)."""
        if self._queued:
            ns, q, tau = self._take()
            if self.smoother is not None or ns[-1] > ns[0]:
                self._smooth(ns, q, tau)
        if self._pending:
            self._flush(math.inf, inclusive=False)
        if self._stats.count and not self._given:
            self._fit()
        return [s for s in self.segments if not math.isnan(s.stamp)]


def _floored(variance: np.ndarray) -> np.ndarray:
    """Per-joint noise variances (N m)^2 at least NOISE_FLOOR^2 (its value where unknown)."""
    return np.maximum(np.nan_to_num(variance, nan=NOISE_FLOOR ** 2), NOISE_FLOOR ** 2)


def segments_document(segments: list[Segment]) -> list[dict]:
    """The ``payload_changes`` of the JSON output: per segment its start ``stamp`` (s; the
    first at the data's start), when the change was ``detected`` (None for the first) and
    the payload fitted over it (payload.PayloadEstimate.document); ``mass_change``: its
    mass minus the segment before's (kg), with ``mass_change_std`` (None where unknown)."""
    out = []
    for k, s in enumerate(segments):
        doc = {'stamp': s.stamp, 'detected': s.detected,
               'payload': None if s.payload is None else s.payload.document(),
               'mass_change': None, 'mass_change_std': None}
        before = segments[k - 1].payload if k else None
        if before is not None and s.payload is not None:
            sd = math.hypot(before.stddev['mass'], s.payload.stddev['mass'])
            if math.isfinite(sd):
                doc['mass_change'] = s.payload.mass - before.mass
                doc['mass_change_std'] = sd
        out.append(doc)
    return out


def monitor_from_settings(settings, robot: RobotModel,
                          base: BaseParameters | None = None) -> PayloadMonitor:
    """The PayloadMonitor of the ``payload.*`` parameters (settings.Settings); errors name the
    parameter. An estimate.yaml as ``payload.arm`` brings its covariance as the arm's prior;
    with 'estimate' the arm's base columns are gathered, the prior given by set_arm.
    ``base``: the arm's base parameters (default: the robot's, as the pipeline's)."""
    from identification_node.payload.fit import attachment, read_arm
    v = settings.values
    config = MonitorConfig(**{k: v[f'payload.{k}'] for k in (
        'fit_time', 'settle', 'refresh', 'window', 'threshold', 'min_change', 'min_z',
        'confirm', 'cutoff')},
        max_gap=v['smoother.max_gap'],
        tolerance={k: v[f'payload.tolerance.{k}'] for k in ('mass', 'com', 'inertia')})
    attach = attachment(robot, v['payload.link'])
    arm = v['payload.arm']
    if arm and base is None:
        base = BaseParameters.from_robot(robot)
    try:
        phi_arm, prior = read_arm(robot, '' if arm == ARM_ESTIMATE else arm, base)
    except IdentificationError as exc:
        raise IdentificationError(f'parameter payload.arm: {exc}') from None
    gathered = arm == ARM_ESTIMATE or prior is not None   # the arm's columns are of use
    return PayloadMonitor(robot, attach, phi_arm, config, arm_base=base if gathered else None,
                          arm_prior=prior)
