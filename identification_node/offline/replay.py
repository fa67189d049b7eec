"""Offline identification: a recorded bag streamed through the live pipeline, without DDS.

The bag's messages go through the same IdentificationPipeline (validation, alignment,
smoother, RLS) as the node feeds, in log-time order and fixed-size batches, so the
result is deterministic and memory does not grow with the bag's length.
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np

from identification_node.config import PER_JOINT
from identification_node.bags.reader import (iter_joint_state_blocks, iter_joint_states, open_bag,
                                             read_string_topic)
from identification_node.errors import IdentificationError
from identification_node.model.robot import RobotModel, load_robot
from identification_node.offline.windows import TimeWindow, empty_window_error, in_window
from identification_node.pipeline import IdentificationPipeline, PipelineOutput
from identification_node.settings import Settings
from identification_node.wire.records import JointStateRecord

JOINT_STATES = '/joint_states'
MOTOR_CURRENTS = '/motor_currents'
ROBOT_DESCRIPTION = '/robot_description'


@dataclass
class Checkpoint:
    """The running estimate after ``num_samples`` samples (for convergence plots)."""
    num_samples: int
    stamp: float
    values: np.ndarray
    stddev: np.ndarray


@dataclass
class ReplayResult:
    """The pipeline after the whole bag, and the estimate's history."""
    bag: str
    pipeline: IdentificationPipeline
    messages: int
    history: list[Checkpoint] = field(default_factory=list)


def bag_robot(bag: str | os.PathLike, settings: Settings) -> RobotModel:
    """The robot of the bag's /robot_description (URDF), with the settings' joints and extras."""
    with open_bag(bag) as reader:
        xml = read_string_topic(reader, ROBOT_DESCRIPTION)
    if not xml:
        raise IdentificationError(f'bag {bag} has no {ROBOT_DESCRIPTION}: name the robot '
                                  '(--robot or --urdf, or robot in --config)')
    return load_robot(xml, settings['joints'] or None, extras=settings['extras'],
                      coulomb_velocity=settings['coulomb_velocity'])


def bag_joint_names(bag: str | os.PathLike, topic: str = JOINT_STATES) -> list[str]:
    """The joint names of the bag's first joint state message on ``topic`` (empty: none)."""
    with open_bag(bag) as reader:
        if topic not in reader.topics:
            return []
        for _, block in iter_joint_state_blocks(reader, topic, lambda *_: None):
            return [str(n) for n in block.names]
    return []


def robot_for_bag(robot: RobotModel, settings: Settings, bag: str | os.PathLike,
                  topic: str = JOINT_STATES) -> tuple[RobotModel, Settings, list[str]]:
    """(robot, settings, locked): without ``joints`` in the settings, the robot's movable
    joints that the bag's joint states carry, the others locked at their zero position (their
    links merged into their parents), the settings' per-joint lists of one value per movable
    joint cut to them, and the joints locked; all unchanged when the bag carries every
    movable joint, or none (the pipeline then says which are missing)."""
    if settings['joints']:
        return robot, settings, []
    names = set(bag_joint_names(bag, topic))
    carried = [j for j in robot.joint_names if j in names]
    locked = [j for j in robot.joint_names if j not in names]
    if not carried or not locked:
        return robot, settings, []
    keep = [robot.joint_names.index(j) for j in carried]
    values = dict(settings.values)
    for name in PER_JOINT + ('joint_noise_std', 'plausibility.current_limit'):
        if len(values[name]) == robot.dof > 1:
            values[name] = [values[name][i] for i in keep]
    return (load_robot(robot.description, carried, extras=robot.extras,
                       coulomb_velocity=robot.coulomb_velocity),
            Settings(values, settings.given), locked)


def foreign_joints_warning(robot: RobotModel, bag: str | os.PathLike,
                           topic: str = JOINT_STATES) -> str | None:
    """The warning when the bag's joint states carry joints the robot's description does not
    have (a description of another robot, or of part of it), else None."""
    names = bag_joint_names(bag, topic)
    foreign = [n for n in names if n not in robot.description_joints]
    if not foreign:
        return None
    return (f"the bag's {topic} carries {len(names)} joints, {len(foreign)} of them not in "
            f"the description of {robot.name} ({', '.join(foreign[:6])}"
            f"{', ...' if len(foreign) > 6 else ''}): is the description of another robot? "
            f"Identifying {', '.join(robot.joint_names)} only")


def locked_warning(robot: RobotModel, locked: list[str], topic: str = JOINT_STATES) -> str:
    """The warning naming the joints robot_for_bag locked."""
    return (f"joint(s) {', '.join(locked)} of {robot.name} are not in the bag's {topic}: "
            f"locked at their zero position; identifying {', '.join(robot.joint_names)}")


def mimic_warning(robot: RobotModel, bag: str | os.PathLike,
                  topic: str = JOINT_STATES) -> str | None:
    """The warning for URDF <mimic> joints (and those they follow) that the bag's joint states
    carry but the robot locks (RobotModel.mimic_locked); None when there are none."""
    carried = [j for j in robot.mimic_locked if j in set(bag_joint_names(bag, topic))]
    if not carried:
        return None
    return (f"joint(s) {', '.join(carried)} of {robot.name} are in the bag's {topic} but locked "
            'at their reference position: mimic joints (URDF <mimic>) and the joints they '
            'follow are not modelled')


def identify_bag(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                 joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS,
                 batch: int = 1000, checkpoints: int = 50,
                 on_output: Callable[[PipelineOutput], None] | None = None,
                 pipeline: IdentificationPipeline | None = None,
                 window: TimeWindow | None = None,
                 until: Callable[[IdentificationPipeline], bool] | None = None
                 ) -> ReplayResult:
    """Identify ``robot`` from the bag's joint states (and motor currents when the settings'
    torque sources need them). ``on_output`` sees every batch the pipeline outputs;
    ``pipeline``: the one to feed (default: the settings' own, new); ``window``: only the
    messages recorded in it (windows.py); ``until``: reading stops after the batch for which
    it is true (e.g. once the smoother is chosen)."""
    pipeline = pipeline or settings.build(robot)
    topics = input_topics(pipeline, joint_states, motor_currents)
    result = ReplayResult(str(bag), pipeline, 0)
    with open_bag(bag) as reader:
        counts = reader.topic_counts
        every = max(batch, counts.get(joint_states, 0) // max(checkpoints, 1))
        next_checkpoint = [every]

        def step(flush: bool) -> bool:
            out = pipeline.process(flush=flush)
            if on_output is not None:
                on_output(out)
            if not flush and pipeline.used >= next_checkpoint[0]:
                result.history.append(_checkpoint(pipeline))
                next_checkpoint[0] = pipeline.used + every
            return until is not None and until(pipeline)
        result.messages = feed_bag(reader, pipeline, topics, batch, step, window)
    check_usable(pipeline.used, pipeline.rejected, bag, topics, counts,
                 pipeline.samples.counters, pipeline.robot.joint_names)
    result.history.append(_checkpoint(pipeline))
    return result


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
    if bounds is not None and kept == 0:
        raise empty_window_error(str(reader.path), window)


def _records(reader, pipeline, topics: list[str], batch: int, bounds: tuple[int, int] | None
             ) -> Iterator[tuple[Callable[[], None], int]]:
    # an undecodable message (a corrupt one in a good bag) is counted 'malformed' and skipped
    malformed = []

    def skip(topic: str, t_ns: int, err: IdentificationError) -> None:
        if bounds is None or bounds[0] <= t_ns < bounds[1]:
            malformed.append(pipeline.add_malformed)
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
        if bounds is not None:
            keep = in_window(log_ns, bounds)
            if not keep.any():
                continue
            if np.ndim(block.stamp_ns) and not keep.all():
                block = JointStateRecord(block.stamp_ns[keep], block.names,
                                         *(a[keep] for a in block[2:]))
        if not np.ndim(block.stamp_ns):
            done += 1
            yield functools.partial(pipeline.add_joint_state, block), 1
            continue
        start = 0
        while start < len(block.stamp_ns):
            stop = min(len(block.stamp_ns), start + batch - done % batch)
            part = JointStateRecord(block.stamp_ns[start:stop], block.names,
                                    *(a[start:stop] for a in block[2:]))
            done += stop - start
            yield functools.partial(pipeline.add_joint_states, part), stop - start
            start = stop
    while malformed:
        yield malformed.pop(), 1


def _checkpoint(pipeline: IdentificationPipeline) -> Checkpoint:
    est = pipeline.estimate()
    return Checkpoint(est.num_samples, est.stamp, est.values, est.stddev)
