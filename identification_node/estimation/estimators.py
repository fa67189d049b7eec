"""Least-squares estimators of (base) inertial parameters: batch and recursive.

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

from dataclasses import dataclass
from typing import Callable

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.normal_equations import NormalEquations

_CHUNK = 4096  # samples per QR: bounds the workspace to ~_CHUNK * n * (p + 1) floats
_DEFAULT_RCOND = 1e-10  # singular-value ratio (column-scaled) below which a direction is unexcited
# Bound on the column-scaled condition number of the information above which the RLS update
# by Cholesky of the information (relative error ~ eps * condition) is redone by QR.
_INFORMATION_MAX_CONDITION = 1e6


@dataclass
class Estimate:
    """A parameter estimate with its uncertainty.

    theta (p,) in the units of the regressor columns; covariance (p, p) of theta; stddev (p,)
    its square-root diagonal; rel_stddev (p,) in percent, 100 stddev / |theta| (inf where
    theta == 0); noise_variance (n,) per joint torque noise variance (N m)^2; num_samples N;
    rss the residual sum of squares sum ||tau - Y theta||^2 (recursive: forgotten, weighted).
    """
    theta: np.ndarray
    covariance: np.ndarray
    stddev: np.ndarray
    rel_stddev: np.ndarray
    noise_variance: np.ndarray
    num_samples: int
    rss: float

    @classmethod
    def from_covariance(cls, theta: np.ndarray, covariance: np.ndarray,
                        noise_variance: np.ndarray, num_samples: int, rss: float) -> Estimate:
        """Build an estimate, deriving stddev and rel_stddev from the covariance."""
        theta = np.asarray(theta, dtype=float)
        covariance = np.asarray(covariance, dtype=float)
        stddev = np.sqrt(np.maximum(np.diag(covariance), 0.0))
        return cls(theta=theta, covariance=covariance, stddev=stddev,
                   rel_stddev=_relative(stddev, theta),
                   noise_variance=np.asarray(noise_variance, dtype=float),
                   num_samples=int(num_samples), rss=float(rss))

    def predict(self, Y: np.ndarray) -> np.ndarray:
        """Predicted torques Y @ theta, (N, n) for Y (N, n, p)."""
        return np.asarray(Y, dtype=float) @ self.theta


# -- helpers ----------------------------------------------------------------------------------
def _relative(stddev: np.ndarray, theta: np.ndarray) -> np.ndarray:
    with np.errstate(divide='ignore', invalid='ignore'):
        rel = 100.0 * stddev / np.abs(theta)
    return np.where(theta == 0, np.inf, rel)


def _qr_r(a: np.ndarray) -> np.ndarray:
    """Upper-triangular R (..., k, k) of the QR factorisation of a (..., m, k), m >= k."""
    return np.linalg.qr(a, mode='r')


def _check_count(name: str, value: int, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise IdentificationError(f'{name} must be an integer >= {minimum}, got {value!r}')
    return int(value)


def _as_float(name: str, a) -> np.ndarray:
    try:
        return np.asarray(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise IdentificationError(f'{name} is not a numeric array: {exc}') from None


def _check_finite(name: str, a: np.ndarray) -> None:
    if not np.isfinite(a).all():
        k = int(np.argwhere(~np.isfinite(a))[0][0])
        raise IdentificationError(f'{name} contains NaN or inf (first at sample {k})')


def _check_data(Y, tau, num_params: int, num_joints: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Validate Y (N, n, p) and tau (N, n) (one sample: (n, p) and (n,))."""
    Y, tau = _as_float('regressor', Y), _as_float('torques', tau)
    if Y.ndim == 2 and tau.ndim == 1:
        Y, tau = Y[None], tau[None]
    n = '{n}' if num_joints is None else num_joints
    if Y.ndim != 3 or Y.shape[2] != num_params or (num_joints is not None
                                                   and Y.shape[1] != num_joints):
        raise IdentificationError(
            f'regressor has shape {Y.shape}; expected (N, {n}, {num_params}) '
            '(samples, joints, parameters)')
    if tau.shape != Y.shape[:2]:
        raise IdentificationError(
            f'torques have shape {tau.shape}; expected {Y.shape[:2]} (samples, joints) to match '
            f'the regressor')
    _check_finite('regressor', Y)
    _check_finite('torques', tau)
    return Y, tau


def _augmented_rows(Y: np.ndarray, tau: np.ndarray, scale: np.ndarray | None = None
                    ) -> np.ndarray:
    """Per-joint row blocks [Y_j | tau_j] (n, N, p+1), rows optionally scaled by scale (N, n)."""
    return _sample_rows(Y, tau, scale).transpose(1, 0, 2)


def _sample_rows(Y: np.ndarray, tau: np.ndarray, scale: np.ndarray | None = None
                 ) -> np.ndarray:
    """Rows [Y_j | tau_j] of each sample and joint (N, n, p+1), optionally scaled by scale
    (N, n)."""
    rows = np.concatenate([Y, tau[:, :, None]], axis=2)
    if scale is not None:
        rows *= scale[:, :, None]
    return rows


def row_information(rows: np.ndarray) -> np.ndarray:
    """Per-joint information sum_k rows[k, j]' rows[k, j] (n, k, k) of rows (N, n, k) (BLAS
    gemm on strided views: einsum would not use BLAS)."""
    return rows.transpose(1, 2, 0) @ rows.transpose(1, 0, 2)


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
    # L z = m: triangular, so LU does no pivoting (numpy only, see _solve)
    F[:p, p] = z = np.linalg.solve(L, M[:p, p])
    F[p, p] = np.sqrt(max(M[p, p] - z @ z, 0.0))
    return F if np.isfinite(F).all() and np.all(np.diagonal(L) > 0) else None


def _joint_rss(R_aug: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """||R_j theta - z_j||^2 + rho_j^2 per joint, for factors R_aug (n, p+1, p+1)."""
    return np.sum((R_aug @ np.append(theta, -1.0)) ** 2, axis=-1)


def _leverage(R_aug: np.ndarray, R_inv: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """h_j = w_j trace(P A_j'A_j) with P = R_inv R_inv' (n,)."""
    p = R_inv.shape[0]
    return weights * np.sum((R_aug[:, :p, :p] @ R_inv) ** 2, axis=(1, 2))


def _column_scale(R: np.ndarray) -> np.ndarray:
    """Column norms of R, for a scale-invariant rank test on R / d."""
    d = np.linalg.norm(R, axis=0)
    # Columns at rounding level (a parameter without effect) must not be scaled up to unit norm.
    return np.where(d > 1e-12 * d.max(), d, max(d.max(), 1e-300))


def _rank(s: np.ndarray, rcond: float) -> int:
    return int(np.sum(s > rcond * s[0])) if s.size and s[0] > 0 else 0


def _solve(R: np.ndarray, z: np.ndarray, rcond: float, theta_ref: np.ndarray | None = None
           ) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """Minimise ||R theta - z|| for upper-triangular R.

    Returns theta, the rank, a generalised inverse G of R (R^-1 at full rank) and a boolean
    mask of the parameters that the data determine. When R is singular, theta is theta_ref
    (default 0) plus the minimum-norm correction in column-scaled coordinates.
    """
    p = R.shape[0]
    d = _column_scale(R)
    try:
        # LU of a triangular matrix does not pivot: this is back substitution (numpy only, so
        # one BLAS thread pool; scipy's would fight it for the cores).
        sol = np.linalg.solve(R, np.column_stack([z, np.eye(p)]))
        R_inv = sol[:, 1:]
        # kappa_2 <= ||Rs||_F ||Rs^-1||_F: full rank without an SVD in the common case
        if (np.isfinite(sol).all() and np.linalg.norm(R / d) * np.linalg.norm(d[:, None] * R_inv)
                < 1.0 / rcond):
            return sol[:, 0], p, R_inv, np.ones(p, dtype=bool)
    except np.linalg.LinAlgError:
        pass
    U, s, Vt = np.linalg.svd(R / d)
    rank = _rank(s, rcond)
    G = (Vt[:rank].T / s[:rank]) @ U[:, :rank].T / d[:, None]
    ref = np.zeros(p) if theta_ref is None else theta_ref
    theta = ref + G @ (z - R @ ref)
    determined = np.linalg.norm(Vt[rank:], axis=0) < 1e-8
    return theta, rank, G, determined


def _covariance(G: np.ndarray, scale: float, determined: np.ndarray) -> np.ndarray:
    """scale * G G', symmetric; inf variance (and zero correlation) for undetermined params."""
    cov = scale * (G @ G.T)
    cov = 0.5 * (cov + cov.T)
    if not determined.all():
        cov[~determined, :] = 0.0
        cov[:, ~determined] = 0.0
        cov[~determined, ~determined] = np.inf
    return cov


def _excitation_error(num_samples: int, num_joints: int, p: int, rank: int) -> IdentificationError:
    rows = num_samples * num_joints
    if rows < p:
        what = (f'{num_samples} samples x {num_joints} joints = {rows} torque rows for '
                f'{p} parameters')
    else:
        what = (f'the data ({num_samples} samples x {num_joints} joints) do not determine all '
                f'{p} parameters; excite more joints/directions or use base parameters')
    return IdentificationError(f'not enough excitation: {what} (rank {rank} < {p})')


# -- batch estimators -------------------------------------------------------------------------
class _BatchAccumulator:
    """Per-joint QR factors of [Y_j | tau_j], filled by add() and merge()."""

    def __init__(self, num_params: int, num_joints: int, rcond: float = _DEFAULT_RCOND):
        self.num_params = _check_count('num_params', num_params)
        self.num_joints = _check_count('num_joints', num_joints)
        if not (np.isfinite(rcond) and 0 < rcond < 1):
            raise IdentificationError(f'rcond must be in (0, 1), got {rcond!r}')
        self.rcond = float(rcond)
        p1 = self.num_params + 1
        self._R_aug = np.zeros((self.num_joints, p1, p1))
        self.num_samples = 0

    def add(self, Y: np.ndarray, tau: np.ndarray) -> None:
        """Add samples: regressor Y (N, n, p) and torques tau (N, n)."""
        Y, tau = _check_data(Y, tau, self.num_params, self.num_joints)
        for start in range(0, Y.shape[0], _CHUNK):
            rows = _augmented_rows(Y[start:start + _CHUNK], tau[start:start + _CHUNK])
            self._R_aug = _qr_r(np.concatenate([self._R_aug, rows], axis=1))
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
        self._R_aug = _qr_r(np.concatenate([self._R_aug, other._R_aug], axis=1))
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
        R_aug = _qr_r(stacked)
        return R_aug[:p, :p], R_aug[:p, p]

    def _require_data(self) -> None:
        if self.num_samples == 0:
            raise IdentificationError('no samples: add data before solving')

    def _weighted_solve(self, weights: np.ndarray):
        """theta, G = R^-1, per-joint rss and leverage for joint weights (n,); raises on rank."""
        R, z = self._combine(np.sqrt(weights))
        theta, rank, G, _ = _solve(R, z, self.rcond)
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
        cov = _covariance(G, sigma2, np.ones(self.num_params, dtype=bool))
        return Estimate.from_covariance(theta, cov, noise, self.num_samples, rss.sum())


class WeightedLeastSquares(_BatchAccumulator):
    """Weighted least squares with per-joint noise variances estimated from the data: the
    samples' QR factors as normal equations into :func:`weighted_solve` (feasible GLS,
    Radkhah et al. eq. 6). noise_variance are the sigma_j^2; rss is unweighted.
    """

    def __init__(self, num_params: int, num_joints: int, *, iterations: int = 20,
                 tol: float = 1e-8, rcond: float = _DEFAULT_RCOND):
        super().__init__(num_params, num_joints, rcond)
        self.iterations = _check_count('iterations', iterations)
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
                 rcond: float = _DEFAULT_RCOND):
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
        Rr_aug = _qr_r(np.vstack([np.column_stack([R, z]), ridge_rows]))
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
        cov = _covariance(M, rss.sum() / dof, np.ones(p, dtype=bool))
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
    weights: np.ndarray | None = None


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


# -- recursive least squares ------------------------------------------------------------------
def _information_factor(name: str, value, p: int) -> np.ndarray:
    """Upper-triangular R with R'R = value: scalar (times I), (p,) diagonal or (p, p) SPD."""
    M = _as_float(name, value)
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
    return _qr_r((V * np.sqrt(np.maximum(w, 0.0))).T)


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
                 rcond: float = _DEFAULT_RCOND):
        self.num_params = p = _check_count('num_params', num_params)
        if not (np.isfinite(forgetting) and 0 < forgetting <= 1):
            raise IdentificationError(f'forgetting factor must be in (0, 1], got {forgetting!r}')
        if not (np.isfinite(rcond) and 0 < rcond < 1):
            raise IdentificationError(f'rcond must be in (0, 1), got {rcond!r}')
        self.forgetting = float(forgetting)
        self.rcond = float(rcond)
        self._R_min = _information_factor('min_information', min_information, p)
        R0 = _information_factor('prior_information', prior_information, p)
        theta0 = np.zeros(p) if theta0 is None else _as_float('theta0', theta0)
        if theta0.shape != (p,) or not np.isfinite(theta0).all():
            raise IdentificationError(
                f'theta0 must be {p} finite values, got shape {theta0.shape}')
        self._theta0 = theta0.copy()
        self._prior_aug = np.zeros((p + 1, p + 1))
        self._prior_aug[:p, :p] = R0
        self._prior_aug[:p, p] = R0 @ theta0
        self._num_joints = None if num_joints is None else _check_count('num_joints', num_joints)
        self.reset()

    @classmethod
    def from_normal_equations(cls, equations: NormalEquations, num_samples: int, *,
                              theta: np.ndarray | None = None, rcond: float = _DEFAULT_RCOND
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
            theta = _as_float('theta', theta)
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
        self._theta, self._rank, self._G, self._determined = _solve(
            self._R, self._F[:p, p], self.rcond, self._theta0)
        if self._rank < p:
            return False
        d = _column_scale(self._R)
        kappa = np.linalg.norm(self._R / d) * np.linalg.norm(d[:, None] * self._G)
        return bool(kappa * kappa <= _INFORMATION_MAX_CONDITION)

    def update(self, Y: np.ndarray, tau: np.ndarray, weights: np.ndarray | None = None
               ) -> np.ndarray:
        """Process a batch: regressor Y (N, n, p), torques tau (N, n), optional weights
        (broadcastable to (N, n), >= 0) multiplying the squared residuals. Returns theta."""
        Y, tau = _check_data(Y, tau, self.num_params, self._num_joints)
        N, n = tau.shape
        root = None
        if weights is not None:
            w = _as_float('weights', weights)
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
            lambda a, b: _sample_rows(Y[a:b], tau[a:b], None if root is None else root[a:b]),
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
        rows(a, b) (see _sample_rows), already scaled by the square roots of the weights (not
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

        spans = [(a, min(a + _CHUNK, N)) for a in range(0, N, _CHUNK)]
        if information is None or decay is not None:
            information = sum(row_information(chunk(a, b)) for a, b in spans)
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
                old = _qr_r(np.concatenate([old, *_qr_r(chunk(a, b).transpose(1, 0, 2))]))
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
        return _covariance(self._G, sigma2, self._determined)

    @property
    def stddev(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def rel_stddev(self) -> np.ndarray:
        """100 stddev / |theta| in percent (inf where theta == 0)."""
        return _relative(self.stddev, self._theta)

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


class ResidualStatistics:
    """Per-joint sums giving, for ANY parameter vector theta, the residuals tau - Y theta's sum
    of squares sample by sample and over blocks of ``block`` consecutive samples, in constant
    memory. The block sums give the long-run (zero-frequency) variance of correlated residuals,
    such as smoothed noise: the variance that least squares actually averages.
    """

    def __init__(self, num_params: int, num_joints: int, block: int):
        self.p, self.n = _check_count('num_params', num_params), _check_count(
            'num_joints', num_joints)
        self.block = _check_count('block', block)
        p, n = self.p, self.n
        # Per joint [Y | tau]'[Y | tau] over the samples and over the block sums: gram, cross
        # and sq (and their block versions) are views into these.
        self._info, self._binfo = np.zeros((n, p + 1, p + 1)), np.zeros((n, p + 1, p + 1))
        self.count = 0
        self.blocks = 0
        # The block being filled: sums of [Y | tau] over its first ``_fill`` samples.
        self._open, self._fill = np.zeros((n, p + 1)), 0

    gram = property(lambda self: self._info[:, :self.p, :self.p], doc="sum Y_j'Y_j (n, p, p)")
    cross = property(lambda self: self._info[:, :self.p, self.p], doc="sum Y_j'tau_j (n, p)")
    sq = property(lambda self: self._info[:, self.p, self.p], doc='sum tau_j^2 (n,)')

    def add(self, Y: np.ndarray, tau: np.ndarray) -> None:
        """Samples Y (N, n, p), tau (N, n), in time order."""
        Y, tau = _check_data(Y, tau, self.p, self.n)
        for start in range(0, len(tau), _CHUNK):
            self.add_rows(_sample_rows(Y[start:start + _CHUNK], tau[start:start + _CHUNK]))

    def add_rows(self, rows: np.ndarray, information: np.ndarray | None = None) -> None:
        """``add`` on trusted data (finite, shapes right: not checked): rows (N, n, p+1) =
        [Y_j | tau_j] of each sample and joint in time order (_sample_rows), ``information``
        their row_information when known."""
        N = len(rows)
        self._info += row_information(rows) if information is None else information
        self.count += N
        # Complete the open block, then whole blocks at once, then open the remainder.
        k = min(self.block - self._fill, N)
        self._open += rows[:k].sum(axis=0)
        self._fill += k
        if self._fill < self.block:
            return
        whole = (N - k) // self.block
        rest = k + whole * self.block
        sums = rows[k:rest].reshape(whole, self.block, self.n, self.p + 1).sum(axis=1)
        self._binfo += row_information(np.concatenate([self._open[None], sums]))
        self.blocks += whole + 1
        self._open = rows[rest:].sum(axis=0)
        self._fill = N - rest

    def close_block(self) -> None:
        """End the block being filled without counting it: the next sample starts a new
        block (a new recording, whose residuals are not correlated with the last's)."""
        self._open[:] = 0.0
        self._fill = 0

    def __add__(self, other: ResidualStatistics) -> ResidualStatistics:
        """The statistics of two separate recordings together (exact: the sums add); each
        one's unfinished block is left out, as close_block does."""
        if (self.p, self.n, self.block) != (other.p, other.n, other.block):
            raise IdentificationError(
                f'cannot merge residual statistics of (params, joints, block) '
                f'{(self.p, self.n, self.block)} and {(other.p, other.n, other.block)}')
        out = ResidualStatistics(self.p, self.n, self.block)
        out._info, out._binfo = self._info + other._info, self._binfo + other._binfo
        out.count, out.blocks = self.count + other.count, self.blocks + other.blocks
        return out

    @staticmethod
    def _ss(gram, cross, sq, theta):
        return np.maximum(sq - 2 * cross @ theta + np.einsum('p,npq,q->n', theta, gram, theta),
                          0.0)

    def normal_equations(self) -> NormalEquations:
        """The samples' per-joint normal equations (sample sums, not block sums)."""
        return NormalEquations(self._info.copy(), np.full(self.n, float(self.count)))

    def rss(self, theta: np.ndarray) -> np.ndarray:
        """Per-joint residual sum of squares of the samples."""
        return self._ss(self.gram, self.cross, self.sq, np.asarray(theta, dtype=float))

    def variance(self, theta: np.ndarray) -> np.ndarray:
        """Per-joint residual variance per sample (nan before any sample)."""
        return self.rss(theta) / self.count if self.count else np.full(self.n, np.nan)

    def long_run_variance(self, theta: np.ndarray) -> np.ndarray:
        """Per-joint long-run variance: (block residual sums)^2 / block, averaged over the
        complete blocks (nan before the first)."""
        if not self.blocks:
            return np.full(self.n, np.nan)
        p = self.p
        ss = self._ss(self._binfo[:, :p, :p], self._binfo[:, :p, p], self._binfo[:, p, p],
                      np.asarray(theta, dtype=float))
        return ss / (self.blocks * self.block)

    def relative_error(self, theta: np.ndarray) -> np.ndarray:
        """Per-joint 100 ||tau - Y theta|| / ||tau|| (percent)."""
        with np.errstate(invalid='ignore', divide='ignore'):
            return 100.0 * np.sqrt(self.rss(theta) / self.sq)
