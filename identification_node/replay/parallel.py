"""One bag on every core: its segments streamed through the node's pipeline in parallel
processes and their statistics merged, as fleet.py merges bags.

The bag is cut into about equal segments, one per worker, at multiples of
estimate.RESIDUAL_GRID, where the residual blocks restart (segments.balanced_segments), as
fleet cuts a long bag; each segment's pipeline is fed a margin of the bag on either side and
keeps only the rows centred inside it (segments.bag_statistics), so its rows are the serial
run's. The smoother is chosen once, as the serial run chooses it (segments.chosen_smoother),
and pinned in every segment. The normal equations and residual statistics add
(BagStatistics.__add__), so the estimate, covariance and noise of the merge are those of the
serial run; so are its warnings: the missing-term sums and the equations left out per joint
add, and the torque's time offset is checked by the first segment only, on the stream's first
``time_offset.seconds`` as the serial run checks it (when that segment is shorter, on all of
it). So are its counters: a segment counts the messages stamped inside it as received or
rejected, not those of its margins (validate.Counters.inside), and an undecodable message
by its log time; only a stream restart seen in a margin is counted by both segments.

Why a result can differ from the serial run: the robust gate (robust.py) arms once the running
estimate has converged and then holds back samples beyond k sigma of it. Its decisions depend
on the estimate reached so far, which a segment's pipeline does not have (it would need every
earlier segment's rows: the cuts would be sequential again): each segment's gate arms on its
own segment's estimate. When no gate holds a sample back (``robust.enabled: false``, or data
without outliers), the result equals the serial one (estimate and stddev to rounding); when
some did, the samples held back may differ from the serial run's, and the Identification's
warnings say how many were held back.

The history: one checkpoint per segment, the estimate of the segments merged so far. The
torque series of reports and plots is not kept (replay_identify keeps it): callers that need
it run serially. ROS-free; worker processes from the standard library's process pool.
"""
from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from identification_node.bags.feed import JOINT_STATES, MOTOR_CURRENTS
from identification_node.model.robot import RobotModel
from identification_node.replay.segments import (BagSegment, BagStatistics, bag_span,
                                                 bag_statistics, balanced_segments,
                                                 chosen_smoother, identification, pinned)
from identification_node.results.identification import Checkpoint
from identification_node.settings import Settings

__all__ = ['default_workers', 'segments', 'parallel_identify']


def default_workers() -> int:
    """The machine's cores (those this process may run on)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:   # not Linux
        return os.cpu_count() or 1


@dataclass(frozen=True)
class _Job:
    """A segment for a worker process (picklable: the RobotModel pickles with its model)."""
    bag: str
    values: dict
    given: frozenset
    robot: RobotModel
    start_ns: int | None
    stop_ns: int | None
    joint_states: str
    motor_currents: str


def _segment(job: _Job) -> BagStatistics:
    settings = Settings(dict(job.values), job.given)
    return bag_statistics(job.bag, settings, job.robot, job.start_ns, job.stop_ns,
                          job.joint_states, job.motor_currents)


def segments(bag: str | os.PathLike, workers: int, joint_states: str = JOINT_STATES
             ) -> list[BagSegment]:
    """The segments of ``bag`` for ``workers`` processes: as many as workers, about equally
    long in its joint states' stamps (segments.bag_span), cut at multiples of the residual
    grid (segments.balanced_segments); fewer when the bag spans fewer grid multiples."""
    from identification_node.bags.reader import open_bag

    with open_bag(bag) as reader:
        start, end = bag_span(reader, joint_states)
    return balanced_segments(start, max(end, start), workers)


def parallel_identify(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                      workers: int, joint_states: str = JOINT_STATES,
                      motor_currents: str = MOTOR_CURRENTS):
    """The Identification of ``bag`` from its segments in ``workers`` processes (the module
    doc), without the physically consistent solve (identify does it after); None when the
    serial run is needed: one segment only, or forgetting_factor != 1 (forgotten statistics
    do not add up)."""
    if settings['forgetting_factor'] != 1.0 or workers < 2:
        return None
    tasks = segments(bag, workers, joint_states)
    if len(tasks) < 2:
        return None
    choice = chosen_smoother(bag, settings, robot, joint_states, motor_currents)
    if choice is not None:   # chosen as the serial run chooses it, then pinned
        settings = pinned(settings, (('smoother.half_window', int(choice.half_window)),
                                     ('smoother.cutoff', float(choice.cutoff))))
    jobs = [_Job(str(bag), dict(settings.values), frozenset(settings.given), robot,
                 t.start_ns, t.stop_ns, joint_states, motor_currents)
            for t in tasks]
    method = 'fork' if 'fork' in multiprocessing.get_all_start_methods() else None
    with ProcessPoolExecutor(min(workers, len(jobs)),
                             mp_context=multiprocessing.get_context(method)) as pool:
        parts = list(pool.map(_segment, jobs))
    merged: BagStatistics | None = None
    history = []
    ident = None    # the identification of the segments merged so far, once they have samples
    for part in parts:
        merged = part if merged is None else merged + part
        ident = (identification(merged, settings, robot, str(bag), physical_consistency=False)
                 if merged.num_samples else None)
        if ident is not None:
            history.append(Checkpoint(ident.num_samples, (merged.last_ns or 0) * 1e-9,
                                      ident.theta, ident.stddev))
    assert merged is not None   # two segments at least
    if ident is None:
        ident = identification(merged, settings, robot, str(bag), physical_consistency=False)
    ident.history = history
    if choice is not None:   # reported as the serial run reports it
        ident.pipeline.row_builder.choice = choice
        ident.details['smoother'] = choice.document()
    held = sum(p.rejected.get('outlier', 0) for p in parts)
    if held:
        ident.warnings.append(
            f'the robust gates of the {len(parts)} segments held back {held} sample(s) as '
            'outliers, each gate armed on its own segment\'s estimate: the serial run '
            '(--workers 1) may hold back others')
    return ident
