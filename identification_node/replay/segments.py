"""Sufficient statistics of a bag or of a segment of it (BagStatistics), streamed through the
node's pipeline, and the Identification of merged statistics (fleet.py's module doc has
the method). Units SI; stamps int64 ns."""
from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np

from identification_node.bags.feed import JOINT_STATES, MOTOR_CURRENTS
from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import ConsistentSolver
from identification_node.estimation.model_terms import ModelTermStatistics
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.model.robot import RobotModel
from identification_node.pipeline.estimate import RESIDUAL_GRID
from identification_node.pipeline.time_offset import TimeOffset
from identification_node.pipeline.window import SegmentWindow
from identification_node.replay.stream import identify_bag
from identification_node.results.identification import Checkpoint, ReplayResult
from identification_node.settings import Settings

__all__ = ['SMOOTHER', 'model_key', 'BagStatistics', 'segment_margin_ns', 'pinned',
           'bag_smoother', 'chosen_smoother', 'bag_statistics', 'Solve', 'solve_unconstrained',
           'identification', 'consistent_solver', 'BagSegment', 'bag_span', 'grid_segments',
           'balanced_segments']

SMOOTHER = ('smoother.half_window', 'smoother.cutoff')   # BagStatistics.smoother


def model_key(robot: RobotModel) -> str:
    """Hash of what the statistics depend on: description, identified joints and extras."""
    text = '\n'.join([robot.description or robot.name, ','.join(robot.joint_names),
                      ','.join(robot.extras), repr(robot.coulomb_velocity)])
    return hashlib.sha256(text.encode()).hexdigest()


# -- map: one bag or segment to its statistics ----------------------------------------------------
@dataclass
class BagStatistics:
    """Sufficient statistics of the rows of some bags (or segments): per-joint normal
    equations of the weighted rows [Yb | tau] (as RecursiveLeastSquares.normal_equations),
    residual sums over samples and blocks, samples in the estimator, the pipeline's counters
    and equations left out per joint (n,), the first and last row stamps (ns), the model they
    belong to (model_key), the missing-term sums (model_terms.py) and the time-offset check's
    result of the first stream start among them (time_offset.py: a segment that starts
    inside its bag does not check)."""
    bags: tuple
    model: str
    normal_equations: NormalEquations
    residuals: ResidualStatistics
    num_samples: int
    used: int
    messages: int
    received: int
    rejected: dict
    excluded: np.ndarray
    restarts: int
    first_ns: int | None
    last_ns: int | None
    smoother: tuple = ()     # (parameter, value) pairs of the smoother the rows went through
    terms: ModelTermStatistics | None = None
    time_offset: TimeOffset | None = None

    def __add__(self, other: BagStatistics) -> BagStatistics:
        if self.model != other.model:
            raise IdentificationError(
                f'bags {self.bags[0]} and {other.bags[0]} are of different robot models '
                '(description, joints or extras): their statistics do not merge')
        if self.smoother != other.smoother:
            raise IdentificationError(
                f'bags {self.bags[0]} and {other.bags[0]} went through different smoothers '
                f'({dict(self.smoother)}, {dict(other.smoother)}): their statistics do not '
                'merge exactly')
        stamps = [s for s in (self.first_ns, other.first_ns) if s is not None]
        lasts = [s for s in (self.last_ns, other.last_ns) if s is not None]
        return BagStatistics(
            tuple(dict.fromkeys(self.bags + other.bags)), self.model,
            self.normal_equations + other.normal_equations, self.residuals + other.residuals,
            self.num_samples + other.num_samples, self.used + other.used,
            self.messages + other.messages, self.received + other.received,
            {k: self.rejected.get(k, 0) + other.rejected.get(k, 0)
             for k in {**self.rejected, **other.rejected}},
            self.excluded + other.excluded, self.restarts + other.restarts,
            min(stamps) if stamps else None, max(lasts) if lasts else None, self.smoother,
            _sum(self.terms, other.terms),
            other.time_offset if self.time_offset is None else self.time_offset)


def _sum(a, b):
    """a + b, or the one that is not None."""
    return b if a is None else a if b is None else a + b


def segment_margin_ns(settings: Settings) -> int:
    """Samples on either side a segment needs: the smoother's half window can span
    half_window * max_gap, currents wait hold_time, alignment reaches align_tolerance."""
    v = settings.values
    return int(math.ceil((v['smoother.half_window'] * v['smoother.max_gap'] + v['hold_time']
                          + v['align_tolerance']) * 1e9)) + 1


def pinned(settings: Settings, values: tuple) -> Settings:
    """``settings`` with parameters ((name, value) pairs) set: the smoother's (bag_smoother),
    or others."""
    if not values:
        return settings
    return Settings({**settings.values, **dict(values)},
                    settings.given | {k for k, _ in values})


def bag_smoother(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                 joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS
                 ) -> tuple:
    """The smoother parameters the pipeline of ``settings`` uses on ``bag`` (as identify):
    () when they fix the half window, else the half window and cut-off it chooses (the bag
    read until chosen)."""
    choice = chosen_smoother(bag, settings, robot, joint_states, motor_currents)
    return () if choice is None else (('smoother.half_window', int(choice.half_window)),
                                      ('smoother.cutoff', float(choice.cutoff)))


def chosen_smoother(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                    joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS):
    """The smoother (rows.SmootherChoice) the pipeline of ``settings`` chooses on ``bag``, the
    bag read until chosen; None when the settings fix the half window. No rows are made of
    what is read (rows.RowBuilder.choose_only): the run given the choice estimates and checks
    the torque's time offset."""
    if settings['smoother.half_window']:
        return None
    pipeline = settings.build(robot)
    pipeline.row_builder.choose_only = True
    identify_bag(bag, settings, robot, joint_states, motor_currents, checkpoints=1,
                 pipeline=pipeline, until=lambda p: p.smoother is not None)
    return pipeline.smoother


def bag_statistics(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                   start_ns: int | None = None, stop_ns: int | None = None,
                   joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS
                   ) -> BagStatistics:
    """The sufficient statistics of a bag's rows through the node's pipeline, or of the rows
    with header stamps in [start_ns, stop_ns) (a segment; None: open). Needs forgetting 1
    (forgotten statistics do not merge). Settings that leave the smoother to be chosen get
    the one the whole bag chooses (bag_smoother); statistics of bags merge only with one
    smoother: pin theirs (``pinned``) to the first bag's, as run_fleet does."""
    if settings['forgetting_factor'] != 1.0:
        raise IdentificationError(
            f"fleet identification needs forgetting_factor 1 (got "
            f"{settings['forgetting_factor']}): forgotten statistics do not add up")
    smoother = bag_smoother(bag, settings, robot, joint_states, motor_currents)
    settings = pinned(settings, smoother)
    if start_ns is not None:   # not the stream's start: its torque offset is not checked
        settings = pinned(settings, (('time_offset.warn', 0.0),))
    pipeline = settings.build(robot)
    window = None
    if start_ns is not None or stop_ns is not None:
        window = pipeline.window = SegmentWindow(start_ns, stop_ns, segment_margin_ns(settings))
    span: list[int] = []     # first and last row stamps, or none

    def stamps(out) -> None:
        if len(out.stamps_ns):
            span[:] = [span[0] if span else int(out.stamps_ns[0]), int(out.stamps_ns[-1])]

    try:
        result = identify_bag(bag, settings, robot, joint_states, motor_currents,
                              checkpoints=1, on_output=stamps, pipeline=pipeline)
        messages = result.messages
    except IdentificationError:
        if window is None or pipeline.used:   # a segment may hold no rows (a gap)
            raise
        messages = 0
    rls = pipeline.rls
    if window is not None:   # the margins' messages are counted by their own segments
        messages = window.messages
    # an estimator without rows knows no joints yet: the zero sums of this robot's instead
    equations = (rls.normal_equations() if rls.num_samples else
                 NormalEquations.zeros(pipeline.base.num_base, robot.dof))
    return BagStatistics(
        (str(bag),), model_key(robot), equations, pipeline.residuals,
        int(rls.num_samples), int(pipeline.used), int(messages), int(pipeline.received),
        {k: v for k, v in pipeline.rejected.items() if v}, pipeline.excluded_equations,
        int(pipeline.restarts), span[0] if span else None, span[-1] if span else None,
        smoother=smoother or tuple((k, settings[k]) for k in SMOOTHER),
        terms=pipeline.estimator.terms, time_offset=pipeline.time_offset.result)


# -- solve ----------------------------------------------------------------------------------------
Solve = Callable[[NormalEquations], np.ndarray]


def solve_unconstrained(equations: NormalEquations) -> np.ndarray:
    """The base parameters minimising sum_j ||tau_j - Y_j theta||^2 over merged normal
    equations, as the streaming estimator solves them. THE SEAM: a physically consistent
    solve with the same signature (normal equations in, base parameters out) replaces it
    (``solve=`` of identification and run_fleet); the covariance stays the information's.
    The physically consistent estimate is solved after it (identification), as identify's."""
    return RecursiveLeastSquares.from_normal_equations(equations, 0).theta


def identification(stats: BagStatistics, settings: Settings, robot: RobotModel,
                   label: str | None = None, solve: Solve = solve_unconstrained,
                   physical_consistency: bool = True, solver: ConsistentSolver | None = None):
    """The Identification of merged statistics, as ``identify`` gives for their bags
    streamed one after another (one stream each): the physically consistent estimate
    too unless ``physical_consistency`` is False or ``settings`` turn it off (``solver``:
    consistent_solver's for this robot, re-used across its groups)."""
    from identification_node.results.identification import from_replay, make_consistent

    if stats.model != model_key(robot):
        raise IdentificationError(f'statistics of {stats.bags[0]} are not of {robot.name}')
    settings = pinned(settings, stats.smoother)
    pipeline = settings.build(robot)
    ne = stats.normal_equations
    rls = RecursiveLeastSquares.from_normal_equations(ne, stats.num_samples, theta=solve(ne))
    pipeline.restore(rls, stats.residuals, stats.used, stats.received, stats.rejected,
                     stats.excluded, stats.restarts, stats.last_ns, stats.terms,
                     stats.time_offset)
    est = pipeline.estimate()
    history = [Checkpoint(est.num_samples, est.stamp, est.values, est.stddev)]
    ident = from_replay(ReplayResult(label or ', '.join(stats.bags), pipeline, stats.messages,
                                     history))
    return make_consistent(ident, settings.consistency_options() if physical_consistency
                           else None, solver)


def consistent_solver(settings: Settings, robot: RobotModel) -> ConsistentSolver | None:
    """The physically consistent solver of a robot's groups (None: switched off in
    ``settings``): made once, so its problem is canonicalised once, not per group."""
    options = settings.consistency_options()
    return (None if options is None else
            ConsistentSolver.for_robot(robot, settings.build(robot).base, options))


@dataclass(frozen=True)
class BagSegment:
    """A time segment [start_ns, stop_ns) of a bag's header stamps (None: open-ended)."""
    start_ns: int | None
    stop_ns: int | None


def bag_span(reader, joint_states: str = JOINT_STATES) -> tuple[int, int]:
    """The span (int ns) of an open bag's (bags.reader.BagReader) stamps to cut segments in:
    the first and last header stamps of its joint states (bags.reader.stamp_span), where its
    rows lie also when its stamps are not its log times (a simulator's clock); its log times
    when those cannot be read (the segments' reads then name the fault)."""
    from identification_node.bags.reader import stamp_span
    try:
        span = stamp_span(reader, joint_states)
    except IdentificationError:
        span = None
    return span or (reader.start_ns, reader.end_ns)


def grid_segments(start_ns: int, end_ns: int, segment_seconds: float) -> list[BagSegment]:
    """The segments of a bag stamped from ``start_ns`` to ``end_ns`` (bag_span):
    ``segment_seconds`` rounded to a multiple of the residual grid (estimate.RESIDUAL_GRID,
    10 s) and cut at multiples of it, where the residual blocks restart, so the segments'
    statistics merge to the whole bag's exactly; the first and last open-ended, so every row
    belongs to one."""
    step = max(1, round(segment_seconds * 1e9 / RESIDUAL_GRID)) * RESIDUAL_GRID
    return _cut(list(range((start_ns // step + 1) * step, end_ns, step)))


def balanced_segments(start_ns: int, end_ns: int, parts: int) -> list[BagSegment]:
    """At most ``parts`` segments of a bag stamped from ``start_ns`` to ``end_ns``, about equally
    long: each cut at the multiple of the residual grid nearest to an equal split (so they merge
    exactly, as grid_segments'); the first and last open-ended."""
    ideal = start_ns + (end_ns - start_ns) * np.arange(1, max(parts, 1)) / max(parts, 1)
    cuts = np.unique(np.rint(ideal / RESIDUAL_GRID).astype(np.int64) * RESIDUAL_GRID)
    return _cut([int(c) for c in cuts if start_ns < c < end_ns])


def _cut(cuts: list[int]) -> list[BagSegment]:
    bounds: list[int | None] = [None, *cuts, None]
    return [BagSegment(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
