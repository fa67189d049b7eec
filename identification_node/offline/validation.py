"""Torque error of an estimate on a bag, the one place validation error is computed.

The reference is the raw joint torque of every sample with valid motion: the torque the
pipeline's input stages give (measured effort, or converted from the motor currents), not
filtered, at every sample the pipeline's smoother produces q, qd, qdd for (all but its edges,
half a window at each end of a stream or a stamp gap). No equation is left out (none near
velocity reversals). The prediction is Yb(q, qd, qdd) theta with the smoothed motion.

    relative error = 100 ||tau - tau_hat||_2 / ||tau||_2      (percent)

stacked over all joints and samples, and per joint. The same figures against the smoothed
torque are reported beside, labelled so (``smoothed``): smoothing the reference removes
noise and so flatters the fit. Units SI; stamps int64 ns.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from identification_node.bags.reader import open_bag
from identification_node.errors import IdentificationError
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.offline.replay import (JOINT_STATES, MOTOR_CURRENTS, check_usable,
                                                feed_bag, input_topics)
from identification_node.offline.windows import TimeWindow
from identification_node.pipeline import IdentificationPipeline
from identification_node.pipeline.signals import smoothing_noise_gain
from identification_node.settings import Settings

BATCH = 1000   # messages per processing batch


@dataclass
class TorqueError:
    """Relative error (percent): ``stacked`` over all joints, ``per_joint`` (n,)."""
    stacked: float
    per_joint: np.ndarray


def relative_error(measured: np.ndarray, predicted: np.ndarray) -> TorqueError:
    """100 ||measured - predicted|| / ||measured|| of (N, n) torques, stacked and per joint."""
    sums = ErrorSums(np.shape(measured)[1], 1)
    sums.add(measured, np.asarray(predicted)[None])
    return sums.error(0)


class ErrorSums:
    """Sums of squares for the relative errors of k predictions of n joint torques."""

    def __init__(self, n: int, k: int):
        self.reference = np.zeros(n)        # sum tau^2 per joint
        self.residual = np.zeros((k, n))    # sum (tau - tau_hat)^2 per prediction and joint
        self.count = 0

    def add(self, measured: np.ndarray, predicted: np.ndarray) -> None:
        """measured (N, n), predicted (k, N, n)."""
        measured = np.asarray(measured, dtype=float)
        self.reference += np.einsum('ij,ij->j', measured, measured)
        r = measured[None] - np.asarray(predicted, dtype=float)
        self.residual += np.einsum('kij,kij->kj', r, r)
        self.count += len(measured)

    def error(self, k: int) -> TorqueError:
        """The relative errors of prediction k (inf where the reference is 0, 0 if both)."""
        with np.errstate(divide='ignore', invalid='ignore'):
            joint = np.where(self.residual[k] == 0, 0.0,
                             100.0 * np.sqrt(self.residual[k] / self.reference))
            stacked = (0.0 if self.residual[k].sum() == 0 else
                       100.0 * np.sqrt(self.residual[k].sum() / self.reference.sum()))
        return TorqueError(float(stacked), joint)


@dataclass
class BagError:
    """Torque errors of several parameter vectors on one bag (``errors`` name -> TorqueError,
    against the raw torque; ``smoothed``: the same against the smoothed torque), over
    ``num_samples`` samples; ``series``: a subsample (stamps ns, raw torque, base regressor
    rows, positions) for plots and checks."""
    bag: str
    joints: list[str]
    num_samples: int
    errors: dict[str, TorqueError]
    smoothed: dict[str, TorqueError]
    window: TimeWindow | None = None
    series: object | None = None       # identification.TorqueSeries
    rejected: dict = field(default_factory=dict)
    # per joint std of the torque sensor's noise (N m): of raw minus smoothed torque, whose
    # white-noise variance is (1 - gain) of the raw one (the smoother's centre weight is its
    # gain, signals.smoothing_noise_gain); nan where unknown
    noise_std: np.ndarray | None = None

    @property
    def relative_error(self) -> np.ndarray:
        """Per-joint error of the estimate (percent)."""
        return self.errors['estimate'].per_joint

    def document(self) -> dict:
        """JSON-ready: per parameter set the stacked and per-joint errors (percent)."""
        def one(e: TorqueError) -> dict:
            return {'stacked': e.stacked, 'per_joint': dict(zip(self.joints,
                                                                e.per_joint.tolist()))}
        return {'bag': self.bag, 'num_samples': self.num_samples,
                'window_s': None if self.window is None or self.window.whole
                else self.window.describe(),
                'reference': 'raw torque (measured, or converted from currents), every '
                             'sample the smoother gives motion for',
                **{k: one(e) for k, e in self.errors.items()},
                'smoothed_torque': {k: one(e) for k, e in self.smoothed.items()}}


def evaluate(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
             base: BaseParameters, thetas: dict[str, np.ndarray],
             window: TimeWindow | None = None, joint_states: str = JOINT_STATES,
             motor_currents: str = MOTOR_CURRENTS, predictions=None, label: str = 'bag',
             series_points: int | None = None, predict: str = 'estimate') -> BagError:
    """The torque errors of each base parameter vector of ``thetas`` (name -> (b,)) on the
    bag's samples in ``window``. ``predictions`` (predictions.PredictionsWriter) receives the
    raw torque and the prediction of ``thetas[predict]`` per sample, under ``label``."""
    from identification_node.offline.identification import (SERIES_POINTS, SeriesSampler,
                                                            TorqueSeries)
    names = list(thetas)
    Theta = np.array([thetas[k] for k in names], dtype=float).T         # (b, k)
    # the pipeline's input stages and smoother, with the estimate's base columns (no estimation)
    pipeline = IdentificationPipeline(robot, settings.pipeline_config(robot.joint_names), base)
    stages, rows = pipeline.samples, pipeline.row_builder
    rows.smooth_sign = False     # the raw torque's own sign friction: sign(qd)
    counters, n, b = stages.counters, robot.dof, base.num_base
    raw, smooth = ErrorSums(n, len(names)), ErrorSums(n, len(names))
    high = np.zeros(n)   # sum of (raw - smoothed torque)^2 per joint
    sampler = SeriesSampler(series_points or SERIES_POINTS)
    tail = [np.zeros(0), np.zeros((0, n))]
    restarts = [0]

    def step(flush: bool) -> None:
        s = stages.process(flush)
        if counters.restarts != restarts[0]:
            restarts[0] = counters.restarts
            rows.reset()
            tail[:] = [np.zeros(0), np.zeros((0, n))]
        if len(s) == 0 and not rows.searching and not (flush and rows.holding):
            return
        r = rows(s, stages.velocity_measured, flush=flush)
        T, X = np.concatenate([tail[0], s.stamps]), np.concatenate([tail[1], s.tau])
        # the smoother's centres are among the last 2L + 1 samples (all, while it is chosen)
        keep = None if rows.half_window is None else 2 * rows.half_window + 1
        tail[:] = [T, X] if keep is None else [T[-keep:], X[-keep:]]
        if len(r.t) == 0:
            return
        idx = np.searchsorted(T, r.t)
        if not np.array_equal(T[np.minimum(idx, len(T) - 1)], r.t):
            raise IdentificationError('internal: smoother centre off the input stamps')
        tau = X[idx]
        Yb = r.rows[:, :, :b]
        pred = np.moveaxis(Yb @ Theta, 2, 0)                           # (k, N, n)
        ok = np.isfinite(pred).all(axis=(0, 2))
        if not ok.all():
            counters.reject('implausible', int(np.count_nonzero(~ok)))
            tau, Yb, pred, t, smoothed, q = (tau[ok], Yb[ok], pred[:, ok], r.t[ok],
                                             r.tau[ok], r.q[ok])
        else:
            t, smoothed, q = r.t, r.tau, r.q
        raw.add(tau, pred)
        smooth.add(smoothed, pred)
        high[:] += np.einsum('ij,ij->j', tau - smoothed, tau - smoothed)
        stamps_ns = counters.stamps_ns(t)
        sampler.add(stamps_ns=stamps_ns, measured=tau, regressor=Yb, q=q)
        if predictions is not None:
            predictions.add(label, stamps_ns, tau, pred[names.index(predict)])

    topics = input_topics(stages, joint_states, motor_currents)
    with open_bag(bag) as reader:
        counts, origin = reader.topic_counts, reader.start_ns
        if predictions is not None:
            predictions.begin(label, origin)
        feed_bag(reader, stages, topics, BATCH, step, window)
    check_usable(raw.count, counters.rejected, bag, topics, counts)
    kept = sampler.arrays()
    gain = (smoothing_noise_gain(rows.half_window, rows.order) if rows.half_window
            else math.nan)
    noise_std = np.sqrt(high / max(raw.count, 1) / (1.0 - gain))
    return BagError(str(bag), list(robot.joint_names), raw.count,
                    {k: raw.error(i) for i, k in enumerate(names)},
                    {k: smooth.error(i) for i, k in enumerate(names)}, window,
                    TorqueSeries(kept['stamps_ns'], kept['measured'], kept['regressor'],
                                 origin, kept['q']),
                    {k: v for k, v in counters.rejected.items() if v}, noise_std)
