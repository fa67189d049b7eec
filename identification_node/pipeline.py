"""The identification pipeline: stamped joint states and currents in, base-parameter estimate out.

One plain class, fed by the ROS node (its processing thread copies the queued messages in) and
by bag replay alike. ``add_joint_state`` / ``add_currents`` queue records (``add_joint_states`` a
block of joint states of one layout, as bag replay reads them; ``add_joint_state_cdr`` /
``add_currents_cdr`` the JointState messages of a poll as CDR bytes, as the node takes them);
``process`` does the numerical work for everything queued, in batches:

1. validation (runs of messages sharing names and layout stacked into blocks checked at once;
   counted rejections by reason, never an exception or a NaN),
2. stamp order (out of order or repeated stamps are rejected; a backward jump larger than
   ``restart_jump`` is taken as a restarted stream),
3. alignment of motor currents to joint states by header stamp (nearest within
   ``align_tolerance``; a joint state waits for the first current stamped at or after it, or
   ``hold_time`` at most),
4. torque from the configured torque sources,
5. the fixed-lag smoother on positions (and measured velocities) and on torque alike, giving
   q, qd, qdd and tau for the window centre, ``delay`` seconds behind the newest sample,
6. regressor, base regressor, recursive least squares (unless frozen), predicted torque.

"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Iterator, Mapping, Sequence

import numpy as np

from .bagio import JointStateDecoder, decode_joint_states
from .errors import IdentificationError
from .estimators import RecursiveLeastSquares, ResidualStatistics, _information
from .identifiability import BaseParameters
from .records import JointStateRecord
from .robot import RobotModel
from .signals import FixedLagSmoother, smoothing_noise_gain
from .torque import JointTorqueConfig, TorqueConverter

REJECT_REASONS = (
    'empty', 'length_mismatch', 'duplicate_names', 'missing_joints', 'non_finite',
    'missing_velocity', 'missing_effort', 'out_of_order', 'repeated_stamp', 'no_current',
    'unmatched_current', 'unknown_channels', 'stream_restart', 'malformed',
)


@dataclass
class PipelineConfig:
    """Settings of the pipeline (the node's ROS parameters map onto these fields)."""
    torque: Mapping[str, JointTorqueConfig] = field(default_factory=dict)
    forgetting: float = 1.0
    half_window: int = 10
    smoother_order: int = 3
    max_gap: float = 0.05
    velocity: str = 'auto'
    align_tolerance: float = 0.002
    hold_time: float = 0.1
    restart_jump: float = 1.0
    update_batch: int = 50
    joint_noise_std: Sequence[float] = ()
    coulomb_exclusion_speed: float = 0.1
    converged_ratio: float = 0.1
    max_condition: float = 1e8
    min_samples: int = 1000

    def validate(self, dof: int) -> None:
        """Raise IdentificationError naming the first bad field."""
        checks = [
            ('forgetting', 0.9 <= self.forgetting <= 1.0, 'in [0.9, 1.0]'),
            ('half_window', int(self.half_window) >= 1, '>= 1'),
            ('smoother_order', 2 <= int(self.smoother_order) <= min(4, 2 * self.half_window),
             'in [2, min(4, 2 * half_window)]'),
            ('max_gap', self.max_gap > 0, '> 0'),
            ('velocity', self.velocity in ('auto', 'measured', 'differentiate'),
             "'auto', 'measured' or 'differentiate'"),
            ('align_tolerance', self.align_tolerance > 0, '> 0'),
            ('hold_time', self.hold_time > 0, '> 0'),
            ('restart_jump', self.restart_jump > 0, '> 0'),
            ('update_batch', int(self.update_batch) >= 1, '>= 1'),
            ('joint_noise_std', len(self.joint_noise_std) in (0, dof)
             and all(s > 0 for s in self.joint_noise_std), f'empty or {dof} values > 0'),
            ('coulomb_exclusion_speed', self.coulomb_exclusion_speed >= 0, '>= 0'),
            ('converged_ratio', self.converged_ratio > 0, '> 0'),
            ('max_condition', self.max_condition > 1, '> 1'),
            ('min_samples', int(self.min_samples) >= 0, '>= 0'),
        ]
        for name, ok, expected in checks:
            value = getattr(self, name)
            if not ok or (isinstance(value, float) and not math.isfinite(value)):
                raise IdentificationError(f'parameter {name} = {value!r} must be {expected}')


@dataclass
class PipelineOutput:
    """Samples processed by one ``process`` call, stamped with their own header stamps
    (``stamps_ns``, int64 ns)."""
    stamps_ns: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    measured: np.ndarray
    predicted: np.ndarray

    @classmethod
    def empty(cls, dof: int) -> PipelineOutput:
        z = np.empty((0, dof))
        return cls(np.empty(0, dtype=np.int64), z, z, z, z, z)


@dataclass
class EstimateReport:
    """The running estimate: base parameters with standard deviations, and health figures."""
    names: list
    values: np.ndarray
    stddev: np.ndarray
    num_samples: int
    stamp: float
    condition_number: float
    min_eigenvalue: float
    residual_rms: np.ndarray
    converged: bool
    frozen: bool


class IdentificationPipeline:
    """Identification of ``robot``'s base parameters from streamed samples (see module doc)."""

    def __init__(self, robot: RobotModel, config: PipelineConfig | None = None,
                 base: BaseParameters | None = None):
        self.robot = robot
        self.config = config or PipelineConfig()
        self.config.validate(robot.dof)
        unknown = set(self.config.torque) - set(robot.joint_names)
        if unknown:
            raise IdentificationError(f'torque sources name unknown joints {sorted(unknown)}')
        self.base = base or BaseParameters.from_robot(robot)
        configs = [self.config.torque.get(j, JointTorqueConfig()) for j in robot.joint_names]
        self.converter = TorqueConverter(robot.joint_names, configs)
        self._channels = {name: (i, k) for name, i, k in self.converter.current_channel_slots()}
        self._measured_columns = np.array([robot.joint_names.index(j)
                                           for j in self.converter.measured_joints], dtype=int)
        # The torque is smoothed too, so residuals are correlated over the window: the
        # covariance uses their long-run variance, from sums over blocks of 8 windows; until
        # there are enough blocks, white raw noise is assumed (see smoothing_noise_gain).
        self._block = 8 * (2 * int(self.config.half_window) + 1)
        self._white_scale = 1.0 / smoothing_noise_gain(int(self.config.half_window),
                                                       int(self.config.smoother_order))
        # Inverse-variance weights per joint (RLS weights multiply squared residuals).
        self._weights = (np.asarray(self.config.joint_noise_std, dtype=float) ** -2
                         if len(self.config.joint_noise_std) else None)
        self._js_queue: collections.deque = collections.deque()
        self._cur_queue: collections.deque = collections.deque()
        self._index_cache: dict[tuple, np.ndarray | slice | str] = {}
        self._channel_cache: dict[tuple, tuple | str] = {}
        self._work: dict[str, np.ndarray] = {}
        # columns of [Y | tau] that make the rows [Yb | tau]
        self._row_columns = np.append(self.base.base_index, robot.num_params)
        self._all_measured = len(self._measured_columns) == robot.dof
        # one decoder per stream (each keeps its stream's last names)
        self._js_decoder, self._cur_decoder = JointStateDecoder(), JointStateDecoder()
        self.frozen = False
        self.reset()

    # -- input: called on the ROS side, so nothing but a copy ------------------------------------
    def add_joint_state(self, record: JointStateRecord) -> None:
        self._js_queue.append(record)

    def add_joint_states(self, block: JointStateRecord) -> None:
        """Joint states sharing names and layout, at once: stamp_ns (M,) int64, position,
        velocity and effort (M, k) ((M, 0) when absent). The same as adding the M records
        one by one (bag replay reads such blocks)."""
        M = np.shape(block.stamp_ns)
        arrays = (block.position, block.velocity, block.effort)
        if len(M) != 1 or any(np.ndim(a) != 2 or len(a) != M[0] for a in arrays):
            raise IdentificationError(
                f'joint state block: stamps {M} and arrays '
                f'{[np.shape(a) for a in arrays]}; expected (M,) and (M, k)')
        self._js_queue.append(block._replace(stamp_ns=np.asarray(block.stamp_ns)))

    def add_joint_state_cdr(self, messages: list[bytes]) -> None:
        """sensor_msgs/JointState messages as CDR bytes, in arrival order; decoded when
        processed (one that cannot be decoded is counted 'malformed')."""
        self._js_queue.append(messages)

    def add_currents(self, record: JointStateRecord) -> None:
        self._cur_queue.append(record)

    def add_currents_cdr(self, messages: list[bytes]) -> None:
        """Motor current messages (sensor_msgs/JointState) as CDR bytes, in arrival order;
        decoded when processed (one that cannot be decoded is counted 'malformed')."""
        self._cur_queue.append(messages)

    @property
    def pending(self) -> int:
        return len(self._js_queue) + len(self._cur_queue)

    # -- state ----------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the estimate and all buffered data; counters restart too."""
        n, b = self.robot.dof, self.base.num_base
        self._rls = RecursiveLeastSquares(b, forgetting=self.config.forgetting)
        self._residuals = ResidualStatistics(b, n, self._block)
        self._updates: list[tuple] = []
        self._pending_samples = 0
        self.rejected = dict.fromkeys(REJECT_REASONS, 0)
        self.restarts = 0
        self.excluded_rows = 0
        self.received = 0
        self.used = 0
        self._velocity_mode: str | None = (None if self.config.velocity == 'auto'
                                           else self.config.velocity)
        self._last_stamp = -math.inf
        self._last_output_stamp = math.nan
        self._epoch_ns: int | None = None
        self._newest_js = -math.inf
        self._pending_js = _Samples.empty(n)
        self._currents = _Samples.empty(n, with_currents=True)
        self._restart_smoother()
        for q in (self._js_queue, self._cur_queue):
            q.clear()

    def _restart_smoother(self) -> None:
        """Forget the smoother's window (a new stream): it is made on first use."""
        self._smoother: FixedLagSmoother | None = None

    @property
    def delay(self) -> float:
        """Smoother delay in samples; multiply by the sample period for seconds."""
        return float(self.config.half_window)

    # -- processing -----------------------------------------------------------------------------
    def process(self, flush: bool = False) -> PipelineOutput:
        """Work through everything queued. ``flush`` decides joint states still waiting for
        currents (end of a bag) instead of holding them for ``hold_time``."""
        n = self.robot.dof
        js = self._decoded(self._take(self._js_queue), self._js_decoder)
        cur = self._decoded(self._take(self._cur_queue), self._cur_decoder)
        if cur:
            self._currents = self._currents.concat(self._convert_currents(cur))
        for block in _blocks(js):
            new = self._convert_block(block)
            # the conversion may restart the stream (dropping what is pending): read after
            self._pending_js = self._pending_js.concat(new)
        ready = self._decide_ready(flush)
        if ready is None or len(ready.stamps) == 0:
            return PipelineOutput.empty(n)
        return self._estimate(ready)

    @staticmethod
    def _take(queue: collections.deque) -> list:
        out = []
        while queue:
            out.append(queue.popleft())
        return out

    def _decoded(self, queued: list, decoder: JointStateDecoder) -> list:
        """Queued records with the lists of CDR messages among them decoded into records, or
        into blocks where they share a layout (bagio.decode_joint_states; the messages that
        cannot be decoded counted as received and 'malformed')."""
        if all(type(m) is not list for m in queued):
            return queued
        out = []
        for item in queued:
            if type(item) is not list:
                out.append(item)
                continue
            for record in decode_joint_states(item, decoder):
                if isinstance(record, IdentificationError):
                    self.add_malformed()
                else:
                    out.append(record)
        return out

    def _seconds(self, stamps_ns: list[int]) -> np.ndarray:
        """Stamps as float seconds since the pipeline's epoch (its first stamp), exact to the
        nanosecond for spans of days."""
        if self._epoch_ns is None:
            self._epoch_ns = int(stamps_ns[0])
        return (np.asarray(stamps_ns, dtype=np.int64) - self._epoch_ns).astype(float) * 1e-9

    def _reject(self, reason: str, count: int = 1) -> None:
        self.rejected[reason] += int(count)

    def add_malformed(self) -> None:
        """Count a message that could not even be decoded (received, and rejected)."""
        self.received += 1
        self._reject('malformed')

    @staticmethod
    def _layout(cache: dict, names: tuple, build):
        """``build(pos)`` for messages with ``names`` (pos: name -> message column), or
        'duplicate_names'; kept in ``cache`` per names (at most 256 layouts)."""
        layout = cache.get(names)
        if layout is None:
            pos = {name: i for i, name in enumerate(names)}
            layout = 'duplicate_names' if len(pos) != len(names) else build(pos)
            if len(cache) > 256:
                cache.clear()
            cache[names] = layout
        return layout

    def _joint_index(self, names: tuple) -> np.ndarray | slice | str:
        """Message columns in the robot's joint order (a plain slice when the message has
        exactly the robot's joints in its order), or the reason to reject the layout."""
        return self._layout(self._index_cache, names, self._joint_columns)

    def _joint_columns(self, pos: dict) -> np.ndarray | slice | str:
        if any(j not in pos for j in self.robot.joint_names):
            return 'missing_joints'
        idx = np.array([pos[j] for j in self.robot.joint_names])
        return slice(None) if len(pos) == len(idx) and (idx == np.arange(len(idx))).all() \
            else idx

    def _convert_block(self, b: JointStateRecord) -> _Samples:
        """Validate a block of joint states (rows sharing names and layout, so one check
        decides for all of them) in the robot's joint order, by stamp; rejects are counted."""
        n, M = self.robot.dof, len(b.stamp_ns)
        self.received += M
        if M == 0:
            return _Samples.empty(n)
        k = len(b.names)
        pos, vel, eff = b.position.shape[1], b.velocity.shape[1], b.effort.shape[1]
        reason = idx = None
        if not k or not pos:
            reason = 'empty'
        elif pos != k or vel not in (0, k) or eff not in (0, k):
            reason = 'length_mismatch'
        else:
            idx = self._joint_index(tuple(b.names))
            reason = idx if isinstance(idx, str) else None
        if reason is None and self._velocity_mode is None:
            self._velocity_mode = 'measured' if vel else 'differentiate'
        if reason is None and self._velocity_mode == 'measured' and not vel:
            reason = 'missing_velocity'
        if reason is None and len(self._measured_columns) and not eff:
            reason = 'missing_effort'
        if reason is not None:
            self._reject(reason, M)
            return _Samples.empty(n)
        nan = np.full((M, n), np.nan) if not (vel and eff) else None
        s = _Samples(self._seconds(b.stamp_ns), np.asarray(b.position, dtype=float)[:, idx],
                     np.asarray(b.velocity, dtype=float)[:, idx] if vel else nan,
                     np.asarray(b.effort, dtype=float)[:, idx] if eff else nan)
        return self._finite_in_order(s)

    def _finite_in_order(self, s: _Samples) -> _Samples:
        """Rows with the needed values finite (the others counted 'non_finite'), in order."""
        finite = np.isfinite(s.q).all(axis=1)
        if self._velocity_mode == 'measured':
            finite &= np.isfinite(s.qd).all(axis=1)
        if len(self._measured_columns):
            finite &= np.isfinite(s.eff[:, self._measured_columns]).all(axis=1)
        if not finite.all():
            self._reject('non_finite', np.count_nonzero(~finite))
            s = s.select(finite)
        return self._in_order(s)

    def _in_order(self, s: _Samples) -> _Samples:
        """Keep samples whose stamp exceeds every stamp accepted before; a backward jump of
        more than ``restart_jump`` starts a new stream (the smoother restarts)."""
        t = s.stamps
        if len(t) and t[0] > self._last_stamp and (len(t) == 1 or (t[1:] > t[:-1]).all()):
            self._last_stamp = float(t[-1])   # the usual case: all in order
            return s
        parts = []
        while len(s.stamps):
            prior = np.maximum.accumulate(np.concatenate([[self._last_stamp], s.stamps]))[:-1]
            jump = np.flatnonzero(prior - s.stamps > self.config.restart_jump)
            k = int(jump[0]) if len(jump) else len(s.stamps)
            head, prior = s.head(k), prior[:k]
            keep = head.stamps > prior
            self._reject('repeated_stamp', np.count_nonzero(head.stamps == prior))
            self._reject('out_of_order', np.count_nonzero(head.stamps < prior))
            parts.append(head.select(keep))
            if len(head.stamps):
                self._last_stamp = max(self._last_stamp, float(head.stamps.max()))
            if k == len(s.stamps):
                break
            self._start_new_stream(parts)
            self._last_stamp = -math.inf
            s = s.tail(k)
        out = _Samples.empty(self.robot.dof)
        for part in parts:
            out = out.concat(part)
        return out

    def _start_new_stream(self, parts: list) -> None:
        """The stream restarted with earlier stamps: what the old stream left pending (not yet
        through the smoother) is dropped and counted as 'stream_restart'. Currents more than
        ``restart_jump`` older than the old stream's newest stamp already belong to the new
        stream (they may come in the same batch) and are kept."""
        self.restarts += 1
        self._reject('stream_restart', sum(len(p.stamps) for p in parts)
                     + len(self._pending_js.stamps))
        parts.clear()
        self._restart_smoother()
        self._pending_js = _Samples.empty(self.robot.dof)
        self._currents = self._currents.select(
            self._currents.stamps < self._last_stamp - self.config.restart_jump)
        self._newest_js = -math.inf

    def _channel_layout(self, names: tuple) -> tuple | str:
        """For current messages with ``names``: the message columns of the configured channels
        and their flat slots joint * 3 + phase, the columns of each joint's electrical angle
        (its last channel) and those joints; or the reason to reject the layout."""
        return self._layout(self._channel_cache, names, self._channel_columns)

    def _channel_columns(self, pos: dict) -> tuple | str:
        known = sum(name in pos for name in self._channels)
        if known < len(self._channels):
            return 'unknown_channels' if not known else 'missing_joints'
        cols = np.array([pos[name] for name in self._channels])
        slots = np.array([3 * i + k for i, k in self._channels.values()])
        angle = {i: col for col, (i, _) in sorted(zip(cols, self._channels.values()))}
        return cols, slots, np.array(list(angle.values())), np.array(list(angle))

    def _convert_currents(self, records: list) -> _Samples:
        """Validate current records into stamps, currents (M, n, 3) and electrical angles
        (M, n) (NaN where not given), by stamp; rejects are counted."""
        n = self.robot.dof
        parts = []
        for b in _blocks(records):
            M, k = len(b.stamp_ns), len(b.names)
            eff, pos = b.effort.shape[1], b.position.shape[1]
            if not k or not eff:
                layout = 'empty'
            elif eff != k or pos not in (0, k):
                layout = 'length_mismatch'
            else:
                layout = self._channel_layout(tuple(b.names))
            if isinstance(layout, str):
                self._reject(layout, M)
                continue
            cols, slots, angle_cols, angle_joints = layout
            values = np.asarray(b.effort, dtype=float)[:, cols]
            cur = np.full((M, 3 * n), np.nan)
            cur[:, slots] = values
            theta = np.full((M, n), np.nan)
            if pos:
                theta[:, angle_joints] = np.asarray(b.position, dtype=float)[:, angle_cols]
            part = (self._seconds(b.stamp_ns), cur.reshape(M, n, 3), theta)
            finite = np.isfinite(values).all(axis=1)
            if not finite.all():
                self._reject('non_finite', np.count_nonzero(~finite))
                part = tuple(a[finite] for a in part)
            parts.append(part)
        if not parts:
            return _Samples.empty(n, with_currents=True)
        stamps, cur, theta = parts[0] if len(parts) == 1 else (
            np.concatenate(a) for a in zip(*parts))
        if (stamps[1:] < stamps[:-1]).any():
            order = np.argsort(stamps, kind='stable')
            stamps, cur, theta = stamps[order], cur[order], theta[order]
        z = np.zeros((len(stamps), 0))
        return _Samples(stamps, z, z, z, cur, theta)

    def _decide_ready(self, flush: bool) -> _Samples | None:
        """Joint states whose currents are known (or will never come), with torque attached."""
        s = self._pending_js
        if len(s.stamps) == 0:
            return None
        self._newest_js = max(self._newest_js, float(s.stamps[-1]))
        if not self.converter.needs_currents:
            self._pending_js = _Samples.empty(self.robot.dof)
            return self._with_torque(s, None, None)
        cur = self._currents
        newest_cur = cur.stamps[-1] if len(cur.stamps) else -math.inf
        if flush:
            decided = np.ones(len(s.stamps), dtype=bool)
        else:
            # Currents come in stamp order: once one at or after t is in, the nearest to t is
            # among those in (the newest before t, the first after), so t is decided.
            decided = ((s.stamps <= newest_cur)
                       | (s.stamps <= self._newest_js - self.config.hold_time))
        # decided is a prefix: stamps are increasing.
        k = int(np.count_nonzero(decided))
        if k == 0:
            return None
        if k == len(s.stamps):
            ready, self._pending_js = s, _Samples.empty(self.robot.dof)
        else:
            ready, self._pending_js = s.head(k), s.tail(k)
        match = self._nearest(cur.stamps, ready.stamps)
        ok = match >= 0
        self._reject('no_current', np.count_nonzero(~ok))
        used = np.zeros(len(cur.stamps), dtype=bool)
        used[match[ok]] = True
        # Currents older than what the next joint state could still match are done with.
        horizon = (self._pending_js.stamps[0] if len(self._pending_js.stamps)
                   else ready.stamps[-1]) - self.config.align_tolerance
        if flush:
            horizon = math.inf
        done = cur.stamps < horizon
        self._reject('unmatched_current', np.count_nonzero(done & ~used & ~cur.used))
        cur.used |= used
        self._currents = cur.select(~done) if done.any() else cur
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
        return np.where(np.abs(ref[pick] - t) <= self.config.align_tolerance, pick, -1)

    def _with_torque(self, s: _Samples, currents, theta) -> _Samples:
        if self._all_measured:
            s.tau = s.eff   # every joint's torque measured: checked finite on the way in
            return s
        s.tau = self.converter.torque(s.q, measured=s.eff, currents=currents, theta_e=theta)
        ok = np.isfinite(s.tau).all(axis=1)
        if ok.all():
            return s
        self._reject('non_finite', np.count_nonzero(~ok))
        return s.select(ok)

    def _estimate(self, s: _Samples) -> PipelineOutput:
        measured_velocity = self._velocity_mode == 'measured'
        channels = np.hstack([s.q, s.qd, s.tau] if measured_velocity else [s.q, s.tau])
        t, q, qd, qdd, tau, rows, predicted = self._smooth_and_regress(
            s.stamps, channels, measured_velocity)
        return self._finish(t, q, qd, qdd, tau, rows, predicted)

    def _finish(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                tau: np.ndarray, rows: np.ndarray, predicted: np.ndarray) -> PipelineOutput:
        """The smoother's outputs of a run: rows gathered for the RLS (unless frozen), the
        output stamped in integer ns."""
        n = self.robot.dof
        if len(t) == 0:
            return PipelineOutput.empty(n)
        if not self.frozen:
            self._gather(rows, self._row_weights(t, qd, qdd))
            self.used += len(t)
        stamps_ns = self._epoch_ns + np.round(t * 1e9).astype(np.int64)
        self._last_output_stamp = float(stamps_ns[-1]) * 1e-9
        return PipelineOutput(stamps_ns, q, qd, qdd, tau, predicted)

    def _smooth_and_regress(self, t: np.ndarray, x: np.ndarray, measured_velocity: bool
                            ) -> tuple[np.ndarray, ...]:
        """Smoother outputs t_c, q, qd, qdd, tau, the rows [Yb | tau] (N, n, b + 1) and the
        predicted torque Yb theta."""
        n = self.robot.dof
        if self._smoother is None:
            self._smoother = FixedLagSmoother(
                x.shape[1], half_window=int(self.config.half_window),
                order=int(self.config.smoother_order), max_gap=self.config.max_gap)
        t, x, xd, xdd = self._smoother.push_checked(t, x)
        q = x[:, :n]
        qd, qdd = (x[:, n:2 * n], xd[:, n:2 * n]) if measured_velocity else (xd[:, :n],
                                                                             xdd[:, :n])
        tau = x[:, -n:]
        # [Y | tau] (N, n, p + 1): the regressor and the torque, for the base rows at once
        p, b = self.robot.num_params, self.base.num_base
        Yt = self._buffer('regressor', (len(t), n, p + 1))
        self.robot.regressor(q, qd, qdd, out=Yt[:, :, :p], checked=True)
        Yt[:, :, p] = tau
        # rows applied within this call live in a reused work array (as Yt's)
        now = not self._updates and len(t) >= self.config.update_batch
        rows = self._buffer('rows', (len(t), n, b + 1)) if now else np.empty((len(t), n, b + 1))
        np.take(Yt, self._row_columns, axis=2, out=rows, mode='clip')
        return t, q, qd, qdd, tau, rows, rows[:, :, :b] @ self._rls.theta

    def _gather(self, rows: np.ndarray, w: np.ndarray | None) -> None:
        """Queue the rows [Yb | tau] (N, n, b + 1) of a batch, weighted by ``w`` (in place),
        for the RLS and residual statistics; update them once ``update_batch`` samples are
        gathered."""
        used = None
        if w is not None:
            root = np.sqrt(np.broadcast_to(w, rows.shape[:2]))
            rows *= root[:, :, None]
            used = root > 0
        self._updates.append((rows, used))
        self._pending_samples += len(rows)
        if self._pending_samples >= self.config.update_batch:
            self._apply_updates()

    def _apply_updates(self) -> None:
        """Feed the rows gathered since the last update to the RLS and residual statistics in
        one batch (exactly what sample-by-sample updates give, at a fraction of the cost): the
        rows are checked once and their per-joint information is formed once for both
        (without forgetting)."""
        if not self._updates:
            return
        parts, self._updates, self._pending_samples = self._updates, [], 0
        rows = parts[0][0] if len(parts) == 1 else np.concatenate([u[0] for u in parts])
        used = None if all(u[1] is None for u in parts) else np.concatenate([
            np.ones(u[0].shape[:2], dtype=bool) if u[1] is None else u[1] for u in parts])
        information = _information(rows)
        if not np.isfinite(information).all():  # the checked path names the culprit
            b = self.base.num_base
            self._rls.update(rows[:, :, :b], rows[:, :, b], used)  # (rows weighted already)
            self._residuals.add(rows[:, :, :b], rows[:, :, b])
            return
        N, n = rows.shape[:2]
        self._rls._update_rows(lambda i, j: rows[i:j], N, n, used, information)
        self._residuals._add_rows(rows, information)

    def _buffer(self, name: str, shape: tuple) -> np.ndarray:
        """A work array of ``shape``, reused across batches (grown when needed): allocating
        megabytes afresh every batch costs more in page faults than the arithmetic on them."""
        size = math.prod(shape)
        buf = self._work.get(name)
        if buf is None or buf.size < size:
            self._work[name] = buf = np.empty(size)
        return buf[:size].reshape(shape)

    @property
    def rls(self) -> RecursiveLeastSquares:
        """The recursive estimator, up to date with every processed sample."""
        self._apply_updates()
        return self._rls

    @property
    def residuals(self) -> ResidualStatistics:
        """Residual statistics, up to date with every processed sample."""
        self._apply_updates()
        return self._residuals

    def _row_weights(self, t: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray | None:
        """Per (sample, joint) weights: the joint weights, and zero for a joint's equation while
        its smoothing window may hold a velocity reversal, |qd| < v_min + |qdd| T_half, when
        Coulomb friction is identified: there the friction torque turns faster than the
        smoother resolves (and stiction is not modelled at all)."""
        if 'fc' not in self.robot.extras:
            return self._weights
        period = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        reach = self.config.coulomb_exclusion_speed + np.abs(qdd) * period * self.delay
        slow = np.abs(qd) < reach
        self.excluded_rows += int(np.count_nonzero(slow))
        w = np.ones(qd.shape) if self._weights is None else np.tile(self._weights, (len(qd), 1))
        w[slow] = 0.0
        return w

    # -- results --------------------------------------------------------------------------------
    def residual_rms(self) -> np.ndarray:
        """Per-joint RMS of the (smoothed, weighted) measured minus predicted torque over the
        samples used, for the current estimate (N m)."""
        return np.sqrt(self.residuals.variance(self.rls.theta))

    def relative_error(self, theta: np.ndarray | None = None) -> np.ndarray:
        """Per-joint 100 ||tau - Yb theta|| / ||tau|| (percent) over the samples used, for
        ``theta`` (default: the current estimate)."""
        return self.residuals.relative_error(self.rls.theta if theta is None else theta)

    def noise_variance(self) -> np.ndarray:
        """Per-joint long-run variance of the torque residual (N m)^2: the noise the estimate
        averages. White raw noise is assumed until 10 blocks of samples are in."""
        theta = self.rls.theta
        if self.residuals.blocks >= 10:
            return self.residuals.long_run_variance(theta)
        return self.residuals.variance(theta) * self._white_scale

    @property
    def covariance(self) -> np.ndarray:
        """Covariance of the base estimate: the RLS covariance, whose noise level comes from
        the smoothed residuals, rescaled to their long-run variance."""
        var = self.residuals.variance(self.rls.theta)
        scale = (float(self.noise_variance().sum() / var.sum()) if np.nansum(var) > 0
                 else self._white_scale)
        return self.rls.covariance * scale

    @property
    def stddev(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    def excitation(self) -> tuple[float, float]:
        """(condition number, smallest eigenvalue) of the information the data brought, without
        the forgetting regulariser: how well the motion excites the base parameters."""
        ev = np.linalg.eigvalsh(self.rls.data_information)
        if ev[-1] <= 0:
            return math.inf, 0.0
        return (float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf), float(max(ev[0], 0.0))

    def converged(self) -> bool:
        """Excited, enough samples, and the parameter uncertainty contributes less than
        ``converged_ratio`` of the torque noise on every joint."""
        return self._converged(self.excitation()[0], self.covariance)

    def _converged(self, condition: float, covariance: np.ndarray) -> bool:
        if self.rls.num_samples < self.config.min_samples:
            return False
        if not condition <= self.config.max_condition:
            return False
        count = max(self.residuals.count, 1)
        # Mean predicted-torque variance from the covariance: trace(P G_j) / N per joint.
        var = np.einsum('pq,nqp->n', covariance, self.residuals.gram) / count
        noise = np.sqrt(self.noise_variance())
        return bool(np.all(np.sqrt(np.maximum(var, 0)) <= self.config.converged_ratio * noise))

    def estimate(self) -> EstimateReport:
        """A snapshot of the running estimate."""
        cond, min_eig = self.excitation()
        cov = self.covariance
        return EstimateReport(
            names=list(self.base.names), values=self.rls.theta.copy(),
            stddev=np.sqrt(np.diag(cov)), num_samples=int(self.rls.num_samples),
            stamp=self._last_output_stamp, condition_number=cond, min_eigenvalue=min_eig,
            residual_rms=self.residual_rms(),
            converged=self._converged(cond, cov), frozen=self.frozen)

    def standard_parameters(self) -> np.ndarray:
        """The full standard parameter vector closest to the model's own that reproduces the
        base estimate (for the identified URDF)."""
        return self.base.closest_standard(self.rls.theta, self.robot.phi_model)


def _blocks(records: list) -> Iterator[JointStateRecord]:
    """The queued joint states as blocks: blocks as they are, and each run of single records
    sharing names and array lengths stacked into one (the live node's usual batch)."""
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


class _Samples:
    """Validated samples in stamp order (internal): stamps (M,) s, q, qd, eff (M, n); for
    currents also currents (M, n, 3), theta (M, n) and the used flags (M,); tau once known."""
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
    def empty(cls, n: int, with_currents: bool = False) -> _Samples:
        z = np.empty((0, n))
        if with_currents:
            return cls(np.empty(0), z, z, z, np.empty((0, n, 3)), z)
        return cls(np.empty(0), z, z, z)

    def _arrays(self) -> list:
        return [getattr(self, name) for name in self.__slots__]

    def _map(self, fn) -> _Samples:
        return _Samples(*[None if a is None else fn(a) for a in self._arrays()])

    def select(self, mask: np.ndarray) -> _Samples:
        return self._map(lambda a: a[mask])

    def head(self, k: int) -> _Samples:
        return self._map(lambda a: a[:k])

    def tail(self, k: int) -> _Samples:
        return self._map(lambda a: a[k:])

    def concat(self, other: _Samples) -> _Samples:
        if len(self.stamps) == 0:
            return other
        if len(other.stamps) == 0:
            return self
        merged = _Samples(*[None if a is None else np.concatenate([a, b])
                            for a, b in zip(self._arrays(), other._arrays())])
        if self.currents is not None and other.stamps[0] < self.stamps[-1]:
            # Current messages may interleave: keep the buffer sorted by stamp (both parts are
            # sorted, so only when they overlap).
            return merged.select(np.argsort(merged.stamps, kind='stable'))
        return merged
