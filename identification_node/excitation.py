"""Excitation trajectories: finite Fourier series optimised for parameter identification.

Radkhah, Kulic and Croft, sections II.C-D and III.A-B. Each joint follows the Fourier series of
:class:`~identification_node.trajectories.FourierTrajectory` (velocity amplitudes a, b in rad/s,
offset q0 in rad, common period); the design picks the 2H + 1 coefficients per joint that
minimise a criterion of the base regressor stacked over N samples of one period, subject to the
joint limits.

Criteria (smaller is better), on the stacked base regressor W (N n rows, b columns):

- ``cond``: the condition number s_max / s_min of W itself, the paper's cond(phi_tot) (II.D,
  and what its experiments used), with the base parameters in SI units (kg, kg m, kg m^2). Not
  the column-scaled number: scaling every column to unit norm makes it blind to how strongly
  each base parameter is excited, so minimising it balances the directions of the columns
  while letting weak ones shrink. On the CRS A465 (5 harmonics, 10 s) minimising the
  column-scaled number took it from 12 to 2.5 but made the largest parameter standard
  deviation 12 times worse than the starting trajectory's; minimising the plain one (29 -> 7)
  lowered every summary of the standard deviations (geometric mean 1.5x, largest 2.6x). The
  plain number depends on the parameters' units, which the package fixes (SI).
  ``condition_number(W, scaled=True)`` gives the column-scaled number for comparison.
- ``dopt``: d-optimality, -log det(W'W), W'W the information matrix (II.D). With per-joint
  torque noise standard deviations the rows of joint j are divided by sigma_j first, so W'W is
  the Fisher information (phi_tot' Sigma^-1 phi_tot, eq. 5) and the criterion is the log volume
  of the covariance ellipsoid of the estimates.

Limits (:class:`ExcitationLimits`): joint positions (with the offset q0), velocities and
accelerations on a grid of one period, and joint torques (inverse dynamics with the robot's own
parameters) at the criterion samples. Each (joint, kind) is one smooth constraint on the
Kreisselmeier-Steinhauser maximum of its ratios to the limit (see _Design). URDFs carry no
acceleration limits: the default is ``DEFAULT_ACCELERATION_RATE`` (2 /s) times the velocity
limit, i.e. full speed reached in 0.5 s (6.3 rad/s^2 on the CRS A465's first three joints;
Table I's trajectory peaks at 6.1 rad/s^2). Every result is verified on a fine grid after the
optimisation (torques on EFFORT_POINTS samples) and, where needed, its motion is scaled down
towards the centre of the position ranges until every ratio is below VERIFY_RATIO.

Initial guess: the paper's least squares on random target velocities (III.A,
least_squares_guess), or Table I (table1_trajectory, offsets moved to our joint zeros).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from .errors import IdentificationError
from .trajectories import (DEFAULT_VELOCITY, TABLE1_PERIOD, FourierTrajectory, Trajectory,
                           check_limits)

CRITERIA = ('cond', 'dopt')
DEFAULT_HARMONICS = 5
DEFAULT_PERIOD = 10.0
DEFAULT_SAMPLES = 100       # criterion samples over one period
DEFAULT_MAXITER = 200       # SLSQP iterations
DEFAULT_ACCELERATION_RATE = 2.0  # 1/s: default acceleration limit = rate * velocity limit
PRISMATIC_VELOCITY = 0.5    # m/s, prismatic joints without a velocity limit
LSQ_POINTS = 100            # random target velocities of the initial guess (paper: 100)
MARGIN = 1.0                # the optimiser's constraints: smooth max of the ratios <= MARGIN
GRID_PER_HARMONIC = 40      # constraint grid points per period and harmonic
KS_RHO = 200.0              # sharpness of the smooth maximum of the limit ratios
INITIAL_MARGIN = 0.95        # the initial guess reaches this fraction of its tightest limit
VERIFY_POINTS = 4001        # kinematic check of the result over one period
EFFORT_POINTS = 2001        # torque check of the result over one period
VERIFY_RATIO = 0.999        # a verified result stays below this fraction of every limit
LIMIT_KINDS = ('position', 'velocity', 'acceleration', 'effort')
# Table I's joint zeros -> ours (crs_a465.urdf: arm straight up at zero), q_ours = q_paper +
# offset. Table I moves joint 2 over [36, 148] deg and joint 3 over [-163, -10] deg: centred on
# +90 and -90 deg, where our symmetric +-90 / +-110 deg ranges are centred on 0. With the
# quarter-turn shifts every joint stays inside our limits; the senses of rotation are kept (the
# paper does not state them).
TABLE1_OFFSET = (0.0, -math.pi / 2, math.pi / 2, 0.0, 0.0, 0.0)
_STEP_Q = 1e-6   # rad, finite-difference step of the regressor in q
_STEP_QD = 1e-6  # rad/s, in qd (qdd enters linearly: exact with step 1)
_RANK_TOL = 1e-12  # singular value (or diagonal of R) ratio below which W is rank deficient


# ---------------------------------------------------------------------------------------------
# Limits
# ---------------------------------------------------------------------------------------------
@dataclass
class ExcitationLimits:
    """Joint limits for excitation design, in the robot's joint order (SI units).

    position_limits (n, 2) [lo, hi] (+-inf: none), velocity_limits (n,), acceleration_limits
    (n,) (finite, > 0), effort_limits (n,) (inf: no torque limit). Works with
    :func:`~identification_node.trajectories.check_limits`.
    """

    joint_names: list[str]
    position_limits: np.ndarray
    velocity_limits: np.ndarray
    acceleration_limits: np.ndarray
    effort_limits: np.ndarray

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    @classmethod
    def from_robot(cls, robot, effort: bool = True) -> ExcitationLimits:
        """The robot's limits; joints without a velocity limit get DEFAULT_VELOCITY (rad/s) or
        PRISMATIC_VELOCITY (m/s), accelerations DEFAULT_ACCELERATION_RATE times the velocity
        limit; ``effort=False`` (or no effort limit in the description) drops the torque
        limit."""
        prismatic = np.asarray(robot.prismatic, dtype=bool)
        vel = np.asarray(robot.velocity_limits, dtype=float)
        vel = np.where(np.isfinite(vel) & (vel > 0), vel,
                       np.where(prismatic, PRISMATIC_VELOCITY, DEFAULT_VELOCITY))
        eff = np.asarray(robot.effort_limits, dtype=float)
        eff = np.where(np.isfinite(eff) & (eff > 0) & bool(effort), eff, np.inf)
        return cls(list(robot.joint_names), np.array(robot.position_limits, dtype=float),
                   vel, DEFAULT_ACCELERATION_RATE * vel, eff)

    def updated(self, overrides: Mapping[str, Any], source: str = 'limits') -> ExcitationLimits:
        """A copy with per-joint overrides ``{joint: {position: [lo, hi], velocity: v,
        acceleration: a, effort: e}}``. Each key is optional; position [-.inf, .inf] and effort
        .inf remove the limit; a default acceleration limit follows a new velocity limit."""
        if not isinstance(overrides, Mapping):
            raise IdentificationError(f'{source}: expected a mapping of joint names to limits, '
                                      f'got {type(overrides).__name__}')
        out = ExcitationLimits(list(self.joint_names), self.position_limits.copy(),
                               self.velocity_limits.copy(), self.acceleration_limits.copy(),
                               self.effort_limits.copy())
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
                    pos = _numbers(where, value)
                    if pos.shape != (2,) or np.isnan(pos).any() or not pos[0] < pos[1] \
                            or np.isfinite(pos).sum() == 1:
                        raise IdentificationError(f'{where} must be [lo, hi] with lo < hi, both '
                                                  f'finite or both infinite, got {value!r}')
                    out.position_limits[i] = pos
                    continue
                v = _numbers(where, value)
                finite_needed = kind != 'effort'
                if v.shape != () or np.isnan(v) or v <= 0 or \
                        (finite_needed and not np.isfinite(v)):
                    need = 'a finite number > 0' if finite_needed else 'a number > 0 (.inf: none)'
                    raise IdentificationError(f'{where} must be {need}, got {value!r}')
                if kind == 'velocity' and 'acceleration' not in spec and np.isclose(
                        out.acceleration_limits[i],
                        DEFAULT_ACCELERATION_RATE * out.velocity_limits[i]):
                    out.acceleration_limits[i] = DEFAULT_ACCELERATION_RATE * float(v)
                getattr(out, f'{kind}_limits')[i] = float(v)
        return out

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


def _numbers(where: str, value: Any) -> np.ndarray:
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
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise IdentificationError(f'cannot read limits file {path}: {exc}') from None
    if data is None:
        return base
    return base.updated(data, f'limits file {path}')


def _as_limits(robot, limits) -> ExcitationLimits:
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
                 num_points: int = VERIFY_POINTS, effort_points: int = EFFORT_POINTS) -> dict:
    """Worst limit ratios of ``traj`` over one pass (1 = at a limit): check_limits'
    position, velocity and acceleration on ``num_points`` times, plus 'effort', |tau| / limit
    with tau the inverse dynamics under the robot's own parameters, on ``effort_points``
    times. Same layout as check_limits: kind -> float, 'worst_joint', 'per_joint'."""
    limits = _as_limits(robot, limits)
    horizon = traj.horizon()
    out = check_limits(traj, limits, np.linspace(0.0, horizon, num_points))
    per = out['per_joint']
    eff = limits.effort_limits
    if np.isfinite(eff).any():
        q, qd, qdd = traj.sample(np.linspace(0.0, horizon, effort_points))
        tau = np.abs(robot.inverse_dynamics(q, qd, qdd)).max(axis=0)
        per['effort'] = np.where(np.isfinite(eff), tau / eff, 0.0)
    else:
        per['effort'] = np.zeros(traj.dof)
    out['effort'] = float(per['effort'].max())
    out['worst_joint']['effort'] = int(np.argmax(per['effort']))
    return out


def _worst(ratios: dict) -> float:
    return max(ratios[k] for k in LIMIT_KINDS)


def _ranges(limits: ExcitationLimits, default: np.ndarray | float = 0.0
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(limited (n,) bool, centre (n,), half width (n,)) of the position ranges; joints
    without position limits get centre ``default`` and half width inf."""
    pos = limits.position_limits
    limited = np.isfinite(pos).all(axis=1)
    p = np.where(limited[:, None], pos, 0.0)
    return (limited, np.where(limited, 0.5 * (p[:, 0] + p[:, 1]), default),
            np.where(limited, 0.5 * (p[:, 1] - p[:, 0]), np.inf))


# ---------------------------------------------------------------------------------------------
# Criteria
# ---------------------------------------------------------------------------------------------
def condition_number(W: np.ndarray, scaled: bool = False) -> float:
    """Condition number s_max / s_min of a stacked regressor W (rows, b) or (N, n, b): of W
    itself (default, the paper's cond(phi_tot)) or of W with its columns scaled to unit norm;
    inf when rank deficient."""
    W = _rows(W)
    if scaled:
        norms = np.linalg.norm(W, axis=0)
        if not (norms > 0).all():
            return math.inf
        W = W / norms
    s = np.linalg.svd(W, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else math.inf


def d_optimality(W: np.ndarray, noise_std: Sequence[float] | None = None) -> float:
    """-log det(W'W) of a stacked regressor W (N, n, b) (or (rows, b) without noise weights);
    with ``noise_std`` (n,), joint j's rows are divided by sigma_j (Fisher information)."""
    W = np.asarray(W, dtype=float)
    if noise_std is not None:
        if W.ndim != 3:
            raise IdentificationError('noise weights need the regressor as (N, n, b)')
        W = W * _noise_weights(noise_std, W.shape[1])[None, :, None]
    s = np.linalg.svd(_rows(W), compute_uv=False)
    return float(-2.0 * np.log(s).sum()) if s[-1] > 0 else math.inf


def _rows(W: np.ndarray) -> np.ndarray:
    W = np.asarray(W, dtype=float)
    return W.reshape(-1, W.shape[-1])


def _noise_weights(noise_std: Sequence[float] | None, n: int) -> np.ndarray:
    if noise_std is None:
        return np.ones(n)
    std = _numbers('noise_std', noise_std).reshape(-1)
    if std.shape != (n,) or not (np.isfinite(std) & (std > 0)).all():
        raise IdentificationError(f'noise_std needs {n} finite values > 0 (one per joint), got '
                                  f'{np.asarray(noise_std).tolist()}')
    return 1.0 / std


def _objective(W: np.ndarray, criterion: str, grad: bool
               ) -> tuple[float, np.ndarray | None]:
    """The optimised function of W (rows, b): log cond(W) or -log det(W'W), and its gradient
    with respect to W (for simple extreme singular values). Both work on the b x b triangular
    factor R of W = Q R; the singular vectors of W are u_k = W v_k / s_k."""
    if criterion == 'cond':
        _, s, Vt = np.linalg.svd(np.linalg.qr(W, mode='r'))
        if not s[-1] > _RANK_TOL * s[0]:
            return math.inf, None
        f = float(np.log(s[0] / s[-1]))
        if not grad:
            return f, None
        return f, (np.outer(W @ Vt[0], Vt[0]) / s[0] ** 2
                   - np.outer(W @ Vt[-1], Vt[-1]) / s[-1] ** 2)
    R = np.linalg.qr(W, mode='r')
    d = np.abs(np.diag(R))
    if not d.min() > _RANK_TOL * d.max():
        return math.inf, None
    f = float(-2.0 * np.log(d).sum())  # det(W'W) = det(R)^2
    if not grad:
        return f, None
    Rinv = np.linalg.inv(R)
    return f, -2.0 * (W @ Rinv) @ Rinv.T  # -2 W (W'W)^-1


def _report_value(f: float, criterion: str) -> float:
    """The reported criterion value from the optimised function value."""
    return float(np.exp(f)) if criterion == 'cond' and np.isfinite(f) else float(f)


def criterion_value(robot, traj: Trajectory, criterion: str = 'cond', base=None,
                    num_samples: int = DEFAULT_SAMPLES,
                    noise_std: Sequence[float] | None = None) -> float:
    """``cond`` (condition number) or ``dopt`` (-log det W'W, noise-weighted) of the base
    regressor stacked over ``num_samples`` equally spaced samples of one pass of ``traj``."""
    _check_criterion(criterion)
    base = _base_of(robot, base)
    t = np.arange(int(num_samples)) * (traj.horizon() / int(num_samples))
    q, qd, qdd = traj.sample(t)
    Yb = base.base_regressor(robot.regressor(q, qd, qdd))
    W = (Yb * _noise_weights(noise_std, robot.dof)[None, :, None]).reshape(-1, base.num_base)
    return _report_value(_objective(W, criterion, False)[0], criterion)


def _check_criterion(criterion: str) -> None:
    if criterion not in CRITERIA:
        raise IdentificationError(f'unknown criterion {criterion!r}; use one of '
                                  f'{", ".join(CRITERIA)}')


def _base_of(robot, base):
    if base is None:
        from .identifiability import BaseParameters
        return BaseParameters.from_robot(robot)
    return base


# ---------------------------------------------------------------------------------------------
# Fourier basis and initial guesses
# ---------------------------------------------------------------------------------------------
def fourier_basis(t: np.ndarray, harmonics: int, period: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matrices (N, 2H + 1) mapping one joint's coefficients [a_1..a_H, b_1..b_H, q0] to its
    position, velocity and acceleration at times t (s), as in FourierTrajectory.sample."""
    t = np.asarray(t, dtype=float)
    wl = 2.0 * math.pi / period * np.arange(1, harmonics + 1)
    S, C = np.sin(np.outer(t, wl)), np.cos(np.outer(t, wl))
    one, zero = np.ones((t.size, 1)), np.zeros((t.size, 1))
    return (np.hstack([S / wl, -C / wl, one]), np.hstack([C, S, zero]),
            np.hstack([-S * wl, C * wl, zero]))


def _to_x(traj: FourierTrajectory) -> np.ndarray:
    return np.hstack([traj.a, traj.b, traj.q0[:, None]]).ravel()


def _from_x(x: np.ndarray, n: int, period: float, names: Sequence[str]) -> FourierTrajectory:
    X = np.asarray(x, dtype=float).reshape(n, -1)
    H = (X.shape[1] - 1) // 2
    return FourierTrajectory(X[:, :H], X[:, H:2 * H], X[:, 2 * H], period, names)


def least_squares_guess(limits: ExcitationLimits, harmonics: int = DEFAULT_HARMONICS,
                        period: float = DEFAULT_PERIOD, seed: int | None = 0,
                        num_points: int = LSQ_POINTS) -> FourierTrajectory:
    """The paper's initial guess (III.A, eq. 7-8), before scaling into the limits: per joint,
    random target velocities, uniform within the velocity limit, at ``num_points`` equally
    spaced instants of one period; the coefficients (a_l, b_l) solve A delta = qd by least
    squares, A the velocity form of the series [cos(w l t), sin(w l t)].

    The paper's printed A (entries s/(w l), c/(w l) and a column of ones) is the position
    form, which cannot reproduce velocities and leaves q0 undetermined; we fit the velocity
    form, as its text says, and put q0 at the centre of the position range (0 when unlimited).
    """
    H = _check_harmonics(harmonics)
    M = max(int(num_points), 2 * H)
    rng = np.random.default_rng(seed)
    t = np.arange(M) * (period / M)
    _, Bv, _ = fourier_basis(t, H, period)
    A = Bv[:, :2 * H]
    vmax = limits.velocity_limits
    target = rng.uniform(-1.0, 1.0, size=(M, limits.dof)) * vmax
    coef = np.linalg.lstsq(A, target, rcond=None)[0].T  # (n, 2H)
    return FourierTrajectory(coef[:, :H], coef[:, H:], _ranges(limits)[1], period,
                             limits.joint_names)


def scale_to_limits(traj: FourierTrajectory, limits: ExcitationLimits,
                    margin: float = INITIAL_MARGIN, num_points: int = VERIFY_POINTS
                    ) -> FourierTrajectory:
    """Per joint, scale the amplitudes (up or down) so the motion reaches ``margin`` of its
    tightest kinematic limit (position range, velocity, acceleration), with q0 centring the
    excursion in the position range (unchanged for joints without position limits)."""
    unit = FourierTrajectory(traj.a, traj.b, np.zeros(traj.dof), traj.period)
    q, qd, qdd = unit.sample(np.linspace(0.0, traj.period, num_points))
    limited, centre, half = _ranges(limits)
    span = 0.5 * (q.max(axis=0) - q.min(axis=0))
    with np.errstate(divide='ignore'):
        scale = margin * np.min([half / span, limits.velocity_limits / np.abs(qd).max(axis=0),
                                 limits.acceleration_limits / np.abs(qdd).max(axis=0)], axis=0)
    if not np.isfinite(scale).all():
        bad = [j for j, s in zip(limits.joint_names, scale) if not np.isfinite(s)]
        raise IdentificationError(f'the trajectory does not move joints {bad}')
    mid = 0.5 * (q.max(axis=0) + q.min(axis=0))
    q0 = np.where(limited, centre - scale * mid, traj.q0)
    return FourierTrajectory(traj.a * scale[:, None], traj.b * scale[:, None], q0,
                             traj.period, traj.joint_names)


def shrink_into_limits(traj: FourierTrajectory, robot, limits: ExcitationLimits,
                       target: float = VERIFY_RATIO, max_steps: int = 60
                       ) -> tuple[FourierTrajectory, float, dict]:
    """Scale the motion down until every limit ratio (limit_ratios) is at most ``target``:
    amplitudes times s, and each offset q0 drawn towards the centre of its position range by
    the same factor (kept where unlimited), so every kinematic ratio scales by s exactly.
    Returns (trajectory, s, ratios); IdentificationError when even the centre of the ranges
    at rest exceeds the effort limits."""
    ratios = limit_ratios(traj, robot, limits)
    kinematic = max(ratios[k] for k in LIMIT_KINDS[:3])
    scale = min(1.0, target / kinematic) if kinematic > 0 else 1.0
    for _ in range(max_steps):
        cur = _scaled(traj, limits, scale)
        if scale != 1.0:
            ratios = limit_ratios(cur, robot, limits)
        if _worst(ratios) <= target:
            return cur, scale, ratios
        scale *= float(np.clip(target / _worst(ratios), 0.5, 0.995))
    raise IdentificationError('cannot scale the trajectory into the effort limits: the static '
                              'torque near the centre of the position ranges exceeds them')


def _scaled(traj: FourierTrajectory, limits: ExcitationLimits, scale: float
            ) -> FourierTrajectory:
    centre = _ranges(limits, traj.q0)[1]
    return FourierTrajectory(traj.a * scale, traj.b * scale, centre + scale * (traj.q0 - centre),
                             traj.period, traj.joint_names)


def table1_trajectory(robot, harmonics: int = DEFAULT_HARMONICS,
                      period: float = TABLE1_PERIOD) -> FourierTrajectory:
    """Table I of Radkhah, Kulic and Croft for a 6-joint robot, with its offsets moved into
    our joint zeros (TABLE1_OFFSET) for the bundled crs_a465; zero-padded beyond its 5
    harmonics."""
    if robot.dof != 6:
        raise IdentificationError(f'Table I is for the 6 joints of the CRS A460/A465; the robot '
                                  f'identifies {robot.dof} ({robot.joint_names})')
    H = _check_harmonics(harmonics)
    t1 = FourierTrajectory.crs_table1(period)
    if H < t1.harmonics:
        raise IdentificationError(f'Table I has {t1.harmonics} harmonics; ask for at least '
                                  f'{t1.harmonics}')
    pad = np.zeros((6, H - t1.harmonics))
    offset = np.array(TABLE1_OFFSET) if robot.name == 'crs_a465' else np.zeros(6)
    return FourierTrajectory(np.hstack([t1.a, pad]), np.hstack([t1.b, pad]), t1.q0 + offset,
                             period, robot.joint_names)


def _check_harmonics(harmonics: int) -> int:
    if isinstance(harmonics, bool) or not isinstance(harmonics, (int, np.integer)) \
            or harmonics < 1:
        raise IdentificationError(f'harmonics must be an integer >= 1, got {harmonics!r}')
    return int(harmonics)


# ---------------------------------------------------------------------------------------------
# Optimisation
# ---------------------------------------------------------------------------------------------
def _ks(r: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray]:
    """Kreisselmeier-Steinhauser smooth maximum over axis 0 of r (m, ...): values (...) with
    max <= KS <= max + log(m) / rho, and its weights dKS/dr (m, ...)."""
    top = r.max(axis=0)
    e = np.exp(rho * (r - top))
    total = e.sum(axis=0)
    return top + np.log(total) / rho, e / total


class _Design:
    """Criterion and limit constraints, with gradients, of coefficient vectors x (per joint
    [a_1..a_H, b_1..b_H, q0], joints in order).

    Each limit is one smooth constraint per joint, KS(ratios) <= margin: the
    Kreisselmeier-Steinhauser maximum (KS_RHO) of |q - centre| / half range, |qd| / limit,
    |qdd| / limit on a grid of GRID_PER_HARMONIC * H points of one period and of |tau| / limit
    at the criterion samples. KS bounds the grid maximum from above, and a few dozen smooth
    constraints keep SLSQP's QP subproblems small and well posed, where one linear constraint
    per grid point (thousands of nearly parallel rows) made them fail.
    """

    def __init__(self, robot, base, limits: ExcitationLimits, harmonics: int, period: float,
                 num_samples: int, criterion: str, noise_std, margin: float):
        self.robot, self.base, self.limits = robot, base, limits
        self.n, self.H, self.period = robot.dof, harmonics, period
        self.k = 2 * harmonics + 1
        self.criterion = criterion
        self.weights = _noise_weights(noise_std, self.n)
        t = np.arange(num_samples) * (period / num_samples)
        self.Bq, self.Bv, self.Ba = fourier_basis(t, harmonics, period)
        grid = GRID_PER_HARMONIC * harmonics
        self.grid = fourier_basis(np.arange(grid) * (period / grid), harmonics, period)
        self.phi = robot.phi_model
        self.margin = margin
        limited, centre, half = _ranges(limits)
        self.pos = np.flatnonzero(limited)
        self.centre, self.half = centre[self.pos], half[self.pos]
        self.effort = np.flatnonzero(np.isfinite(limits.effort_limits))
        self.evaluations = 0
        self._value: tuple[bytes, float, np.ndarray] | None = None
        self._grad: tuple[bytes, np.ndarray, np.ndarray] | None = None

    def kinematics(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        X = x.reshape(self.n, self.k).T
        return self.Bq @ X, self.Bv @ X, self.Ba @ X

    def _W(self, Y: np.ndarray) -> np.ndarray:
        Yb = self.base.base_regressor(Y) * self.weights[None, :, None]
        return Yb.reshape(-1, self.base.num_base)

    def value(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """(optimised function, torques (N, n) under the robot's parameters)."""
        key = x.tobytes()
        if self._value is None or self._value[0] != key:
            self.evaluations += 1
            Y = self.robot.regressor(*self.kinematics(x))
            f = _objective(self._W(Y), self.criterion, False)[0]
            self._value = (key, f, Y @ self.phi)
        return self._value[1], self._value[2]

    def gradient(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gradient of the function (nx,), Jacobian of the torques (N, n, nx)).

        The regressor is differentiated per sample in each joint's q, qd (forward differences)
        and qdd (exact: it enters linearly), then chained through the Fourier basis: 3n + 1
        regressor evaluations instead of one per coefficient."""
        key = x.tobytes()
        if self._grad is not None and self._grad[0] == key:
            return self._grad[1], self._grad[2]
        self.evaluations += 1
        n, N = self.n, self.Bq.shape[0]
        q, qd, qdd = self.kinematics(x)
        Q, QD, QDD = (np.repeat(a[None], 3 * n + 1, axis=0) for a in (q, qd, qdd))
        rows = np.arange(n)
        Q[1 + rows, :, rows] += _STEP_Q
        QD[1 + n + rows, :, rows] += _STEP_QD
        QDD[1 + 2 * n + rows, :, rows] += 1.0
        Y = self.robot.regressor(Q.reshape(-1, n), QD.reshape(-1, n), QDD.reshape(-1, n))
        Y = Y.reshape(3 * n + 1, N, n, -1)
        steps = np.repeat([_STEP_Q, _STEP_QD, 1.0], n)
        dY = (Y[1:] - Y[0]) / steps[:, None, None, None]        # (3n, N, n, p)
        f, dfdW = _objective(self._W(Y[0]), self.criterion, True)
        self._value = (key, f, Y[0] @ self.phi)
        if dfdW is None:
            raise IdentificationError('the trajectory does not excite every base parameter')
        M = dfdW.reshape(N, n, -1) * self.weights[None, :, None]
        g = np.einsum('knjc,njc->kn', dY[..., self.base.base_index], M)  # (3n, N)
        B = (self.Bq, self.Bv, self.Ba)
        grad = np.concatenate([sum(B[s].T @ g[s * n + i] for s in range(3)) for i in range(n)])
        dtau = dY @ self.phi                                     # (3n, N, n)
        J = np.concatenate([sum(dtau[s * n + i][:, :, None] * B[s][:, None, :]
                                for s in range(3)) for i in range(n)], axis=2)
        self._grad = (key, grad, J)
        return grad, J

    # -- scipy callbacks --------------------------------------------------------------------
    def fun(self, x: np.ndarray) -> float:
        f = self.value(x)[0]
        return f if np.isfinite(f) else 1e6

    def jac(self, x: np.ndarray) -> np.ndarray:
        return self.gradient(x)[0]

    def _limits(self, x: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """KS ratios of every limited (joint, kind) and their Jacobian (rows, nx)."""
        X = x.reshape(self.n, self.k)
        Bq, Bv, Ba = self.grid
        lim = self.limits
        parts = [((Bq @ X[self.pos].T - self.centre) / self.half, Bq, self.half, self.pos),
                 (Bv @ X.T / lim.velocity_limits, Bv, lim.velocity_limits, np.arange(self.n)),
                 (Ba @ X.T / lim.acceleration_limits, Ba, lim.acceleration_limits,
                  np.arange(self.n))]
        values, rows = [], []
        for r, B, scale, joints in parts:
            if not joints.size:
                continue
            ks, w = _ks(np.concatenate([r, -r]), KS_RHO)
            values.append(ks)
            if jac:
                G = len(B)
                dr = ((w[:G] - w[G:]).T @ B) / scale[:, None]   # (joints, k)
                block = np.zeros((len(joints), self.n, self.k))
                block[np.arange(len(joints)), joints] = dr
                rows.append(block.reshape(len(joints), -1))
        if self.effort.size:
            e = lim.effort_limits[self.effort]
            r = self.value(x)[1][:, self.effort] / e
            ks, w = _ks(np.concatenate([r, -r]), KS_RHO)
            values.append(ks)
            if jac:
                J = self.gradient(x)[1][:, self.effort]           # (N, ne, nx)
                N = J.shape[0]
                rows.append(np.einsum('tj,tjx->jx', w[:N] - w[N:], J) / e[:, None])
        return np.concatenate(values), (np.vstack(rows) if jac else None)

    def constraint(self, x: np.ndarray) -> np.ndarray:
        return self.margin - self._limits(x, False)[0]

    def constraint_jac(self, x: np.ndarray) -> np.ndarray:
        return -self._limits(x, True)[1]


@dataclass
class ExcitationResult:
    """An optimised excitation and how it was found.

    trajectory: the optimised FourierTrajectory (verified inside every limit); initial: the
    starting trajectory; criterion: 'cond' or 'dopt'; value, initial_value: the criterion of
    each (criterion_value with num_samples samples); ratios: limit_ratios of the result;
    iterations (SLSQP), evaluations (criterion or gradient), success and message (SLSQP's),
    scale: factor applied to the optimiser's amplitudes to satisfy the limits on the fine grid
    (1: none); runtime (s).
    """

    trajectory: FourierTrajectory
    initial: FourierTrajectory
    criterion: str
    value: float
    initial_value: float
    ratios: dict
    iterations: int
    evaluations: int
    success: bool
    message: str
    scale: float
    runtime: float
    num_samples: int
    limits: ExcitationLimits | None = None
    noise_std: list[float] | None = None

    @property
    def improved(self) -> bool:
        return self.value < self.initial_value

    def summary(self) -> dict:
        """Plain data for YAML: criterion, limit ratios, optimisation statistics."""
        names = self.trajectory.joint_names or []
        return {
            'criterion': {'name': self.criterion, 'value': self.value,
                          'initial': self.initial_value, 'samples': self.num_samples,
                          **({'noise_std': self.noise_std} if self.noise_std else {})},
            'limit_ratios': {k: {'worst': float(self.ratios[k]),
                                 'joint': names[self.ratios['worst_joint'][k]] if names
                                 else int(self.ratios['worst_joint'][k]),
                                 'per_joint': [float(v) for v in self.ratios['per_joint'][k]]}
                             for k in LIMIT_KINDS},
            'optimisation': {'method': 'SLSQP', 'iterations': self.iterations,
                             'evaluations': self.evaluations, 'success': bool(self.success),
                             'message': self.message, 'scale': self.scale,
                             'runtime': round(self.runtime, 3)},
        }


def initial_trajectory(robot, initial: str | FourierTrajectory | None,
                       limits: ExcitationLimits, harmonics: int, period: float,
                       seed: int | None) -> FourierTrajectory:
    """The starting point: 'lsq' (None; least_squares_guess scaled into the limits), 'table1'
    (table1_trajectory) or a FourierTrajectory, shrunk into every limit."""
    if initial is None or (isinstance(initial, str) and initial == 'lsq'):
        guess = scale_to_limits(least_squares_guess(limits, harmonics, period, seed), limits)
    elif isinstance(initial, str) and initial == 'table1':
        guess = table1_trajectory(robot, harmonics, period)
    elif isinstance(initial, FourierTrajectory):
        guess = initial
        if (guess.dof, guess.harmonics, guess.period) != (robot.dof, harmonics, period):
            raise IdentificationError(
                f'initial trajectory has {guess.dof} joints, {guess.harmonics} harmonics, '
                f'period {guess.period} s; need {robot.dof}, {harmonics}, {period} s')
        guess = FourierTrajectory(guess.a, guess.b, guess.q0, period, robot.joint_names)
    else:
        raise IdentificationError(f"unknown initial trajectory {initial!r}: use 'lsq', "
                                  "'table1' or a FourierTrajectory")
    return shrink_into_limits(guess, robot, limits)[0]


def optimize_excitation(robot, harmonics: int = DEFAULT_HARMONICS,
                        period: float = DEFAULT_PERIOD, criterion: str = 'cond',
                        limits: ExcitationLimits | Mapping | str | None = None,
                        seed: int | None = 0, maxiter: int = DEFAULT_MAXITER,
                        num_samples: int = DEFAULT_SAMPLES,
                        initial: str | FourierTrajectory | None = None, base=None,
                        noise_std: Sequence[float] | None = None,
                        margin: float = MARGIN) -> ExcitationResult:
    """Optimise a Fourier excitation of ``robot`` (a RobotModel) with SLSQP (the paper used
    Matlab's fmincon, also SQP).

    Minimises ``criterion`` ('cond' or 'dopt', see the module docstring; ``noise_std`` (n,)
    N m weights the rows of each joint) on ``num_samples`` samples of one period (s), from
    ``initial`` (see initial_trajectory), under ``limits`` (ExcitationLimits, a mapping of
    per-joint overrides or a YAML path; default the robot's) as smooth constraints (see
    _Design) at ``margin`` of the limits. The result is verified on a fine grid and scaled
    into the limits (shrink_into_limits); should it not beat the initial trajectory, the
    initial one is returned (``improved`` False). ``base``: BaseParameters of the robot
    (default: computed).
    """
    from scipy.optimize import minimize

    start = time.perf_counter()
    _check_criterion(criterion)
    H = _check_harmonics(harmonics)
    try:
        period = float(period)
    except (TypeError, ValueError):
        raise IdentificationError(f'period must be a number, got {period!r}') from None
    if not (math.isfinite(period) and period > 0):
        raise IdentificationError(f'period must be finite and > 0, got {period}')
    for name, v, low in (('maxiter', maxiter, 0), ('num_samples', num_samples, 2)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
            raise IdentificationError(f'{name} must be an integer >= {low}, got {v!r}')
    if not 0 < margin <= 1:
        raise IdentificationError(f'margin must lie in (0, 1], got {margin}')
    limits = _as_limits(robot, limits)
    base = _base_of(robot, base)
    if num_samples * robot.dof < base.num_base:
        raise IdentificationError(f'{num_samples} samples x {robot.dof} joints cannot '
                                  f'determine {base.num_base} base parameters')
    design = _Design(robot, base, limits, H, period, int(num_samples), criterion, noise_std,
                     margin)
    init = initial_trajectory(robot, initial, limits, H, period, seed)
    x0 = _to_x(init)
    f0 = design.value(x0)[0]
    if not np.isfinite(f0):
        raise IdentificationError('the initial trajectory does not excite every base '
                                  'parameter: try another seed or more harmonics')
    # SLSQP's first step follows the gradient with a unit Hessian: scale the function so that
    # its gradient has unit norm at the start, or the first steps leave the limits far behind.
    g0 = float(np.linalg.norm(design.jac(x0)))
    fscale = 1.0 / g0 if g0 > 0 else 1.0
    # Keep the best iterate that satisfies the KS constraints (SLSQP's own tolerance); the
    # last iterate may violate them slightly, shrink_into_limits then scales it in.
    feasible = [(f0, x0)]

    def track(x: np.ndarray) -> None:
        f = design.value(x)[0]
        if np.isfinite(f) and design.constraint(x).min() >= -1e-6:
            feasible.append((f, x.copy()))

    res = None
    if maxiter > 0:
        res = minimize(lambda x: design.fun(x) * fscale, x0,
                       jac=lambda x: design.jac(x) * fscale, method='SLSQP',
                       constraints=[{'type': 'ineq', 'fun': design.constraint,
                                     'jac': design.constraint_jac}],
                       callback=track, options={'maxiter': int(maxiter), 'ftol': 1e-9})
    names = list(robot.joint_names)
    best, scale, value = init, 1.0, _report_value(f0, criterion)
    candidates = [min(feasible, key=lambda item: item[0])[1]]
    if res is not None and np.all(np.isfinite(res.x)):
        candidates.append(res.x)
    for x in candidates:
        if x is x0:
            continue
        try:
            cand, s, _ = shrink_into_limits(_from_x(x, robot.dof, period, names), robot,
                                            limits)
        except IdentificationError:  # cannot be brought inside the limits: not a candidate
            continue
        v = _report_value(design.value(_to_x(cand))[0], criterion)
        if v < value:
            best, scale, value = cand, s, v
    return ExcitationResult(
        trajectory=best, initial=init, criterion=criterion, value=value,
        initial_value=_report_value(f0, criterion), ratios=limit_ratios(best, robot, limits),
        iterations=int(res.nit) if res is not None else 0, evaluations=design.evaluations,
        success=bool(res.success) if res is not None else False,
        message=str(res.message) if res is not None else 'no iterations',
        scale=scale, runtime=time.perf_counter() - start, num_samples=int(num_samples),
        limits=limits,
        noise_std=None if noise_std is None else [float(s) for s in noise_std])


# ---------------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------------
def sample_times(traj: Trajectory, rate: float, periods: int = 1) -> np.ndarray:
    """Times 0, 1/rate, ... up to and including ``periods`` passes of ``traj`` (s)."""
    if not (math.isfinite(rate) and rate > 0):
        raise IdentificationError(f'sample rate must be finite and > 0, got {rate}')
    if isinstance(periods, bool) or not isinstance(periods, (int, np.integer)) or periods < 1:
        raise IdentificationError(f'periods must be an integer >= 1, got {periods!r}')
    end = periods * traj.horizon()
    count = int(math.floor(end * rate + 1e-9))
    t = np.arange(count + 1) / rate
    return t if math.isclose(t[-1], end, abs_tol=1e-9) else np.append(t, end)


def trajectory_to_joint_trajectory(traj: Trajectory, rate: float = 100.0, periods: int = 1,
                                   joint_names: Sequence[str] | None = None,
                                   stamp: float = 0.0) -> Any:
    """A trajectory_msgs/JointTrajectory (rosbags message) of ``traj`` sampled at ``rate``
    (Hz) over ``periods`` passes including the end point: positions, velocities,
    accelerations and time_from_start per point. The motion starts at q(0) with velocity
    qd(0): bring the robot there first."""
    from .bagio import make_joint_trajectory
    names = list(joint_names or traj.joint_names or [])
    if len(names) != traj.dof:
        raise IdentificationError(f'need {traj.dof} joint names, got {names}')
    t = sample_times(traj, rate, periods)
    q, qd, qdd = traj.sample(t)
    return make_joint_trajectory(stamp, names, t, q, qd, qdd)
