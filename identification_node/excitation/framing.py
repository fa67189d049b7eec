"""Framing a periodic excitation by ramps from and back to rest, and checking the framed
trajectory's collisions densely."""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from identification_node.config import Excitation
from identification_node.errors import IdentificationError
from identification_node.excitation.limits import (LIMIT_KINDS, VERIFY_RATE, ExcitationLimits,
                                                   numbers, worst_ratio, limit_ratios)
from identification_node.excitation.problem import no_tick
from identification_node.excitation.trajectories import FourierTrajectory, FramedTrajectory

__all__ = ['COLLISION_RATE', 'DEFAULT_PERIODS', 'RAMP_GROWTH', 'RAMP_MAX', 'RAMP_MIN',
           'check_start', 'frame_excitation', 'framed_clearance']

DEFAULT_PERIODS = Excitation.periods   # periods of the periodic part between the ramps
COLLISION_RATE = 100.0      # Hz: collision check of the final trajectory (and 10 ms at most)
RAMP_MIN = 0.5              # s: shortest ramp tried; then RAMP_GROWTH times longer each try
RAMP_GROWTH = 1.15
RAMP_MAX = 120.0            # s: longest ramp tried
_CHUNK = 4096               # grid times sampled at once by framed_clearance


def _ramp(periodic: FourierTrajectory, robot, limits: ExcitationLimits, start: np.ndarray,
          side: str, phis: Sequence[np.ndarray] | None) -> float:
    """The shortest ramp (RAMP_MIN, growing by RAMP_GROWTH up to RAMP_MAX s, in 0.1 s steps)
    between ``start`` at rest and the periodic motion within every limit."""
    T = RAMP_MIN
    worst = None
    while T <= RAMP_MAX:
        T = math.ceil(T * 10.0 - 1e-9) / 10.0
        framed = FramedTrajectory(periodic, start, T, T, 1)
        t0, t1 = framed.periodic_window
        window = (0.0, t0) if side == 'in' else (t1, t1 + T)
        ratios = limit_ratios(framed, robot, limits, 0, 0, phis, window)
        if worst_ratio(ratios) <= 1.0:   # the periodic part keeps VERIFY_RATIO: room to blend in
            return T
        worst = max(LIMIT_KINDS, key=lambda k: ratios[k])
        T *= RAMP_GROWTH
    names: Sequence[str | int] = periodic.joint_names or list(range(periodic.dof))
    raise IdentificationError(
        f'infeasible: no ramp {side} of at most {RAMP_MAX:g} s between the start configuration '
        f'and the motion stays within the limits ({worst} of '
        f'{names[ratios["worst_joint"][worst]]} at {ratios[worst]:.3g} of its limit with '
        'margin)')


def frame_excitation(periodic: FourierTrajectory, robot, limits: ExcitationLimits,
                     start: np.ndarray | None = None, periods: int = DEFAULT_PERIODS,
                     phis: Sequence[np.ndarray] | None = None) -> FramedTrajectory:
    """``periods`` periods of ``periodic`` framed by the shortest ramps from and back to
    ``start`` (default its offset q0) at rest that keep every limit of ``limits``
    (position, velocity, acceleration, and torque under ``phis``)."""
    start = periodic.q0 if start is None else check_start(start, limits)
    t_in = _ramp(periodic, robot, limits, start, 'in', phis)
    t_out = _ramp(periodic, robot, limits, start, 'out', phis)
    return FramedTrajectory(periodic, start, t_in, t_out, periods)


def check_start(start: Sequence[float] | np.ndarray, limits: ExcitationLimits) -> np.ndarray:
    """The start configuration (n,) rad, checked inside the position limits of ``limits``."""
    q = numbers('start configuration', start).reshape(-1)
    if q.shape != (limits.dof,) or not np.all(np.isfinite(q)):
        raise IdentificationError(f'start configuration needs {limits.dof} finite values '
                                  f'(joints {", ".join(limits.joint_names)}), got '
                                  f'{np.asarray(start).tolist()}')
    lo, hi = limits.position_limits.T
    out = [f'{j} {v:.4g} not in [{a:.4g}, {b:.4g}]'
           for j, v, a, b in zip(limits.joint_names, q, lo, hi) if not a <= v <= b]
    if out:
        raise IdentificationError('start configuration outside the position limits with '
                                  'their margin: ' + '; '.join(out))
    return q


def framed_clearance(framed: FramedTrajectory, robot, checker, travel: float = 0.005,
                     tick: Callable[[], None] = no_tick) -> dict:
    """CollisionChecker.clearance of a framed trajectory: its ramps and one period (the others
    repeat it), each pair checked at times that advance conservatively. No point of the arm
    (reach: the sum of the joint offsets + 0.5 m) moves faster than v = reach * peak summed
    joint speed, so from a time where a pair's distance is d (the hulls' lower bound), it is
    next checked (d - min_distance) / v later or sooner: between them it comes no closer
    than the minimum distance. The times lie on a uniform grid of each part with steps of at
    most ``travel`` / v (no point moves more than ``travel`` m between a pair's checks) and
    1 / COLLISION_RATE s at most between a pair's checks: far pairs are checked seldom."""
    t0, t1 = framed.periodic_window
    assert framed.periodic.period is not None   # a framed trajectory's is periodic
    period = float(framed.periodic.period)
    probe = np.linspace(0.0, framed.duration, max(2001, int(framed.duration * VERIFY_RATE)))
    speed = float(np.abs(framed.sample(probe)[1]).sum(axis=1).max())
    reach = sum(float(np.linalg.norm(p.translation)) for p in robot.model.jointPlacements) + 0.5
    v = max(reach * speed, 1e-12)
    shortest, longest = min(travel / v, 1.0 / COLLISION_RATE), 1.0 / COLLISION_RATE
    bounds = checker.hulls()
    configs: list[np.ndarray] = []
    entries: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []   # (sample, pair, bound)
    for a, b in [(0.0, t0), (t0, t0 + period), (t1, framed.duration)]:
        last = max(1, math.ceil((b - a) / shortest))   # grid a + (b - a) k / last, k <= last
        h = (b - a) / last
        most = max(1, int(longest / h)) if h > 0 else 1
        # each pair is due at the latest by due_at and checked with the others from ready_at
        # (half its step early: at most twice as often, on far fewer distinct times)
        due_at = np.zeros(bounds.num_pairs, dtype=int)
        ready_at = due_at.copy()
        chunk, first = np.zeros((0, robot.dof)), 0    # the grid's positions from ``first``
        while due_at.size and (k := int(due_at.min())) <= last:
            if not first <= k < first + len(chunk):
                first = k
                chunk = framed.sample(a + h * np.arange(k, min(k + _CHUNK, last + 1)))[0]
            due = np.flatnonzero(ready_at <= k)
            configs.append(chunk[k - first])
            d = bounds.pair_distances(configs[-1], due)
            entries.append((np.full(due.size, len(configs) - 1), due, d))
            steps = np.clip((d - checker.min_distance) // (v * h), 1, most).astype(int)
            due_at[due] = last + 1 if k == last else np.minimum(last, k + steps)
            ready_at[due] = np.minimum(due_at[due], k + (steps + 1) // 2)
            tick()
    if not entries:
        return checker.clearance(np.zeros((0, robot.dof)))
    return checker.clearance(np.array(configs), tuple(np.concatenate(e) for e in zip(*entries)))
