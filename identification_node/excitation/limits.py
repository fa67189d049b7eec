"""Joint limits of excitation design (:class:`ExcitationLimits`) and the limit ratios of a
trajectory (1 = at a limit).

Limits (:class:`ExcitationLimits`), each with a margin kept free (default
DEFAULT_LIMIT_MARGIN, 10 %; ExcitationLimits.with_margin): joint positions (with the offset
q0), velocities and accelerations on a grid of one period, and joint torques (inverse dynamics
under the robot's own parameters and, when given, an estimate's) at the criterion samples.
Each (joint, kind) is one smooth constraint on the Kreisselmeier-Steinhauser maximum of its
ratios to the limit (see problem.DesignProblem); with a collision.CollisionChecker, one more
per checked geometry pair on its distances. URDFs carry no acceleration limits: the default is
``DEFAULT_ACCELERATION_RATE`` (2 /s) times the velocity limit, i.e. full speed reached in 0.5 s
(6.3 rad/s^2 on the CRS A465's first three joints; Table I's trajectory peaks at 6.1 rad/s^2);
every limit the description lacks is recorded in ``ExcitationLimits.assumed``. Every result is
every limit the description lacks is recorded in ``ExcitationLimits.assumed``.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.safe_yaml import read_yaml
from identification_node.excitation.trajectory_base import (DEFAULT_VELOCITY, Trajectory,
                                                            check_limits)

DEFAULT_ACCELERATION_RATE = 2.0  # 1/s: default acceleration limit = rate * velocity limit
PRISMATIC_VELOCITY = 0.5    # m/s, prismatic joints without a velocity limit
VERIFY_RATE = 400.0         # Hz: kinematic check of a framed trajectory (torques at half)
VERIFY_POINTS = 4001        # kinematic check of the result over one period
EFFORT_POINTS = 2001        # torque check of the result over one period
LIMIT_KINDS = ('position', 'velocity', 'acceleration', 'effort')


@dataclass
class ExcitationLimits:
    """Joint limits for excitation design, in the robot's joint order (SI units).

    position_limits (n, 2) [lo, hi] (+-inf: none), velocity_limits (n,), acceleration_limits
    (n,) (finite, > 0), effort_limits (n,) (inf: no torque limit). ``assumed``: the limits the
    robot description did not give, {joint: {kind: value assumed (None: no limit)}}. Works with
    :func:`~identification_node.excitation.trajectory_base.check_limits`.
    """

    joint_names: list[str]
    position_limits: np.ndarray
    velocity_limits: np.ndarray
    acceleration_limits: np.ndarray
    effort_limits: np.ndarray
    assumed: dict = field(default_factory=dict)

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    @classmethod
    def from_robot(cls, robot, effort: bool = True) -> ExcitationLimits:
        """The robot's limits; joints without a velocity limit get DEFAULT_VELOCITY (rad/s) or
        PRISMATIC_VELOCITY (m/s), accelerations DEFAULT_ACCELERATION_RATE times the velocity
        limit; ``effort=False`` (or no effort limit in the description) drops the torque
        limit. What the description lacks is recorded in ``assumed``."""
        prismatic = np.asarray(robot.prismatic, dtype=bool)
        given_vel = np.asarray(robot.velocity_limits, dtype=float)
        has_vel = np.isfinite(given_vel) & (given_vel > 0)
        vel = np.where(has_vel, given_vel,
                       np.where(prismatic, PRISMATIC_VELOCITY, DEFAULT_VELOCITY))
        given_eff = np.asarray(robot.effort_limits, dtype=float)
        has_eff = np.isfinite(given_eff) & (given_eff > 0)
        eff = np.where(has_eff & bool(effort), given_eff, np.inf)
        pos = np.array(robot.position_limits, dtype=float)
        # pinocchio fills a URDF joint without <limit> with +-max float: no limit either
        has_pos = np.isfinite(pos).all(axis=1) & (np.abs(pos) < 1e30).all(axis=1)
        pos[~has_pos] = [-np.inf, np.inf]
        acc = DEFAULT_ACCELERATION_RATE * vel
        assumed: dict = {}
        for i, j in enumerate(robot.joint_names):
            entry: dict[str, float | None] = {}
            if not has_pos[i]:
                entry['position'] = None
            if not has_vel[i]:
                entry['velocity'] = float(vel[i])
            entry['acceleration'] = float(acc[i])   # URDF has no acceleration limits
            if effort and not has_eff[i]:
                entry['effort'] = None
            assumed[j] = entry
        return cls(list(robot.joint_names), pos, vel, acc, eff, assumed)

    def updated(self, overrides: Mapping[str, Any], source: str = 'limits') -> ExcitationLimits:
        """A copy with per-joint overrides ``{joint: {position: [lo, hi], velocity: v,
        acceleration: a, effort: e}}``. Each key is optional; position [-.inf, .inf] and effort
        .inf remove the limit; a default acceleration limit follows a new velocity limit."""
        if not isinstance(overrides, Mapping):
            raise IdentificationError(f'{source}: expected a mapping of joint names to limits, '
                                      f'got {type(overrides).__name__}')
        out = ExcitationLimits(list(self.joint_names), self.position_limits.copy(),
                               self.velocity_limits.copy(), self.acceleration_limits.copy(),
                               self.effort_limits.copy(),
                               {j: dict(v) for j, v in self.assumed.items()})
        for joint, spec in overrides.items():
            if joint not in self.joint_names:
                raise IdentificationError(f'{source}: unknown joint {joint!r} (joints: '
                                          f'{", ".join(self.joint_names)})')
            if not isinstance(spec, Mapping):
                raise IdentificationError(f'{source}: limits of {joint} must be a mapping with '
                                          f'keys {", ".join(LIMIT_KINDS)}')
            unknown = set(spec) - set(LIMIT_KINDS)
            if unknown:
                raise IdentificationError(f'{source}: unknown keys {sorted(map(str, unknown))} '
                                          f'for {joint}; use {", ".join(LIMIT_KINDS)}')
            i = self.joint_names.index(joint)
            for kind, value in spec.items():
                where = f'{source}: {joint}.{kind}'
                if kind == 'position':
                    pos = numbers(where, value)
                    if pos.shape != (2,) or np.isnan(pos).any() or not pos[0] < pos[1] \
                            or np.isfinite(pos).sum() == 1:
                        raise IdentificationError(f'{where} must be [lo, hi] with lo < hi, both '
                                                  f'finite or both infinite, got {value!r}')
                    out.position_limits[i] = pos
                    continue
                v = numbers(where, value)
                finite_needed = kind != 'effort'
                if v.shape != () or np.isnan(v) or v <= 0 or \
                        (finite_needed and not np.isfinite(v)):
                    need = 'a finite number > 0' if finite_needed else 'a number > 0 (.inf: none)'
                    raise IdentificationError(f'{where} must be {need}, got {value!r}')
                if kind == 'velocity' and 'acceleration' not in spec and np.isclose(
                        out.acceleration_limits[i],
                        DEFAULT_ACCELERATION_RATE * out.velocity_limits[i]):
                    out.acceleration_limits[i] = DEFAULT_ACCELERATION_RATE * float(v)
                    if 'acceleration' in out.assumed.get(joint, {}):
                        out.assumed[joint]['acceleration'] = float(out.acceleration_limits[i])
                getattr(out, f'{kind}_limits')[i] = float(v)
            for kind in spec:
                out.assumed.get(joint, {}).pop(kind, None)
            if joint in out.assumed and not out.assumed[joint]:
                del out.assumed[joint]
        return out

    def with_margin(self, margin: float) -> ExcitationLimits:
        """The limits with ``margin`` (0 <= margin < 1) of each kept free: position ranges
        shrunk about their centres to (1 - margin) of their half widths, velocity,
        acceleration and effort limits times (1 - margin)."""
        if isinstance(margin, bool) or not isinstance(margin, (int, float, np.floating)) \
                or not 0 <= margin < 1:
            raise IdentificationError(f'limit margin must lie in [0, 1), got {margin!r}')
        keep = 1.0 - float(margin)
        limited, centre, half = position_ranges(self)
        pos = self.position_limits.copy()
        pos[limited] = np.stack([centre - keep * half, centre + keep * half], axis=1)[limited]
        return ExcitationLimits(list(self.joint_names), pos, keep * self.velocity_limits,
                                keep * self.acceleration_limits, keep * self.effort_limits,
                                {j: dict(v) for j, v in self.assumed.items()})

    def assumed_list(self) -> list[str]:
        """One line per assumed limit, e.g. 'joint1.acceleration: 4.35 rad/s^2'."""
        units = {'position': '', 'velocity': ' rad/s', 'acceleration': ' rad/s^2',
                 'effort': ' N m'}
        return [f'{j}.{k}: ' + ('none' if v is None else f'{v:.4g}{units[k]}')
                for j, kinds in self.assumed.items() for k, v in kinds.items()]

    def to_dict(self) -> dict:
        """Plain data for YAML, per joint (None for a missing limit)."""
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None
        return {j: {'position': [num(self.position_limits[i, 0]),
                                 num(self.position_limits[i, 1])],
                    'velocity': num(self.velocity_limits[i]),
                    'acceleration': num(self.acceleration_limits[i]),
                    'effort': num(self.effort_limits[i])}
                for i, j in enumerate(self.joint_names)}


def numbers(where: str, value: Any) -> np.ndarray:
    if isinstance(value, bool):
        raise IdentificationError(f'{where} must be numeric, got {value!r}')
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise IdentificationError(f'{where} must be numeric, got {value!r}') from None


def load_limits(path: str | os.PathLike, robot, effort: bool = True) -> ExcitationLimits:
    """The robot's limits (:meth:`ExcitationLimits.from_robot`) overridden by a YAML file of
    per-joint limits: ``joint: {position: [lo, hi], velocity, acceleration, effort}``."""
    base = ExcitationLimits.from_robot(robot, effort)
    data = read_yaml(path, f'limits file {path}')
    if data is None:
        return base
    return base.updated(data, f'limits file {path}')


def as_limits(robot, limits) -> ExcitationLimits:
    if limits is None:
        return ExcitationLimits.from_robot(robot)
    if isinstance(limits, ExcitationLimits):
        if limits.joint_names != list(robot.joint_names):
            raise IdentificationError(f'limits are for joints {limits.joint_names}, the robot '
                                      f'identifies {robot.joint_names}')
        return limits
    if isinstance(limits, (str, os.PathLike)):
        return load_limits(limits, robot)
    return ExcitationLimits.from_robot(robot).updated(limits)


def limit_ratios(traj: Trajectory, robot, limits: ExcitationLimits | None = None,
                 num_points: int = VERIFY_POINTS, effort_points: int = EFFORT_POINTS,
                 phis: Sequence[np.ndarray] | None = None,
                 window: tuple[float, float] | None = None) -> dict:
    """Worst limit ratios of ``traj`` over one pass, or over ``window`` (t0, t1) s (1 = at a
    limit): check_limits' position, velocity and acceleration on ``num_points`` times (at
    least VERIFY_RATE per second), plus 'effort', |tau| / limit on ``effort_points`` times (at
    least half that rate), tau the inverse dynamics under each parameter vector of ``phis``
    (default: the robot's own). Same layout as check_limits: kind -> float, 'worst_joint',
    'per_joint'."""
    limits = as_limits(robot, limits)
    t0, t1 = (0.0, traj.horizon()) if window is None else window
    span = t1 - t0
    num_points = max(num_points, int(math.ceil(span * VERIFY_RATE)) + 1)
    effort_points = max(effort_points, int(math.ceil(span * VERIFY_RATE / 2)) + 1)
    out = check_limits(traj, limits, np.linspace(t0, t1, num_points))
    per = out['per_joint']
    eff = limits.effort_limits
    if np.isfinite(eff).any():
        q, qd, qdd = traj.sample(np.linspace(t0, t1, effort_points))
        tau = _peak_torques(robot, q, qd, qdd, phis)
        per['effort'] = np.where(np.isfinite(eff), tau / eff, 0.0)
    else:
        per['effort'] = np.zeros(traj.dof)
    out['effort'] = float(per['effort'].max())
    out['worst_joint']['effort'] = int(np.argmax(per['effort']))
    return out


def static_ratios(robot, limits: ExcitationLimits, q: np.ndarray,
                  phis: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Per joint (n,) |static torque| at pose q (n,) over its effort limit, the largest under
    the parameter vectors ``phis`` (default: the robot's own); 0 where unlimited."""
    zero = np.zeros((1, robot.dof))
    eff = limits.effort_limits
    return np.where(np.isfinite(eff), _peak_torques(robot, q[None], zero, zero, phis) / eff, 0.0)


def _peak_torques(robot, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                  phis: Sequence[np.ndarray] | None) -> np.ndarray:
    """Largest |tau| per joint (n,) over the samples and the parameter vectors ``phis``."""
    Y = np.concatenate([robot.regressor(q[k:k + 4096], qd[k:k + 4096], qdd[k:k + 4096])
                        for k in range(0, len(q), 4096)])
    P = np.column_stack(torque_models(robot, phis))
    return np.abs(Y @ P).max(axis=(0, 2))


def torque_models(robot, phis: Sequence[np.ndarray] | None) -> list[np.ndarray]:
    if phis is None or len(phis) == 0:
        return [robot.phi_model]
    return [robot._check_phi(p) for p in phis]


def estimate_parameters(path: str | os.PathLike, robot) -> np.ndarray:
    """The standard parameters (robot.param_names order) of an estimate file (estimate.yaml
    of the node or ``identify``: its 'standard_parameters' mapping)."""
    doc = read_yaml(path, f'estimate {path}')
    given = doc.get('standard_parameters') if isinstance(doc, Mapping) else None
    if not isinstance(given, Mapping):
        raise IdentificationError(f'estimate {path} has no standard_parameters mapping')
    missing = [n for n in robot.param_names if n not in given]
    extra = [n for n in given if n not in robot.param_names]
    if missing or extra:
        raise IdentificationError(
            f'estimate {path} does not match the robot\'s parameters (missing '
            f'{missing[:4]}, unknown {extra[:4]}): give the same robot, joints and --extras')
    phi = np.array([numbers(f'estimate {path}: {n}', given[n]) for n in robot.param_names],
                   dtype=float)
    if not np.all(np.isfinite(phi)):
        raise IdentificationError(f'estimate {path} holds non-finite parameters')
    return phi


def worst_ratio(ratios: dict) -> float:
    return max(ratios[k] for k in LIMIT_KINDS)


def position_ranges(limits: ExcitationLimits, default: np.ndarray | float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(limited (n,) bool, centre (n,), half width (n,)) of the position ranges; joints
    without position limits get centre ``default`` and half width inf."""
    pos = limits.position_limits
    limited = np.isfinite(pos).all(axis=1)
    p = np.where(limited[:, None], pos, 0.0)
    return (limited, np.where(limited, 0.5 * (p[:, 0] + p[:, 1]), default),
            np.where(limited, 0.5 * (p[:, 1] - p[:, 0]), np.inf))
