"""Joint-space reference trajectories with analytic derivatives.

Every trajectory has ``dof``, ``duration`` (s; ``math.inf`` when periodic), ``period`` (s, or
``None`` when not periodic), optional ``joint_names`` and a vectorised
``sample(t (N,)) -> (q, qd, qdd)``, each (N, n), in rad, rad/s, rad/s^2 (m for prismatic joints).
"""
from __future__ import annotations

import io
import math
import os
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence

import numpy as np
from scipy.interpolate import CubicSpline

from identification_node.errors import IdentificationError
from identification_node.safe_yaml import read_yaml
from identification_node.fileio import atomic_write_text

# Table I of Radkhah, Kulic and Croft: rows are harmonics l = 1..5, columns joints 1..6.
_TABLE1_A = [[0.156, 0.064, 0.634, -0.197, 0.499, 0.435],
             [-0.478, -0.335, -0.421, -0.282, -0.135, 0.111],
             [0.078, 0.451, 0.216, 0.173, -0.112, -0.245],
             [-0.388, 0.292, -0.310, 0.154, -0.263, -0.162],
             [-0.070, 1.046, -0.357, -0.095, -0.086, -0.442]]
_TABLE1_B = [[0.088, -0.125, -0.359, 0.408, 0.552, -0.017],
             [0.253, 0.292, 0.112, -0.714, 0.085, -0.178],
             [-0.207, -0.369, -0.128, 0.267, -0.184, 0.340],
             [0.549, 0.557, -0.069, 0.291, -0.065, -0.552],
             [0.150, 0.964, 0.183, 0.751, 0.116, -0.089]]
_TABLE1_Q0 = [0.0, 1.813, -1.184, 0.087, -0.415, 0.124]
# The paper does not state the fundamental frequency. With a 10 s period (0.1 Hz) q(0) equals the
# paper's start points (section IV.C) for joints 2-6 within 0.1 deg (joint 3 up to the sign the
# OCR dropped); peak speeds are then 1.05-2.08 rad/s, inside the A465's limits (velocity does not
# depend on the period; position range grows and acceleration shrinks with it).
TABLE1_PERIOD = 10.0

# MIT direct drive arm test moves (An, Atkeson, Hollerbach 1986, section 3), degrees.
_MIT_MOVES_DEG = [((330.0, 289.1, 230.0), (80.0, 39.1, -10.0)),
                  ((330.0, 269.1, -30.0), (80.0, 19.1, 220.0)),
                  ((80.0, 269.1, -30.0), (330.0, 19.1, 220.0))]
MIT_MOVE_DURATION = 1.3

# Joints without a velocity limit in the description get this one in the default Fourier
# trajectory, and a half range of pi if they have no position limit (rad/s, rad).
DEFAULT_VELOCITY = 2.0
DEFAULT_HALF_RANGE = math.pi


class _Joints(Protocol):
    """A robot as match_joints sees it: a RobotModel, or anything naming its joints."""

    @property
    def joint_names(self) -> Sequence[str]: ...


class _JointLimits(_Joints, Protocol):
    """Joint limits as a RobotModel or ExcitationLimits give them: position (n, 2) rad or
    m, velocity (n,) rad/s or m/s (an acceleration_limits (n,) too when they have one)."""

    @property
    def position_limits(self) -> np.ndarray: ...

    @property
    def velocity_limits(self) -> np.ndarray: ...


class _Robot(_JointLimits, Protocol):
    """A RobotModel as load_trajectory uses it."""

    @property
    def dof(self) -> int: ...


def _as_times(t: np.ndarray | float) -> np.ndarray:
    t = np.atleast_1d(np.asarray(t, dtype=float))
    if t.ndim != 1:
        raise IdentificationError(f'times must be a 1-D array, got shape {t.shape}')
    if not np.all(np.isfinite(t)):
        raise IdentificationError('times contain NaN or inf')
    return t


def _finite(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if not np.all(np.isfinite(a)):
        raise IdentificationError(f'{name} contains NaN or inf')
    return a


class Trajectory:
    """Base class: subclasses set dof, duration, period, joint_names and implement sample."""

    dof: int
    duration: float
    period: float | None = None
    joint_names: list[str] | None = None

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError

    def horizon(self) -> float:
        """Length of one pass: the duration, or one period for periodic trajectories."""
        if math.isfinite(self.duration):
            return self.duration
        assert self.period is not None   # an endless trajectory is periodic
        return float(self.period)


class FourierTrajectory(Trajectory):
    """Finite Fourier series of Radkhah, Kulic and Croft (section II.C), per joint i:
    q_i(t) = sum_l a_il/(w l) sin(w l t) - b_il/(w l) cos(w l t) + q0_i, w = 2 pi / period.

    ``a``, ``b``: (n, H) velocity amplitudes (rad/s), ``q0``: (n,) offsets (rad), period in s.
    """

    period: float

    def __init__(self, a: np.ndarray, b: np.ndarray, q0: np.ndarray, period: float,
                 joint_names: Sequence[str] | None = None):
        a, b, q0 = _finite('a', np.atleast_2d(a)), _finite('b', np.atleast_2d(b)), \
            _finite('q0', np.atleast_1d(q0))
        if a.ndim != 2 or a.shape != b.shape or q0.shape != (a.shape[0],):
            raise IdentificationError(
                f'Fourier coefficients: a {a.shape} and b {b.shape} must both be (n, H) and '
                f'q0 {q0.shape} must be (n,)')
        if a.shape[1] < 1:
            raise IdentificationError('Fourier trajectory needs at least one harmonic')
        try:
            period = float(period)
        except (TypeError, ValueError):
            raise IdentificationError(f'Fourier period must be a number, got {period!r}') \
                from None
        if not (math.isfinite(period) and period > 0):
            raise IdentificationError(f'Fourier period must be finite and > 0, got {period}')
        if joint_names is not None and len(joint_names) != a.shape[0]:
            raise IdentificationError(
                f'{len(joint_names)} joint names for {a.shape[0]} joints of Fourier coefficients')
        self.a, self.b, self.q0, self.period = a, b, q0, period
        self.dof = a.shape[0]
        self.harmonics = a.shape[1]
        self.duration = math.inf
        self.joint_names = None if joint_names is None else [str(j) for j in joint_names]

    @property
    def omega(self) -> float:
        """Fundamental pulsation w = 2 pi / period (rad/s)."""
        return 2.0 * math.pi / self.period

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = _as_times(t)
        wl = self.omega * np.arange(1, self.harmonics + 1)
        s, c = np.sin(np.outer(t, wl)), np.cos(np.outer(t, wl))
        q = s @ (self.a / wl).T - c @ (self.b / wl).T + self.q0
        qd = c @ self.a.T + s @ self.b.T
        qdd = -s @ (self.a * wl).T + c @ (self.b * wl).T
        return q, qd, qdd

    def to_dict(self) -> dict:
        """Plain data for YAML: period, q0, a, b (lists of floats) and joints when known."""
        d = {'type': 'fourier', 'period': self.period, 'q0': self.q0.tolist(),
             'a': self.a.tolist(), 'b': self.b.tolist()}
        if self.joint_names is not None:
            d['joints'] = list(self.joint_names)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> FourierTrajectory:
        """Inverse of to_dict; keys period, q0, a, b, optional joints (and type: fourier)."""
        _check_keys(d, ('period', 'q0', 'a', 'b'), 'Fourier trajectory')
        if d.get('type', 'fourier') != 'fourier':
            raise IdentificationError(f"trajectory type {d['type']!r} is not 'fourier'")
        try:
            a, b, q0 = (np.array(d[k], dtype=float) for k in ('a', 'b', 'q0'))
        except (TypeError, ValueError) as exc:
            raise IdentificationError(f'Fourier trajectory: non-numeric coefficients ({exc})') \
                from None
        return cls(a, b, q0, d['period'], d.get('joints'))

    @classmethod
    def crs_table1(cls, period: float = TABLE1_PERIOD,
                   joint_names: Sequence[str] | None = None) -> FourierTrajectory:
        """Table I of Radkhah, Kulic and Croft (CRS A460/A465, 6 joints, 5 harmonics)."""
        return cls(np.array(_TABLE1_A).T, np.array(_TABLE1_B).T, np.array(_TABLE1_Q0),
                   period, joint_names)

    @classmethod
    def random(cls, limits: _JointLimits | Mapping, harmonics: int = 5, period: float = 10.0,
               seed: int = 0, margin: float = 0.8) -> FourierTrajectory:
        """A seeded random excitation inside ``margin`` times the position and velocity limits
        of a RobotModel or limits mapping (see check_limits), centred in the position range.
        Amplitudes fall as 1/l with the harmonic l."""
        pos, vel, _, names = _limits_of(limits)
        n = pos.shape[0]
        if harmonics < 1 or not 0 < margin <= 1:
            raise IdentificationError('need harmonics >= 1 and 0 < margin <= 1')
        rng = np.random.default_rng(seed)
        decay = 1.0 / np.arange(1, harmonics + 1)
        a = rng.standard_normal((n, harmonics)) * decay
        b = rng.standard_normal((n, harmonics)) * decay
        centre, half = _centre_half(pos)
        half = np.where(np.isfinite(half), half, DEFAULT_HALF_RANGE)
        vmax = np.where(np.isfinite(vel) & (vel > 0), vel, DEFAULT_VELOCITY)
        unit = cls(a, b, np.zeros(n), period)
        q, qd, _ = unit.sample(np.linspace(0.0, period, 4001))
        # q0 centres the excursion in the range, so the half span is what must fit.
        span = 0.5 * (q.max(axis=0) - q.min(axis=0))
        scale = margin * np.minimum(half / span, vmax / np.abs(qd).max(axis=0))
        q0 = centre - scale * 0.5 * (q.max(axis=0) + q.min(axis=0))
        return cls(a * scale[:, None], b * scale[:, None], q0, period, names)


def _check_keys(d: object, keys: Sequence[str], what: str) -> None:
    if not isinstance(d, Mapping):
        raise IdentificationError(f'{what}: expected a mapping with keys {", ".join(keys)}')
    missing = [k for k in keys if k not in d]
    if missing:
        raise IdentificationError(f'{what}: missing keys {missing}')


def _per_move(name: str, value: Sequence[float] | float, m: int) -> np.ndarray:
    """A scalar or one value per move, as a finite (m,) array."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise IdentificationError(f'{name} must be numbers, got {value!r}') from None
    if arr.ndim == 0:
        arr = np.full(m, float(arr))
    if arr.shape != (m,):
        raise IdentificationError(f'{name}: need a number or {m} values, got shape {arr.shape}')
    return _finite(name, arr)


def _quintic_shape(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """h(s) = 10 s^3 - 15 s^4 + 6 s^5 and its first two derivatives (rest-to-rest profile)."""
    s2 = s * s
    return (s2 * s * (10.0 - 15.0 * s + 6.0 * s2), 30.0 * s2 * (1.0 - s) ** 2,
            60.0 * s * (1.0 - s) * (1.0 - 2.0 * s))


class QuinticMoves(Trajectory):
    """Rest-to-rest fifth-order polynomial moves through ``waypoints`` (M+1, n), move k taking
    ``durations[k]`` s, with zero velocity and acceleration at every waypoint; ``rest`` (s, a
    scalar or one per move) holds still after each move. ``repeat`` appends a quintic move back
    to the first waypoint (lasting ``return_duration``, default the longest move) and makes the
    trajectory periodic. Before t = 0 it holds the first waypoint, after the end the last one.
    """

    def __init__(self, waypoints: np.ndarray, durations: Sequence[float] | float,
                 rest: Sequence[float] | float = 0.0, repeat: bool = False,
                 return_duration: float | None = None,
                 joint_names: Sequence[str] | None = None):
        wp = _finite('waypoints', np.asarray(waypoints, dtype=float))
        if wp.ndim != 2 or wp.shape[0] < 2 or wp.shape[1] < 1:
            raise IdentificationError(
                f'waypoints must be (M+1, n) with at least two points, got {wp.shape}')
        m = wp.shape[0] - 1
        dur, rests = _per_move('durations', durations, m), _per_move('rest', rest, m)
        if np.any(dur <= 0) or np.any(rests < 0):
            raise IdentificationError(f'need move durations > 0 and rests >= 0, got '
                                      f'{dur.tolist()} and {rests.tolist()}')
        if repeat:
            back = float(dur.max() if return_duration is None else return_duration)
            if not (math.isfinite(back) and back > 0):
                raise IdentificationError(f'return_duration must be > 0, got {back}')
            wp = np.vstack([wp, wp[:1]])
            dur = np.append(dur, back)
            rests = np.append(rests, rests[-1])
        if joint_names is not None and len(joint_names) != wp.shape[1]:
            raise IdentificationError(
                f'{len(joint_names)} joint names for {wp.shape[1]}-joint waypoints')
        # Segments: each move followed by its rest (a zero-displacement segment).
        starts, ends, lengths = [], [], []
        for k in range(dur.shape[0]):
            starts.append(wp[k])
            ends.append(wp[k + 1])
            lengths.append(dur[k])
            if rests[k] > 0:
                starts.append(wp[k + 1])
                ends.append(wp[k + 1])
                lengths.append(rests[k])
        self.waypoints, self.durations, self.rests = wp, dur, rests
        self._p0, self._dp = np.array(starts), np.array(ends) - np.array(starts)
        self._len = np.array(lengths)
        self._t0 = np.concatenate([[0.0], np.cumsum(self._len)[:-1]])
        total = float(self._len.sum())
        self.repeat = bool(repeat)
        self.dof = wp.shape[1]
        self.period = total if repeat else None
        self.duration = math.inf if repeat else total
        self.joint_names = None if joint_names is None else [str(j) for j in joint_names]

    @classmethod
    def from_moves(cls, moves: Sequence[tuple[Sequence[float] | np.ndarray,
                                              Sequence[float] | np.ndarray]],
                   durations: Sequence[float] | float, rest: float = 0.0,
                   transfer_duration: float | None = None, repeat: bool = False,
                   joint_names: Sequence[str] | None = None) -> QuinticMoves:
        """Moves given as (start, end) pairs; where a move does not start where the previous
        one ended, a quintic transfer move joins them. A transfer lasts ``transfer_duration``,
        by default the previous move's duration stretched by the ratio of the largest joint
        displacements (transfer / previous move) when larger, so its peak speed stays at or
        below the moves'."""
        pairs = [(np.asarray(s, float), np.asarray(e, float)) for s, e in moves]
        if not pairs:
            raise IdentificationError('no moves given')
        dur = _per_move('durations', durations, len(pairs))
        points, lengths = [pairs[0][0], pairs[0][1]], [float(dur[0])]
        for k in range(1, len(pairs)):
            start, end = pairs[k]
            if not np.allclose(start, points[-1], rtol=0, atol=1e-12):
                points.append(start)
                lengths.append(cls._transfer_time(points[-2], start, pairs[k - 1],
                                                  float(dur[k - 1]), transfer_duration))
            points.append(end)
            lengths.append(float(dur[k]))
        back = None
        if repeat and not np.allclose(points[-1], points[0], rtol=0, atol=1e-12):
            back = cls._transfer_time(points[-1], points[0], pairs[-1], float(dur[-1]),
                                      transfer_duration)
        elif repeat:
            points, back = points[:-1], lengths.pop()  # the last move already returns
        return cls(np.array(points), lengths, rest, repeat, back, joint_names)

    @staticmethod
    def _transfer_time(a: np.ndarray, b: np.ndarray, prev: tuple[np.ndarray, np.ndarray],
                       prev_duration: float, fixed: float | None) -> float:
        if fixed is not None:
            return float(fixed)
        span = float(np.abs(prev[1] - prev[0]).max())
        need = float(np.abs(b - a).max())
        return prev_duration * max(1.0, need / span) if span > 0 else prev_duration

    @classmethod
    def mit_paper(cls, rest: float = 0.0, transfer_duration: float | None = None,
                  repeat: bool = False,
                  joint_names: Sequence[str] | None = None) -> QuinticMoves:
        """The three 1.3 s test moves of An, Atkeson and Hollerbach (section 3), in radians
        (the paper's joint angles, used as given), joined by quintic transfer moves (see
        from_moves) since each move starts away from the previous one's end."""
        moves = [(np.radians(s), np.radians(e)) for s, e in _MIT_MOVES_DEG]
        return cls.from_moves(moves, MIT_MOVE_DURATION, rest, transfer_duration, repeat,
                              joint_names)

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = _as_times(t)
        total = float(self._len.sum())
        if self.repeat:
            t = np.mod(t, total)
        k = np.clip(np.searchsorted(self._t0, t, side='right') - 1, 0, self._len.size - 1)
        s = np.clip((t - self._t0[k]) / self._len[k], 0.0, 1.0)
        h, hd, hdd = _quintic_shape(s)
        dp, T = self._dp[k], self._len[k][:, None]
        q = self._p0[k] + dp * h[:, None]
        return q, dp * hd[:, None] / T, dp * hdd[:, None] / T ** 2


class SampledTrajectory(Trajectory):
    """A trajectory from samples ``t`` (N,), strictly increasing, shifted to start at 0, and
    ``q`` (N, n); derivatives from a cubic spline (not-a-knot ends). Outside the sampled span
    it holds the end positions with zero velocity and acceleration."""

    def __init__(self, t: np.ndarray, q: np.ndarray, joint_names: Sequence[str] | None = None):
        t = _finite('t', np.asarray(t, dtype=float))
        q = _finite('q', np.asarray(q, dtype=float))
        if q.ndim == 1:
            q = q[:, None]
        if t.ndim != 1 or q.ndim != 2 or q.shape[0] != t.shape[0] or q.shape[1] < 1:
            raise IdentificationError(f'sampled trajectory: t {t.shape} and q {q.shape} must be '
                                      '(N,) and (N, n)')
        if t.shape[0] < 2:
            raise IdentificationError('sampled trajectory needs at least 2 samples')
        if np.any(np.diff(t) <= 0):
            k = int(np.argmax(np.diff(t) <= 0))
            raise IdentificationError(f'sample times must increase strictly (row {k + 1})')
        if joint_names is not None and len(joint_names) != q.shape[1]:
            raise IdentificationError(f'{len(joint_names)} joint names for {q.shape[1]} columns')
        self.t, self.q = t - t[0], q
        self.dof = q.shape[1]
        self.duration = float(self.t[-1])
        self.joint_names = None if joint_names is None else [str(j) for j in joint_names]
        self._spline = CubicSpline(self.t, q, axis=0)
        self._d1, self._d2 = self._spline.derivative(1), self._spline.derivative(2)

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = _as_times(t)
        inside = ((t >= 0) & (t <= self.duration))[:, None]
        tc = np.clip(t, 0.0, self.duration)
        return (self._spline(tc), np.where(inside, self._d1(tc), 0.0),
                np.where(inside, self._d2(tc), 0.0))

    def to_csv(self, path: str | os.PathLike) -> Path:
        """Write columns t, then one per joint (header: t and the joint names, or q1..qn),
        atomically."""
        names = self.joint_names or [f'q{i + 1}' for i in range(self.dof)]
        buf = io.StringIO()
        np.savetxt(buf, np.column_stack([self.t, self.q]), delimiter=',', fmt='%.17g',
                   header=','.join(['t'] + names), comments='')
        return atomic_write_text(path, buf.getvalue())

    @classmethod
    def from_csv(cls, path: str | os.PathLike) -> SampledTrajectory:
        """Read a CSV written by to_csv (first column time in s, header row with names)."""
        try:
            with open(path) as f:
                header = f.readline().strip()
                data = np.loadtxt(f, delimiter=',', ndmin=2)
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise IdentificationError(f'cannot read trajectory CSV {path}: {exc}') from None
        names = [h.strip() for h in header.split(',')]
        if len(names) < 2 or names[0].lower() not in ('t', 'time'):
            raise IdentificationError(
                f'trajectory CSV {path}: header must be t,<joint>,... got {header!r}')
        if data.shape[1] != len(names):
            raise IdentificationError(f'trajectory CSV {path}: {data.shape[1]} columns, header '
                                      f'names {len(names)}')
        position = [k for k, h in enumerate(names) if h.endswith('.position')]
        if position:   # write_motion_csv's layout: the positions, derivatives from the spline
            return cls(data[:, 0], data[:, position],
                       [names[k][:-len('.position')] for k in position])
        return cls(data[:, 0], data[:, 1:], names[1:])


class FramedTrajectory(Trajectory):
    """A periodic trajectory run for ``periods`` whole periods between smooth ramps from and
    back to the configuration ``start`` at rest.

    With p the periodic trajectory, u(t) = p(t - ramp_in) - start and w the quintic
    smoothstep (0 -> 1 with zero first and second derivatives at both ends):

    - ramp in, 0 <= t < ramp_in: q = start + w(t / ramp_in) u(t);
    - periodic part, ramp_in <= t <= ramp_in + periods * period: q = p(t - ramp_in), from the
      periodic trajectory's phase 0;
    - ramp out, over ramp_out s: q = start + (1 - w(s)) u(t), s the fraction of the ramp.

    q, qd and qdd are continuous; the motion starts and ends at ``start`` with zero velocity
    and acceleration, and a ramp's positions lie between ``start`` and p(t) (inside any
    position range holding both). Before 0 and after the end it holds ``start``.
    """

    def __init__(self, periodic: Trajectory, start: np.ndarray | None = None,
                 ramp_in: float = 1.0, ramp_out: float | None = None, periods: int = 1):
        if periodic.period is None:
            raise IdentificationError('framing needs a periodic trajectory')
        if isinstance(periods, bool) or not isinstance(periods, (int, np.integer)) \
                or periods < 1:
            raise IdentificationError(f'periods must be an integer >= 1, got {periods!r}')
        ramp_out = ramp_in if ramp_out is None else ramp_out
        for name, v in (('ramp_in', ramp_in), ('ramp_out', ramp_out)):
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating)) \
                    or not (math.isfinite(v) and v > 0):
                raise IdentificationError(f'{name} must be a duration > 0 s, got {v!r}')
        if start is None:
            start = getattr(periodic, 'q0', None)
            if start is None:
                raise IdentificationError('give the start configuration of the framing')
        start = _finite('start', np.atleast_1d(np.asarray(start, dtype=float)))
        if start.shape != (periodic.dof,):
            raise IdentificationError(f'start configuration has {start.size} values for '
                                      f'{periodic.dof} joints')
        self.periodic, self.start = periodic, start
        self.ramp_in, self.ramp_out = float(ramp_in), float(ramp_out)
        self.periods = int(periods)
        self.dof = periodic.dof
        self.joint_names = periodic.joint_names
        self.harmonics = getattr(periodic, 'harmonics', None)
        self.period = None
        self.duration = self.ramp_in + self.periods * float(periodic.period) + self.ramp_out

    @property
    def periodic_window(self) -> tuple[float, float]:
        """(start, end) of the periodic part, s from the start of the trajectory."""
        assert self.periodic.period is not None   # checked by __init__
        return self.ramp_in, self.ramp_in + self.periods * float(self.periodic.period)

    def parts(self) -> dict:
        """Durations (s) of the ramp in, the periodic part and the ramp out, and the total."""
        t0, t1 = self.periodic_window
        return {'ramp_in': self.ramp_in, 'periodic': t1 - t0, 'ramp_out': self.ramp_out,
                'total': self.duration}

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = _as_times(t)
        t0, t1 = self.periodic_window
        tc = np.clip(t, 0.0, self.duration)
        p, pd, pdd = self.periodic.sample(tc - t0)
        s_in = np.clip(tc / self.ramp_in, 0.0, 1.0)
        s_out = np.clip((tc - t1) / self.ramp_out, 0.0, 1.0)
        h_in, hd_in, hdd_in = _quintic_shape(s_in)
        h_out, hd_out, hdd_out = _quintic_shape(s_out)
        after = tc > t1
        w = np.where(after, 1.0 - h_out, h_in)[:, None]
        wd = np.where(after, -hd_out / self.ramp_out, hd_in / self.ramp_in)[:, None]
        wdd = np.where(after, -hdd_out / self.ramp_out ** 2,
                       hdd_in / self.ramp_in ** 2)[:, None]
        u = p - self.start
        return (self.start + w * u, w * pd + wd * u, w * pdd + 2.0 * wd * pd + wdd * u)

    def to_dict(self) -> dict:
        """The periodic trajectory's to_dict plus 'framing': start, ramp_in, ramp_out,
        periods (and the parts' durations)."""
        if not hasattr(self.periodic, 'to_dict'):
            raise IdentificationError('the periodic trajectory cannot be written as YAML')
        return {**self.periodic.to_dict(),
                'framing': {'start': self.start.tolist(), 'ramp_in': self.ramp_in,
                            'ramp_out': self.ramp_out, 'periods': self.periods,
                            'durations': self.parts()}}

    @classmethod
    def from_dict(cls, d: Mapping) -> FramedTrajectory:
        """Inverse of to_dict (a Fourier trajectory with a 'framing' mapping)."""
        f: Any = d.get('framing') if isinstance(d, Mapping) else None   # YAML data
        _check_keys(f, ('start', 'ramp_in', 'ramp_out', 'periods'), 'framing')
        periodic = FourierTrajectory.from_dict(d)
        try:
            start = np.array(f['start'], dtype=float)
        except (TypeError, ValueError):
            raise IdentificationError(f"framing start must be numbers, got {f['start']!r}") \
                from None
        return cls(periodic, start, f['ramp_in'], f['ramp_out'], f['periods'])


def write_motion_csv(path: str | os.PathLike, t: np.ndarray, q: np.ndarray, qd: np.ndarray,
                     qdd: np.ndarray, joint_names: Sequence[str]) -> Path:
    """Write samples as CSV, header ``t,<joint>.position,...,<joint>.velocity,...,
    <joint>.acceleration,...`` (s, rad, rad/s, rad/s^2; m for prismatic joints), atomically."""
    names = [str(j) for j in joint_names]
    header = ['t'] + [f'{j}.{kind}' for kind in ('position', 'velocity', 'acceleration')
                      for j in names]
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack([t, q, qd, qdd]), delimiter=',', fmt='%.17g',
               header=','.join(header), comments='')
    return atomic_write_text(path, buf.getvalue())


def _limits_of(limits: _JointLimits | Mapping
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list | None]:
    """(position (n,2), velocity (n,), acceleration (n,), joint names) of a RobotModel or a
    mapping with keys position, velocity and optional acceleration; missing -> inf."""
    if hasattr(limits, 'position_limits') and not isinstance(limits, Mapping):
        pos = np.asarray(limits.position_limits, float)
        vel = np.asarray(limits.velocity_limits, float)
        acc = np.asarray(getattr(limits, 'acceleration_limits', np.full(pos.shape[0], np.inf)),
                         float)
        return pos, vel, acc, list(limits.joint_names)
    if not isinstance(limits, Mapping) or 'position' not in limits:
        raise IdentificationError('limits: give a RobotModel or a mapping with keys position '
                                  '(n, 2), velocity (n,), acceleration (n,)')
    pos = np.asarray(limits['position'], float)
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise IdentificationError(f'position limits must be (n, 2), got {pos.shape}')
    n = pos.shape[0]
    vel = np.asarray(limits.get('velocity', np.full(n, np.inf)), float)
    acc = np.asarray(limits.get('acceleration', np.full(n, np.inf)), float)
    if vel.shape != (n,) or acc.shape != (n,):
        raise IdentificationError(f'velocity {vel.shape} and acceleration {acc.shape} limits '
                                  f'must be ({n},)')
    return pos, vel, acc, limits.get('joints')


def _centre_half(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre and half width of position ranges (n, 2); unlimited joints: 0 and inf."""
    finite = np.isfinite(pos).all(axis=1)
    p = np.where(finite[:, None], pos, 0.0)
    return 0.5 * (p[:, 0] + p[:, 1]), np.where(finite, 0.5 * (p[:, 1] - p[:, 0]), np.inf)


def check_limits(traj: Trajectory, limits: _JointLimits | Mapping,
                 t: np.ndarray | None = None) -> dict:
    """Worst limit ratios of ``traj`` over times ``t`` (default: 2001 samples of one pass).

    Position ratio: |q - centre| / half range (1 = at a limit); velocity and acceleration:
    |qd| / limit, |qdd| / limit. Missing, infinite or non-positive limits give 0. Returns
    {'position', 'velocity', 'acceleration': worst ratios (float), 'worst_joint': {kind: joint
    index}, 'per_joint': {kind: (n,) ratios}}.
    """
    pos, vel, acc, _ = _limits_of(limits)
    if pos.shape[0] != traj.dof:
        raise IdentificationError(f'{pos.shape[0]} joint limits for a {traj.dof}-joint '
                                  'trajectory')
    if t is None:
        t = np.linspace(0.0, traj.horizon(), 2001)
    q, qd, qdd = traj.sample(t)

    def ratio(x: np.ndarray, lim: np.ndarray) -> np.ndarray:
        ok = np.isfinite(lim) & (lim > 0)
        return np.where(ok, x.max(axis=0) / np.where(ok, lim, 1.0), 0.0)

    centre, half = _centre_half(pos)
    per = {'position': ratio(np.abs(q - centre), half), 'velocity': ratio(np.abs(qd), vel),
           'acceleration': ratio(np.abs(qdd), acc)}
    out: dict[str, Any] = {k: float(v.max()) for k, v in per.items()}
    out['worst_joint'] = {k: int(np.argmax(v)) for k, v in per.items()}
    out['per_joint'] = per
    return out


def match_joints(traj: Trajectory, robot: _Joints, source: str = 'trajectory') -> Trajectory:
    """``traj`` with its columns in the robot's joint order (by joint names when it has them);
    IdentificationError when the joints do not match."""
    joints = list(robot.joint_names)
    names = traj.joint_names
    if names is None:
        if traj.dof != len(joints):
            raise IdentificationError(f'{source} has {traj.dof} joints, robot has '
                                      f'{len(joints)} ({joints})')
        return traj
    if sorted(names) != sorted(joints):
        raise IdentificationError(f'{source} names joints {names}; the robot '
                                  f'identifies {joints}')
    order = [names.index(j) for j in joints]
    if isinstance(traj, FourierTrajectory):
        return FourierTrajectory(traj.a[order], traj.b[order], traj.q0[order], traj.period,
                                 joints)
    if isinstance(traj, SampledTrajectory):
        return SampledTrajectory(traj.t, traj.q[:, order], joints)
    if isinstance(traj, FramedTrajectory):
        return FramedTrajectory(match_joints(traj.periodic, robot, source), traj.start[order],
                                traj.ramp_in, traj.ramp_out, traj.periods)
    return traj


def load_trajectory(spec: str, robot: _Robot, seed: int = 0) -> Trajectory:
    """A trajectory for ``robot`` (a RobotModel) from a name or a file.

    'paper_moves': the MIT arm's quintic moves (3 joints); 'table1': the CRS A460/A465 Table I
    Fourier series (6 joints); 'fourier': a 5-harmonic Fourier series of random coefficients
    (``seed``) inside 80 % of the robot's position and velocity limits; a .yaml/.yml file of
    Fourier coefficients (keys period, q0, a, b, optional joints; with a 'framing' mapping, the
    FramedTrajectory that ramps in and out of it, as ``excite`` writes) or a .csv file (t, one
    column per joint, header with names; or write_motion_csv's layout, whose positions are
    used).
    """
    spec = str(spec).strip()
    n = robot.dof
    if spec in ('paper_moves', 'table1'):
        need = 3 if spec == 'paper_moves' else 6
        if n != need:
            raise IdentificationError(f"trajectory '{spec}' is for {need} joints; the robot "
                                      f'identifies {n} ({robot.joint_names})')
        if spec == 'paper_moves':
            return QuinticMoves.mit_paper(joint_names=robot.joint_names)
        return FourierTrajectory.crs_table1(joint_names=robot.joint_names)
    if spec == 'fourier':
        return FourierTrajectory.random(robot, seed=seed)
    path = Path(spec)
    suffix = path.suffix.lower()
    if suffix not in ('.yaml', '.yml', '.csv'):
        raise IdentificationError(
            f"unknown trajectory {spec!r}: use 'paper_moves', 'table1', 'fourier', or a "
            '.yaml/.yml (Fourier coefficients) or .csv (samples) file')
    if not path.is_file():
        raise IdentificationError(f'trajectory file {spec} does not exist')
    if suffix == '.csv':
        return match_joints(SampledTrajectory.from_csv(path), robot, f'trajectory {spec}')
    data = read_yaml(path, f'trajectory YAML {spec}')
    if isinstance(data, Mapping) and 'framing' in data:
        return match_joints(FramedTrajectory.from_dict(data), robot, f'trajectory {spec}')
    return match_joints(FourierTrajectory.from_dict(data), robot, f'trajectory {spec}')
