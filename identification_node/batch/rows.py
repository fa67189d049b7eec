"""None"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Iterator

import numpy as np

from identification_node.batch.samples import BagSamples, Stream
from identification_node.config import BatchConfig
from identification_node.errors import IdentificationError
from identification_node.estimation.model_terms import features as model_features
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.pipeline.rows import AUTO_WAIT, choose_smoother
from identification_node.pipeline.signals import (central_derivatives, period_average,
                                                  zero_phase_lowpass)
from identification_node.settings import Settings

__all__ = ['DEFAULT_CUTOFF', 'FILTER_ORDER', 'EDGE_PERIODS', 'REVERSAL_PERIODS',
           'OVERLAP_PERIODS', 'CHUNK', 'JITTER', 'BatchRows', 'BatchOptions', 'fourier_fit',
           'periodic_rows', 'reversal_exclusion_speed', 'harmonic_range', 'batch_rows',
           'auto_cutoff']


DEFAULT_CUTOFF = BatchConfig.cutoff   # Hz: zero-phase low-pass of the filtered path; Fourier band
FILTER_ORDER = BatchConfig.order      # Butterworth order (run twice: squared gain, no phase)
EDGE_PERIODS = 3.0        # 1/cutoff periods trimmed at each segment end (filter start-up)
REVERSAL_PERIODS = 1.0    # 1/cutoff periods around a velocity reversal left out (with fc)
OVERLAP_PERIODS = 10.0    # 1/cutoff periods of overlap between chunks: joins exact to ~1e-10
CHUNK = 4096              # raw samples per regressor chunk
JITTER = 0.01             # relative stamp jitter above which a segment is resampled uniformly


# -- rows for the estimators --------------------------------------------------------------------
@dataclass
class BatchRows:
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

    def slice(self, a: int, b: int) -> BatchRows:
        def cut(x: np.ndarray | None) -> np.ndarray | None:
            return None if x is None else x[a:b]
        return BatchRows(self.stamps_ns[a:b], self.regressor[a:b], self.tau[a:b],
                         cut(self.scale), cut(self.mask), cut(self.index), cut(self.features))


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
    assert cutoff is not None   # batch_rows chose one
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


def _reversal_mask(qd: np.ndarray, picks: np.ndarray, speed: np.ndarray, reach: int
                   ) -> np.ndarray:
    """(len(picks), n): False where the joint's speed falls below its ``speed`` (n,) within
    ``reach`` samples of the row, so inside the filter's reach of a velocity reversal."""
    slow = np.concatenate([np.zeros((1, qd.shape[1])), np.cumsum(np.abs(qd) < speed, axis=0)])
    lo = np.clip(picks - reach, 0, len(qd))
    hi = np.clip(picks + reach + 1, 0, len(qd))
    return slow[hi] - slow[lo] == 0


def _segment_rows(seg: _Segment, robot: RobotModel, base: BaseParameters, cutoff: float,
                  order: int, velocity_measured: bool, reversal_speed: np.ndarray | None
                  ) -> Iterator[BatchRows]:
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
        yield BatchRows(seg.stamps_ns[core], X[:, :n * b].reshape(-1, n, b),
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


def periodic_rows(stream: Stream, robot: RobotModel, base: BaseParameters, period: float,
                  harmonics: int | None, max_harmonics: int, min_harmonics: int,
                  velocity_measured: bool, reversal_speed: np.ndarray | None
                  ) -> tuple[BatchRows, dict]:
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
    return BatchRows(stamps, Yb, avg_tau.mean, scale, mask, features=model_features(q, qd)), info


def reversal_exclusion_speed(settings: Settings, robot: RobotModel) -> np.ndarray | None:
    """(n,) coulomb_exclusion_speed per joint (RobotModel.in_joint_units), None when no
    equation is left out."""
    speed = float(settings['coulomb_exclusion_speed'])
    return robot.in_joint_units(speed) if 'fc' in robot.extras and speed > 0 else None


def harmonic_range(options: BatchOptions) -> tuple[float, int | None, int, int]:
    """period, fixed harmonics, most and fewest harmonics of the periodic path."""
    assert options.period is not None   # the periodic path
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
               base: BaseParameters, options: BatchOptions) -> tuple[dict, Iterator[BatchRows]]:
    """The rows a batch identification fits (periodic or filtered, by ``options``), with a
    description of the processing."""
    speed = reversal_exclusion_speed(settings, robot)
    if options.period is not None:
        if len(samples.streams) != 1:
            raise IdentificationError(
                f'{samples.bag}: periodic averaging needs one continuous recording; its stamps '
                f'restart {len(samples.streams) - 1} time(s)')
        stream = samples.streams[0]
        if options.window is not None:
            stream = _windowed(stream, *options.window)
        rows, info = periodic_rows(stream, robot, base, *harmonic_range(options),
                                   samples.velocity_measured, speed)
        if options.window is not None:
            info['window_s'] = list(options.window)
        info['rows'] = len(rows)
        return info, iter([rows])
    source = 'given'
    cutoff = options.cutoff
    if cutoff is None:
        cutoff, source = auto_cutoff(samples, settings, robot, base)
        options = replace(options, cutoff=cutoff)
    segments, info = _plan_filtered(samples, options, settings['smoother.max_gap'])
    info['cutoff_source'] = source

    def segment_rows() -> Iterator[BatchRows]:
        for seg in segments:
            yield from _segment_rows(seg, robot, base, cutoff, options.order,
                                     samples.velocity_measured, speed)
    return info, segment_rows()


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
    assert choice is not None   # final: no more samples to wait for
    return float(choice.cutoff), choice.source
