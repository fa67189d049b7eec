"""Feeding a bag's messages to the pipeline or its input stages, in log-time order and batches;
why a bag gave no usable sample. Stamps int64 ns."""
from __future__ import annotations

import functools
from typing import Callable, Iterator

import numpy as np

from identification_node.bags.reader import iter_joint_state_blocks, iter_joint_states
from identification_node.bags.windows import TimeWindow, empty_window_error, in_window
from identification_node.errors import IdentificationError
from identification_node.wire.records import JointStateRecord

__all__ = ['JOINT_STATES', 'MOTOR_CURRENTS', 'ROBOT_DESCRIPTION', 'check_usable',
           'input_topics', 'feed_bag', 'feed_records']


JOINT_STATES = '/joint_states'
MOTOR_CURRENTS = '/motor_currents'
ROBOT_DESCRIPTION = '/robot_description'


def check_usable(used: int, rejected: dict[str, int], bag, topics: list[str],
                 counts: dict[str, int], counters=None, joints: list[str] | None = None
                 ) -> None:
    """IdentificationError saying why, when no sample of the bag could be used (``used``
    samples, ``rejected`` messages per reason), naming the identified ``joints`` and those
    the messages lacked (validate.Counters ``counters``)."""
    if used == 0:
        rejected = {k: v for k, v in rejected.items() if v}
        lacking = []
        if counters is not None and counters.missing_joints:
            lacking.append(f'{topics[0]} lacks joint(s) '
                           f'{", ".join(sorted(counters.missing_joints))}')
        if counters is not None and counters.missing_current_joints:
            lacking.append(f'{topics[-1]} lacks the current channels of joint(s) '
                           f'{", ".join(sorted(counters.missing_current_joints))}')
        raise IdentificationError(
            f'no usable samples in {bag} (messages on {", ".join(topics)}: '
            f'{sum(counts.get(t, 0) for t in topics)}; rejected: {rejected or "none"}'
            + ''.join(f'; {x}' for x in lacking) + ')'
            + (f'; identified joints: {", ".join(joints)}' if joints else '')
            + '; check the joint names and the torque sources (--config)')


def input_topics(pipeline, joint_states: str = JOINT_STATES,
                 motor_currents: str = MOTOR_CURRENTS) -> list[str]:
    """The topics ``pipeline`` (an IdentificationPipeline or TorqueSamples) reads: the joint
    states, and the motor currents when its torque sources need them."""
    return [joint_states] + ([motor_currents] if pipeline.converter.needs_currents else [])


def feed_bag(reader, pipeline, topics: list[str], batch: int,
             step: Callable[[bool], bool | None], window: TimeWindow | None = None) -> int:
    """Feed ``pipeline`` the bag's messages (feed_records), calling ``step(False)`` after every
    ``batch`` of them (reading stops when it returns true) and ``step(True)`` (flush) after
    the last; returns the number of messages fed."""
    messages = 0
    for add, count in feed_records(reader, pipeline, topics, batch, window):
        add()
        messages += count
        if messages % batch == 0 and step(False):
            break
    step(True)
    return messages


def feed_records(reader, pipeline, topics: list[str], batch: int,
                 window: TimeWindow | None = None
                 ) -> Iterator[tuple[Callable[[], None], int]]:
    """(add, number of messages): what feeds ``pipeline`` (an IdentificationPipeline or its
    input stages, TorqueSamples) the bag's messages in log-time order, those of ``window``
    only. Joint states alone are read in blocks (iter_joint_state_blocks), cut where a batch
    of ``batch`` messages ends: the pipeline sees the same batches as message by message.
    IdentificationError when the window keeps no message."""
    bounds = None if window is None or window.whole else window.bounds_ns(
        str(reader.path), reader.start_ns, reader.end_ns)
    kept = 0
    for item in _records(reader, pipeline, topics, batch, bounds):
        kept += item[1]
        yield item
    if window is not None and bounds is not None and kept == 0:
        raise empty_window_error(str(reader.path), window)


def _records(reader, pipeline, topics: list[str], batch: int, bounds: tuple[int, int] | None
             ) -> Iterator[tuple[Callable[[], None], int]]:
    # an undecodable message (a corrupt one in a good bag) is counted 'malformed' and skipped
    malformed = []

    def skip(topic: str, t_ns: int, err: IdentificationError) -> None:
        if bounds is None or bounds[0] <= t_ns < bounds[1]:
            malformed.append(functools.partial(pipeline.add_malformed, t_ns))
    if len(topics) > 1:
        add = {topics[0]: pipeline.add_joint_state, topics[1]: pipeline.add_currents}
        for topic, t_ns, record in iter_joint_states(reader, topics, skip):
            while malformed:
                yield malformed.pop(), 1
            if bounds is None or bounds[0] <= t_ns < bounds[1]:
                yield functools.partial(add[topic], record), 1
        while malformed:
            yield malformed.pop(), 1
        return
    done = 0
    for log_ns, block in iter_joint_state_blocks(reader, topics[0], skip):
        while malformed:
            done += 1
            yield malformed.pop(), 1
        stamps = block.stamp_ns
        if bounds is not None:
            keep = in_window(log_ns, bounds)
            if not keep.any():
                continue
            if isinstance(stamps, np.ndarray) and stamps.ndim and not keep.all():
                stamps = stamps[keep]
                block = JointStateRecord(stamps, block.names, *(a[keep] for a in block[2:]))
        if not isinstance(stamps, np.ndarray) or not stamps.ndim:
            done += 1
            yield functools.partial(pipeline.add_joint_state, block), 1
            continue
        start = 0
        while start < len(stamps):
            stop = min(len(stamps), start + batch - done % batch)
            part = JointStateRecord(stamps[start:stop], block.names,
                                    *(a[start:stop] for a in block[2:]))
            done += stop - start
            yield functools.partial(pipeline.add_joint_states, part), stop - start
            start = stop
    while malformed:
        yield malformed.pop(), 1
