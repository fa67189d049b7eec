"""Stage 4, current alignment and torque: joint states paired with the motor currents
nearest in header stamp, and the joint torque of every sample.

A joint state is matched to the nearest current within ``align_tolerance``; it waits until a
current stamped at or after it is in (then its nearest is known), or ``hold_time`` at most,
and is counted 'no_current' when none is near ('before_currents' when no current had come
yet or it is older than the first: the currents' topic started, or was discovered, after the
joint states', a start-up transient rather than currents lost). With a ``clock`` (a live
stream: the node's monotonic time), a joint state also waits ``hold_time`` of that clock from
when it was first processed: two topics are not delivered in step on a busy machine, and
stamps alone would give up joint states whose currents are merely late. Currents no joint
state took are counted 'unmatched_current' ('before_joint_states' when older than the
stream's first joint state: the converse start-up transient). With every joint's torque
measured there is nothing to wait for: the torque is the effort (checked finite on the way
in).
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from identification_node.model.plausibility import PlausibilityBounds
from identification_node.model.torque import TorqueConverter
from identification_node.pipeline.samples import Samples
from identification_node.pipeline.validate import Counters


class CurrentAlignment:
    """Pending joint states and buffered currents; ``ready`` gives the samples decided, with
    torque."""

    def __init__(self, converter: TorqueConverter, dof: int, align_tolerance: float,
                 hold_time: float, counters: Counters, bounds: PlausibilityBounds | None = None):
        self.converter, self.dof, self.counters = converter, dof, counters
        self.bounds = bounds   # torques from currents beyond them: 'implausible'
        self.align_tolerance, self.hold_time = float(align_tolerance), float(hold_time)
        self._all_measured = len(converter.measured_joints) == dof
        self.clock: Callable[[], float] | None = None    # see the module doc
        self.reset()

    def reset(self) -> None:
        self.pending = Samples.empty(self.dof)
        self._seen = np.empty(0)      # clock time each pending joint state was first processed
        self.currents = Samples.empty(self.dof, with_currents=True)
        self._newest_js = -math.inf
        self._first_current = math.inf   # stamp of the stream's first current
        self._first_js = math.inf        # and of its first joint state

    def add_joint_states(self, s: Samples) -> None:
        self.pending = self.pending.concat(s)
        if len(s):
            self._first_js = min(self._first_js, float(s.stamps[0]))
            if self.clock is not None:
                self._seen = np.concatenate([self._seen, np.full(len(s), self.clock())])

    def add_currents(self, s: Samples) -> None:
        if len(s):
            self.currents = self.currents.concat(s)
            self._first_current = min(self._first_current, float(s.stamps[0]))

    def restart(self, old_newest: float, restart_jump: float) -> int:
        """A restarted stream: drop the pending joint states (returns how many) and the
        currents stamped within ``restart_jump`` of the old stream's newest stamp; older
        ones already belong to the new stream (they may come in the same batch)."""
        dropped = len(self.pending)
        self.pending, self._seen = Samples.empty(self.dof), np.empty(0)
        self.currents = self.currents.select(self.currents.stamps < old_newest - restart_jump)
        self._newest_js = -math.inf
        self._first_current = float(self.currents.stamps[0]) if len(self.currents) else math.inf
        self._first_js = math.inf
        return dropped

    def ready(self, flush: bool = False) -> Samples:
        """Joint states whose currents are known (or will never come), with torque; ``flush``
        decides all of them (end of a bag)."""
        s = self.pending
        if len(s) == 0:
            return s
        self._newest_js = max(self._newest_js, float(s.stamps[-1]))
        if not self.converter.needs_currents:
            self.pending, self._seen = Samples.empty(self.dof), np.empty(0)
            return self._with_torque(s, None, None)
        cur = self.currents
        assert cur.currents is not None and cur.theta is not None and cur.used is not None
        newest_cur = cur.stamps[-1] if len(cur) else -math.inf
        if flush:
            decided = np.ones(len(s), dtype=bool)
        else:
            # Currents come in stamp order: once one at or after t is in, the nearest to t is
            # among those in (the newest before t, the first after), so t is decided.
            held = s.stamps <= self._newest_js - self.hold_time
            if self.clock is not None and len(self._seen) == len(s):
                held &= self._seen <= self.clock() - self.hold_time
            decided = (s.stamps <= newest_cur) | held
        # decided is a prefix: stamps are increasing.
        k = int(np.count_nonzero(decided))
        if k == 0:
            return Samples.empty(self.dof)
        if k == len(s):
            ready, self.pending = s, Samples.empty(self.dof)
        else:
            ready, self.pending = s.head(k), s.tail(k)
        self._seen = self._seen[k:]
        match = self._nearest(cur.stamps, ready.stamps)
        ok = match >= 0
        early = ready.stamps < self._first_current - self.align_tolerance
        among = self.counters.among_seconds
        self.counters.reject('before_currents', among(ready.stamps, ~ok & early))
        self.counters.reject('no_current', among(ready.stamps, ~ok & ~early))
        used = np.zeros(len(cur), dtype=bool)
        used[match[ok]] = True
        # Currents older than what the next joint state could still match are done with.
        horizon = (self.pending.stamps[0] if len(self.pending)
                   else ready.stamps[-1]) - self.align_tolerance
        if flush:
            horizon = math.inf
        done = cur.stamps < horizon
        stale = done & ~used & ~cur.used
        # older than the stream's first joint state, which took the nearest: none could match
        early = cur.stamps < self._first_js
        self.counters.reject('before_joint_states', among(cur.stamps, stale & early))
        self.counters.reject('unmatched_current', among(cur.stamps, stale & ~early))
        cur.used |= used
        self.currents = cur.select(~done) if done.any() else cur
        if not ok.all():
            ready, match = ready.select(ok), match[ok]
        return self._with_torque(ready, cur.currents[match], cur.theta[match])

    def _nearest(self, ref: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Index of the nearest ``ref`` stamp within tolerance for each ``t``, else -1."""
        if len(ref) == 0:
            return np.full(len(t), -1)
        hi = np.minimum(np.maximum(np.searchsorted(ref, t), 1), len(ref) - 1) if len(ref) > 1 \
            else np.zeros(len(t), dtype=int)
        lo = np.maximum(hi - 1, 0)
        pick = np.where(np.abs(ref[lo] - t) <= np.abs(ref[hi] - t), lo, hi)
        return np.where(np.abs(ref[pick] - t) <= self.align_tolerance, pick, -1)

    def _with_torque(self, s: Samples, currents, theta) -> Samples:
        if self._all_measured:
            s.tau = s.eff   # every joint's torque measured: checked finite on the way in
            return s
        s.tau = self.converter.torque(s.q, measured=s.eff, currents=currents, theta_e=theta)
        ok = np.isfinite(s.tau).all(axis=1)
        if not ok.all():
            self.counters.reject('non_finite', self.counters.among_seconds(s.stamps, ~ok))
            s = s.select(ok)
        plausible = self.bounds.ok(tau=s.tau) if self.bounds is not None else None
        if plausible is None or plausible.all():
            return s
        self.counters.reject('implausible', self.counters.among_seconds(s.stamps, ~plausible))
        return s.select(plausible)
