"""Excitation criteria of a stacked base regressor (smaller is better) and the function the
optimiser minimises, with its gradient.

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
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from identification_node.config import Excitation
from identification_node.errors import IdentificationError
from identification_node.excitation.limits import numbers
from identification_node.excitation.trajectories import FramedTrajectory
from identification_node.excitation.trajectory_base import Trajectory

CRITERIA = ('cond', 'dopt')
DEFAULT_SAMPLES = Excitation.samples   # criterion samples over one period
_RANK_TOL = 1e-12  # singular value (or diagonal of R) ratio below which W is rank deficient


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
        W = W * noise_weights(noise_std, W.shape[1])[None, :, None]
    s = np.linalg.svd(_rows(W), compute_uv=False)
    return float(-2.0 * np.log(s).sum()) if s[-1] > 0 else math.inf


def _rows(W: np.ndarray) -> np.ndarray:
    W = np.asarray(W, dtype=float)
    return W.reshape(-1, W.shape[-1])


def noise_weights(noise_std: Sequence[float] | None, n: int) -> np.ndarray:
    if noise_std is None:
        return np.ones(n)
    std = numbers('noise_std', noise_std).reshape(-1)
    if std.shape != (n,) or not (np.isfinite(std) & (std > 0)).all():
        raise IdentificationError(f'noise_std needs {n} finite values > 0 (one per joint), got '
                                  f'{np.asarray(noise_std).tolist()}')
    return 1.0 / std


def objective(W: np.ndarray, criterion: str, grad: bool
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


def report_value(f: float, criterion: str) -> float:
    """The reported criterion value from the optimised function value."""
    return float(np.exp(f)) if criterion == 'cond' and np.isfinite(f) else float(f)


def criterion_value(robot, traj: Trajectory, criterion: str = 'cond', base=None,
                    num_samples: int = DEFAULT_SAMPLES,
                    noise_std: Sequence[float] | None = None) -> float:
    """``cond`` (condition number) or ``dopt`` (-log det W'W, noise-weighted) of the base
    regressor stacked over ``num_samples`` equally spaced samples of one pass of ``traj`` (of
    one period of the periodic part of a FramedTrajectory)."""
    check_criterion(criterion)
    if isinstance(traj, FramedTrajectory):
        traj = traj.periodic
    base = base_of(robot, base)
    t = np.arange(int(num_samples)) * (traj.horizon() / int(num_samples))
    q, qd, qdd = traj.sample(t)
    Yb = base.base_regressor(robot.regressor(q, qd, qdd))
    W = (Yb * noise_weights(noise_std, robot.dof)[None, :, None]).reshape(-1, base.num_base)
    return report_value(objective(W, criterion, False)[0], criterion)


def check_criterion(criterion: str) -> None:
    if criterion not in CRITERIA:
        raise IdentificationError(f'unknown criterion {criterion!r}; use one of '
                                  f'{", ".join(CRITERIA)}')


def base_of(robot, base):
    if base is None:
        from identification_node.model.identifiability import BaseParameters
        return BaseParameters.from_robot(robot)
    return base
