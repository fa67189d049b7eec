"""Weighted least squares on a bag's batch rows (rows.py): the estimate, its covariance, history
and warnings as an Identification. Units SI; stamps int64 ns."""
from __future__ import annotations

import math
import os

import numpy as np

from identification_node.bags.feed import JOINT_STATES, MOTOR_CURRENTS
from identification_node.bags.windows import TimeWindow
from identification_node.batch.rows import (BatchOptions, BatchRows, batch_rows, harmonic_range,
                                            periodic_rows, reversal_exclusion_speed)
from identification_node.batch.samples import BagSamples, Stream, read_samples
from identification_node.errors import IdentificationError
from identification_node.estimation.batch import WeightedFit, weighted_solve
from identification_node.estimation.model_terms import (ModelTermStatistics,
                                                        missing_term_warnings)
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.pipeline import PipelineConfig, converged
from identification_node.pipeline.time_offset import TimeOffsetCheck
from identification_node.results.identification import (Checkpoint, Identification, SERIES_POINTS,
                                                        SeriesSampler, TorqueSeries,
                                                        exclusion_warnings)
from identification_node.settings import Settings

__all__ = ['RESIDUAL_BLOCK', 'offline_identify', 'identify_samples']


RESIDUAL_BLOCK = 8        # rows per block of the residual statistics


class _Accumulator:
    """Residual sums of the equations fitted (scaled and masked) and of the same equations
    unscaled (for relative errors), with per-joint equation counts."""

    def __init__(self, b: int, n: int):
        self.fit = ResidualStatistics(b, n, RESIDUAL_BLOCK)
        self.plain = ResidualStatistics(b, n, RESIDUAL_BLOCK)
        self.counts = np.zeros(n)
        self.terms = ModelTermStatistics(n, b + 1)   # over the fit's (scaled) equations

    def add(self, rows: BatchRows) -> None:
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
                    assert part.index is not None   # filtered rows carry it
                    _checkpoint(history, acc, int(part.index[-1]), part.stamps_ns[-1])
    else:
        rows = next(rows_iter)
        acc.add(rows)
        sampler.add(stamps_ns=rows.stamps_ns, measured=rows.tau, regressor=rows.regressor)
        history = _periodic_history(samples.streams[0], robot, base, options, info,
                                    reversal_exclusion_speed(settings, robot), checkpoints)
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
        + exclusion_warnings(robot, info['rows'] - acc.counts, info['rows'],
                             settings['coulomb_exclusion_speed'])
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
                      options: BatchOptions, info: dict, speed: np.ndarray | None,
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
            rows, _ = periodic_rows(part, robot, base, *harmonic_range(options), False, speed)
            acc = _Accumulator(base.num_base, robot.dof)
            acc.add(rows)
            fit = acc.solve()
        except IdentificationError:
            continue
        history.append(Checkpoint(m, float(part.stamps_ns[-1]) * 1e-9, fit.theta,
                                  np.sqrt(np.maximum(np.diag(fit.covariance), 0.0))))
    return history
