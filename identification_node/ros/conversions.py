"""Conversions between ROS messages and the core's plain records."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import JointState

from ..records import JointStateRecord


def stamp_ns(stamp: Time) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def time_msg(ns: int) -> Time:
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def joint_state_record(msg: JointState) -> JointStateRecord:
    """Copy a JointState into the pipeline's record (no validation: the pipeline does it)."""
    return JointStateRecord(stamp_ns(msg.header.stamp), tuple(msg.name),
                            np.array(msg.position, dtype=float),
                            np.array(msg.velocity, dtype=float),
                            np.array(msg.effort, dtype=float))


def joint_state_msgs(stamps_ns: np.ndarray, names: Sequence[str], position=None, velocity=None,
                     effort=None, frame_id: str = '') -> list[JointState]:
    """One JointState per row of the given (N, n) arrays, stamped with ``stamps_ns``."""
    names = list(names)
    cols = [None if a is None else np.asarray(a).tolist() for a in (position, velocity, effort)]
    out = []
    for k, ns in enumerate(np.asarray(stamps_ns).tolist()):
        msg = JointState(name=names)
        msg.header.stamp = time_msg(ns)
        msg.header.frame_id = frame_id
        if cols[0] is not None:
            msg.position = cols[0][k]
        if cols[1] is not None:
            msg.velocity = cols[1][k]
        if cols[2] is not None:
            msg.effort = cols[2][k]
        out.append(msg)
    return out
