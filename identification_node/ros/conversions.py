"""Conversions between ROS messages and the core's plain arrays: stamps and JointState output."""
from __future__ import annotations

import array
from typing import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import JointState


def time_msg(ns: int) -> Time:
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def publish_joint_states(publisher, stamps_ns: np.ndarray, names: Sequence[str], position=None,
                         velocity=None, effort=None) -> None:
    """Publish one JointState per row of the given (N, n) arrays, stamped with ``stamps_ns``.
    One message object is refilled for every row (rclpy serializes at publish), and arrays go
    in as array('d'), which the message setters take without checking element by element."""
    msg = JointState(name=list(names))
    stamp = msg.header.stamp
    fields = [(name, np.ascontiguousarray(a, dtype=float))
              for name, a in (('position', position), ('velocity', velocity), ('effort', effort))
              if a is not None]
    for k, ns in enumerate(np.asarray(stamps_ns).tolist()):
        stamp.sec, stamp.nanosec = divmod(ns, 1_000_000_000)
        for name, a in fields:
            row = array.array('d')
            row.frombytes(a[k].tobytes())
            setattr(msg, name, row)
        publisher.publish(msg)
