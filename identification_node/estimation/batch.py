"""Batch least-squares estimators of (base) inertial parameters: ordinary, weighted (feasible
GLS) and ridge, and ``weighted_solve``, the one weighted least squares on normal equations.

Data are regressor rows grouped per sample: ``Y`` (N, n, p) and measured joint torques ``tau``
(N, n) with tau ~ Y @ theta (SI units of the regressor columns; p parameters, n joints).

Sufficient statistics. The batch estimators keep, per joint j, the upper-triangular factor of
the augmented data matrix [Y_j | tau_j] (QR, updated by stacking [R_aug; new rows] and
re-factoring):

    R_aug_j = [[R_j, z_j], [0, rho_j]],  R_j'R_j = Y_j'Y_j,  R_j'z_j = Y_j'tau_j,
    ||tau_j - Y_j theta||^2 = ||R_j theta - z_j||^2 + rho_j^2   for every theta.

Memory is O(n p^2) whatever N; recordings merge by stacking factors; per-joint noise weights are
applied by scaling the factors (feasible GLS) without revisiting the data; normal equations are
never formed, so the condition number is not squared.

Noise variances use the exact per-joint leverage h_j = w_j trace((A'WA)^-1 A_j'A_j)
(sum_j h_j = p): E||r_j||^2 = sigma_j^2 (N - h_j), so sigma_j^2 = rss_j / (N - h_j).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.lsq import (CHUNK, DEFAULT_RCOND, Estimate, check_count,
                                                check_data, covariance_from_root, qr_r,
                                                sample_rows, solve_triangular_lsq)
from identification_node.estimation.normal_equations import NormalEquations


def _augmented_rows(Y: np.ndarray, tau: np.ndarray, scale: np.ndarray | None = None
                    ) -> np.ndarray:
    """Per-joint row blocks [Y_j | tau_j] (n, N, p+1), rows optionally scaled by scale (N, n)."""
    return sample_rows(Y, tau, scale).transpose(1, 0, 2)


def _joint_rss(R_aug: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """||R_j theta - z_j||^2 + rho_j^2 per joint, for factors R_aug (n, p+1, p+1)."""
    return np.sum((R_aug @ np.append(theta, -1.0)) ** 2, axis=-1)


def _leverage(R_aug: np.ndarray, R_inv: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """h_j = w_j trace(P A_j'A_j) with P = R_inv R_inv' (n,)."""
    p = R_inv.shape[0]
    return weights * np.sum((R_aug[:, :p, :p] @ R_inv) ** 2, axis=(1, 2))


def _excitation_error(num_samples: int, num_joints: int, p: int, rank: int) -> IdentificationError:
    rows = num_samples * num_joints
    if rows < p:
        what = (f'{num_samples} samples x {num_joints} joints = {rows} torque rows for '
                f'{p} parameters')
    else:
        what = (f'the data ({num_samples} samples x {num_joints} joints) do not determine all '
                f'{p} parameters; excite more joints/directions or use base parameters')
    return IdentificationError(f'not enough excitation: {what} (rank {rank} < {p})')


class _BatchAccumulator:
    """Per-joint QR factors of [Y_j | tau_j], filled by add() and merge()."""

    def __init__(self, num_params: int, num_joints: int, rcond: float = DEFAULT_RCOND):
        self.num_params = check_count('num_params', num_params)
        self.num_joints = check_count('num_joints', num_joints)
        if not (np.isfinite(rcond) and 0 < rcond < 1):
            raise IdentificationError(f'rcond must be in (0, 1), got {rcond!r}')
        self.rcond = float(rcond)
        p1 = self.num_params + 1
        self._R_aug = np.zeros((self.num_joints, p1, p1))
        self.num_samples = 0

    def add(self, Y: np.ndarray, tau: np.ndarray) -> None:
        """Add samples: regressor Y (N, n, p) and torques tau (N, n)."""
        Y, tau = check_data(Y, tau, self.num_params, self.num_joints)
        for start in range(0, Y.shape[0], CHUNK):
            rows = _augmented_rows(Y[start:start + CHUNK], tau[start:start + CHUNK])
            self._R_aug = qr_r(np.concatenate([self._R_aug, rows], axis=1))
        self.num_samples += Y.shape[0]

    def merge(self, other: _BatchAccumulator) -> _BatchAccumulator:
        """Add the data of another batch estimator (e.g. another recording); returns self."""
        if not isinstance(other, _BatchAccumulator):
            raise IdentificationError(
                f'cannot merge {type(other).__name__} into a batch estimator')
        if (other.num_params, other.num_joints) != (self.num_params, self.num_joints):
            raise IdentificationError(
                f'cannot merge estimators of different size: {other.num_params} parameters x '
                f'{other.num_joints} joints into {self.num_params} x {self.num_joints}')
        self._R_aug = qr_r(np.concatenate([self._R_aug, other._R_aug], axis=1))
        self.num_samples += other.num_samples
        return self

    @property
    def information(self) -> np.ndarray:
        """Unweighted information matrix A'A (p, p) of all rows."""
        R = self._combine(np.ones(self.num_joints))[0]
        return R.T @ R

    def _combine(self, sqrt_weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Factor R (p, p) and z (p,) of all joints, joint j's rows scaled by sqrt_weights[j]."""
        p = self.num_params
        stacked = (self._R_aug * sqrt_weights[:, None, None]).reshape(-1, p + 1)
        R_aug = qr_r(stacked)
        return R_aug[:p, :p], R_aug[:p, p]

    def _require_data(self) -> None:
        if self.num_samples == 0:
            raise IdentificationError('no samples: add data before solving')

    def _weighted_solve(self, weights: np.ndarray):
        """theta, G = R^-1, per-joint rss and leverage for joint weights (n,); raises on rank."""
        R, z = self._combine(np.sqrt(weights))
        theta, rank, G, _ = solve_triangular_lsq(R, z, self.rcond)
        if rank < self.num_params:
            raise _excitation_error(self.num_samples, self.num_joints, self.num_params, rank)
        rows = self.num_samples * self.num_joints
        if rows <= self.num_params:
            raise IdentificationError(
                f'not enough samples: {rows} torque rows for {self.num_params} parameters leave '
                'no degrees of freedom to estimate the noise')
        rss = _joint_rss(self._R_aug, theta)
        lev = _leverage(self._R_aug, G, weights)
        # max(., 1): a joint whose rows are (almost) all fitted exactly has rss ~ 0 anyway.
        noise = rss / np.maximum(self.num_samples - lev, 1.0)
        return theta, G, rss, noise


class LeastSquares(_BatchAccumulator):
    """Ordinary least squares, theta = argmin ||tau - Y theta||^2 over all samples and joints.

    Covariance sigma^2 (A'A)^-1 with sigma^2 = RSS / (N n - p); noise_variance per joint
    rss_j / (N - h_j) (leverage-corrected).
    """

    def solve(self) -> Estimate:
        """Estimate from all data added so far; IdentificationError if not excited enough."""
        self._require_data()
        theta, G, rss, noise = self._weighted_solve(np.ones(self.num_joints))
        sigma2 = rss.sum() / (self.num_samples * self.num_joints - self.num_params)
        cov = covariance_from_root(G, sigma2, np.ones(self.num_params, dtype=bool))
        return Estimate.from_covariance(theta, cov, noise, self.num_samples, rss.sum())


class WeightedLeastSquares(_BatchAccumulator):
    """Weighted least squares with per-joint noise variances estimated from the data: the
    samples' QR factors as normal equations into :func:`weighted_solve` (feasible GLS,
    Radkhah et al. eq. 6). noise_variance are the sigma_j^2; rss is unweighted.
    """

    def __init__(self, num_params: int, num_joints: int, *, iterations: int = 20,
                 tol: float = 1e-8, rcond: float = DEFAULT_RCOND):
        super().__init__(num_params, num_joints, rcond)
        self.iterations = check_count('iterations', iterations)
        self.tol = float(tol)

    def normal_equations(self) -> NormalEquations:
        return NormalEquations(self._R_aug.transpose(0, 2, 1) @ self._R_aug,
                               np.full(self.num_joints, float(self.num_samples)))

    def solve(self) -> Estimate:
        """Estimate from all data added so far; IdentificationError if not excited enough."""
        self._require_data()
        equations = self.normal_equations()
        fit = weighted_solve(equations, iterations=self.iterations, tol=self.tol)
        return Estimate.from_covariance(fit.theta, fit.covariance, fit.noise_variance,
                                        self.num_samples, equations.rss(fit.theta).sum())


class RidgeRegression(_BatchAccumulator):
    """Ridge regression on the full (possibly rank-deficient) standard regressor.

    An, Atkeson and Hollerbach eq. 9: psi = (K'K + d I)^-1 K' tau; nearly the least-squares
    solution of the identifiable part when d << the smallest nonzero eigenvalue of K'K, and
    close to zero in the unidentifiable directions. Covariance of the linear estimator
    sigma^2 G K'K G with G = (K'K + d I)^-1 and sigma^2 = RSS / (N n - trace(G K'K)).
    """

    def __init__(self, num_params: int, num_joints: int, d: float,
                 rcond: float = DEFAULT_RCOND):
        super().__init__(num_params, num_joints, rcond)
        if not (np.isfinite(d) and d > 0):
            raise IdentificationError(f'ridge parameter d must be finite and > 0, got {d!r}')
        self.d = float(d)

    def solve(self) -> Estimate:
        """Ridge estimate from all data added so far."""
        self._require_data()
        p = self.num_params
        R, z = self._combine(np.ones(self.num_joints))
        ridge_rows = np.hstack([np.sqrt(self.d) * np.eye(p), np.zeros((p, 1))])
        Rr_aug = qr_r(np.vstack([np.column_stack([R, z]), ridge_rows]))
        Rr = Rr_aug[:p, :p]
        sol = np.linalg.solve(Rr, np.column_stack([Rr_aug[:p, p], np.eye(p)]))
        theta, Rr_inv = sol[:, 0], sol[:, 1:]
        dof = self.num_samples * self.num_joints - np.sum((R @ Rr_inv) ** 2)
        if dof < 1:
            raise IdentificationError(
                f'not enough samples: {self.num_samples * self.num_joints} torque rows leave no '
                'degrees of freedom to estimate the noise')
        rss = _joint_rss(self._R_aug, theta)
        lev = _leverage(self._R_aug, Rr_inv, np.ones(self.num_joints))
        noise = rss / np.maximum(self.num_samples - lev, 1.0)
        M = Rr_inv @ (Rr_inv.T @ R.T)  # G K'K G = M M'
        cov = covariance_from_root(M, rss.sum() / dof, np.ones(p, dtype=bool))
        return Estimate.from_covariance(theta, cov, noise, self.num_samples, rss.sum())


# -- weighted least squares on normal equations ------------------------------------------------
@dataclass
class WeightedFit:
    """theta (p,), covariance (p, p), per-joint noise variance of the equations (n,) and s2, the
    weighted residual variance (1 when the weights are the true inverse variances); weights
    (n,): the objective's per-joint weights, covariance = (sum_j w_j Y_j'Y_j)^-1 (the
    physically consistent solve uses the same objective)."""
    theta: np.ndarray
    covariance: np.ndarray
    noise_variance: np.ndarray
    s2: float
    weights: np.ndarray


def weighted_solve(equations: NormalEquations, known: bool = False, iterations: int = 20,
                   tol: float = 1e-8) -> WeightedFit:
    """Weighted least squares of tau_j = Y_j theta from per-joint normal equations, each
    joint's equations counted in ``equations.count`` (left-out equations added as zeros).

    known: the equations were scaled by their inverse noise standard deviation; covariance
    (A'A)^-1 max(1, s2) (inflated when the residuals exceed the noise model). Otherwise
    feasible GLS, Radkhah et al. eq. 6: per-joint variances sigma_j^2 = rss_j / (N_j - h_j)
    (h_j the joint's leverage), re-solved until they change by less than ``tol`` (relative) or
    ``iterations``; covariance (A' S^-1 A)^-1. Column-scaled normal equations: an information
    whose scaled condition exceeds 1e14 is not excited enough.
    """
    n, b = equations.num_joints, equations.num_params
    counts, gram, cross = equations.count, equations.gram, equations.cross
    if counts.sum() <= b:
        raise IdentificationError(
            f'not enough samples: {int(counts.sum())} torque equations for {b} parameters')

    def solve(w: np.ndarray):
        M = np.einsum('j,jpq->pq', w, gram)
        d = np.sqrt(np.diag(M))
        ev = np.linalg.eigvalsh(M / np.outer(d, d)) if d.min() > 0 else np.zeros(1)
        if ev[0] <= 1e-14 * ev[-1]:
            raise IdentificationError(
                f'not enough excitation: the data ({int(counts.max())} samples x {n} joints) '
                f'do not determine all {b} parameters; excite more joints/directions')
        P = np.linalg.inv(M / np.outer(d, d)) / np.outer(d, d)
        P = 0.5 * (P + P.T)
        theta = P @ (w @ cross)
        lev = w * np.einsum('pq,jqp->j', P, gram)
        return theta, P, equations.rss(theta), lev

    if known:
        theta, P, rss, _ = solve(np.ones(n))
        s2 = float(rss.sum() / (counts.sum() - b))
        return WeightedFit(theta, P * max(1.0, s2), rss / np.maximum(counts, 1), s2,
                           np.full(n, 1.0 / max(1.0, s2)))
    w = np.ones(n)
    theta, P, rss, lev = solve(w)
    # rss from the information form is exact only to about 1e-12 of sum tau^2 (cancellation):
    # below that floor a joint counts as noise-free, and no weight may grow beyond it.
    floor = np.maximum(1e-12 * equations.sq / np.maximum(counts, 1.0), 1e-300)
    sigma2 = rss / np.maximum(counts - lev, 1.0)
    if np.all(sigma2 <= floor):      # noise-free: any weights give the same exact fit
        return WeightedFit(theta, np.zeros((b, b)), sigma2, 0.0, w)
    for _ in range(iterations):
        w = 1.0 / np.maximum(sigma2, floor)
        theta, P, rss, lev = solve(w)
        new = rss / np.maximum(counts - lev, 1.0)
        done = np.max(np.abs(new - sigma2) / np.maximum(new, 1e-300)) < tol
        sigma2 = new
        if done:
            break
    s2 = float((w * rss).sum() / (counts.sum() - b))
    return WeightedFit(theta, P, sigma2, s2, w)
