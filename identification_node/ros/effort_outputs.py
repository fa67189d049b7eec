"""``~/predicted_effort`` and ``~/measured_effort`` (sensor_msgs/JointState: position and
effort per joint, N m or N, stamped with each sample's own header stamp), published from the
processing thread while they have subscribers, thinned to ``publish.effort_rate`` (0: every
sample)."""
from __future__ import annotations

import math
import time
from typing import Sequence

import numpy as np
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from identification_node.pipeline import PipelineOutput
from identification_node.ros.conversions import publish_joint_states

__all__ = ['LISTENER_CHECK_PERIOD', 'OUTPUT_QOS', 'EffortOutputs']

OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                        reliability=ReliabilityPolicy.RELIABLE)
# Whether the effort topics have subscribers is asked this often (s), not every run (it is a
# middleware query): a new subscriber may miss the efforts of its first ~0.1 s.
LISTENER_CHECK_PERIOD = 0.1


class EffortOutputs:
    """The effort publishers of ``node`` for joints ``names``, at most ``rate`` Hz (0: all)."""

    def __init__(self, node: Node, names: Sequence[str], rate: float):
        self.names, self.rate = list(names), rate
        self.predicted = node.create_publisher(JointState, '~/predicted_effort', OUTPUT_QOS)
        self.measured = node.create_publisher(JointState, '~/measured_effort', OUTPUT_QOS)
        self._last_slot = -1
        self._listened = (False, False)   # (predicted, measured), checked at most
        self._listeners_checked = -math.inf      # every LISTENER_CHECK_PERIOD s

    @property
    def listened(self) -> bool:
        """Whether anything subscribes to either output (as of at most
        LISTENER_CHECK_PERIOD s ago)."""
        self._check_listeners()
        return any(self._listened)

    def _check_listeners(self) -> None:
        now = time.monotonic()
        if now - self._listeners_checked >= LISTENER_CHECK_PERIOD:
            self._listeners_checked = now
            self._listened = (self.predicted.get_subscription_count() > 0,
                              self.measured.get_subscription_count() > 0)

    def publish(self, out: PipelineOutput) -> None:
        """Publish the efforts of ``out`` (one processing run's output)."""
        if len(out.stamps_ns) == 0:
            return
        self._check_listeners()
        outputs = [(pub, effort) for pub, effort, listened in zip(
            (self.predicted, self.measured), (out.predicted, out.measured),
            self._listened) if listened]   # none serialized for nobody
        if not outputs:
            return
        keep: slice | np.ndarray = slice(None)
        if self.rate > 0:
            slots = (out.stamps_ns * self.rate // 1e9).astype(np.int64)
            prev = np.concatenate([[self._last_slot], slots[:-1]])
            keep = slots != prev
            self._last_slot = int(slots[-1])
        stamps = out.stamps_ns[keep]
        for pub, effort in outputs:
            publish_joint_states(pub, stamps, self.names, position=out.q[keep],
                                 effort=effort[keep])
