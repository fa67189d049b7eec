"""The excitation design as an optimisation problem: the criterion and the smooth limit and
collision constraints of Fourier coefficient vectors, with gradients (see DesignProblem)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.excitation.criteria import noise_weights, objective
from identification_node.excitation.initial_guess import fourier_basis
from identification_node.excitation.limits import ExcitationLimits, position_ranges, torque_models

__all__ = ['BOUND_SLACK', 'COLLISION_CULL_PAIRS', 'COLLISION_FAR', 'COLLISION_OVERSAMPLE',
           'COLLISION_PAD', 'COLLISION_RHO', 'COLLISION_SCALE', 'GRADIENT_WEIGHT',
           'GRID_PER_HARMONIC', 'KS_RHO', 'RAMP_BLENDS', 'DesignProblem', 'ks_max', 'no_tick']

COLLISION_PAD = 0.01        # m added to the minimum distance in the optimiser's constraints
COLLISION_SCALE = 0.05      # m of distance per unit of the collision constraints' ratio
COLLISION_RHO = 20.0        # KS sharpness over the samples: 2.5 mm of distance, smooth
# a sample's KS weight in a pair's constraint below which its distance gradient is not computed
# (it would change the constraint's gradient by less than this fraction; 7 cm farther than the
# pair's closest sample)
GRADIENT_WEIGHT = 1e-12
# m beyond a pair's need where its distance is not computed, its bounding spheres' standing in
# (CollisionChecker.distances' within): 4 units of the constraint's ratio from its bound; only
# with more than COLLISION_CULL_PAIRS pairs (the spheres' test costs what ~45 pairs' distances do)
COLLISION_FAR = 0.2
COLLISION_CULL_PAIRS = 100
COLLISION_OVERSAMPLE = 4    # collision samples per criterion sample (these and between them)
RAMP_BLENDS = (0.25, 0.5, 0.75)  # ramp configurations start + w (motion - start) constrained
GRID_PER_HARMONIC = 40      # constraint grid points per period and harmonic
KS_RHO = 200.0              # sharpness of the smooth maximum of the limit ratios
BOUND_SLACK = 1.1           # the coefficients' bounds over those of the limits (see bounds)
_STEP_Q = 1e-6   # rad, finite-difference step of the regressor in q
_STEP_QD = 1e-6  # rad/s, in qd (qdd enters linearly: exact with step 1)


def ks_max(r: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray]:
    """Kreisselmeier-Steinhauser smooth maximum over axis 0 of r (m, ...): values (...) with
    max <= KS <= max + log(m) / rho, and its weights dKS/dr (m, ...)."""
    top = r.max(axis=0)
    e = np.exp(rho * (r - top))
    total = e.sum(axis=0)
    return top + np.log(total) / rho, e / total


def no_tick() -> None:
    """A progress tick that does nothing."""
    pass


class DesignProblem:
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
    (CollisionChecker.hulls: lower bounds of the mesh distances, and much faster). A pair the
    start already breaks in that measure is held no worse than there (hold_collisions_at):
    SLSQP cannot restore it (its distance gradients are not smooth at that scale) and diverges.
    """

    def __init__(self, robot, base, limits: ExcitationLimits, harmonics: int, period: float,
                 num_samples: int, criterion: str, noise_std, margin: float,
                 phis: Sequence[np.ndarray] | None = None, checker=None,
                 start: np.ndarray | None = None):
        self.robot, self.base, self.limits = robot, base, limits
        self.n, self.H, self.period = robot.dof, harmonics, period
        self.k = 2 * harmonics + 1
        self.criterion = criterion
        self.weights = noise_weights(noise_std, self.n)
        t = np.arange(num_samples) * (period / num_samples)
        self.Bq, self.Bv, self.Ba = fourier_basis(t, harmonics, period)
        grid = GRID_PER_HARMONIC * harmonics
        self.grid = fourier_basis(np.arange(grid) * (period / grid), harmonics, period)
        self.Phi = np.column_stack(torque_models(robot, phis))    # (p, models)
        self.margin = margin
        self.checker = checker.hulls() if checker is not None and checker.num_pairs else None
        self.tick = no_tick
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
        # m, per pair: the distance the collision constraints ask for (see hold_collisions_at)
        self.need = (np.full(self.checker.num_pairs, self.checker.min_distance + COLLISION_PAD)
                     if self.checker is not None else np.zeros(0))
        limited, centre, half = position_ranges(limits)
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
            f = objective(self._W(Y), self.criterion, False)[0]
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
        f, dfdW = objective(self._W(Y[0]), self.criterion, True)
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
            ks, w = ks_max(np.concatenate([r, -r]), KS_RHO)
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
            ks, w = ks_max(np.concatenate([r, -r]), KS_RHO)
            values.append(ks)
            if jac:
                J = self.gradient(x)[1][:, self.effort]           # (N, ne, m, nx)
                dw = (w[:N * m] - w[N * m:]).reshape(N, m, -1)
                rows.append(np.einsum('tmj,tjmx->jx', dw, J) / e[:, None])
        if self.checker is not None:
            ks, dks = self.collision_ks(x, jac)
            values.append(ks)
            if dks is not None:   # jac
                rows.append(dks)
        return np.concatenate(values), (np.vstack(rows) if jac else None)

    def collision_configs(self, x: np.ndarray) -> np.ndarray:
        """The joint positions (S, n) the collision constraints hold at."""
        return self.Bc @ x.reshape(self.n, self.k).T + self.Cc

    def collision_distances(self, x: np.ndarray) -> np.ndarray:
        """Distances (S, pairs) in m at the collision samples of x, on the hulls; farther
        than COLLISION_FAR beyond a pair's need, a lower bound of them (with many pairs)."""
        assert self.checker is not None   # called only with collision constraints
        key = x.tobytes()
        if self._collision is None or self._collision[0] != key:
            self.tick()
            self._collision = (key, self.checker.distances(self.collision_configs(x),
                                                           self._within()), None)
        return self._collision[1]

    def _within(self) -> np.ndarray | None:
        """Per pair the distance (m) beyond which its bounding spheres stand in for it (the
        checker's ``within``), with more than COLLISION_CULL_PAIRS pairs; else None."""
        assert self.checker is not None   # called only with collision constraints
        cull = self.checker.num_pairs > COLLISION_CULL_PAIRS
        return self.need + COLLISION_FAR if cull else None

    def collision_ks(self, x: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Per pair, KS over the collision samples of 1 + (d_req - d) / COLLISION_SCALE, and
        its Jacobian (pairs, nx)."""
        d = self.collision_distances(x)                                     # (S, P)
        assert self.checker is not None and self._collision is not None   # computed above
        key, _, g = self._collision
        ks, w = ks_max(1.0 + (self.need - d) / COLLISION_SCALE, COLLISION_RHO)  # (P,), (S, P)
        if jac and g is None:   # where a sample's KS weight counts (GRADIENT_WEIGHT): (S, P, n)
            self.tick()
            g = self.checker.gradients(self.collision_configs(x), w > GRADIENT_WEIGHT,
                                       self._within())
            self._collision = (key, d, g)
        if not jac:
            return ks, None
        assert g is not None   # computed above
        # d r / d x[i, :] = -g[s, p, i] Bc[s, :] / scale, weighted by w[s, p]
        dks = -np.einsum('sp,spi,sk->pik', w, g, self.Bc) / COLLISION_SCALE
        return ks, dks.reshape(len(ks), -1)

    def hold_collisions_at(self, x: np.ndarray) -> np.ndarray:
        """Lower the need of each pair whose collision constraint x breaks by all x lacks, so
        that x meets it exactly (the pair held no worse than at x); the pairs' indices. The
        KS maximum overestimates the closest distance, so x may still keep the minimum
        distance; the final dense check on the meshes decides."""
        if self.checker is None:
            return np.zeros(0, dtype=int)
        lack = (self.collision_ks(x, False)[0] - self.margin) * COLLISION_SCALE   # m
        held = np.flatnonzero(lack > 0)
        self.need[held] -= lack[held]
        return held

    def bounds(self) -> list[tuple[float | None, float | None]]:
        """Box bounds of x that no design within the velocity, acceleration and position limits
        leaves: a Fourier coefficient of a signal bounded by m is at most 4 m / pi, so
        |a_l|, |b_l| <= 4 / pi min(qd_max, qdd_max / (l omega)) (with BOUND_SLACK for the
        grid), and q0, the mean position, lies in the position range. They keep SLSQP's steps
        from running off (TIAGo Pro's arm: |x| to 60 in two iterations)."""
        lim = self.limits
        wl = 2.0 * np.pi / self.period * np.arange(1, self.H + 1)
        amp = (4.0 / np.pi * BOUND_SLACK
               * np.minimum(lim.velocity_limits[:, None], lim.acceleration_limits[:, None] / wl))
        out: list[tuple[float | None, float | None]] = []
        for i in range(self.n):
            out += [(-a, a) if np.isfinite(a) else (None, None) for a in np.tile(amp[i], 2)]
            lo, hi = lim.position_limits[i]
            out.append((float(lo) if np.isfinite(lo) else None,
                        float(hi) if np.isfinite(hi) else None))
        return out

    def constraint(self, x: np.ndarray) -> np.ndarray:
        return self.margin - self._limits(x, False)[0]

    def constraint_jac(self, x: np.ndarray) -> np.ndarray:
        jacobian = self._limits(x, True)[1]
        assert jacobian is not None   # asked for
        return -jacobian
