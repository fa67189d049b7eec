"""Stage 1, intake: what the node and bag replay hand in, queued, and decoded when processed.

The node adds the JointState messages of a poll as CDR bytes (``add_joint_state_cdr``), bag
replay adds decoded records or blocks of them; ``take`` decodes the CDR lists with the decoder
bag reading uses (bagio.decode_joint_states: runs of one layout as one block) and counts a
message that cannot be decoded as received and 'malformed'. Nothing but a copy happens on the
caller's side.
"""
from __future__ import annotations

import collections

import numpy as np

from identification_node.wire.cdr import JointStateDecoder, decode_joint_states
from identification_node.errors import IdentificationError
from identification_node.pipeline.validate import Counters
from identification_node.wire.records import JointStateRecord


class Intake:
    """The queue of one input stream (joint states, or motor currents) and its decoder (one
    per stream: it keeps its stream's last names)."""

    def __init__(self, counters: Counters):
        self._queue: collections.deque = collections.deque()
        self._decoder = JointStateDecoder()
        self._counters = counters

    def add(self, record: JointStateRecord) -> None:
        self._queue.append(record)

    def add_block(self, block: JointStateRecord) -> None:
        """Records sharing names and layout, at once: stamp_ns (M,) int64, position, velocity
        and effort (M, k) ((M, 0) when absent); the same as adding the M records one by one."""
        M = np.shape(block.stamp_ns)
        arrays = (block.position, block.velocity, block.effort)
        if len(M) != 1 or any(np.ndim(a) != 2 or len(a) != M[0] for a in arrays):
            raise IdentificationError(
                f'joint state block: stamps {M} and arrays '
                f'{[np.shape(a) for a in arrays]}; expected (M,) and (M, k)')
        self._queue.append(block._replace(stamp_ns=np.asarray(block.stamp_ns)))

    def add_cdr(self, messages: list[bytes]) -> None:
        """sensor_msgs/JointState messages as CDR bytes, in arrival order."""
        self._queue.append(messages)

    def __len__(self) -> int:
        return len(self._queue)

    def clear(self) -> None:
        self._queue.clear()

    def take(self) -> list[JointStateRecord]:
        """Everything queued, in order, as records or blocks (CDR lists decoded)."""
        out = []
        while self._queue:
            item = self._queue.popleft()
            if type(item) is not list:
                out.append(item)
                continue
            for record in decode_joint_states(item, self._decoder):
                if isinstance(record, IdentificationError):
                    self.malformed()
                else:
                    out.append(record)
        return out

    def malformed(self, log_ns: int | None = None) -> None:
        """Count a message that could not even be decoded (received, and rejected; by its
        log time ``log_ns`` when given: Counters.malformed)."""
        self._counters.malformed(log_ns)
