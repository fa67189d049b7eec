"""The segment window: the stage that makes a pipeline process one time segment of a stream
(parallel replay and fleet cut a bag into segments and merge their statistics).

Its pipeline is fed the messages within ``margin_ns`` of [start_ns, stop_ns) (the smoother, the
currents' alignment and hold time reach that far) and keeps only the rows whose stamps lie
inside, so a segment's rows are those the whole stream gives there; the messages it counts
(received, rejected) are those inside too, those of the margins being its neighbours'. Stamps
are header stamps, int64 ns; None is an open end.
"""
from __future__ import annotations

import numpy as np

__all__ = ['SegmentWindow']

_OPEN = 2 ** 62   # ns: beyond any stamp


class SegmentWindow:
    """[start_ns, stop_ns) of a stream, fed with ``margin_ns`` on either side; ``messages``
    counts the messages fed whose stamps lie inside (each belongs to one segment)."""

    def __init__(self, start_ns: int | None, stop_ns: int | None, margin_ns: int):
        self.inside = (-_OPEN if start_ns is None else int(start_ns),
                       _OPEN if stop_ns is None else int(stop_ns))
        self.fed = (self.inside[0] - int(margin_ns), self.inside[1] + int(margin_ns))
        self.messages = 0

    def feed(self, stamps_ns):
        """Mask of the messages (stamps (M,)) the pipeline takes, or for one stamp (int)
        whether it does; counts those inside."""
        if isinstance(stamps_ns, (int, np.integer)):   # one message: no array calls
            self.messages += int(self.inside[0] <= stamps_ns < self.inside[1])
            return bool(self.fed[0] <= stamps_ns < self.fed[1])
        stamps_ns = np.asarray(stamps_ns)
        self.messages += int(np.count_nonzero(self.keep(stamps_ns)))
        return (stamps_ns >= self.fed[0]) & (stamps_ns < self.fed[1])

    def keep(self, stamps_ns) -> np.ndarray:
        """Mask of the rows (stamps (M,)) inside the segment."""
        stamps_ns = np.asarray(stamps_ns)
        return (stamps_ns >= self.inside[0]) & (stamps_ns < self.inside[1])
