"""Building blocks shared by the least-squares estimators (``batch``, ``rls``, ``residuals``):
the parameter ``Estimate``, data checks, per-joint regressor rows and their information, the
triangular least-squares solve with its rank test, and the covariance. Package-internal (the
underscored names are not part of the public API; ``Estimate`` and ``row_information`` are).

Data are regressor rows grouped per sample: ``Y`` (N, n, p) and measured joint torques ``tau``
(N, n) with tau ~ Y @ theta (SI units of the regressor columns; p parameters, n joints).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identification_node.errors import IdentificationError

CHUNK = 4096  # samples per QR: bounds the workspace to ~CHUNK * n * (p + 1) floats
DEFAULT_RCOND = 1e-10  # singular-value ratio (column-scaled) below which a direction is unexcited


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
                   rel_stddev=relative_stddev(stddev, theta),
                   noise_variance=np.asarray(noise_variance, dtype=float),
                   num_samples=int(num_samples), rss=float(rss))

    def predict(self, Y: np.ndarray) -> np.ndarray:
        """Predicted torques Y @ theta, (N, n) for Y (N, n, p)."""
        return np.asarray(Y, dtype=float) @ self.theta


def relative_stddev(stddev: np.ndarray, theta: np.ndarray) -> np.ndarray:
    with np.errstate(divide='ignore', invalid='ignore'):
        rel = 100.0 * stddev / np.abs(theta)
    return np.where(theta == 0, np.inf, rel)


def qr_r(a: np.ndarray) -> np.ndarray:
    """Upper-triangular R (..., k, k) of the QR factorisation of a (..., m, k), m >= k."""
    return np.linalg.qr(a, mode='r')  # type: ignore[return-value]  # stubs: QRResult always


def check_count(name: str, value: int, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise IdentificationError(f'{name} must be an integer >= {minimum}, got {value!r}')
    return int(value)


def as_float(name: str, a) -> np.ndarray:
    try:
        return np.asarray(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise IdentificationError(f'{name} is not a numeric array: {exc}') from None


def _check_finite(name: str, a: np.ndarray) -> None:
    if not np.isfinite(a).all():
        k = int(np.argwhere(~np.isfinite(a))[0][0])
        raise IdentificationError(f'{name} contains NaN or inf (first at sample {k})')


def check_data(Y, tau, num_params: int, num_joints: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Validate Y (N, n, p) and tau (N, n) (one sample: (n, p) and (n,))."""
    Y, tau = as_float('regressor', Y), as_float('torques', tau)
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


def sample_rows(Y: np.ndarray, tau: np.ndarray, scale: np.ndarray | None = None
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


def column_scale(R: np.ndarray) -> np.ndarray:
    """Column norms of R, for a scale-invariant rank test on R / d."""
    d = np.linalg.norm(R, axis=0)
    # Columns at rounding level (a parameter without effect) must not be scaled up to unit norm.
    return np.where(d > 1e-12 * d.max(), d, max(d.max(), 1e-300))


def _rank(s: np.ndarray, rcond: float) -> int:
    return int(np.sum(s > rcond * s[0])) if s.size and s[0] > 0 else 0


def solve_triangular_lsq(R: np.ndarray, z: np.ndarray, rcond: float,
                         theta_ref: np.ndarray | None = None
                         ) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """Minimise ||R theta - z|| for upper-triangular R.

    Returns theta, the rank, a generalised inverse G of R (R^-1 at full rank) and a boolean
    mask of the parameters that the data determine. When R is singular, theta is theta_ref
    (default 0) plus the minimum-norm correction in column-scaled coordinates.
    """
    p = R.shape[0]
    d = column_scale(R)
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


def covariance_from_root(G: np.ndarray, scale: float, determined: np.ndarray) -> np.ndarray:
    """scale * G G', symmetric; inf variance (and zero correlation) for undetermined params."""
    cov = scale * (G @ G.T)
    cov = 0.5 * (cov + cov.T)
    if not determined.all():
        cov[~determined, :] = 0.0
        cov[:, ~determined] = 0.0
        cov[~determined, ~determined] = np.inf
    return cov
