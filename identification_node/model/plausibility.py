"""Physical bounds on the pipeline's input and smoothed samples, and the gate that applies them.

Finite but absurd values (a 1e5 rad/s velocity, a 1e200 A current) are not noise: one such
sample would dominate every sum of the estimator. The bounds come from the robot description,
widened by ``margin`` (URDF ``<limit>`` values are ratings, not what sensors can never show):

- position: the URDF range widened about its centre, centre +- margin * half range; joints
  without a range (continuous) |q| <= ``position`` (rad or m),
- velocity: margin * URDF velocity limit, else ``velocity`` (rad/s; prismatic / 10 m/s),
- acceleration: ``acceleration`` (rad/s^2; prismatic / 10 m/s^2; URDF has none),
- torque: margin * URDF effort limit, else ``effort`` (N m, or N),
- motor current: per joint ``current_limit`` (A) when given (> 0), else the current that
  makes the torque bound through the joint's gear ratio and torque constant.

Units SI; arrays per identified joint in the robot's joint order.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from identification_node.config import Plausibility, default
from identification_node.errors import IdentificationError


@dataclass
class PlausibilitySettings:
    """How the bounds are made (the node's ``plausibility.*`` parameters)."""
    margin: float = Plausibility.margin
    position: float = Plausibility.position
    velocity: float = Plausibility.velocity
    acceleration: float = Plausibility.acceleration
    effort: float = Plausibility.effort
    current_limit: Sequence[float] = field(
        default_factory=lambda: default('plausibility.current_limit'))

    def validate(self, dof: int) -> None:
        """Raise IdentificationError naming the first bad field."""
        for name in ('margin', 'position', 'velocity', 'acceleration', 'effort'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0) or (name == 'margin' and value < 1):
                raise IdentificationError(
                    f'parameter plausibility.{name} = {value!r} must be finite and '
                    + ('>= 1' if name == 'margin' else '> 0'))
        limits = list(self.current_limit)
        if len(limits) not in (0, 1, dof) or not all(np.isfinite(c) and c >= 0 for c in limits):
            raise IdentificationError(
                f'parameter plausibility.current_limit = {limits!r} must be empty, 1 or {dof} '
                'values >= 0 (A; 0: from the effort limit)')


@dataclass
class PlausibilityBounds:
    """Per-joint bounds (n,): position lower/upper, |velocity|, |acceleration|, |torque|,
    |motor current| (inf: no bound)."""
    position_lower: np.ndarray
    position_upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    effort: np.ndarray
    current: np.ndarray
    _limits: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # the position range's centre; 0 where an end is inf (its half range is inf: no bound)
        with np.errstate(invalid='ignore'):
            centre = 0.5 * (self.position_lower + self.position_upper)
        self._centre = np.where(np.isfinite(centre), centre, 0.0)

    @classmethod
    def from_robot(cls, robot, settings: PlausibilitySettings | None = None,
                   gear_ratio: Sequence[float] = (), kt: Sequence[float] = ()
                   ) -> PlausibilityBounds:
        """Bounds from ``robot``'s limits (RobotModel), widened by ``settings.margin``;
        ``gear_ratio`` and ``kt`` per joint turn the torque bound into a current bound."""
        s = settings or PlausibilitySettings()
        n = robot.dof
        s.validate(n)
        k = s.margin
        scale = robot.in_joint_units(1.0)
        lo, hi = robot.position_limits[:, 0], robot.position_limits[:, 1]
        ranged = np.isfinite(lo) & np.isfinite(hi) & (hi >= lo)
        lo, hi = np.where(ranged, lo, 0.0), np.where(ranged, hi, 0.0)
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        wide = s.position * scale
        lower = np.where(ranged, centre - k * half, -wide)
        upper = np.where(ranged, centre + k * half, wide)

        def rated(limits: np.ndarray, default: np.ndarray | float) -> np.ndarray:
            limits = np.asarray(limits, dtype=float)
            return np.where(np.isfinite(limits) & (limits > 0), k * limits, default)

        velocity = rated(robot.velocity_limits, s.velocity * scale)
        effort = rated(robot.effort_limits, s.effort)
        acceleration = s.acceleration * scale
        ratio = _per_joint(gear_ratio, n, 1.0) * _per_joint(kt, n, 1.0)
        with np.errstate(divide='ignore'):
            derived = effort / np.abs(ratio)
        given = _per_joint(s.current_limit, n, 0.0)
        current = np.where(given > 0, given, derived)
        return cls(lower, upper, velocity, np.asarray(acceleration, dtype=float), effort, current)

    def update(self, new: PlausibilityBounds) -> None:
        """Take ``new``'s bounds in place (this object is shared by the pipeline's stages)."""
        for name in ('position_lower', 'position_upper', 'velocity', 'acceleration', 'effort',
                     'current'):
            setattr(self, name, getattr(new, name))
        self.__post_init__()
        self._limits.clear()

    def describe(self, joint_names: Sequence[str]
                 ) -> dict[str, dict[str, list[float] | float]]:
        """The bounds per joint, for logs and the README's table."""
        return {j: {'position': [float(self.position_lower[i]), float(self.position_upper[i])],
                    'velocity': float(self.velocity[i]),
                    'acceleration': float(self.acceleration[i]),
                    'effort': float(self.effort[i]), 'current': float(self.current[i])}
                for i, j in enumerate(joint_names)}

    # -- gates: a bool per sample (row), True when every value is within its bound ------------
    def ok(self, q: np.ndarray | None = None, qd: np.ndarray | None = None,
           qdd: np.ndarray | None = None, tau: np.ndarray | None = None,
           columns: np.ndarray | None = None) -> np.ndarray:
        """Samples (rows of the (M, n) arrays given) within every bound, and finite: NaN
        and inf fail, also where the bound is inf. ``tau`` may hold the joints ``columns`` only
        (the measured ones). One comparison of all the values side by side (the check runs on
        every batch)."""
        given = (q is not None, qd is not None, qdd is not None, tau is not None)
        key = given + (None if columns is None else tuple(columns),)
        limit = self._limits.get(key)
        if limit is None:   # the bounds side by side, as the values will be (inf: the largest)
            effort = self.effort if columns is None else self.effort[columns]
            parts = (0.5 * (self.position_upper - self.position_lower), self.velocity,
                     self.acceleration, effort)
            limit = self._limits[key] = np.minimum(
                np.concatenate([b for b, g in zip(parts, given) if g]), np.finfo(float).max)
        values = [a for a in (None if q is None else q - self._centre, qd, qdd, tau)
                  if a is not None]
        x = values[0] if len(values) == 1 else np.concatenate(values, axis=1)
        return (np.abs(x) <= limit).all(axis=1)   # NaN compares false, silently

    def currents_ok(self, currents: np.ndarray) -> np.ndarray:
        """Samples of currents (M, n, 3) (NaN where a joint has no such channel) within the
        per-joint current bound."""
        over = np.abs(currents) > self.current[None, :, None]
        return ~over.any(axis=(1, 2))


def _per_joint(values: Sequence[float], n: int, default: float) -> np.ndarray:
    array = np.asarray(list(values), dtype=float)
    if array.size == 0:
        return np.full(n, default)
    return np.broadcast_to(array, (n,)).astype(float) if array.size == 1 else array
