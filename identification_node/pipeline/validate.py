"""Stage 2, validation: joint state and current blocks checked and mapped to the robot's joints.

A block (messages sharing names and array lengths) is decided at once; every rejected message
is counted by reason (``REJECT_REASONS``), never an exception or a NaN passed on. Accepted
rows come out as Samples in the robot's joint order, stamps in seconds since the stream's
epoch (its first stamp). Values beyond the physical bounds (plausibility.py) are rejected as
'implausible'; a message with more than ``max_names`` names as 'too_many_names', before any
layout is made of it.
"""
from __future__ import annotations

import math
import sys
from typing import Callable

import numpy as np

from identification_node.model.plausibility import PlausibilityBounds
from identification_node.model.robot import RobotModel
from identification_node.model.torque import TorqueConverter
from identification_node.pipeline.samples import Samples, stack_records
from identification_node.wire.records import JointStateRecord

REJECT_REASONS = (
    'empty', 'length_mismatch', 'duplicate_names', 'missing_joints', 'non_finite',
    'missing_velocity', 'missing_effort', 'out_of_order', 'repeated_stamp', 'no_current',
    'before_currents', 'unmatched_current', 'before_joint_states', 'unknown_channels',
    'stream_restart', 'malformed', 'too_many_names', 'implausible', 'outlier',
    'regressor_overflow', 'numerical_failure',
)


class Counters:
    """Messages received, rejected per reason, stream restarts; and the stream's epoch, the
    first stamp (ns), shared by both streams so their stamps compare.

    ``inside``: the mask of the stamps (int64 ns, (M,)) whose messages are counted here, a
    segment window's (window.py: each message is counted by the one segment its stamp lies in,
    not again in its neighbours' margins); None: all."""

    def __init__(self) -> None:
        self.inside: Callable[[np.ndarray], np.ndarray] | None = None
        self.reset()

    def reset(self) -> None:
        self.received = 0
        self.restarts = 0
        self.rejected = dict.fromkeys(REJECT_REASONS, 0)
        self.epoch_ns: int | None = None
        # identified joints that rejected messages lacked ('missing_joints'), by topic
        self.missing_joints: set[str] = set()
        self.missing_current_joints: set[str] = set()

    def reject(self, reason: str, count: int | np.integer = 1) -> None:
        self.rejected[reason] += int(count)

    def among(self, stamps_ns, marked: np.ndarray | None = None) -> int:
        """How many of the messages stamped ``stamps_ns`` (int ns, (M,)), those ``marked``
        when given, are counted here (``inside``)."""
        if self.inside is None:
            return int(np.size(stamps_ns) if marked is None else np.count_nonzero(marked))
        keep = self.inside(np.atleast_1d(np.asarray(stamps_ns, dtype=np.int64)))
        return int(np.count_nonzero(keep if marked is None else keep & marked))

    def among_seconds(self, seconds: np.ndarray, marked: np.ndarray | None = None) -> int:
        """``among`` for stamps in s since the epoch (converted only for ``inside``)."""
        stamps = seconds if self.inside is None else self.stamps_ns(np.atleast_1d(seconds))
        return self.among(stamps, marked)

    def malformed(self, log_ns: int | None = None) -> None:
        """A message that could not even be decoded: received, and rejected 'malformed';
        counted here by its log time ``log_ns`` when given (its stamp is unknown)."""
        count = 1 if log_ns is None else self.among([log_ns])
        self.received += count
        self.reject('malformed', count)

    def seconds(self, stamps_ns) -> np.ndarray:
        """Stamps (int ns) as float seconds since the epoch, exact to the nanosecond for spans
        of days."""
        if self.epoch_ns is None:
            self.epoch_ns = int(stamps_ns[0])
        return (np.asarray(stamps_ns, dtype=np.int64) - self.epoch_ns).astype(float) * 1e-9

    def stamps_ns(self, seconds: np.ndarray) -> np.ndarray:
        """Seconds since the epoch back to int64 ns."""
        assert self.epoch_ns is not None   # set by the stream's first stamps (seconds)
        return self.epoch_ns + (seconds * 1e9).round().astype(np.int64)


class LayoutCache:
    """Message layouts per name tuple, the oldest forgotten beyond ``limit`` bytes
    (estimated: the tuple, its strings, the name -> column map and the column arrays)."""

    def __init__(self, limit: int):
        self.limit, self.bytes = int(limit), 0
        self._layouts: dict[tuple, object] = {}

    def __len__(self) -> int:
        return len(self._layouts)

    @staticmethod
    def size(names: tuple) -> int:
        return sys.getsizeof(names) + sum(sys.getsizeof(x) + 100 for x in names)

    def get(self, names: tuple, build):
        """``build(pos)`` for messages with ``names`` (pos: name -> message column), or
        'duplicate_names'."""
        layout = self._layouts.get(names)
        if layout is None:
            pos = {name: i for i, name in enumerate(names)}
            layout = 'duplicate_names' if len(pos) != len(names) else build(pos)
            size = self.size(names)
            while self._layouts and self.bytes + size > self.limit:
                oldest = next(iter(self._layouts))
                self.bytes -= self.size(oldest)
                del self._layouts[oldest]
            if size <= self.limit:
                self._layouts[names] = layout
                self.bytes += size
        return layout


class JointStateValidator:
    """Joint state blocks to Samples in ``robot``'s joint order: layouts checked (names,
    lengths, velocity and effort where needed), rows with a needed value not finite dropped;
    every rejection counted. ``velocity`` 'auto' is decided by the first accepted block."""

    def __init__(self, robot: RobotModel, converter: TorqueConverter, velocity: str,
                 counters: Counters, bounds: PlausibilityBounds, max_names: int = 256,
                 cache_bytes: int = 4 << 20):
        self.robot, self.counters, self.bounds = robot, counters, bounds
        self.max_names = int(max_names)
        self._auto = velocity == 'auto'
        self.velocity_mode: str | None = None if self._auto else velocity
        self._measured_columns = np.array([robot.joint_names.index(j)
                                           for j in converter.measured_joints], dtype=int)
        self.cache = LayoutCache(cache_bytes)

    def reset(self) -> None:
        if self._auto:
            self.velocity_mode = None

    @property
    def velocity_measured(self) -> bool:
        return self.velocity_mode == 'measured'

    def columns(self, names: tuple) -> np.ndarray | slice | str:
        """Message columns in the robot's joint order (a plain slice when the message has
        exactly the robot's joints in its order), or the reason to reject the layout."""
        return self.cache.get(names, self._columns)

    def _columns(self, pos: dict) -> np.ndarray | slice | str:
        if any(j not in pos for j in self.robot.joint_names):
            return 'missing_joints'
        idx = np.array([pos[j] for j in self.robot.joint_names])
        return slice(None) if len(pos) == len(idx) and (idx == np.arange(len(idx))).all() \
            else idx

    def __call__(self, b: JointStateRecord) -> Samples:
        """One block (rows sharing names and layout) validated; rejects counted."""
        n, M = self.robot.dof, np.size(b.stamp_ns)
        self.counters.received += self.counters.among(b.stamp_ns)
        if M == 0:
            return Samples.empty(n)
        k = len(b.names)
        pos, vel, eff = b.position.shape[1], b.velocity.shape[1], b.effort.shape[1]
        reason = idx = None
        if not k or not pos:
            reason = 'empty'
        elif k > self.max_names:
            reason = 'too_many_names'
        elif pos != k or vel not in (0, k) or eff not in (0, k):
            reason = 'length_mismatch'
        else:
            idx = self.columns(tuple(b.names))
            reason = idx if isinstance(idx, str) else None
        if reason is None and self.velocity_mode is None:
            self.velocity_mode = 'measured' if vel else 'differentiate'
        if reason is None and self.velocity_measured and not vel:
            reason = 'missing_velocity'
        if reason is None and len(self._measured_columns) and not eff:
            reason = 'missing_effort'
        if reason is not None:
            self.counters.reject(reason, self.counters.among(b.stamp_ns))
            if reason == 'missing_joints':
                names = set(b.names)
                self.counters.missing_joints.update(
                    j for j in self.robot.joint_names if j not in names)
            return Samples.empty(n)
        assert idx is not None and not isinstance(idx, str)   # no reason: the columns
        nan = np.full((M, n), np.nan) if not (vel and eff) else None
        s = Samples(self.counters.seconds(b.stamp_ns),
                    np.asarray(b.position, dtype=float)[:, idx],
                    np.asarray(b.velocity, dtype=float)[:, idx] if vel or nan is None else nan,
                    np.asarray(b.effort, dtype=float)[:, idx] if eff or nan is None else nan)
        measured = self._measured_columns
        plausible = self.bounds.ok(s.q, s.qd if self.velocity_measured else None,
                                   tau=s.eff[:, measured] if len(measured) else None,
                                   columns=measured)   # False where not finite too
        if plausible.all():
            return s
        finite = np.isfinite(s.q).all(axis=1)
        if self.velocity_measured:
            finite &= np.isfinite(s.qd).all(axis=1)
        if len(measured):
            finite &= np.isfinite(s.eff[:, measured]).all(axis=1)
        self.counters.reject('non_finite', self.counters.among(b.stamp_ns, ~finite))
        self.counters.reject('implausible',
                             self.counters.among(b.stamp_ns, finite & ~plausible))
        return s.select(plausible)


class CurrentValidator:
    """Motor current records to Samples of currents (M, n, 3) and electrical angles (M, n)
    (NaN where not given), in stamp order; rejects counted."""

    def __init__(self, robot: RobotModel, converter: TorqueConverter, counters: Counters,
                 bounds: PlausibilityBounds, max_names: int = 256, cache_bytes: int = 4 << 20):
        self.robot, self.counters, self.bounds = robot, counters, bounds
        self.max_names = int(max_names)
        self._channels = {name: (i, k) for name, i, k in converter.current_channel_slots()}
        self.cache = LayoutCache(cache_bytes)
        configs = converter.configs
        self._turns = np.array([abs(c.pole_pairs * c.gear_ratio) for c in configs])
        self._offsets = np.abs([c.angle_offset for c in configs]) + 2 * math.pi

    @property
    def _angle_bound(self) -> np.ndarray:
        """|electrical angle| that positions within the bounds can give (rad); from the
        bounds as they are now (the node may widen them at run time)."""
        b = self.bounds
        reach = np.maximum(np.abs(b.position_lower), np.abs(b.position_upper))
        return self._turns * reach + self._offsets

    def layout(self, names: tuple) -> tuple | str:
        """For current messages with ``names``: the message columns of the configured channels
        and their flat slots joint * 3 + phase, the columns of each joint's electrical angle
        (its last channel) and those joints; or the reason to reject the layout."""
        return self.cache.get(names, self._layout)

    def _layout(self, pos: dict) -> tuple | str:
        known = sum(name in pos for name in self._channels)
        if known < len(self._channels):
            return 'unknown_channels' if not known else 'missing_joints'
        cols = np.array([pos[name] for name in self._channels])
        slots = np.array([3 * i + k for i, k in self._channels.values()])
        angle = {i: col for col, (i, _) in sorted(zip(cols, self._channels.values()))}
        return cols, slots, np.array(list(angle.values())), np.array(list(angle))

    def __call__(self, records: list) -> Samples:
        n = self.robot.dof
        parts: list[tuple[np.ndarray, ...]] = []
        for b in stack_records(records):
            M, k = np.size(b.stamp_ns), len(b.names)
            eff, pos = b.effort.shape[1], b.position.shape[1]
            layout: tuple | str
            if not k or not eff:
                layout = 'empty'
            elif k > self.max_names:
                layout = 'too_many_names'
            elif eff != k or pos not in (0, k):
                layout = 'length_mismatch'
            else:
                layout = self.layout(tuple(b.names))
            if isinstance(layout, str):
                self.counters.reject(layout, self.counters.among(b.stamp_ns))
                if layout == 'missing_joints':
                    names = set(b.names)
                    self.counters.missing_current_joints.update(
                        self.robot.joint_names[i] for c, (i, _) in self._channels.items()
                        if c not in names)
                continue
            cols, slots, angle_cols, angle_joints = layout
            values = np.asarray(b.effort, dtype=float)[:, cols]
            cur = np.full((M, 3 * n), np.nan)
            cur[:, slots] = values
            theta = np.full((M, n), np.nan)
            if pos:
                theta[:, angle_joints] = np.asarray(b.position, dtype=float)[:, angle_cols]
            part: tuple[np.ndarray, ...] = (self.counters.seconds(b.stamp_ns),
                                            cur.reshape(M, n, 3), theta)
            # an electrical angle is NaN where not given, but never infinite
            finite = np.isfinite(values).all(axis=1) & ~np.isinf(theta).any(axis=1)
            if not finite.all():
                self.counters.reject('non_finite', self.counters.among(b.stamp_ns, ~finite))
                part = tuple(a[finite] for a in part)
            plausible = (self.bounds.currents_ok(part[1])
                         & ~(np.abs(part[2]) > self._angle_bound).any(axis=1))
            if not plausible.all():
                self.counters.reject('implausible',
                                     self.counters.among_seconds(part[0], ~plausible))
                part = tuple(a[plausible] for a in part)
            parts.append(part)
        if not parts:
            return Samples.empty(n, with_currents=True)
        stamps, cur, theta = parts[0] if len(parts) == 1 else (
            np.concatenate(a) for a in zip(*parts))
        if (stamps[1:] < stamps[:-1]).any():
            order = np.argsort(stamps, kind='stable')
            stamps, cur, theta = stamps[order], cur[order], theta[order]
        z = np.zeros((len(stamps), 0))
        return Samples(stamps, z, z, z, cur, theta)
