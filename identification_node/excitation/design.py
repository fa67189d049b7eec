"""Excitation trajectories: finite Fourier series optimised for parameter identification.

Radkhah, Kulic and Croft, sections II.C-D and III.A-B. Each joint follows the Fourier series of
:class:`~identification_node.excitation.trajectories.FourierTrajectory` (velocity
amplitudes a, b in rad/s, offset q0 in rad, common period); the design picks the 2H + 1
coefficients per joint that minimise a criterion of the base regressor stacked over N samples of
one period, subject to the joint limits.

The criteria (``cond``, ``dopt``) are in ``excitation.criteria``, the limits and the limit
ratios in ``excitation.limits``. Each (joint, kind) of limit is one smooth constraint on the
Kreisselmeier-Steinhauser maximum of its ratios to the limit (see _Design); with a
collision.CollisionChecker, one more per checked geometry pair on its distances. Every result is
verified on a fine grid after the optimisation (torques on EFFORT_POINTS samples) and, where
needed, its motion is scaled down towards the centre of the position ranges until every ratio
is below VERIFY_RATIO; then framed by ramps from and back to rest (frame_excitation,
trajectories.FramedTrajectory) and its collisions verified densely (framed_clearance).

Initial guess: the paper's least squares on random target velocities (III.A,
least_squares_guess), or Table I (table1_trajectory, offsets moved to our joint zeros).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from identification_node.config import Excitation
from identification_node.errors import IdentificationError
from identification_node.excitation.criteria import (DEFAULT_SAMPLES, _base_of, _check_criterion,
                                                     _noise_weights, _objective, _report_value)
from identification_node.excitation.limits import (LIMIT_KINDS, VERIFY_POINTS, VERIFY_RATE,
                                                   ExcitationLimits, _as_limits, _numbers,
                                                   _ranges, _torque_models, _worst,
                                                   limit_ratios)
from identification_node.excitation.trajectories import (TABLE1_PERIOD, FourierTrajectory,
                                                         FramedTrajectory, Trajectory)

DEFAULT_HARMONICS = Excitation.harmonics
DEFAULT_PERIOD = Excitation.period
DEFAULT_MAXITER = Excitation.maxiter   # SLSQP iterations
LSQ_POINTS = 100            # random target velocities of the initial guess (paper: 100)
MARGIN = 1.0                # the optimiser's constraints: smooth max of the ratios <= MARGIN
DEFAULT_LIMIT_MARGIN = Excitation.margin   # fraction of every limit kept free
DEFAULT_PERIODS = Excitation.periods   # periods of the periodic part between the ramps
COLLISION_RATE = 100.0      # Hz: collision check of the final trajectory (and 10 ms at most)
COLLISION_PAD = 0.01        # m added to the minimum distance in the optimiser's constraints
COLLISION_SCALE = 0.05      # m of distance per unit of the collision constraints' ratio
COLLISION_RHO = 20.0        # KS sharpness over the samples: 2.5 mm of distance, smooth
COLLISION_OVERSAMPLE = 4    # collision samples per criterion sample (these and between them)
RAMP_BLENDS = (0.25, 0.5, 0.75)  # ramp configurations start + w (motion - start) constrained
RAMP_MIN = 0.5              # s: shortest ramp tried; then RAMP_GROWTH times longer each try
RAMP_GROWTH = 1.15
RAMP_MAX = 120.0            # s: longest ramp tried
CANDIDATES = 8              # iterates (best first) verified as final candidates, at most
NEAR_FEASIBLE = 0.1         # KS constraint violation of the iterates still tried as candidates
BLENDS = (0.9, 0.75, 0.5, 0.3, 0.15)  # fractions of the way from the initial guess tried last
GRID_PER_HARMONIC = 40      # constraint grid points per period and harmonic
KS_RHO = 200.0              # sharpness of the smooth maximum of the limit ratios
INITIAL_MARGIN = 0.95        # the initial guess reaches this fraction of its tightest limit
VERIFY_RATIO = 0.999        # a verified result stays below this fraction of every limit
PROGRESS_INTERVAL = 10.0    # s between progress lines, at most
# Table I's joint zeros -> ours (crs_a465.urdf: arm straight up at zero), q_ours = q_paper +
# offset. Table I moves joint 2 over [36, 148] deg and joint 3 over [-163, -10] deg: centred on
# +90 and -90 deg, where our symmetric +-90 / +-110 deg ranges are centred on 0. With the
# quarter-turn shifts every joint stays inside our limits; the senses of rotation are kept (the
# paper does not state them).
TABLE1_OFFSET = (0.0, -math.pi / 2, math.pi / 2, 0.0, 0.0, 0.0)
_STEP_Q = 1e-6   # rad, finite-difference step of the regressor in q
_STEP_QD = 1e-6  # rad/s, in qd (qdd enters linearly: exact with step 1)


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
                       target: float = VERIFY_RATIO, max_steps: int = 60,
                       phis: Sequence[np.ndarray] | None = None
                       ) -> tuple[FourierTrajectory, float, dict]:
    """Scale the motion down until every limit ratio (limit_ratios) is at most ``target``:
    amplitudes times s, and each offset q0 drawn towards the centre of its position range by
    the same factor (kept where unlimited), so every kinematic ratio scales by s exactly.
    Returns (trajectory, s, ratios); IdentificationError when even the centre of the ranges
    at rest exceeds the effort limits. ``phis``: the torque models (see limit_ratios)."""
    ratios = limit_ratios(traj, robot, limits, phis=phis)
    kinematic = max(ratios[k] for k in LIMIT_KINDS[:3])
    scale = min(1.0, target / kinematic) if kinematic > 0 else 1.0
    for _ in range(max_steps):
        cur = _scaled(traj, limits, scale)
        if scale != 1.0:
            ratios = limit_ratios(cur, robot, limits, phis=phis)
        if _worst(ratios) <= target:
            return cur, scale, ratios
        scale *= float(np.clip(target / _worst(ratios), 0.5, 0.995))
    raise IdentificationError('infeasible limits: the trajectory cannot be scaled into the '
                              'effort limits (with their margin): the static torque near the '
                              'centre of the position ranges exceeds them')


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


def _no_tick() -> None:
    pass


class _TimeUp(Exception):
    """The optimisation's time limit passed (raised from inside SLSQP's callbacks)."""


class _Progress:
    """Progress lines (iteration, criterion, worst constraint, elapsed) to ``report`` at most
    ``interval`` s apart, checked at every evaluation; and the optimiser's time limit (s after
    ``start``, None: none), which raises _TimeUp from the next evaluation."""

    def __init__(self, report: Callable[[str], None] | None, time_limit: float | None,
                 start: float, criterion: str):
        self.report, self.start, self.interval = report, start, PROGRESS_INTERVAL
        self.deadline = None if time_limit is None else start + time_limit
        self.criterion = criterion
        self.iteration, self.value, self.worst = 0, math.nan, math.nan
        self.best = math.inf     # criterion of the best iterate meeting the constraints
        self.last = start
        self.optimising = False
        self.verifying = False

    def iterate(self, value: float, worst: float) -> None:
        self.iteration += 1
        self.value, self.worst = value, worst
        if worst >= 0:
            self.best = min(self.best, value)
        self.tick()

    def tick(self) -> None:
        now = time.perf_counter()
        if self.optimising and self.deadline is not None and now >= self.deadline:
            self.optimising = False
            raise _TimeUp
        if self.report is not None and now - self.last >= self.interval:
            self.say(now)

    def say(self, now: float | None = None, what: str = '') -> None:
        now = time.perf_counter() if now is None else now
        self.last = now
        if self.report is None:
            return
        best = f', best feasible {self.best:.6g}' if math.isfinite(self.best) else ''
        if what:
            self.report(what)
        elif self.verifying:
            self.report(f'verifying: {now - self.start:.0f} s')
        elif not self.iteration:
            self.report(f'{"optimising" if self.optimising else "preparing"}: no iteration '
                        f'finished yet, {now - self.start:.0f} s')
        else:
            self.report(f'iteration {self.iteration}: criterion {self.criterion} '
                        f'{self.value:.6g}{best}, worst constraint {self.worst:+.3g} '
                        f'(< 0: violated), {now - self.start:.0f} s')


class _Design:
    """Criterion and limit constraints, with gradients, of coefficient vectors x (per joint
    [a_1..a_H, b_1..b_H, q0], joints in order).

    Each limit is one smooth constraint per joint, KS(ratios) <= margin: the
    Kreisselmeier-Steinhauser maximum (KS_RHO) of |q - centre| / half range, |qd| / limit,
    |qdd| / limit on a grid of GRID_PER_HARMONIC * H points of one period and of |tau| / limit
    at the criterion samples (under every parameter vector of ``phis``). KS bounds the grid
    maximum from above, and a few dozen smooth constraints keep SLSQP's QP subproblems small
    and well posed, where one linear constraint per grid point (thousands of nearly parallel
    rows) made them fail.

    With a CollisionChecker, one more constraint per checked pair: the KS maximum
    (COLLISION_RHO) over the criterion samples, COLLISION_OVERSAMPLE - 1 samples between each
    two of them, the ramps' configurations start + w (q(t) - start) at the criterion samples
    for w in RAMP_BLENDS, and the start (q0 unless ``start`` is given) of
    1 + (d_min + COLLISION_PAD - distance) / COLLISION_SCALE, on the checker's convex hulls
    (CollisionChecker.hulls: lower bounds of the mesh distances, and much faster).
    """

    def __init__(self, robot, base, limits: ExcitationLimits, harmonics: int, period: float,
                 num_samples: int, criterion: str, noise_std, margin: float,
                 phis: Sequence[np.ndarray] | None = None, checker=None,
                 start: np.ndarray | None = None):
        self.robot, self.base, self.limits = robot, base, limits
        self.n, self.H, self.period = robot.dof, harmonics, period
        self.k = 2 * harmonics + 1
        self.criterion = criterion
        self.weights = _noise_weights(noise_std, self.n)
        t = np.arange(num_samples) * (period / num_samples)
        self.Bq, self.Bv, self.Ba = fourier_basis(t, harmonics, period)
        grid = GRID_PER_HARMONIC * harmonics
        self.grid = fourier_basis(np.arange(grid) * (period / grid), harmonics, period)
        self.Phi = np.column_stack(_torque_models(robot, phis))    # (p, models)
        self.margin = margin
        self.checker = checker.hulls() if checker is not None and checker.num_pairs else None
        self.tick = _no_tick
        # collision samples q = Bc X + Cc: the motion, then the ramps' blends of the start
        # (q0, or the given ``start``) and the motion at the criterion samples, then the start
        m = COLLISION_OVERSAMPLE * num_samples
        path = fourier_basis(np.arange(m) * (period / m), harmonics, period)[0]
        e0 = np.zeros((1, self.k))
        e0[0, -1] = 1.0   # q = q0
        fixed = start is not None
        from_start = np.zeros_like(e0) if fixed else e0
        self.Bc = np.vstack([path] + [w * self.Bq + (1 - w) * from_start for w in RAMP_BLENDS]
                            + [from_start])
        weight = np.concatenate([np.zeros(m)] + [np.full(num_samples, 1 - w)
                                                 for w in RAMP_BLENDS] + [np.ones(1)])
        self.Cc = (weight[:, None] * np.asarray(start, dtype=float)[None] if fixed
                   else np.zeros((len(weight), self.n)))
        self._collision: tuple[bytes, np.ndarray, np.ndarray | None] | None = None
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
        """(optimised function, torques (N, n, models) under the torque models)."""
        key = x.tobytes()
        if self._value is None or self._value[0] != key:
            self.evaluations += 1
            self.tick()
            Y = self.robot.regressor(*self.kinematics(x))
            f = _objective(self._W(Y), self.criterion, False)[0]
            self._value = (key, f, Y @ self.Phi)
        return self._value[1], self._value[2]

    def gradient(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gradient of the function (nx,), Jacobian of the torques (N, n, models, nx)).

        The regressor is differentiated per sample in each joint's q, qd (forward differences)
        and qdd (exact: it enters linearly), then chained through the Fourier basis: 3n + 1
        regressor evaluations instead of one per coefficient."""
        key = x.tobytes()
        if self._grad is not None and self._grad[0] == key:
            return self._grad[1], self._grad[2]
        self.evaluations += 1
        self.tick()
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
        self._value = (key, f, Y[0] @ self.Phi)
        if dfdW is None:
            raise IdentificationError('the trajectory does not excite every base parameter')
        M = dfdW.reshape(N, n, -1) * self.weights[None, :, None]
        g = np.einsum('knjc,njc->kn', dY[..., self.base.base_index], M)  # (3n, N)
        B = (self.Bq, self.Bv, self.Ba)
        grad = np.concatenate([sum(B[s].T @ g[s * n + i] for s in range(3)) for i in range(n)])
        dtau = dY @ self.Phi                                     # (3n, N, n, models)
        J = np.concatenate([sum(dtau[s * n + i][..., None] * B[s][:, None, None, :]
                                for s in range(3)) for i in range(n)], axis=3)
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
            tau = self.value(x)[1][:, self.effort]                # (N, ne, m)
            N, m = tau.shape[0], tau.shape[2]
            r = tau.transpose(0, 2, 1).reshape(N * m, -1) / e
            ks, w = _ks(np.concatenate([r, -r]), KS_RHO)
            values.append(ks)
            if jac:
                J = self.gradient(x)[1][:, self.effort]           # (N, ne, m, nx)
                dw = (w[:N * m] - w[N * m:]).reshape(N, m, -1)
                rows.append(np.einsum('tmj,tjmx->jx', dw, J) / e[:, None])
        if self.checker is not None:
            ks, dks = self._collision_ks(x, jac)
            values.append(ks)
            if dks is not None:   # jac
                rows.append(dks)
        return np.concatenate(values), (np.vstack(rows) if jac else None)

    def collision_configs(self, x: np.ndarray) -> np.ndarray:
        """The joint positions (S, n) the collision constraints hold at."""
        return self.Bc @ x.reshape(self.n, self.k).T + self.Cc

    def _collision_ks(self, x: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Per pair, KS over the collision samples of 1 + (d_req - d) / COLLISION_SCALE, and
        its Jacobian (pairs, nx)."""
        assert self.checker is not None   # called only with collision constraints
        key = x.tobytes()
        cached = self._collision
        if cached is None or cached[0] != key or (jac and cached[2] is None):
            self.tick()
            q = self.collision_configs(x)                            # (S, n)
            if jac:
                d, g = self.checker.distances_and_gradients(q)       # (S, P), (S, P, n)
            else:
                d, g = self.checker.distances(q), None
            self._collision = cached = (key, d, g)
        _, d, g = cached
        need = self.checker.min_distance + COLLISION_PAD
        ks, w = _ks(1.0 + (need - d) / COLLISION_SCALE, COLLISION_RHO)  # (P,), (S, P)
        if not jac:
            return ks, None
        assert g is not None   # computed with the Jacobian
        # d r / d x[i, :] = -g[s, p, i] Bc[s, :] / scale, weighted by w[s, p]
        dks = -np.einsum('sp,spi,sk->pik', w, g, self.Bc) / COLLISION_SCALE
        return ks, dks.reshape(len(ks), -1)

    def constraint(self, x: np.ndarray) -> np.ndarray:
        return self.margin - self._limits(x, False)[0]

    def constraint_jac(self, x: np.ndarray) -> np.ndarray:
        jacobian = self._limits(x, True)[1]
        assert jacobian is not None   # asked for
        return -jacobian


@dataclass
class ExcitationResult:
    """An optimised excitation and how it was found.

    trajectory: the optimised FourierTrajectory, the periodic part (verified inside every
    limit with its margin); framed: the FramedTrajectory a robot runs (ramps from and back to
    the start configuration at rest around ``periods`` periods of it); initial: the starting
    trajectory; criterion: 'cond' or 'dopt'; value, initial_value: the criterion of each on the
    periodic part (criterion_value with num_samples samples); ratios: limit_ratios of the
    framed trajectory against the limits without margin; iterations (SLSQP), evaluations
    (criterion or gradient), success, status and message (SLSQP's); scale: factor applied to
    the optimiser's amplitudes to satisfy the limits on the fine grid (1: none); runtime (s);
    margin: the limit margin; warnings: what the user should know (iteration limit, no
    improvement); clearance: the smallest collision distance on the final trajectory's dense
    grid (CollisionChecker.clearance), None without collision checking; initial_feasible:
    whether the initial guess met every constraint.
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
    framed: FramedTrajectory | None = None
    margin: float = DEFAULT_LIMIT_MARGIN
    status: int = 0
    warnings: list[str] = field(default_factory=list)
    clearance: dict | None = None
    collision: dict | None = None
    initial_feasible: bool = True

    @property
    def improved(self) -> bool:
        return self.value < self.initial_value

    def summary(self) -> dict:
        """Plain data for YAML: criterion, parts' durations, limit ratios (of the limits
        without margin), collision clearance, optimisation statistics and warnings."""
        names = self.trajectory.joint_names or []
        out: dict[str, Any] = {
            'criterion': {'name': self.criterion, 'value': self.value,
                          'initial': self.initial_value,
                          'initial_feasible': bool(self.initial_feasible),
                          'samples': self.num_samples,
                          **({'noise_std': self.noise_std} if self.noise_std else {})},
        }
        if self.framed is not None:
            out['durations'] = self.framed.parts()
        out['limit_margin'] = self.margin
        out['limit_ratios'] = {
            k: {'worst': float(self.ratios[k]),
                'joint': names[self.ratios['worst_joint'][k]] if names
                else int(self.ratios['worst_joint'][k]),
                'per_joint': [float(v) for v in self.ratios['per_joint'][k]]}
            for k in LIMIT_KINDS}
        if self.collision is not None:
            c = self.clearance or {}
            out['collision'] = {**self.collision, 'clearance': c.get('distance'),
                                'closest_pair': list(c['pair']) if c.get('pair') else None}
        out['optimisation'] = {'method': 'SLSQP', 'iterations': self.iterations,
                               'evaluations': self.evaluations, 'success': bool(self.success),
                               'status': self.status, 'message': self.message,
                               'scale': self.scale, 'runtime': round(self.runtime, 3)}
        out['warnings'] = list(self.warnings)
        return out


def initial_trajectory(robot, initial: str | FourierTrajectory | None,
                       limits: ExcitationLimits, harmonics: int, period: float,
                       seed: int | None, phis: Sequence[np.ndarray] | None = None
                       ) -> FourierTrajectory:
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
    return shrink_into_limits(guess, robot, limits, phis=phis)[0]


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
        if _worst(ratios) <= 1.0:   # the periodic part keeps VERIFY_RATIO: room to blend in
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
    start = periodic.q0 if start is None else _start(start, limits)
    t_in = _ramp(periodic, robot, limits, start, 'in', phis)
    t_out = _ramp(periodic, robot, limits, start, 'out', phis)
    return FramedTrajectory(periodic, start, t_in, t_out, periods)


def _start(start: Sequence[float] | np.ndarray, limits: ExcitationLimits) -> np.ndarray:
    q = _numbers('start configuration', start).reshape(-1)
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
                     tick: Callable[[], None] = _no_tick) -> dict:
    """CollisionChecker.clearance of a framed trajectory: its ramps and one period (the others
    repeat it) checked at times that advance conservatively. No point of the arm (reach: the
    sum of the joint offsets + 0.5 m) moves faster than v = reach * peak summed joint speed,
    so from a time with distance d (the hulls' lower bound), the next is (d - min_distance) / v
    later: between them no pair comes closer than the minimum distance. The step is at least
    ``travel`` / v (no point moves more than ``travel`` m between checked times, as on a
    uniform grid of that step) and at most 1 / COLLISION_RATE."""
    t0, t1 = framed.periodic_window
    assert framed.periodic.period is not None   # a framed trajectory's is periodic
    period = float(framed.periodic.period)
    probe = np.linspace(0.0, framed.duration, max(2001, int(framed.duration * VERIFY_RATE)))
    speed = float(np.abs(framed.sample(probe)[1]).sum(axis=1).max())
    reach = sum(float(np.linalg.norm(p.translation)) for p in robot.model.jointPlacements) + 0.5
    v = max(reach * speed, 1e-12)
    shortest, longest = min(travel / v, 1.0 / COLLISION_RATE), 1.0 / COLLISION_RATE
    bounds = checker.hulls()
    times = []
    for a, b in [(0.0, t0), (t0, t0 + period), (t1, framed.duration)]:
        t = a
        while True:
            times.append(t)
            if t >= b:
                break
            d = float(bounds.distances(framed.sample(np.array([t]))[0]).min())
            t = min(b, t + min(longest, max(shortest, (d - checker.min_distance) / v)))
            tick()
    return checker.clearance(framed.sample(np.array(times))[0])


def optimize_excitation(robot, harmonics: int = DEFAULT_HARMONICS,
                        period: float = DEFAULT_PERIOD, criterion: str = 'cond',
                        limits: ExcitationLimits | Mapping | str | None = None,
                        seed: int | None = 0, maxiter: int = DEFAULT_MAXITER,
                        num_samples: int = DEFAULT_SAMPLES,
                        initial: str | FourierTrajectory | None = None, base=None,
                        noise_std: Sequence[float] | None = None,
                        margin: float = DEFAULT_LIMIT_MARGIN,
                        start: Sequence[float] | None = None, periods: int = DEFAULT_PERIODS,
                        phis: Sequence[np.ndarray] | None = None,
                        checker=None, progress: Callable[[str], None] | None = None,
                        time_limit: float | None = None) -> ExcitationResult:
    """Optimise a Fourier excitation of ``robot`` (a RobotModel) with SLSQP (the paper used
    Matlab's fmincon, also SQP), and frame it with ramps from and back to rest.

    Minimises ``criterion`` ('cond' or 'dopt', see the module docstring; ``noise_std`` (n,)
    N m weights the rows of each joint) on ``num_samples`` samples of one period (s), from
    ``initial`` (see initial_trajectory), under ``limits`` (ExcitationLimits, a mapping of
    per-joint overrides or a YAML path; default the robot's) with ``margin`` of each kept free
    (ExcitationLimits.with_margin), torques under every parameter vector of ``phis`` (default
    the robot's own; e.g. the model's and an estimate's), and with a CollisionChecker
    ``checker`` at least its min_distance between the checked pairs, as smooth constraints
    (see _Design). Feasible iterates are verified on fine grids and scaled into the limits
    (shrink_into_limits), framed by ramps from ``start`` (default: the offset q0) into
    ``periods`` periods and back (frame_excitation), and the framed trajectory's collisions
    checked densely (framed_clearance); the best verified one is kept. Stopping at the
    iteration limit (``maxiter``) or the time limit (``time_limit`` s of optimisation; the
    verification follows) is said in ``message``; stopping on infeasibility is a warning
    (``warnings``); IdentificationError when no feasible point was found. ``base``:
    BaseParameters of the robot (default: computed). ``progress`` receives a line at least
    every PROGRESS_INTERVAL s: iteration, criterion, worst constraint, elapsed time.
    """
    from scipy.optimize import minimize

    start_time = time.perf_counter()
    _check_criterion(criterion)
    H = _check_harmonics(harmonics)
    try:
        period = float(period)
    except (TypeError, ValueError):
        raise IdentificationError(f'period must be a number, got {period!r}') from None
    if not (math.isfinite(period) and period > 0):
        raise IdentificationError(f'period must be finite and > 0, got {period}')
    for name, v, low in (('maxiter', maxiter, 0), ('num_samples', num_samples, 2),
                         ('periods', periods, 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
            raise IdentificationError(f'{name} must be an integer >= {low}, got {v!r}')
    if time_limit is not None and not (isinstance(time_limit, (int, float)) and time_limit > 0
                                       and not isinstance(time_limit, bool)):
        raise IdentificationError(f'time limit must be a number of seconds > 0, got '
                                  f'{time_limit!r}')
    limits = _as_limits(robot, limits)
    work = limits.with_margin(margin)
    start_q = None if start is None else _start(start, work)
    checker = checker if checker is not None and checker.num_pairs else None
    if checker is not None and start_q is not None:
        c = checker.clearance(start_q[None])
        if c['distance'] < checker.min_distance:
            raise IdentificationError(f'the start configuration is in collision: {c["pair"][0]}'
                                      f' - {c["pair"][1]} at {c["distance"]:.4g} m (minimum '
                                      f'{checker.min_distance:g} m)')
    base = _base_of(robot, base)
    if num_samples * robot.dof < base.num_base:
        raise IdentificationError(f'{num_samples} samples x {robot.dof} joints cannot '
                                  f'determine {base.num_base} base parameters')
    design = _Design(robot, base, work, H, period, int(num_samples), criterion, noise_std,
                     MARGIN, phis, checker, start_q)
    watch = _Progress(progress, time_limit, start_time, criterion)
    design.tick = watch.tick
    init = initial_trajectory(robot, initial, work, H, period, seed, phis)
    if checker is not None:
        init = _out_of_collision(init, design, work)
    x0 = _to_x(init)
    f0 = design.value(x0)[0]
    if not np.isfinite(f0):
        raise IdentificationError('the initial trajectory does not excite every base '
                                  'parameter: try another seed or more harmonics')
    # init is inside the limits (shrunk on the fine grid); collisions at the design's samples
    initial_feasible = design.checker is None or bool(   # None iff checker is
        design.checker.distances(design.collision_configs(x0)).min()
        >= checker.min_distance)
    # SLSQP's first step follows the gradient with a unit Hessian: scale the function so that
    # its gradient has unit norm at the start, or the first steps leave the limits far behind.
    g0 = float(np.linalg.norm(design.jac(x0)))
    fscale = 1.0 / g0 if g0 > 0 else 1.0
    # Keep every iterate that satisfies the constraints (SLSQP's own tolerance); the last
    # iterate may violate them slightly, shrink_into_limits then scales it in.
    # (function, worst constraint, x) of the iterates; SLSQP's approach the constraints from
    # outside, and shrink_into_limits scales small kinematic violations away
    iterates = [(f0, 0.0, x0)] if initial_feasible else []

    def track(x: np.ndarray) -> None:
        f = design.value(x)[0]
        if np.isfinite(f):
            worst = float(design.constraint(x).min())
            iterates.append((f, worst, x.copy()))
            watch.iterate(_report_value(f, criterion), worst)

    res = None
    if maxiter > 0:
        watch.say(what=f'optimising: {x0.size} coefficients, {design.constraint(x0).size} '
                  f'constraints, at most {maxiter} iterations'
                  + ('' if time_limit is None else f' or {time_limit:g} s'))
        watch.optimising = True
        try:
            res = minimize(lambda x: design.fun(x) * fscale, x0,
                           jac=lambda x: design.jac(x) * fscale, method='SLSQP',
                           constraints=[{'type': 'ineq', 'fun': design.constraint,
                                         'jac': design.constraint_jac}],
                           callback=track, options={'maxiter': int(maxiter), 'ftol': 1e-9})
        except _TimeUp:
            last = iterates[-1][2] if iterates else x0
            res = SimpleNamespace(x=last, nit=watch.iteration, success=False, status=-1,
                                  message=f'time limit of {time_limit:g} s reached')
        watch.optimising, watch.verifying = False, True
        watch.say(what=f'{watch.iteration} iterations in {time.perf_counter() - start_time:.0f}'
                  ' s; verifying the best iterates on dense grids')
    names = list(robot.joint_names)
    reasons: list[str] = []

    def verified(x: np.ndarray) -> tuple | None:
        """(criterion, periodic, framed, scale, clearance) of x brought inside every limit,
        framed and checked for collisions; None (the reason noted) when it cannot be."""
        try:
            cand, s, _ = shrink_into_limits(_from_x(x, robot.dof, period, names), robot, work,
                                            phis=phis)
            framed = frame_excitation(cand, robot, work, start_q, periods, phis)
        except IdentificationError as exc:   # cannot be brought inside the limits
            reasons.append(str(exc))
            return None
        clearance = None
        if checker is not None:
            for check in (lambda: checker.clearance(design.collision_configs(_to_x(cand))),
                          lambda: framed_clearance(framed, robot, checker, tick=watch.tick)):
                clearance = check()   # the design's samples first: cheap
                if clearance['distance'] < checker.min_distance:
                    reasons.append(f'collision between {clearance["pair"][0]} and '
                                   f'{clearance["pair"][1]} ({clearance["distance"]:.4g} m)')
                    return None
        return (_report_value(design.value(_to_x(cand))[0], criterion), cand, framed, s,
                clearance)

    f_init = _report_value(f0, criterion)
    # the feasible iterates and those within NEAR_FEASIBLE of the constraints: the best of each
    # of CANDIDATES stretches of the iterations (consecutive iterates are alike and tend to
    # fail the dense checks alike), best first

    def rank(it: tuple) -> tuple:
        return it[0], it[1] < -1e-6
    close = [it for it in iterates if it[1] >= -NEAR_FEASIBLE]
    near = sorted((min((close[i] for i in part), key=rank)
                   for part in np.array_split(np.arange(len(close)), CANDIDATES) if part.size),
                  key=rank)
    candidates = [x for _, _, x in near]
    if res is not None and np.all(np.isfinite(res.x)):
        candidates.insert(0, res.x)
    if not initial_feasible:
        candidates.append(x0)   # the shrinking may still bring it inside
    best, initial_kept = None, False
    for x in candidates[:CANDIDATES]:
        found = verified(x)
        if found is not None and (best is None or found[0] < best[0]):
            best, initial_kept = found, x is x0
        if best is not None and x is not candidates[0]:
            break   # the iterates come best first
    if (best is None or best[0] >= f_init) and res is not None and initial_feasible:
        # blend the best near-feasible iterate (else the last) with the feasible initial
        # guess, x0 + alpha (x - x0), and keep the first verified blend improving on it
        x_end = near[0][2] if near and near[0][2] is not x0 else (
            iterates[-1][2] if iterates else res.x)
        for alpha in BLENDS:
            found = verified(x0 + alpha * (x_end - x0))
            if found is not None and found[0] < f_init:
                best, initial_kept = found, False
                break
    if best is None:
        why = reasons[-1] if reasons else 'no iterate met the constraints'
        raise IdentificationError(
            f'no feasible excitation found ({why}): loosen the limits or their margin, lower '
            'the minimum distance, or try another start configuration, seed or fewer '
            'harmonics')
    value, traj, framed, scale, clearance = best
    is_initial = initial_kept
    warnings = []
    message = str(res.message) if res is not None else 'no iterations'
    if res is not None and res.status == 9:   # the iteration limit: said, not a warning
        message = (f'stopped at the limit of {res.nit} iterations (--maxiter); kept the best '
                   'feasible point found')
    elif res is not None and res.status == -1:
        message = f'stopped at the {message}; kept the best feasible point found'
    elif res is not None and not res.success:
        warnings.append(f'SLSQP stopped without converging after {res.nit} iterations '
                        f'({res.message}); kept the best feasible point found (the '
                        'constraints may be too tight: loosen the limits or the margin)')
    if is_initial or value >= f_init:
        warnings.append('no feasible point improved on the initial guess; kept '
                        + ('it' if initial_feasible else 'it, scaled into the constraints'))
    return ExcitationResult(
        trajectory=traj, initial=init, criterion=criterion, value=value,
        initial_value=f_init, ratios=limit_ratios(framed, robot, limits, phis=phis),
        iterations=int(res.nit) if res is not None else 0, evaluations=design.evaluations,
        success=bool(res.success) if res is not None else False,
        message=message,
        scale=scale, runtime=time.perf_counter() - start_time, num_samples=int(num_samples),
        limits=limits,
        noise_std=None if noise_std is None else [float(s) for s in noise_std],
        framed=framed, margin=float(margin),
        status=int(res.status) if res is not None else 0, warnings=warnings,
        clearance=clearance, collision=None if checker is None else checker.summary(),
        initial_feasible=initial_feasible)


def _out_of_collision(traj: FourierTrajectory, design: _Design, limits: ExcitationLimits,
                      steps: int = 20) -> FourierTrajectory:
    """``traj``, or its motion scaled towards the centre of the position ranges (by 0.8 per
    step) until it meets the collision constraints (at the design's collision samples); ``traj``
    unchanged when no scaling does (the optimiser then starts infeasible)."""
    cur, scale = traj, 1.0
    for _ in range(steps):
        if design._collision_ks(_to_x(cur), False)[0].max() <= design.margin:
            return cur
        scale *= 0.8
        cur = _scaled(traj, limits, scale)
    return traj


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
    qd(0) (at rest for a FramedTrajectory): bring the robot there first."""
    from identification_node.bags.writer import make_joint_trajectory
    names = list(joint_names or traj.joint_names or [])
    if len(names) != traj.dof:
        raise IdentificationError(f'need {traj.dof} joint names, got {names}')
    t = sample_times(traj, rate, periods)
    q, qd, qdd = traj.sample(t)
    return make_joint_trajectory(stamp, names, t, q, qd, qdd)


def plot_excitation(framed: FramedTrajectory, limits: ExcitationLimits, path: str | os.PathLike,
                    margin: float = DEFAULT_LIMIT_MARGIN, rate: float = 100.0,
                    title: str = '') -> Path:
    """PNG of q, qd, qdd (columns) per joint (rows) against time, with the limits (dashed)
    and the limits with their margin (dotted) drawn and the ramps shaded; written
    atomically."""
    from matplotlib.figure import Figure

    from identification_node.fileio import save_figure

    t = sample_times(framed, rate)
    motion = framed.sample(t)
    work = limits.with_margin(margin)
    names = framed.joint_names or [f'q{i + 1}' for i in range(framed.dof)]
    n = framed.dof
    fig = Figure(figsize=(13, 1.2 + 1.9 * n))
    axes = fig.subplots(n, 3, sharex=True, squeeze=False)
    t0, t1 = framed.periodic_window
    bounds = [(limits.position_limits, work.position_limits)] + [
        (np.stack([-v, v], axis=1), np.stack([-w, w], axis=1))
        for v, w in ((limits.velocity_limits, work.velocity_limits),
                     (limits.acceleration_limits, work.acceleration_limits))]
    units = ('rad', 'rad/s', 'rad/s^2')
    for col, (label, x, (raw, kept)) in enumerate(zip(('position', 'velocity', 'acceleration'),
                                                      motion, bounds)):
        for j in range(n):
            ax = axes[j, col]
            ax.axvspan(0.0, t0, color='0.92')
            ax.axvspan(t1, framed.duration, color='0.92')
            ax.plot(t, x[:, j], color='tab:blue', lw=0.9)
            for value in raw[j]:
                if np.isfinite(value):
                    ax.axhline(value, color='tab:red', ls='--', lw=0.8)
            for value in kept[j]:
                if np.isfinite(value):
                    ax.axhline(value, color='tab:orange', ls=':', lw=0.8)
            ax.grid(alpha=0.3)
            ax.set_ylabel(f'{names[j]} ({units[col]})', fontsize='small')
        axes[0, col].set_title(label)
        axes[-1, col].set_xlabel('time (s)')
    fig.suptitle(title or f'excitation: ramp in {t0:.1f} s (shaded), periodic '
                 f'{t1 - t0:.1f} s, ramp out {framed.duration - t1:.1f} s; limits dashed, '
                 f'with {100 * margin:g} % margin dotted', fontsize='medium')
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.98))
    return save_figure(fig, Path(path))
