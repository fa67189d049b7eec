"""The one input record of the pipeline, produced alike by the ROS node and by bag reading."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


class JointStateRecord(NamedTuple):
    """A copied sensor_msgs/JointState: header stamp (integer ns), joint names in message order,
    position, velocity, effort (1-D float64 arrays, possibly empty; SI units). For motor
    currents (channels ``<joint>/ia`` ...): amperes in effort, electrical angles in position.
    A block of M messages sharing names and lengths: stamp_ns (M,) int64, the arrays (M, k)."""
    stamp_ns: int | np.ndarray
    names: tuple
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
