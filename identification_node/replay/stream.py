"""Offline identification: a recorded bag streamed through the live pipeline, without DDS.

The bag's messages go through the same IdentificationPipeline (validation, alignment,
smoother, RLS) as the node feeds, in log-time order and fixed-size batches, so the
result is deterministic and memory does not grow with the bag's length.
"""
from __future__ import annotations

import os
from typing import Callable

from identification_node.bags.feed import (JOINT_STATES, MOTOR_CURRENTS, ROBOT_DESCRIPTION,
                                           check_usable, feed_bag, input_topics)
from identification_node.bags.reader import iter_joint_state_blocks, open_bag, read_string_topic
from identification_node.bags.windows import TimeWindow
from identification_node.config import PER_JOINT
from identification_node.errors import IdentificationError
from identification_node.model.robot import RobotModel, load_robot
from identification_node.pipeline import IdentificationPipeline, PipelineOutput
from identification_node.results.identification import (Checkpoint, Identification, ReplayResult,
                                                        SERIES_POINTS, SeriesSampler, TorqueSeries,
                                                        from_replay)
from identification_node.settings import Settings

__all__ = ['bag_robot', 'bag_joint_names', 'robot_for_bag', 'foreign_joints_warning',
           'locked_warning', 'mimic_warning', 'identify_bag', 'replay_identify']


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
    it is true (e.g. once the smoother is chosen), and what was read is not checked for
    usable samples (check_usable): the caller has what it read for."""
    pipeline = pipeline or settings.build(robot)
    topics = input_topics(pipeline, joint_states, motor_currents)
    result = ReplayResult(str(bag), pipeline, 0)
    with open_bag(bag) as reader:
        counts = reader.topic_counts
        every = max(batch, counts.get(joint_states, 0) // max(checkpoints, 1))
        next_checkpoint = [every]
        stopped = [False]

        def step(flush: bool) -> bool:
            out = pipeline.process(flush=flush)
            if on_output is not None:
                on_output(out)
            if not flush and pipeline.used >= next_checkpoint[0]:
                result.history.append(_checkpoint(pipeline))
                next_checkpoint[0] = pipeline.used + every
            stopped[0] = until is not None and until(pipeline)
            return stopped[0]
        result.messages = feed_bag(reader, pipeline, topics, batch, step, window)
    if not stopped[0]:
        check_usable(pipeline.used, pipeline.rejected, bag, topics, counts,
                     pipeline.samples.counters, pipeline.robot.joint_names)
    result.history.append(_checkpoint(pipeline))
    return result


def _checkpoint(pipeline: IdentificationPipeline) -> Checkpoint:
    est = pipeline.estimate()
    return Checkpoint(est.num_samples, est.stamp, est.values, est.stddev)


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
