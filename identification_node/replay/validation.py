"""Torque error of an estimate on a bag, the one place validation error is computed.

The reference is the raw joint torque of every sample with valid motion: the torque the
pipeline's input stages give (measured effort, or converted from the motor currents), not
filtered, at every sample the pipeline's smoother produces q, qd, qdd for (all but its edges,
half a window at each end of a stream or a stamp gap). No equation is left out (none near
velocity reversals). The prediction is Yb(q, qd, qdd) theta with the smoothed motion.

    relative error = 100 ||tau - tau_hat||_2 / ||tau||_2      (percent)

stacked over all joints and samples, and per joint. The same figures against the smoothed
torque are reported beside, labelled so (``smoothed``): smoothing the reference removes
noise and so flatters the fit. There the sign-model Coulomb columns hold the smoothed sign,
as the estimator's rows do (the smoothed torque's sign friction is smoothed across
reversals). Units SI; stamps int64 ns.
"""
from __future__ import annotations

import math
import os

import numpy as np

from identification_node.bags.feed import (JOINT_STATES, MOTOR_CURRENTS, ROBOT_DESCRIPTION,
                                           check_usable, feed_bag, input_topics)
from identification_node.bags.reader import open_bag, read_string_topic
from identification_node.bags.windows import TimeWindow
from identification_node.errors import IdentificationError
from identification_node.model.identifiability import BaseParameters, sample_motion
from identification_node.model.robot import RobotModel, load_robot
from identification_node.pipeline import IdentificationPipeline
from identification_node.pipeline.rows import coulomb_columns, smooths_sign
from identification_node.pipeline.signals import (half_window_for_cutoff, smoothed_sign,
                                                  smoothing_noise_gain)
from identification_node.results.identification import Identification, SERIES_POINTS
from identification_node.results.torque_error import BagError, ErrorSums
from identification_node.settings import Settings

__all__ = ['BATCH', 'evaluate', 'check_same_robot', 'parameter_sets', 'evaluation_settings',
           'bag_error']

BATCH = 1000   # messages per processing batch


def evaluate(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
             base: BaseParameters, thetas: dict[str, np.ndarray],
             window: TimeWindow | None = None, joint_states: str = JOINT_STATES,
             motor_currents: str = MOTOR_CURRENTS, predictions=None, label: str = 'bag',
             series_points: int | None = None, predict: str = 'estimate') -> BagError:
    """The torque errors of each base parameter vector of ``thetas`` (name -> (b,)) on the
    bag's samples in ``window``. ``predictions`` (predictions.PredictionsWriter) receives the
    raw torque and the prediction of ``thetas[predict]`` per sample, under ``label``."""
    from identification_node.results.identification import (SERIES_POINTS, SeriesSampler,
                                                            TorqueSeries)
    names = list(thetas)
    Theta = np.array([thetas[k] for k in names], dtype=float).T         # (b, k)
    # the pipeline's input stages and smoother, with the estimate's base columns (no estimation)
    pipeline = IdentificationPipeline(robot, settings.pipeline_config(robot.joint_names), base)
    stages, rows = pipeline.samples, pipeline.row_builder
    rows.smooth_sign = False     # the raw torque's own sign friction: sign(qd)
    # against the smoothed torque, the Coulomb columns as the smoother makes them (the
    # estimator's rows): base columns of each joint's fc
    coulomb = fc = None
    if smooths_sign(robot):
        where = {k: i for i, k in enumerate(base.base_index)}
        cols = [where.get(c, -1) for c in coulomb_columns(robot)]
        if min(cols) >= 0:
            coulomb = np.array(cols)
            fc = Theta[coulomb].T[:, None, :]     # (k, 1, n): each set's fc per joint
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
        if coulomb is not None:   # pred with each fc column's sign(qd) made smoothed_sign
            assert rows.half_window is not None   # rows came out: the window is chosen
            shift = smoothed_sign(r.qd[ok], r.qdd[ok], rows.half_window, rows.order,
                                  rows.period(r.t)) - Yb[:, np.arange(n), coulomb]
            smooth.add(smoothed, pred + shift[None] * fc)
        else:
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


def bag_error(ident: Identification, bag: str | os.PathLike, settings: Settings,
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
