"""The joint-space trajectory interface, shared argument checks and limit ratios.

Every trajectory has ``dof``, ``duration`` (s; ``math.inf`` when periodic), ``period`` (s, or
``None`` when not periodic), optional ``joint_names`` and a vectorised
``sample(t (N,)) -> (q, qd, qdd)``, each (N, n), in rad, rad/s, rad/s^2 (m for prismatic joints).
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Protocol, Sequence

import numpy as np

from identification_node.errors import IdentificationError

__all__ = ['DEFAULT_HALF_RANGE', 'DEFAULT_VELOCITY', 'JointLimits', 'Joints', 'RobotJoints',
           'Trajectory', 'as_times', 'centre_half', 'check_keys', 'check_limits', 'finite',
           'limits_of', 'quintic_shape']

# Joints without a velocity limit in the description get this one in the default Fourier
# trajectory, and a half range of pi if they have no position limit (rad/s, rad).
DEFAULT_VELOCITY = 2.0
DEFAULT_HALF_RANGE = math.pi


class Joints(Protocol):
    """A robot as match_joints sees it: a RobotModel, or anything naming its joints."""

    @property
    def joint_names(self) -> Sequence[str]: ...


class JointLimits(Joints, Protocol):
    """Joint limits as a RobotModel or ExcitationLimits give them: position (n, 2) rad or
    m, velocity (n,) rad/s or m/s (an acceleration_limits (n,) too when they have one)."""

    @property
    def position_limits(self) -> np.ndarray: ...

    @property
    def velocity_limits(self) -> np.ndarray: ...


class RobotJoints(JointLimits, Protocol):
    """A RobotModel as load_trajectory uses it."""

    @property
    def dof(self) -> int: ...


def as_times(t: np.ndarray | float) -> np.ndarray:
    t = np.atleast_1d(np.asarray(t, dtype=float))
    if t.ndim != 1:
        raise IdentificationError(f'times must be a 1-D array, got shape {t.shape}')
    if not np.all(np.isfinite(t)):
        raise IdentificationError('times contain NaN or inf')
    return t


def finite(name: str, a: np.ndarray) -> np.ndarray:
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


def check_keys(d: object, keys: Sequence[str], what: str) -> None:
    if not isinstance(d, Mapping):
        raise IdentificationError(f'{what}: expected a mapping with keys {", ".join(keys)}')
    missing = [k for k in keys if k not in d]
    if missing:
        raise IdentificationError(f'{what}: missing keys {missing}')


def quintic_shape(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """h(s) = 10 s^3 - 15 s^4 + 6 s^5 and its first two derivatives (rest-to-rest profile)."""
    s2 = s * s
    return (s2 * s * (10.0 - 15.0 * s + 6.0 * s2), 30.0 * s2 * (1.0 - s) ** 2,
            60.0 * s * (1.0 - s) * (1.0 - 2.0 * s))


def limits_of(limits: JointLimits | Mapping
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


def centre_half(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre and half width of position ranges (n, 2); unlimited joints: 0 and inf."""
    finite = np.isfinite(pos).all(axis=1)
    p = np.where(finite[:, None], pos, 0.0)
    return 0.5 * (p[:, 0] + p[:, 1]), np.where(finite, 0.5 * (p[:, 1] - p[:, 0]), np.inf)


def check_limits(traj: Trajectory, limits: JointLimits | Mapping,
                 t: np.ndarray | None = None) -> dict:
    """Worst limit ratios of ``traj`` over times ``t`` (default: 2001 samples of one pass).

    Position ratio: |q - centre| / half range (1 = at a limit); velocity and acceleration:
    |qd| / limit, |qdd| / limit. Missing, infinite or non-positive limits give 0. Returns
    {'position', 'velocity', 'acceleration': worst ratios (float), 'worst_joint': {kind: joint
    index}, 'per_joint': {kind: (n,) ratios}}.
    """
    pos, vel, acc, _ = limits_of(limits)
    if pos.shape[0] != traj.dof:
        raise IdentificationError(f'{pos.shape[0]} joint limits for a {traj.dof}-joint '
                                  'trajectory')
    if t is None:
        t = np.linspace(0.0, traj.horizon(), 2001)
    q, qd, qdd = traj.sample(t)

    def ratio(x: np.ndarray, lim: np.ndarray) -> np.ndarray:
        ok = np.isfinite(lim) & (lim > 0)
        return np.where(ok, x.max(axis=0) / np.where(ok, lim, 1.0), 0.0)

    centre, half = centre_half(pos)
    per = {'position': ratio(np.abs(q - centre), half), 'velocity': ratio(np.abs(qd), vel),
           'acceleration': ratio(np.abs(qdd), acc)}
    out: dict[str, Any] = {k: float(v.max()) for k, v in per.items()}
    out['worst_joint'] = {k: int(np.argmax(v)) for k, v in per.items()}
    out['per_joint'] = per
    return out
