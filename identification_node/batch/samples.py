"""The validated samples of a bag, read through the pipeline's own input stages. Units SI;
stamps int64 ns."""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from identification_node.bags.feed import (JOINT_STATES, MOTOR_CURRENTS, check_usable, feed_bag,
                                           input_topics)
from identification_node.bags.reader import open_bag
from identification_node.bags.windows import TimeWindow
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.pipeline import TorqueSamples
from identification_node.settings import Settings

__all__ = ['Stream', 'BagSamples', 'read_samples']


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
            assert s.tau is not None   # what process() returns carries its torque
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
