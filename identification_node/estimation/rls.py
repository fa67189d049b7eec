"""Recursive least squares of (base) inertial parameters (the node's estimator).

Data are regressor rows grouped per sample: ``Y`` (N, n, p) and measured joint torques ``tau``
(N, n) with tau ~ Y @ theta (SI units of the regressor columns; p parameters, n joints).

Recursive least squares (:class:`RecursiveLeastSquares`) keeps the estimate in
square-root-information form, with *stabilised (regularised) forgetting*::

    J_k(theta) = lam J_{k-1}(theta) + (1 - lam) ||R_min (theta - theta_{k-1})||^2 + new rows.

Why this choice: plain exponential forgetting divides the information by lam every sample, so in
directions the data do not excite (arm at rest: only gravity rows) the covariance grows as
lam^-k ("wind-up") until it overflows. The added term keeps the information >= (1 - lam^k)
R_min'R_min in every direction and pulls unexcited directions towards the previous estimate
(they do not drift), while excited directions see a bias of order |R_min|^2 / data information.
Unlike directional forgetting it needs no per-sample rank-one updates, so a whole batch is
processed exactly at once: over a batch of N samples the regularisation weight is 1 - lam^N,
anchored at the estimate at the start of the batch, and sample k gets weight lam^(N-1-k).
With lam = 1 the term vanishes and the estimate equals batch least squares.

The RLS factor F = [[R, z], [0, rho]] (prior, regulariser and data together) is updated per
batch in information form: F_new'F_new = lam^N F'F + regulariser + sum_j A_j'A_j, the batch's
information formed by one BLAS product per joint and factored by one small Cholesky (instead of
a QR of all the batch's rows). F_new is upper-triangular and its R is positive definite by
construction. Forming A'A squares the condition number, so the update is accepted only when the
column-scaled condition number of the new information is at most _INFORMATION_MAX_CONDITION
(relative error ~ eps * condition <= 1e-10); otherwise, or when the Cholesky fails (not yet
excited, or the information is singular), the batch is re-done by the QR update of the stacked
old factor, regulariser and rows. The per-joint residuals and leverages (diagnostics) come from
per-joint information sums, forgotten alike.
"""
from __future__ import annotations

from typing import Callable, cast

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.lsq import (CHUNK, DEFAULT_RCOND, Estimate, as_float,
                                                check_count, check_data, column_scale,
                                                covariance_from_root, qr_r, relative_stddev,
                                                row_information, sample_rows,
                                                solve_triangular_lsq)
from identification_node.estimation.normal_equations import NormalEquations

# Bound on the column-scaled condition number of the information above which the RLS update
# by Cholesky of the information (relative error ~ eps * condition) is redone by QR.
_INFORMATION_MAX_CONDITION = 1e6


def _cholesky_augmented(M: np.ndarray) -> np.ndarray | None:
    """Upper-triangular F (k, k) = [[R, z], [0, rho]] with F'F = M for an augmented
    information M (k, k) whose leading (k-1, k-1) block is positive definite, else None.
    rho^2 = M_kk - z'z is clipped at 0 (an exact fit)."""
    p = M.shape[0] - 1
    if not np.isfinite(M).all():
        return None
    try:
        L = np.linalg.cholesky(M[:p, :p])
    except np.linalg.LinAlgError:
        return None
    F = np.zeros_like(M)
    F[:p, :p] = L.T
    # L z = m: triangular, so LU does no pivoting (numpy only, see solve_triangular_lsq)
    F[:p, p] = z = np.linalg.solve(L, M[:p, p])
    F[p, p] = np.sqrt(max(M[p, p] - z @ z, 0.0))
    return F if np.isfinite(F).all() and np.all(np.diagonal(L) > 0) else None


def _information_factor(name: str, value, p: int) -> np.ndarray:
    """Upper-triangular R with R'R = value: scalar (times I), (p,) diagonal or (p, p) SPD."""
    M = as_float(name, value)
    if not np.isfinite(M).all():
        raise IdentificationError(f'{name} must be finite')
    if M.ndim == 0 or M.shape == (p,):
        if np.any(M < 0):
            raise IdentificationError(f'{name} must be >= 0, got {value!r}')
        return np.diag(np.broadcast_to(np.sqrt(M), (p,))).copy()
    if M.shape != (p, p) or not np.allclose(M, M.T, rtol=1e-10, atol=0):
        raise IdentificationError(
            f'{name} must be a scalar, ({p},) or a symmetric ({p}, {p}) matrix; got shape '
            f'{M.shape}')
    w, V = np.linalg.eigh(M)
    if w.min() < -1e-12 * max(w.max(), 0.0):
        raise IdentificationError(f'{name} must be positive semi-definite')
    return qr_r((V * np.sqrt(np.maximum(w, 0.0))).T)


class RecursiveLeastSquares:
    """Recursive least squares in square-root information form with stabilised forgetting.

    State: the upper-triangular factor [[R, z], [0, rho]] of the prior, the forgetting
    regulariser and the forgotten, weighted data together (R'R = information, z = R theta;
    updated by Cholesky or QR, see the module docstring), and per joint the augmented
    information of its data, for its residuals. The covariance sigma^2 (R'R)^-1 is symmetric
    positive (semi-)definite by construction.

    forgetting lam in (0, 1]: sample k of a batch of N is weighted lam^(N-1-k) relative to the
    last. min_information: R_min'R_min (scalar times I, (p,) diagonal or (p, p)), the floor the
    information approaches in every direction under forgetting, in units of the (weighted)
    information of the rows; unused when lam == 1. prior_information / theta0: an optional
    prior theta0 with that information (forgotten like data); with none, theta starts at theta0
    (default 0) and is the minimum-norm (column-scaled) solution until the data excite all
    directions. ``num_joints`` is taken from the first update when not given.
    """

    def __init__(self, num_params: int, forgetting: float = 1.0,
                 min_information=1e-6, *, num_joints: int | None = None,
                 prior_information=0.0, theta0: np.ndarray | None = None,
                 rcond: float = DEFAULT_RCOND):
        self.num_params = p = check_count('num_params', num_params)
        if not (np.isfinite(forgetting) and 0 < forgetting <= 1):
            raise IdentificationError(f'forgetting factor must be in (0, 1], got {forgetting!r}')
        if not (np.isfinite(rcond) and 0 < rcond < 1):
            raise IdentificationError(f'rcond must be in (0, 1), got {rcond!r}')
        self.forgetting = float(forgetting)
        self.rcond = float(rcond)
        self._R_min = _information_factor('min_information', min_information, p)
        R0 = _information_factor('prior_information', prior_information, p)
        theta0 = np.zeros(p) if theta0 is None else as_float('theta0', theta0)
        if theta0.shape != (p,) or not np.isfinite(theta0).all():
            raise IdentificationError(
                f'theta0 must be {p} finite values, got shape {theta0.shape}')
        self._theta0 = theta0.copy()
        self._prior_aug = np.zeros((p + 1, p + 1))
        self._prior_aug[:p, :p] = R0
        self._prior_aug[:p, p] = R0 @ theta0
        self._num_joints = None if num_joints is None else check_count('num_joints', num_joints)
        self.reset()

    @classmethod
    def from_normal_equations(cls, equations: NormalEquations, num_samples: int, *,
                              theta: np.ndarray | None = None, rcond: float = DEFAULT_RCOND
                              ) -> RecursiveLeastSquares:
        """The estimator (no forgetting, no prior) that has seen data with these per-joint
        normal equations, e.g. the merged statistics of many bags: the same estimate,
        covariance and residuals as streaming those rows in, to rounding. ``theta``: another
        solution to hold instead of the least-squares one (e.g. a physically consistent
        solve); residuals and noise are then those of it."""
        rls = cls(equations.num_params, rcond=rcond, num_joints=equations.num_joints)
        total = equations.augmented.sum(axis=0)
        F = _cholesky_augmented(total)
        rls._F = F if F is not None else _information_factor('information', total,
                                                             equations.num_params + 1)
        rls._joint_info = equations.augmented.copy()
        rls._count = equations.count.copy()
        rls.num_samples = int(num_samples)
        rls._refresh()
        if theta is not None:
            theta = as_float('theta', theta)
            if theta.shape != (equations.num_params,) or not np.isfinite(theta).all():
                raise IdentificationError(f'theta must be {equations.num_params} finite '
                                          f'values, got shape {theta.shape}')
            rls._theta = theta.copy()
        return rls

    # -- state ----------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget all data: back to the prior."""
        p1 = self.num_params + 1
        self._F = self._prior_aug.copy()
        n = self._num_joints or 0
        self._joint_info = np.zeros((n, p1, p1))
        self._count = np.zeros(n)
        self.num_samples = 0
        self._refresh()

    def _refresh(self) -> bool:
        """theta, rank and inverse from the factor. Returns whether the information is full
        rank with a column-scaled condition number (bound) of at most
        _INFORMATION_MAX_CONDITION: accurate enough if it was Cholesky-factored."""
        p = self.num_params
        self._R = self._F[:p, :p]
        self._theta, self._rank, self._G, self._determined = solve_triangular_lsq(
            self._R, self._F[:p, p], self.rcond, self._theta0)
        if self._rank < p:
            return False
        d = column_scale(self._R)
        kappa = np.linalg.norm(self._R / d) * np.linalg.norm(d[:, None] * self._G)
        return bool(kappa * kappa <= _INFORMATION_MAX_CONDITION)

    def update(self, Y: np.ndarray, tau: np.ndarray, weights: np.ndarray | None = None
               ) -> np.ndarray:
        """Process a batch: regressor Y (N, n, p), torques tau (N, n), optional weights
        (broadcastable to (N, n), >= 0) multiplying the squared residuals. Returns theta."""
        Y, tau = check_data(Y, tau, self.num_params, self._num_joints)
        N, n = tau.shape
        root = None
        if weights is not None:
            w = as_float('weights', weights)
            try:
                w = np.broadcast_to(w, (N, n))
            except ValueError:
                raise IdentificationError(
                    f'weights have shape {w.shape}; expected broadcastable to {(N, n)}') from None
            if not np.isfinite(w).all() or np.any(w < 0):
                raise IdentificationError('weights must be finite and >= 0')
            root = np.sqrt(w)
        if N == 0:
            return self.theta
        self._update_rows(
            lambda a, b: sample_rows(Y[a:b], tau[a:b], None if root is None else root[a:b]),
            N, n, None if root is None else root > 0)
        return self.theta

    def update_rows(self, rows: np.ndarray, used: np.ndarray | None = None,
                    information: np.ndarray | None = None) -> None:
        """``update`` on trusted data (finite, shapes right: not checked): rows (N, n, p+1)
        = [Y_j | tau_j] of each sample and joint, already scaled by the square roots of their
        weights; used (N, n) bool: the rows of weight > 0 (None: all); information: their
        row_information when known (used only without forgetting)."""
        N, n = rows.shape[:2]
        if N:
            self._update_rows(lambda a, b: rows[a:b], N, n, used, information)

    def _update_rows(self, rows: Callable[[int, int], np.ndarray], N: int, n: int,
                     used: np.ndarray | None = None, information: np.ndarray | None = None
                     ) -> None:
        """``update_rows`` with the rows [Y_j | tau_j] of samples a:b (b - a, n, p+1) given by
        rows(a, b) (see sample_rows), already scaled by the square roots of the weights (not
        by the forgetting)."""
        if self._num_joints is None:
            self._num_joints = n
            self.reset()
        lam = self.forgetting
        f = lam ** N
        # log-space powers: lam^(N-1-k) underflows to 0 harmlessly for long batches
        decay = np.exp(np.arange(N - 1, -1, -1) * np.log(lam)) if lam < 1.0 else None

        def chunk(a: int, b: int) -> np.ndarray:
            r = rows(a, b)
            return r if decay is None else r * np.sqrt(decay[a:b])[:, None, None]

        spans = [(a, min(a + CHUNK, N)) for a in range(0, N, CHUNK)]
        if information is None or decay is not None:
            # N >= 1, so at least one span: an array, never sum's start 0
            information = cast(np.ndarray, sum(row_information(chunk(a, b)) for a, b in spans))
        # The forgetting regulariser, anchored at the estimate before the batch.
        old = self._F if f == 1.0 else np.sqrt(f) * self._F
        if f < 1.0:
            anchor = np.sqrt(1.0 - f) * np.column_stack([self._R_min, self._R_min @ self._theta])
            old = np.vstack([old, anchor])
        # Information form (one Cholesky); QR of the old factor and all rows when it fails or
        # is not accurate enough. The decay is relative to the batch end: old is scaled once.
        candidate = _cholesky_augmented(old.T @ old + information.sum(axis=0))
        accurate = False
        if candidate is not None:
            self._F = candidate
            accurate = self._refresh()
        if not accurate:
            for a, b in spans:  # each joint's rows first: fewer rounding errors
                old = qr_r(np.concatenate([old, *qr_r(chunk(a, b).transpose(1, 0, 2))]))
            self._F = old
            self._refresh()
        if f < 1.0:
            self._joint_info *= f
            self._count *= f
        self._joint_info += information
        if decay is None:
            self._count += N if used is None else used.sum(axis=0)
        else:
            self._count += decay.sum() if used is None else decay @ used
        self.num_samples += N

    # -- results --------------------------------------------------------------------------
    @property
    def num_joints(self) -> int | None:
        return self._num_joints

    @property
    def theta(self) -> np.ndarray:
        """Current estimate (p,)."""
        return self._theta.copy()

    @property
    def rank(self) -> int:
        """Numerical rank of the information matrix (column-scaled, rcond)."""
        return self._rank

    @property
    def information(self) -> np.ndarray:
        """Information matrix R'R (p, p), including prior and forgetting regulariser."""
        return self._R.T @ self._R

    @property
    def data_information(self) -> np.ndarray:
        """Forgotten, weighted information of the data alone, sum_j Y_j'Y_j (p, p)."""
        p = self.num_params
        return self._joint_info[:, :p, :p].sum(axis=0)

    def normal_equations(self) -> NormalEquations:
        """The forgotten, weighted data alone (no prior, no forgetting regulariser), per
        joint: what the physically consistent solve and the payload fit read."""
        return NormalEquations(self._joint_info.copy(), self._count.copy())

    def _information_eigenvalues(self) -> np.ndarray:
        return np.linalg.svd(self._R, compute_uv=False) ** 2

    @property
    def min_eigenvalue(self) -> float:
        """Smallest eigenvalue of the information matrix (excitation monitor)."""
        return float(self._information_eigenvalues()[-1])

    @property
    def condition_number(self) -> float:
        """Condition number of the information matrix (inf when singular)."""
        ev = self._information_eigenvalues()
        return float(ev[0] / ev[-1]) if ev[-1] > 0 else np.inf

    def _joint_rss(self) -> np.ndarray:
        v = np.append(self._theta, -1.0)
        return np.maximum(np.einsum('p,jpq,q->j', v, self._joint_info, v), 0.0)

    @property
    def residual_rms(self) -> np.ndarray:
        """Per-joint RMS of the (weighted) residuals at the current theta, with the same
        forgetting as the data (n,); 0 for a joint without samples."""
        with np.errstate(invalid='ignore', divide='ignore'):
            ms = self._joint_rss() / self._count
        return np.sqrt(np.where(self._count > 0, ms, 0.0))

    @property
    def noise_variance(self) -> float:
        """sigma^2 = forgotten weighted RSS / (forgotten row count - rank); inf while unknown."""
        dof = self._count.sum() - self._rank
        return float(self._joint_rss().sum() / dof) if dof >= 1 else np.inf

    @property
    def covariance(self) -> np.ndarray:
        """sigma^2 (R'R)^-1 (p, p); inf variance for parameters the data do not determine."""
        sigma2 = self.noise_variance
        if not np.isfinite(sigma2):
            return np.diag(np.full(self.num_params, np.inf))
        return covariance_from_root(self._G, sigma2, self._determined)

    @property
    def stddev(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def rel_stddev(self) -> np.ndarray:
        """100 stddev / |theta| in percent (inf where theta == 0)."""
        return relative_stddev(self.stddev, self._theta)

    def estimate(self) -> Estimate:
        """The current estimate as an :class:`Estimate` (noise_variance per joint)."""
        rss = self._joint_rss()
        p = self.num_params
        lev = np.einsum('jpq,pq->j', self._joint_info[:, :p, :p], self._G @ self._G.T)
        dof = self._count - lev
        with np.errstate(invalid='ignore', divide='ignore'):
            noise = np.where(dof >= 1, rss / dof, np.inf)
        return Estimate.from_covariance(self.theta, self.covariance, noise, self.num_samples,
                                        rss.sum())

    snapshot = estimate
