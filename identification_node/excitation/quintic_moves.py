"""Rest-to-rest quintic moves through waypoints, and the MIT direct drive arm's test moves."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.excitation.trajectory_base import (Trajectory, as_times, finite,
                                                            quintic_shape)

__all__ = ['MIT_MOVE_DURATION', 'QuinticMoves']

# MIT direct drive arm test moves (An, Atkeson, Hollerbach 1986, section 3), degrees.
_MIT_MOVES_DEG = [((330.0, 289.1, 230.0), (80.0, 39.1, -10.0)),
                  ((330.0, 269.1, -30.0), (80.0, 19.1, 220.0)),
                  ((80.0, 269.1, -30.0), (330.0, 19.1, 220.0))]
MIT_MOVE_DURATION = 1.3


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
    return finite(name, arr)


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
        wp = finite('waypoints', np.asarray(waypoints, dtype=float))
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
        t = as_times(t)
        total = float(self._len.sum())
        if self.repeat:
            t = np.mod(t, total)
        k = np.clip(np.searchsorted(self._t0, t, side='right') - 1, 0, self._len.size - 1)
        s = np.clip((t - self._t0[k]) / self._len[k], 0.0, 1.0)
        h, hd, hdd = quintic_shape(s)
        dp, T = self._dp[k], self._len[k][:, None]
        q = self._p0[k] + dp * h[:, None]
        return q, dp * hd[:, None] / T, dp * hdd[:, None] / T ** 2
