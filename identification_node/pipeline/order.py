"""Stage 3, stamp order: samples kept only when stamped after every sample accepted before.

Out-of-order and repeated stamps are counted and dropped; a backward jump of more than
``restart_jump`` seconds is a restarted stream (a replayed bag, a rebooted driver): what the
old stream left pending is dropped (counted 'stream_restart') and the later stages restart.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from identification_node.pipeline.samples import Samples
from identification_node.pipeline.validate import Counters


class StampOrder:
    """Samples in stamp order. ``on_restart(old_newest_stamp)`` is called at a restart and
    returns how many samples pending downstream it dropped (counted here)."""

    def __init__(self, restart_jump: float, counters: Counters,
                 on_restart: Callable[[float], int]):
        self.restart_jump = float(restart_jump)
        self.counters = counters
        self.on_restart = on_restart
        self.reset()

    def reset(self) -> None:
        self.last_stamp = -math.inf

    def __call__(self, s: Samples) -> Samples:
        """Keep samples whose stamp exceeds every stamp accepted before."""
        t = s.stamps
        if len(t) and t[0] > self.last_stamp and (len(t) == 1 or (t[1:] > t[:-1]).all()):
            self.last_stamp = float(t[-1])   # the usual case: all in order
            return s
        reject = self.counters.reject
        parts = []
        while len(s.stamps):
            prior = np.maximum.accumulate(np.concatenate([[self.last_stamp], s.stamps]))[:-1]
            jump = np.flatnonzero(prior - s.stamps > self.restart_jump)
            k = int(jump[0]) if len(jump) else len(s.stamps)
            head, prior = s.head(k), prior[:k]
            keep = head.stamps > prior
            among = self.counters.among_seconds
            reject('repeated_stamp', among(head.stamps, head.stamps == prior))
            reject('out_of_order', among(head.stamps, head.stamps < prior))
            parts.append(head.select(keep))
            if len(head.stamps):
                self.last_stamp = max(self.last_stamp, float(head.stamps.max()))
            if k == len(s.stamps):
                break
            # a restart: the old stream's samples of this block and those pending are dropped
            self.counters.restarts += 1
            reject('stream_restart', sum(len(p) for p in parts)
                   + self.on_restart(self.last_stamp))
            parts.clear()
            self.last_stamp = -math.inf
            s = s.tail(k)
        out = Samples.empty(s.q.shape[1])
        for part in parts:
            out = out.concat(part)
        return out
