"""Validated samples between the pipeline's stages, and joint state records stacked into blocks.

Stamps are float seconds since the stream's epoch (its first header stamp, exact to the
nanosecond for spans of days); per-joint arrays follow the robot's joint order (README
"Conventions").
"""
from __future__ import annotations

from typing import Callable, Iterator

import numpy as np

from identification_node.wire.records import JointStateRecord


class Samples:
    """Validated samples in stamp order: stamps (M,) s, q, qd, eff (M, n) (NaN where not
    measured); for currents also currents (M, n, 3), theta (M, n) electrical angles and the
    used flags (M,); the joint torque tau (M, n) once known."""
    __slots__ = ('stamps', 'q', 'qd', 'eff', 'currents', 'theta', 'used', 'tau')

    def __init__(self, stamps: np.ndarray, q: np.ndarray, qd: np.ndarray, eff: np.ndarray,
                 currents: np.ndarray | None = None, theta: np.ndarray | None = None,
                 used: np.ndarray | None = None, tau: np.ndarray | None = None):
        self.stamps, self.q, self.qd, self.eff = stamps, q, qd, eff
        self.currents, self.theta, self.tau = currents, theta, tau
        if currents is not None and used is None:
            used = np.zeros(len(stamps), dtype=bool)
        self.used = used

    @classmethod
    def empty(cls, n: int, with_currents: bool = False) -> Samples:
        z = np.empty((0, n))
        if with_currents:
            return cls(np.empty(0), z, z, z, np.empty((0, n, 3)), z)
        return cls(np.empty(0), z, z, z)

    def __len__(self) -> int:
        return len(self.stamps)

    def _arrays(self) -> list:
        return [getattr(self, name) for name in self.__slots__]

    def _map(self, fn: Callable[[np.ndarray], np.ndarray]) -> Samples:
        stamps, q, qd, eff, *optional = self._arrays()   # the first four are never None
        return Samples(fn(stamps), fn(q), fn(qd), fn(eff),
                       *[None if a is None else fn(a) for a in optional])

    def select(self, mask: np.ndarray) -> Samples:
        return self._map(lambda a: a[mask])

    def head(self, k: int) -> Samples:
        return self._map(lambda a: a[:k])

    def tail(self, k: int) -> Samples:
        return self._map(lambda a: a[k:])

    def concat(self, other: Samples) -> Samples:
        if len(self.stamps) == 0:
            return other
        if len(other.stamps) == 0:
            return self
        pairs = list(zip(self._arrays(), other._arrays()))   # the first four never None
        merged = Samples(*[np.concatenate([a, b]) for a, b in pairs[:4]],
                         *[None if a is None else np.concatenate([a, b]) for a, b in pairs[4:]])
        if self.currents is not None and other.stamps[0] < self.stamps[-1]:
            # Current messages may interleave: keep the buffer sorted by stamp (both parts are
            # sorted, so only when they overlap).
            return merged.select(np.argsort(merged.stamps, kind='stable'))
        return merged


def stack_records(records: list) -> Iterator[JointStateRecord]:
    """Joint state records as blocks: blocks as they are, and each run of single records
    sharing names and array lengths stacked into one (stamp_ns (M,) int64, (M, k) arrays)."""
    i = 0
    while i < len(records):
        r = records[i]
        if isinstance(r.stamp_ns, np.ndarray):
            yield r
            i += 1
            continue
        names, lengths = r.names, (len(r.position), len(r.velocity), len(r.effort))
        j = i + 1
        while j < len(records) and not isinstance(records[j].stamp_ns, np.ndarray) and (
                records[j].names is names or records[j].names == names) and (
                len(records[j].position), len(records[j].velocity),
                len(records[j].effort)) == lengths:
            j += 1
        run = records[i:j]
        M = len(run)
        yield JointStateRecord(
            np.array([x.stamp_ns for x in run], dtype=np.int64), names,
            *(np.array([getattr(x, f) for x in run], dtype=float).reshape(M, k)
              for f, k in zip(('position', 'velocity', 'effort'), lengths)))
        i = j
