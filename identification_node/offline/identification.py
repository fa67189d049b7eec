"""Offline (batch) identification of a whole bag, and held-out validation.

The bag's messages go through the pipeline's own input stages (pipeline.TorqueSamples:
validation, stamp ordering, current alignment and torque conversion), then:

- periodic data (``period`` given, e.g. from a Fourier trajectory file): positions, measured
  velocities and torques are averaged over the whole periods (Radkhah, Kulic, Croft, section
  II.C; signals.period_average), and the spread over the periods gives each joint's torque noise
  variance. A Fourier series of the known period fitted to the averaged positions by least
  squares (harmonics carrying only noise left out, fourier_fit) gives q, qd, qdd analytically.
  Weighted least squares (their eq. 6) on the averaged period weights each row by the inverse
  variance of its average, sigma_j^2 / periods.
- otherwise: a zero-phase Butterworth low-pass of positions and measured velocities, derivatives
  by central differences of the filtered signals, then the same zero-phase low-pass applied to
  the torque and, alike, to every column of the base regressor ("parallel filtering": F(tau) =
  F(Y) theta holds exactly whatever the nonlinearity of Y), decimation to about twice the
  cutoff (nearly white residuals, so the least-squares covariance is honest), and feasible
  weighted least squares (their eq. 6) with per-joint noise variances from the residuals.

When Coulomb friction is identified, a joint's equations within the filter's reach of its
velocity reversals (speed below ``coulomb_exclusion_speed``) are left out, as the pipeline does:
stiction, and a simulated light joint's stiff friction switch, are where the model fails. The
least squares therefore works on residual sums (ResidualStatistics) with per-joint equation
counts (estimators.weighted_solve).

Memory: unlike the streaming pipeline (replay.identify_bag), this path holds the bag's validated
samples in memory (q, qd, torque: three (N, n) float arrays); the regressor is built and filtered
in overlapping chunks, the estimators keep O(n p^2) sums and the series kept for plots are
subsampled, so nothing else grows with the bag. Units SI; stamps int64 ns (header stamps).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from typing import Callable, Iterator

import numpy as np

from identification_node.config import BatchConfig
from identification_node.bags.reader import open_bag, read_string_topic
from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import (ConsistencyOptions, ConsistentEstimate,
                                                        ConsistentSolver, pipeline_equations)
from identification_node.estimation.batch import WeightedFit, weighted_solve
from identification_node.estimation.model_terms import (ModelTermStatistics,
                                                        missing_term_warnings)
from identification_node.estimation.model_terms import features as model_features
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.estimation.prior import safe_prior
from identification_node.model.identifiability import (BaseParameters, sample_motion,
                                                       unexcited_directions)
from identification_node.model.robot import RobotModel, load_robot
from identification_node.model.urdf_export import consistency_problems
from identification_node.offline.replay import (JOINT_STATES, MOTOR_CURRENTS, ROBOT_DESCRIPTION,
                                                Checkpoint, ReplayResult, check_usable, feed_bag,
                                                identify_bag, input_topics)
from identification_node.offline.validation import BagError, evaluate
from identification_node.offline.windows import TimeWindow
from identification_node.pipeline import (IdentificationPipeline, PipelineConfig, PipelineOutput,
                                          TorqueSamples, converged)
from identification_node.pipeline.rows import AUTO_WAIT, choose_smoother
from identification_node.pipeline.time_offset import TimeOffset, TimeOffsetCheck
from identification_node.pipeline.signals import (central_derivatives, half_window_for_cutoff,
                                                  period_average,
                                                  zero_phase_lowpass)
from identification_node.settings import Settings

DEFAULT_CUTOFF = BatchConfig.cutoff   # Hz: zero-phase low-pass of the filtered path; Fourier band
FILTER_ORDER = BatchConfig.order      # Butterworth order (run twice: squared gain, no phase)
EDGE_PERIODS = 3.0        # 1/cutoff periods trimmed at each segment end (filter start-up)
REVERSAL_PERIODS = 1.0    # 1/cutoff periods around a velocity reversal left out (with fc)
OVERLAP_PERIODS = 10.0    # 1/cutoff periods of overlap between chunks: joins exact to ~1e-10
CHUNK = 4096              # raw samples per regressor chunk
JITTER = 0.01             # relative stamp jitter above which a segment is resampled uniformly
SERIES_POINTS = 4000      # samples kept for the torque plots
RESIDUAL_BLOCK = 8        # rows per block of the residual statistics


# -- samples of a bag ---------------------------------------------------------------------------
@dataclass
class Stream:
    """Validated samples of one stream (no restart inside), in stamp order: header stamps
    (N,) int64 ns, q, qd (NaN when not measured) and joint torque tau, each (N, n)."""
    stamps_ns: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    tau: np.ndarray


@dataclass
class BagSamples:
    """The validated samples of a bag: streams, counters, and whether velocity is measured."""
    bag: str
    streams: list[Stream]
    messages: int
    rejected: dict
    velocity_measured: bool

    @property
    def num_samples(self) -> int:
        return sum(len(s.stamps_ns) for s in self.streams)

    @property
    def first_ns(self) -> int:
        return int(self.streams[0].stamps_ns[0])

    @property
    def last_ns(self) -> int:
        return int(self.streams[-1].stamps_ns[-1])


def read_samples(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                 joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS,
                 base: BaseParameters | None = None, batch: int = 1000,
                 window: TimeWindow | None = None) -> BagSamples:
    """The bag's joint states (and motor currents when the torque sources need them) validated,
    ordered, aligned and converted to joint torque exactly as the pipeline does; those
    recorded in ``window`` only (windows.py)."""
    config = settings.build(robot).config if base is None else \
        settings.pipeline_config(robot.joint_names)
    stages = TorqueSamples(robot, config)
    counters = stages.counters
    topics = input_topics(stages, joint_states, motor_currents)
    parts: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def collect(flush: bool) -> None:
        s = stages.process(flush)
        if len(s):   # all of the newest stream
            parts.append((counters.restarts, counters.stamps_ns(s.stamps), s.q, s.qd, s.tau))

    with open_bag(bag) as reader:
        counts = reader.topic_counts
        messages = feed_bag(reader, stages, topics, batch, collect, window)
    check_usable(sum(len(p[1]) for p in parts), counters.rejected, bag, topics, counts,
                 counters, robot.joint_names)
    streams = []
    for sid in sorted({p[0] for p in parts}):
        stream = [p[1:] for p in parts if p[0] == sid]
        streams.append(Stream(*(np.concatenate(a) for a in zip(*stream))))
    return BagSamples(str(bag), streams, messages,
                      {k: v for k, v in counters.rejected.items() if v},
                      stages.velocity_measured)


# -- rows for the estimators --------------------------------------------------------------------
@dataclass
class Rows:
    """Processed samples ready for least squares: stamps (N,) int64 ns, base regressor (N, n, b),
    torque (N, n); ``scale`` (N, n): inverse noise standard deviation of each equation (None:
    the noise variances are estimated from the residuals); ``mask`` (N, n): False for the
    equations left out (a joint near a velocity reversal while Coulomb friction is identified;
    None: all used); ``index`` (N,): how many of the bag's samples lie up to each row;
    ``features`` (N, n, 4): model_terms.features of the rows' motion, processed as they are."""
    stamps_ns: np.ndarray
    regressor: np.ndarray
    tau: np.ndarray
    scale: np.ndarray | None = None
    mask: np.ndarray | None = None
    index: np.ndarray | None = None
    features: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def slice(self, a: int, b: int) -> Rows:
        return Rows(*(None if x is None else x[a:b] for x in (
            self.stamps_ns, self.regressor, self.tau, self.scale, self.mask, self.index,
            self.features)))


@dataclass(frozen=True)
class BatchOptions:
    """How a bag is processed offline. ``period`` (s) selects periodic averaging; the Fourier
    series fitted to the averaged positions has ``harmonics`` per joint, by default chosen from
    the data (fourier_fit) between ``min_harmonics`` (e.g. a known trajectory's) and
    cutoff * period; ``cutoff`` (Hz) of the zero-phase low-pass of the filtered path (None:
    the settings' smoother.cutoff when > 0, else the smoother's automatic cut-off chosen on
    the bag's first smoother.auto_seconds of motion, auto_cutoff; the periodic path's band is
    then DEFAULT_CUTOFF); ``decimation`` there defaults to floor(rate / (2 cutoff)).
    ``window`` (t0, t1), s after the first sample: periodic averaging uses only the samples
    in it (the periodic part of a trajectory framed by ramps,
    trajectories.FramedTrajectory.periodic_window)."""
    period: float | None = None
    window: tuple[float, float] | None = None
    harmonics: int | None = None
    min_harmonics: int = BatchConfig.min_harmonics
    cutoff: float | None = None
    decimation: int | None = None
    order: int = FILTER_ORDER

    def validate(self) -> None:
        if self.period is not None and not (math.isfinite(self.period) and self.period > 0):
            raise IdentificationError(f'period must be > 0 s, got {self.period!r}')
        if self.window is not None:
            t0, t1 = self.window
            if not (math.isfinite(t0) and math.isfinite(t1) and 0 <= t0 < t1):
                raise IdentificationError(f'window must be 0 <= t0 < t1 s, got {self.window}')
            if self.period is None:
                raise IdentificationError('a window needs a period (periodic averaging)')
        if self.cutoff is not None and not (math.isfinite(self.cutoff) and self.cutoff > 0):
            raise IdentificationError(f'cutoff must be > 0 Hz, got {self.cutoff!r}')
        for name in ('harmonics', 'decimation', 'min_harmonics'):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or int(v) != v or v < 1):
                raise IdentificationError(f'{name} must be an integer >= 1, got {v!r}')


@dataclass
class _Segment:
    stamps_ns: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    tau: np.ndarray
    rate: float
    picks: np.ndarray      # indices of the rows kept (trimmed, decimated)
    offset: int            # bag samples before the segment


def _uniform(s: Stream, start: int, stop: int) -> tuple[Stream, float, bool]:
    """Samples start:stop of a stream on a uniform time grid (linear interpolation when the
    stamps jitter by more than JITTER of the median step), with the rate (Hz)."""
    ns = s.stamps_ns[start:stop]
    t = (ns - ns[0]) * 1e-9
    step = float(np.median(np.diff(t)))
    part = Stream(ns, s.q[start:stop], s.qd[start:stop], s.tau[start:stop])
    if np.max(np.abs(np.diff(t) - step)) <= JITTER * step:
        return part, 1.0 / step, False
    grid = np.arange(int(math.floor(t[-1] / step + 1e-9)) + 1) * step

    def interp(x: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(grid, t, x[:, j]) for j in range(x.shape[1])])

    return (Stream(ns[0] + np.round(grid * 1e9).astype(np.int64), interp(part.q),
                   interp(part.qd), interp(part.tau)), 1.0 / step, True)


def _plan_filtered(samples: BagSamples, options: BatchOptions, max_gap: float
                   ) -> tuple[list[_Segment], dict]:
    """Split the streams at stamp gaps > max_gap into segments and choose the rows kept."""
    segments, dropped, resampled, decimations, rates = [], 0, 0, set(), set()
    cutoff = options.cutoff
    offset = 0
    for s in samples.streams:
        gaps = np.flatnonzero(np.diff(s.stamps_ns) * 1e-9 > max_gap) + 1
        bounds = np.concatenate([[0], gaps, [len(s.stamps_ns)]])
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b - a < 8:
                dropped += int(b - a)
                continue
            seg, rate, interpolated = _uniform(s, int(a), int(b))
            if not cutoff < 0.5 * rate:
                raise IdentificationError(
                    f'cutoff {cutoff:g} Hz must be below half the sampling rate '
                    f'({rate:.6g} Hz)')
            k = options.decimation or max(1, int(math.floor(rate / (2.0 * cutoff) + 1e-6)))
            if 2.0 * cutoff > rate / k * (1 + 1e-9):
                raise IdentificationError(
                    f'decimation {k} leaves {rate / k:.4g} Hz, less than twice the cutoff '
                    f'{cutoff:g} Hz: the decimated rows would alias; lower --decimate or '
                    '--cutoff')
            trim = int(math.ceil(EDGE_PERIODS * rate / cutoff))
            n = len(seg.stamps_ns)
            picks = np.arange(trim, n - trim, k)
            if n < 3 * trim or len(picks) == 0:
                dropped += n
                continue
            resampled += interpolated
            decimations.add(k)
            rates.add(round(rate, 6))
            segments.append(_Segment(seg.stamps_ns, seg.q, seg.qd, seg.tau, rate, picks,
                                     offset + int(a)))
        offset += len(s.stamps_ns)
    if not segments:
        raise IdentificationError(
            f'no segment of {samples.bag} is long enough for a {cutoff:g} Hz zero-phase '
            f'filter (each needs {3 * EDGE_PERIODS:g} / cutoff s without stamp gaps over '
            f'{max_gap:g} s)')
    rows = int(sum(len(g.picks) for g in segments))
    info = {'processing': 'filtered', 'cutoff_hz': cutoff, 'filter_order': options.order,
            'rate_hz': sorted(rates), 'decimation': sorted(decimations),
            'segments': len(segments), 'resampled_segments': resampled,
            'dropped_samples': dropped, 'rows': rows}
    return segments, info


def _reversal_mask(qd: np.ndarray, picks: np.ndarray, speed: float, reach: int) -> np.ndarray:
    """(len(picks), n): False where the joint's speed falls below ``speed`` within ``reach``
    samples of the row, so inside the filter's reach of a velocity reversal."""
    slow = np.concatenate([np.zeros((1, qd.shape[1])), np.cumsum(np.abs(qd) < speed, axis=0)])
    lo = np.clip(picks - reach, 0, len(qd))
    hi = np.clip(picks + reach + 1, 0, len(qd))
    return slow[hi] - slow[lo] == 0


def _segment_rows(seg: _Segment, robot: RobotModel, base: BaseParameters, cutoff: float,
                  order: int, velocity_measured: bool, reversal_speed: float | None
                  ) -> Iterator[Rows]:
    """Filtered, decimated rows of one uniform segment (parallel filtering, in chunks)."""
    t = (seg.stamps_ns - seg.stamps_ns[0]) * 1e-9
    rate, n, b = seg.rate, robot.dof, base.num_base
    q = zero_phase_lowpass(seg.q, rate, cutoff, order)
    qd = (zero_phase_lowpass(seg.qd, rate, cutoff, order) if velocity_measured
          else central_derivatives(t, q)[0])
    qdd = central_derivatives(t, qd)[0]
    mask = None
    if reversal_speed is not None:
        reach = int(math.ceil(REVERSAL_PERIODS * rate / cutoff))
        mask = _reversal_mask(qd, seg.picks, reversal_speed, reach)
    overlap = int(math.ceil(OVERLAP_PERIODS * rate / cutoff))
    k = int(seg.picks[1] - seg.picks[0]) if len(seg.picks) > 1 else 1
    per_chunk = max(1, CHUNK // k)
    for c in range(0, len(seg.picks), per_chunk):
        core = seg.picks[c:c + per_chunk]
        lo, hi = max(0, int(core[0]) - overlap), min(len(t), int(core[-1]) + 1 + overlap)
        Yb = base.base_regressor(robot.regressor(q[lo:hi], qd[lo:hi], qdd[lo:hi]))
        F = model_features(q[lo:hi], qd[lo:hi])
        X = np.concatenate([Yb.reshape(hi - lo, n * b), seg.tau[lo:hi],
                            F.reshape(hi - lo, -1)], axis=1)
        X = zero_phase_lowpass(X, rate, cutoff, order)[core - lo]
        yield Rows(seg.stamps_ns[core], X[:, :n * b].reshape(-1, n, b),
                   X[:, n * b:n * b + n],
                   mask=None if mask is None else mask[c:c + per_chunk],
                   index=seg.offset + np.minimum(core, len(seg.q) - 1) + 1,
                   features=X[:, n * b + n:].reshape(-1, n, F.shape[2]))


def fourier_fit(x: np.ndarray, period: float, max_harmonics: int, min_harmonics: int = 1,
                harmonics: int | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fourier series of one period fitted to x (N, c), sampled at t_k = k period / N: value,
    first and second time derivative at the samples (each (N, c)) and the harmonics used per
    channel (c,). On this grid the least-squares coefficients are the DFT's, so each channel
    takes the number of harmonics in [min_harmonics, max_harmonics] that minimises the BIC
    N log(RSS_H / N) + (2H + 1) log N, unless ``harmonics`` fixes it: harmonics carrying
    only noise (e.g. encoder quantisation, identical in every period) are left out, since
    differentiating them twice would amplify it."""
    N = x.shape[0]
    top = min(int(max_harmonics) if harmonics is None else int(harmonics), (N - 1) // 2)
    if top < 1:
        raise IdentificationError(f'{N} samples per period cannot carry a harmonic')
    X = np.fft.rfft(x, axis=0)[:top + 1]
    power = 2.0 * np.abs(X[1:]) ** 2 / N                  # RSS reduction per harmonic
    if harmonics is None:
        rss = np.maximum(np.sum((x - x.mean(axis=0)) ** 2, axis=0) - np.concatenate(
            [np.zeros((1, x.shape[1])), np.cumsum(power, axis=0)]), 1e-300)
        H = np.arange(top + 1)[:, None]
        bic = N * np.log(rss / N) + (2 * H + 1) * math.log(N)
        bic[:min(max(int(min_harmonics), 1), top)] = np.inf
        used = np.argmin(bic, axis=0)
    else:
        used = np.full(x.shape[1], top)
    keep = np.arange(1, top + 1)[:, None] <= used[None, :]
    w = 2.0 * math.pi / period * np.arange(1, top + 1)
    coef = np.where(keep, 2.0 * X[1:] / N, 0.0)           # x = mean + Re(sum c_l e^{i w_l t})
    e = np.exp(1j * np.outer(np.arange(N) * period / N, w))
    value = x.mean(axis=0) + np.real(e @ coef)
    first = np.real(e @ (1j * w[:, None] * coef))
    second = np.real(e @ (-(w ** 2)[:, None] * coef))
    return value, first, second, used


def _periodic_rows(stream: Stream, robot: RobotModel, base: BaseParameters, period: float,
                   harmonics: int | None, max_harmonics: int, min_harmonics: int,
                   velocity_measured: bool, reversal_speed: float | None) -> tuple[Rows, dict]:
    """Average a stream over its whole periods; rows of the averaged period, scaled by the
    inverse standard deviation of the averages (from the spread over the periods)."""
    t = (stream.stamps_ns - stream.stamps_ns[0]) * 1e-9
    avg_tau = period_average(t, stream.tau, period)
    avg_q = period_average(t, stream.q, period)
    q, qd, qdd, used = fourier_fit(avg_q.mean, period, max_harmonics, min_harmonics,
                                   harmonics)
    dof = (avg_tau.counts - 1)[:, None]
    noise = (dof * avg_tau.var).sum(axis=0) / dof.sum()       # pooled per-sample variance
    floor = max(1e-12 * float(noise.max()), 1e-300)
    scale = np.sqrt(avg_tau.counts[:, None] / np.maximum(noise, floor))
    Yb = np.concatenate([base.base_regressor(robot.regressor(q[i:i + CHUNK], qd[i:i + CHUNK],
                                                             qdd[i:i + CHUNK]))
                         for i in range(0, len(q), CHUNK)])
    mask = None if reversal_speed is None else np.abs(qd) >= reversal_speed
    info = {'processing': 'periodic', 'period_s': period, 'periods': avg_tau.periods,
            'bins': len(avg_tau.t), 'harmonics': used.tolist(),
            'samples_averaged': int(avg_tau.counts.sum()),
            'torque_noise_std': np.sqrt(noise).tolist(),
            'position_noise_std': np.sqrt((dof * avg_q.var).sum(axis=0) / dof.sum()).tolist(),
            'position_fit_rms': np.sqrt(np.mean((avg_q.mean - q) ** 2, axis=0)).tolist()}
    if velocity_measured:
        avg_qd = period_average(t, stream.qd, period)
        info['velocity_fit_rms'] = np.sqrt(np.mean((avg_qd.mean - qd) ** 2, axis=0)).tolist()
    stamps = stream.stamps_ns[0] + np.round(avg_tau.t * 1e9).astype(np.int64)
    return Rows(stamps, Yb, avg_tau.mean, scale, mask, features=model_features(q, qd)), info


# -- series for plots ---------------------------------------------------------------------------
@dataclass
class TorqueSeries:
    """An evenly strided subsample of processed rows: stamps (N,) int64 ns, measured torque
    (N, n) and base regressor rows (N, n, b), so that predicted = regressor @ theta;
    ``origin_ns``: the bag's first sample (time zero of plots); ``q`` (N, n): the rows'
    positions (rad, m) when kept."""
    stamps_ns: np.ndarray
    measured: np.ndarray
    regressor: np.ndarray
    origin_ns: int | None = None
    q: np.ndarray | None = None

    def predicted(self, theta: np.ndarray) -> np.ndarray:
        return self.regressor @ np.asarray(theta, dtype=float)


class SeriesSampler:
    """Keeps every ``stride``-th row added, doubling the stride (and dropping every other kept
    row) when more than ``capacity`` are kept: bounded memory, evenly spread rows."""

    def __init__(self, capacity: int = SERIES_POINTS):
        self.capacity = max(2, int(capacity))
        self.stride = 1
        self.count = 0
        self._index = np.zeros(0, dtype=np.int64)
        self._arrays: dict[str, np.ndarray] = {}

    def add(self, **arrays: np.ndarray) -> None:
        m = len(next(iter(arrays.values())))
        idx = self.count + np.arange(m)
        keep = idx % self.stride == 0
        self.count += m
        if not keep.any():
            return
        self._index = np.concatenate([self._index, idx[keep]])
        for k, v in arrays.items():
            v = np.asarray(v)[keep]
            self._arrays[k] = v if k not in self._arrays else np.concatenate([self._arrays[k], v])
        while len(self._index) > self.capacity:
            self.stride *= 2
            sel = self._index % self.stride == 0
            self._index = self._index[sel]
            self._arrays = {k: v[sel] for k, v in self._arrays.items()}

    def arrays(self) -> dict[str, np.ndarray]:
        return dict(self._arrays)


# -- the outcome of an identification, whichever the method --------------------------------------
@dataclass
class Identification:
    """An identification's outcome: the base estimate theta with its covariance (SI units of the
    base parameters), the residual sums of the rows fitted (relative error for any theta), the
    per-joint torque noise variance (N m)^2, the estimate's history and a torque series."""
    bag: str
    method: str                      # 'rls' or 'batch'
    processing: str                  # 'smoothed', 'filtered' or 'periodic'
    robot: RobotModel
    base: BaseParameters
    theta: np.ndarray
    covariance: np.ndarray
    num_samples: int                 # samples used (before filtering or averaging)
    messages: int
    rejected: dict
    condition_number: float
    residuals: ResidualStatistics
    noise_variance: np.ndarray       # per joint, of the torque noise the fit averages (N m)^2
    converged: bool
    history: list[Checkpoint] = field(default_factory=list)
    series: TorqueSeries | None = None
    details: dict = field(default_factory=dict)
    pipeline: IdentificationPipeline | None = None
    # the information fitted and its per-joint weights (the WLS objective), for the
    # constrained solve; its outcome (make_consistent)
    fit_equations: NormalEquations | None = None
    fit_weights: np.ndarray | float = 1.0
    consistent: ConsistentEstimate | None = None
    # what the user should know: a missing model term (model_terms.py), locked joints
    warnings: list[str] = field(default_factory=list)
    # per joint, the N m of a unit residual of ``residuals``' rows (weighted rows: their
    # joint_noise_std)
    residual_scale: np.ndarray | float = 1.0
    # the torque's offset against the motion (pipeline/time_offset.py), None: not estimated
    time_offset: TimeOffset | None = None

    @property
    def estimate(self) -> np.ndarray:
        """The estimate published: the consistent one when solved, else theta (unconstrained)."""
        ok = self.consistent is not None and self.consistent.ok
        return self.consistent.theta if ok else self.theta

    @property
    def stddev(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def rel_stddev(self) -> np.ndarray:
        """100 stddev / |theta| (percent; inf where theta is 0)."""
        with np.errstate(divide='ignore', invalid='ignore'):
            return np.where(self.theta == 0, np.inf, 100 * self.stddev / np.abs(self.theta))

    @property
    def unexcited(self) -> list[tuple[str, list[str]]]:
        """The base-parameter directions the data do not determine (identifiability.
        unexcited_directions of the rows fitted; empty when the motion excites them all)."""
        limit = self.pipeline.config.max_condition if self.pipeline is not None else 1e8
        return unexcited_directions(self.residuals.gram.sum(axis=0), self.base.names, limit)

    @property
    def theta_model(self) -> np.ndarray:
        """The base parameters of the robot description's own (URDF/CAD) parameters."""
        return self.base.to_base(self.robot.phi_model)

    def relative_error(self, theta: np.ndarray | None = None) -> np.ndarray:
        """Per-joint 100 ||tau - Yb theta|| / ||tau|| over the rows fitted (percent)."""
        return self.residuals.relative_error(self.theta if theta is None else theta)

    @property
    def residual_rms(self) -> np.ndarray:
        """Per-joint RMS of the fitted rows' torque residual (N m)."""
        return np.sqrt(self.residuals.variance(self.theta)) * self.residual_scale

    def standard_parameters(self) -> np.ndarray:
        """The consistent full parameter vector when solved, else the one closest to the
        model's that reproduces theta."""
        if self.consistent is not None and self.consistent.ok:
            return self.consistent.phi
        return self.base.closest_standard(self.theta, safe_prior(self.robot)[0])

    def consistency_problems(self) -> list[str]:
        return consistency_problems(self.robot, self.standard_parameters())


class _Accumulator:
    """Residual sums of the equations fitted (scaled and masked) and of the same equations
    unscaled (for relative errors), with per-joint equation counts."""

    def __init__(self, b: int, n: int):
        self.fit = ResidualStatistics(b, n, RESIDUAL_BLOCK)
        self.plain = ResidualStatistics(b, n, RESIDUAL_BLOCK)
        self.counts = np.zeros(n)
        self.terms = ModelTermStatistics(n, b + 1)   # over the fit's (scaled) equations

    def add(self, rows: Rows) -> None:
        m = np.ones(rows.tau.shape) if rows.mask is None else rows.mask.astype(float)
        self.counts += m.sum(axis=0)
        Y, tau = rows.regressor * m[..., None], rows.tau * m
        self.plain.add(Y, tau)
        if rows.scale is None:
            self.fit = self.plain
        else:
            Y, tau = Y * rows.scale[..., None], tau * rows.scale
            self.fit.add(Y, tau)
        if rows.features is not None:
            f = rows.features * m[..., None]
            f[..., 0] = m   # the equations counted, not the filtered ones feature
            if rows.scale is not None:   # weighted sums, as the fit's: sum s^2 f r ...
                f *= rows.scale[..., None]
            self.terms.add(f, np.concatenate([Y, tau[..., None]], axis=2))

    def solve(self) -> WeightedFit:
        equations = NormalEquations(self.fit.normal_equations().augmented, self.counts)
        return weighted_solve(equations, known=self.fit is not self.plain)


# -- batch identification -----------------------------------------------------------------------
def _batch_converged(config: PipelineConfig, residuals: ResidualStatistics, cov: np.ndarray,
                     noise: np.ndarray, cond: float, raw_samples: int, rows: int) -> bool:
    """The pipeline's criterion (pipeline.converged). The noise of a row (filtered or
    averaged) is that of raw_samples / rows raw samples: compared per raw sample, as the
    pipeline does."""
    return converged(cov, residuals.gram, residuals.count, noise * raw_samples / max(rows, 1),
                     raw_samples, cond, config)


def _condition(residuals: ResidualStatistics) -> float:
    ev = np.linalg.eigvalsh(residuals.gram.sum(axis=0))
    return float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf


def _reversal_speed(settings: Settings, robot: RobotModel) -> float | None:
    speed = float(settings['coulomb_exclusion_speed'])
    return speed if 'fc' in robot.extras and speed > 0 else None


def _harmonics(options: BatchOptions) -> tuple[float, int | None, int, int]:
    """period, fixed harmonics, most and fewest harmonics of the periodic path."""
    period = float(options.period)
    top = max(1, int(math.floor((options.cutoff or DEFAULT_CUTOFF) * period)),
              options.min_harmonics)
    return period, options.harmonics, top, options.min_harmonics


def _windowed(stream: Stream, t0: float, t1: float) -> Stream:
    """The samples of ``stream`` from t0 (inclusive) to t1 (exclusive), s after its first."""
    t = (stream.stamps_ns - stream.stamps_ns[0]) * 1e-9
    keep = (t >= t0 - 1e-9) & (t < t1 - 1e-9)
    if not keep.any():
        raise IdentificationError(f'no samples between {t0:g} s and {t1:g} s after the first '
                                  f'(the recording lasts {t[-1]:.6g} s)')
    if t[-1] < t1 - 2 * float(np.median(np.diff(t))):
        raise IdentificationError(f'the recording ends {t[-1]:.6g} s after its first sample, '
                                  f'before the end of the periodic part at {t1:g} s')
    return Stream(*(a[keep] for a in (stream.stamps_ns, stream.q, stream.qd, stream.tau)))


def batch_rows(samples: BagSamples, settings: Settings, robot: RobotModel,
               base: BaseParameters, options: BatchOptions) -> tuple[dict, Iterator[Rows]]:
    """The rows a batch identification fits (periodic or filtered, by ``options``), with a
    description of the processing."""
    speed = _reversal_speed(settings, robot)
    if options.period is not None:
        if len(samples.streams) != 1:
            raise IdentificationError(
                f'{samples.bag}: periodic averaging needs one continuous recording; its stamps '
                f'restart {len(samples.streams) - 1} time(s)')
        stream = samples.streams[0]
        if options.window is not None:
            stream = _windowed(stream, *options.window)
        rows, info = _periodic_rows(stream, robot, base, *_harmonics(options),
                                    samples.velocity_measured, speed)
        if options.window is not None:
            info['window_s'] = list(options.window)
        info['rows'] = len(rows)
        return info, iter([rows])
    source = 'given'
    if options.cutoff is None:
        cutoff, source = auto_cutoff(samples, settings, robot, base)
        options = replace(options, cutoff=cutoff)
    segments, info = _plan_filtered(samples, options, settings['smoother.max_gap'])
    info['cutoff_source'] = source

    def rows() -> Iterator[Rows]:
        for seg in segments:
            yield from _segment_rows(seg, robot, base, options.cutoff, options.order,
                                     samples.velocity_measured, speed)
    return info, rows()


def auto_cutoff(samples: BagSamples, settings: Settings, robot: RobotModel,
                base: BaseParameters) -> tuple[float, str]:
    """The filtered path's cut-off (Hz) when none is given, and where it comes from: the
    settings' smoother.cutoff when > 0, else the cut-off of the smoother the pipeline would
    choose on the first stream's first smoother.auto_seconds of motion (rows.choose_smoother;
    'automatic', or 'fallback' on too short a stream)."""
    if settings['smoother.cutoff'] > 0:
        return float(settings['smoother.cutoff']), 'smoother.cutoff'
    s = samples.streams[0]
    t = (s.stamps_ns - s.stamps_ns[0]) * 1e-9
    keep = t <= (AUTO_WAIT + 1) * settings['smoother.auto_seconds']
    noise = settings['joint_noise_std']
    choice = choose_smoother(robot, base, t[keep], s.q[keep], s.qd[keep], s.tau[keep],
                             settings['smoother.order'], settings['smoother.max_gap'], 0.0,
                             settings['smoother.auto_seconds'],
                             np.asarray(noise, dtype=float) ** -2 if noise else None,
                             final=True,
                             exclusion_speed=settings['coulomb_exclusion_speed'])
    return float(choice.cutoff), choice.source


def offline_identify(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                     options: BatchOptions | None = None, joint_states: str = JOINT_STATES,
                     motor_currents: str = MOTOR_CURRENTS, checkpoints: int = 50,
                     series_points: int = SERIES_POINTS,
                     window: TimeWindow | None = None) -> Identification:
    """Batch identification of ``robot`` from a bag (its messages in ``window`` only):
    periodic averaging when ``options.period`` is set, else the zero-phase filtered path
    (see the module doc)."""
    options = options or BatchOptions()
    options.validate()
    base = settings.build(robot).base
    samples = read_samples(bag, settings, robot, joint_states, motor_currents, base,
                           window=window)
    return identify_samples(samples, settings, robot, base, options, checkpoints,
                            series_points)


def identify_samples(samples: BagSamples, settings: Settings, robot: RobotModel,
                     base: BaseParameters, options: BatchOptions, checkpoints: int = 50,
                     series_points: int = SERIES_POINTS) -> Identification:
    """Batch identification from validated samples (read_samples, or made directly)."""
    n, b = robot.dof, base.num_base
    info, rows_iter = batch_rows(samples, settings, robot, base, options)
    acc = _Accumulator(b, n)
    sampler = SeriesSampler(series_points)
    history: list[Checkpoint] = []
    offsets = TimeOffsetCheck(*(settings[f'time_offset.{k}']
                                for k in ('warn', 'refuse', 'seconds', 'search')))
    if options.period is None:
        every = max(1, info['rows'] // max(checkpoints, 1))
        done = 0
        for rows in rows_iter:
            a = 0
            while a < len(rows):   # pieces ending at the checkpoints
                part = rows.slice(a, a + every - done % every)
                a, done = a + len(part), done + len(part)
                acc.add(part)
                sampler.add(stamps_ns=part.stamps_ns, measured=part.tau,
                            regressor=part.regressor)
                offsets.add(part.stamps_ns * 1e-9, part.regressor, part.tau,
                            None if part.features is None else part.features[..., :3])
                if done % every == 0 and done < info['rows'] and done * n >= 4 * b:
                    _checkpoint(history, acc, int(part.index[-1]), part.stamps_ns[-1])
    else:
        rows = next(rows_iter)
        acc.add(rows)
        sampler.add(stamps_ns=rows.stamps_ns, measured=rows.tau, regressor=rows.regressor)
        history = _periodic_history(samples.streams[0], robot, base, options, info,
                                    _reversal_speed(settings, robot), checkpoints)
    fit = acc.solve()
    offsets.finish()   # periodic averaging: one period, no offset estimated
    offset = offsets.result
    info['time_offset'] = None if offset is None else offset.document()
    info['raw_samples'] = samples.num_samples
    info['excluded_equations'] = int(info['rows'] * n - acc.counts.sum())
    info['excluded_per_joint'] = dict(zip(robot.joint_names, (
        info['rows'] - acc.counts).astype(int).tolist()))
    info['fit_ratio'] = fit.s2
    if options.period is None and acc.fit.blocks >= 10 and fit.s2 > 0:
        # Long-run over plain residual variance: about 1 when the rows' residuals are white.
        w = 1.0 / np.maximum(fit.noise_variance, 1e-300)
        info['residual_correlation'] = float((w * acc.fit.long_run_variance(fit.theta)).sum()
                                             / (w * acc.fit.variance(fit.theta)).sum())
    stddev = np.sqrt(np.maximum(np.diag(fit.covariance), 0.0))
    history.append(Checkpoint(int(samples.num_samples), samples.last_ns * 1e-9, fit.theta,
                              stddev))
    noise = (fit.noise_variance if options.period is None
             else np.asarray(info['torque_noise_std']) ** 2 / info['periods'])
    cond = _condition(acc.plain)
    kept = sampler.arrays()
    return Identification(
        samples.bag, 'batch', info['processing'], robot, base, fit.theta, fit.covariance,
        samples.num_samples, samples.messages, samples.rejected, cond, acc.plain, noise,
        _batch_converged(settings.pipeline_config(robot.joint_names), acc.plain,
                         fit.covariance, noise, cond,
                         samples.num_samples, info['rows']),
        history, TorqueSeries(kept['stamps_ns'], kept['measured'], kept['regressor'],
                              samples.first_ns), info,
        fit_equations=acc.fit.normal_equations(), fit_weights=fit.weights,
        warnings=([offset.describe()] if offset is not None and offset.level else [])
        + exclusion_warnings(robot.joint_names, info['rows'] - acc.counts,
                             info['rows'], settings['coulomb_exclusion_speed'])
        + missing_term_warnings(acc.terms, fit.theta, acc.fit.rss(fit.theta),
                                robot.joint_names, robot.extras), time_offset=offset)


def _checkpoint(history: list, acc: _Accumulator, samples: int, stamp_ns: int) -> None:
    try:
        fit = acc.solve()
    except IdentificationError:      # not excited yet
        return
    history.append(Checkpoint(samples, float(stamp_ns) * 1e-9, fit.theta,
                              np.sqrt(np.maximum(np.diag(fit.covariance), 0.0))))


def _periodic_history(stream: Stream, robot: RobotModel, base: BaseParameters,
                      options: BatchOptions, info: dict, speed: float | None,
                      checkpoints: int) -> list[Checkpoint]:
    """The estimates from the first k whole periods, k = 2 .. all but the last."""
    period, periods = info['period_s'], info['periods']
    t = (stream.stamps_ns - stream.stamps_ns[0]) * 1e-9
    history = []
    for k in sorted({int(round(x)) for x in np.linspace(2, periods, max(2, checkpoints))}):
        if k >= periods:
            break
        m = int(np.searchsorted(t, (k - 0.5 / info['bins']) * period))
        part = Stream(stream.stamps_ns[:m], stream.q[:m], stream.qd[:m], stream.tau[:m])
        try:
            rows, _ = _periodic_rows(part, robot, base, *_harmonics(options), False, speed)
            acc = _Accumulator(base.num_base, robot.dof)
            acc.add(rows)
            fit = acc.solve()
        except IdentificationError:
            continue
        history.append(Checkpoint(m, float(part.stamps_ns[-1]) * 1e-9, fit.theta,
                                  np.sqrt(np.maximum(np.diag(fit.covariance), 0.0))))
    return history


# -- the streaming pipeline as an Identification -------------------------------------------------
def replay_identify(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                    joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS,
                    series_points: int = SERIES_POINTS,
                    on_output: Callable[[PipelineOutput], None] | None = None,
                    window: TimeWindow | None = None,
                    pipeline: IdentificationPipeline | None = None) -> Identification:
    """identify_bag (the node's pipeline, streaming; the bag's messages in ``window`` only)
    with a bounded torque series kept; ``on_output`` sees every batch too; ``pipeline``: the
    one to feed (default: new)."""
    sampler = SeriesSampler(series_points)
    sample = _sampling(sampler)

    def outputs(out: PipelineOutput) -> None:
        sample(out)
        if on_output is not None:
            on_output(out)
    result = identify_bag(bag, settings, robot, joint_states, motor_currents,
                          on_output=outputs, window=window, pipeline=pipeline)
    return from_replay(result, _series(sampler, result.pipeline))


def _sampling(sampler: SeriesSampler) -> Callable[[PipelineOutput], None]:
    def add(out: PipelineOutput) -> None:
        if len(out.stamps_ns):
            sampler.add(stamps_ns=out.stamps_ns, q=out.q, qd=out.qd, qdd=out.qdd,
                        measured=out.measured)
    return add


def _series(sampler: SeriesSampler, pipeline: IdentificationPipeline) -> TorqueSeries | None:
    a = sampler.arrays()
    if not a:
        return None
    Yb = pipeline.base.base_regressor(pipeline.robot.regressor(a['q'], a['qd'], a['qdd']))
    return TorqueSeries(a['stamps_ns'], a['measured'], Yb, pipeline.epoch_ns)


def from_replay(result: ReplayResult, series: TorqueSeries | None = None) -> Identification:
    """The Identification of a streamed replay (replay.ReplayResult)."""
    p = result.pipeline
    est = p.estimate()
    offset = p.time_offset.result   # the torque against the motion (time_offset.py)
    return Identification(
        result.bag, 'rls', 'smoothed', p.robot, p.base, est.values, p.covariance,
        est.num_samples, result.messages, {k: v for k, v in p.rejected.items() if v},
        est.condition_number, p.residuals, p.noise_std() ** 2, est.converged,
        list(result.history), series,
        {'processing': 'smoothed',
         'smoother_half_window': None if p.smoother is None else p.smoother.half_window,
         'smoother_order': int(p.config.smoother_order),
         'smoother': None if p.smoother is None else p.smoother.document(),
         'forgetting_factor': float(p.config.forgetting),
         'excluded_equations': p.excluded_rows,
         'excluded_per_joint': dict(zip(p.robot.joint_names,
                                        p.excluded_equations.tolist())),
         'time_offset': None if offset is None else offset.document()}, p,
        *pipeline_equations(p),
        warnings=([offset.describe()] if offset is not None and offset.level else [])
        + exclusion_warnings(p.robot.joint_names, p.excluded_equations, p.used,
                             p.config.coulomb_exclusion_speed)
        + p.model_term_warnings(), residual_scale=p.estimator.joint_scale, time_offset=offset)


def exclusion_warnings(joints: list[str], excluded: np.ndarray, total: int, speed: float,
                       most: float = 0.5) -> list[str]:
    """Warnings for the joints of which more than ``most`` of the ``total`` equations were
    left out near velocity reversals (``excluded`` (n,))."""
    share = np.asarray(excluded, dtype=float) / max(int(total), 1)
    return [f'{j}: {100 * f:.0f} % of its equations left out near velocity reversals '
            f'(coulomb_exclusion_speed {speed:g}): a slow joint; lower coulomb_exclusion_speed '
            'or set it to 0' for j, f in zip(joints, share) if f > most]


def make_consistent(ident: Identification, options: ConsistencyOptions | None,
                    solver: ConsistentSolver | None = None) -> Identification:
    """``ident`` with its constrained solve (consistency.py) on the information it fitted,
    with the same weights; unchanged when ``options`` is None (physical_consistency off).
    ``solver``: ConsistentSolver.for_robot of this robot, base and ``options``, made once for
    many solves (its problem is canonicalised once: a warm solve costs a tenth of a cold).
    """
    if options is not None and ident.fit_equations is not None:
        solver = solver or ConsistentSolver.for_robot(ident.robot, ident.base, options)
        ident.consistent = solver.solve(ident.fit_equations, ident.fit_weights)
    return ident


# -- validation on a held-out bag ---------------------------------------------------------------
def check_same_robot(bag: str | os.PathLike, robot: RobotModel, role: str = 'validation'
                     ) -> None:
    """IdentificationError when the bag's /robot_description is not ``robot`` (its identified
    joints missing, or other kinematics: the regressor differs at random motions); ``role``
    names the bag in the message (validation, training)."""
    with open_bag(bag) as reader:
        xml = read_string_topic(reader, ROBOT_DESCRIPTION)
    if not xml:
        return
    try:
        other = load_robot(xml, robot.joint_names, extras=robot.extras,
                           coulomb_velocity=robot.coulomb_velocity)
    except IdentificationError as exc:
        raise IdentificationError(f'{role} bag {bag} is of another robot than '
                                  f'{robot.name} ({exc})') from None
    q, qd, qdd = sample_motion(robot, 20, seed=7)
    Y, Z = robot.regressor(q, qd, qdd), other.regressor(q, qd, qdd)
    if Y.shape != Z.shape or not np.allclose(Y, Z, rtol=1e-6, atol=1e-9 * np.abs(Y).max()):
        raise IdentificationError(
            f'{role} bag {bag} describes another robot: its {ROBOT_DESCRIPTION} '
            f'({other.name}) gives other dynamics than {robot.name} for the joints '
            f'{robot.joint_names}')


def parameter_sets(ident: Identification) -> dict[str, np.ndarray]:
    """The base parameter vectors whose torque errors are reported: the estimate (the
    consistent one when solved), the unconstrained one and the model's own."""
    return {'estimate': ident.estimate, 'unconstrained': ident.theta,
            'model': ident.theta_model}


def evaluation_settings(settings: Settings, ident: Identification) -> Settings:
    """``settings`` with the smoother ``ident`` was fitted with, for evaluating it on a bag
    (processed as the training bag was, not with a window chosen on itself): its pipeline's
    choice, or the half window of a batch fit's cut-off at the bag's rate; unchanged when the
    settings fix the half window."""
    if settings['smoother.half_window']:
        return settings
    choice = None if ident.pipeline is None else ident.pipeline.smoother
    if choice is not None:
        half = int(choice.half_window)
    elif ident.details.get('cutoff_hz') and ident.details.get('rate_hz'):
        half = half_window_for_cutoff(float(ident.details['cutoff_hz']),
                                      float(ident.details['rate_hz'][0]),
                                      settings['smoother.order'])
    else:
        return settings
    return Settings({**settings.values, 'smoother.half_window': half},
                    settings.given | {'smoother.half_window'})


def validate(ident: Identification, bag: str | os.PathLike, settings: Settings,
             window: TimeWindow | None = None, joint_states: str = JOINT_STATES,
             motor_currents: str = MOTOR_CURRENTS, predictions=None,
             label: str = 'validation', series_points: int = SERIES_POINTS,
             training: bool = False) -> BagError:
    """Torque errors of ``ident``'s parameter sets on ``bag`` (validation.evaluate: raw
    torque, every sample with valid motion), its messages in ``window`` only; ``training``:
    the bag the estimate was fitted to (its robot not checked again)."""
    if window is not None and not isinstance(window, TimeWindow):
        raise TypeError(f'window must be a TimeWindow, not {type(window).__name__}')
    if not training:
        check_same_robot(bag, ident.robot)
    try:
        return evaluate(bag, evaluation_settings(settings, ident), ident.robot, ident.base,
                        parameter_sets(ident), window, joint_states, motor_currents,
                        predictions, label, series_points)
    except IdentificationError as exc:
        raise IdentificationError(f'{"training" if training else "validation"} bag: {exc}'
                                  ) from None
