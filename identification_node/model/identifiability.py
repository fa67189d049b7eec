"""Identifiability: base parameters of the regressor, found numerically.

Radkhah, Kulic and Croft, section II.B: stack the regressor at random samples, drop the columns
that are zero (unidentifiable), walk the remaining columns in standard order keeping each one that
is independent of the columns kept so far, and express every dependent column as a combination of
the kept ones, f_dep = W_B alpha. The base parameters are then beta = K phi with
K[:, base_index] = 1 and K[:, dep] = alpha, so that Y phi = Y[..., base_index] beta for every
motion. Since the columns are walked in order, the representative of each group is its first
column, and dependent columns only ever combine with earlier ones.
"""
from __future__ import annotations

import re
from typing import Mapping, Sequence

import numpy as np

from identification_node.errors import IdentificationError

DEFAULT_TOL = 1e-8
_CLEAN = 1e-10  # coefficients below this are numerical noise
_SIGNIFICANT = 12  # digits kept in the coefficients


def sample_motion(robot, num_samples: int, seed: int | None = 0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random (q, qd, qdd), each (N, n): q uniform within the position limits ([-pi, pi] for
    unlimited revolute joints, +-0.5 m for unlimited prismatic ones), qd and qdd standard
    normal (rad/s, rad/s^2 or m/s, m/s^2)."""
    rng = np.random.default_rng(seed)
    n = robot.dof
    lower, upper = np.asarray(robot.position_limits, dtype=float).T
    limited = np.isfinite(lower) & np.isfinite(upper) & (upper > lower)
    span = np.where(np.asarray(robot.prismatic, dtype=bool), 0.5, np.pi)
    lower = np.where(limited, lower, -span)
    upper = np.where(limited, upper, span)
    q = rng.uniform(lower, upper, size=(num_samples, n))
    qd = rng.standard_normal((num_samples, n))
    qdd = rng.standard_normal((num_samples, n))
    return q, qd, qdd


def _clean(c: np.ndarray) -> np.ndarray:
    """Zero the noise and round to _SIGNIFICANT digits (0.20250000000000004 -> 0.2025)."""
    c = np.where(np.abs(c) < _CLEAN, 0.0, c)
    exponent = np.floor(np.log10(np.where(c == 0, 1.0, np.abs(c))))
    scale = 10.0 ** (_SIGNIFICANT - 1 - exponent)
    return np.round(c * scale) / scale


def _ros_name(name: str) -> str:
    return re.sub(r'[^A-Za-z0-9_.]', '_', name)


def _coefficient(c: float) -> str:
    text = f'{abs(c):.6g}'
    return '' if text == '1' else text + ' '


def format_expression(terms: dict[str, float]) -> str:
    """``{'a': 1, 'b': -1, 'c': 0.2025}`` -> ``'a - b + 0.2025 c'``."""
    parts = []
    for k, (name, c) in enumerate(terms.items()):
        sign = ('-' if c < 0 else '') if k == 0 else (' - ' if c < 0 else ' + ')
        parts.append(f'{sign}{_coefficient(c)}{name}')
    return ''.join(parts)


def unexcited_directions(information: np.ndarray, names: Sequence[str],
                         max_condition: float = 1e8) -> list[tuple[str, list[str]]]:
    """The directions of parameter space the data do not determine: eigenvectors of the
    column-scaled information (p, p) of the parameters ``names`` whose eigenvalue is below
    1 / ``max_condition`` of the largest (parameters with no information at all, each alone).
    Returns (readable combination, names of the parameters in it) per direction, the
    combination normalised to its largest coefficient 1 and rounded."""
    info = np.asarray(information, dtype=float)
    if not np.isfinite(info).all():
        return [('all parameters (the information is not finite)', list(names))]
    d = np.sqrt(np.maximum(np.diag(info), 0.0))
    ok = d > 1e-12 * max(d.max(), 1e-300)
    out = [(str(names[i]), [str(names[i])]) for i in np.flatnonzero(~ok).tolist()]
    if ok.any():
        scaled = info[np.ix_(ok, ok)] / np.outer(d[ok], d[ok])
        ev, vec = np.linalg.eigh(scaled)
        kept = [str(n) for n, k in zip(names, ok) if k]
        for k in np.flatnonzero(ev < ev[-1] / max_condition):
            v = vec[:, k] / d[ok]                      # back to the parameters' units
            v = v / v[np.argmax(np.abs(v))]
            terms = {kept[i]: float(c) for i, c in enumerate(_clean(v))
                     if abs(c) >= 1e-3}
            out.append((format_expression(terms), list(terms)))
    return out


class BaseParameters:
    """The base parameters beta = K phi of a regressor with standard columns ``param_names``.

    ``base_index`` lists the standard columns kept (the base regressor is Y[..., base_index]);
    row k of K expresses base parameter k in the standard parameters. Build it with
    ``from_robot`` (random samples) or ``from_regressor`` (a given stacked regressor).
    """

    def __init__(self, param_names: Sequence[str], base_index: np.ndarray, K: np.ndarray, *,
                 robot: str = '', joints: Sequence[str] = (),
                 phi_model: np.ndarray | None = None):
        self.param_names = list(param_names)
        self.num_params = len(self.param_names)
        self.base_index = np.asarray(base_index, dtype=int)
        self.K = np.asarray(K, dtype=float)
        self.robot = robot
        self.joints = list(joints)
        self.phi_model = None if phi_model is None else np.asarray(phi_model, dtype=float)
        if self.K.shape != (self.num_base, self.num_params):
            raise ValueError(f'K has shape {self.K.shape}, expected '
                             f'({self.num_base}, {self.num_params})')
        self._pinv: np.ndarray | None = None
        self._derive()

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_robot(cls, robot, num_samples: int | None = None, seed: int | None = 0,
                   tol: float = DEFAULT_TOL) -> 'BaseParameters':
        """Base parameters of a RobotModel from its regressor at random samples
        (``sample_motion``); ``num_samples`` defaults to enough rows for 4 per column."""
        if num_samples is None:
            num_samples = max(100, int(np.ceil(4 * robot.num_params / robot.dof)))
        q, qd, qdd = sample_motion(robot, int(num_samples), seed)
        return cls.from_regressor(robot.regressor(q, qd, qdd), robot.param_names, tol=tol,
                                  robot=robot.name, joints=robot.joint_names,
                                  phi_model=robot.phi_model)

    @classmethod
    def from_regressor(cls, Y: np.ndarray, param_names: Sequence[str],
                       tol: float = DEFAULT_TOL, **kwargs) -> 'BaseParameters':
        """Base parameters of a stacked regressor Y, (N, n, p) or (rows, p).

        A column is zero when its norm is below ``tol`` times the largest column norm, and
        independent when its part orthogonal to the kept columns, relative to its own norm,
        exceeds ``tol``.
        """
        Y = np.asarray(Y, dtype=float)
        p = len(param_names)
        if Y.shape[-1] != p:
            raise IdentificationError(f'regressor has {Y.shape[-1]} columns, expected {p}')
        W = Y.reshape(-1, p)
        if not np.isfinite(W).all():
            raise IdentificationError('regressor contains NaN or inf')
        if not 0 < tol < 1:
            raise IdentificationError(f'rank tolerance must lie in (0, 1), got {tol}')
        norms = np.linalg.norm(W, axis=0)
        if norms.max(initial=0.0) == 0.0:
            raise IdentificationError('regressor is zero: no parameter is identifiable')
        nonzero = norms > tol * norms.max()
        if W.shape[0] < nonzero.sum():
            raise IdentificationError(
                f'{W.shape[0]} regressor rows cannot reveal the rank of {int(nonzero.sum())} '
                'columns: use more samples')
        base: list[int] = []
        Q = np.zeros((W.shape[0], 0))
        for j in np.flatnonzero(nonzero):
            v = W[:, j] / norms[j]
            for _ in range(2):  # twice is enough (Kahan-Parlett) for a stable projection
                v = v - Q @ (Q.T @ v)
            residual = np.linalg.norm(v)
            if residual > tol:
                base.append(int(j))
                Q = np.column_stack([Q, v / residual])
        base_index = np.array(base, dtype=int)
        dependent = np.flatnonzero(nonzero & ~np.isin(np.arange(p), base_index))
        K = np.zeros((len(base), p))
        K[np.arange(len(base)), base_index] = 1.0
        if dependent.size:
            # Scale columns so lstsq sees a well-conditioned problem, then undo the scaling.
            WB = W[:, base_index] / norms[base_index]
            alpha, *_ = np.linalg.lstsq(WB, W[:, dependent], rcond=None)
            K[:, dependent] = _clean(alpha / norms[base_index][:, None])
        return cls(param_names, base_index, K, **kwargs)

    def _derive(self) -> None:
        K = self.K
        nnz_rows = (K != 0).sum(axis=1)
        used = (K != 0).any(axis=0)
        self.terms: list[dict[str, float]] = [
            {self.param_names[j]: float(K[k, j]) for j in np.flatnonzero(K[k])}
            for k in range(self.num_base)]
        self.expressions = [format_expression(t) for t in self.terms]
        alone = self.base_index[nnz_rows == 1]
        self.identifiable = [self.param_names[j] for j in alone]
        self.unidentifiable = [self.param_names[j] for j in np.flatnonzero(~used)]
        self.combined = [self.param_names[j] for j in np.flatnonzero(used)
                         if j not in set(alone.tolist())]
        names, seen = [], set()
        for k, j in enumerate(self.base_index):
            name = _ros_name(self.param_names[j] + ('' if nnz_rows[k] == 1 else 'R'))
            unique, i = name, 2
            while unique in seen:
                unique, i = f'{name}_{i}', i + 1
            seen.add(unique)
            names.append(unique)
        self.names = names

    # -- dimensions -----------------------------------------------------------------------------
    @property
    def num_base(self) -> int:
        return len(self.base_index)

    def __repr__(self) -> str:
        return (f'BaseParameters({self.robot or "?"}: {self.num_base} base of '
                f'{self.num_params} standard parameters)')

    # -- maps -------------------------------------------------------------------------------------
    def _check(self, phi: np.ndarray, width: int, what: str) -> np.ndarray:
        phi = np.asarray(phi, dtype=float)
        if phi.shape[-1:] != (width,):
            raise IdentificationError(f'{what} has shape {phi.shape}, expected (..., {width})')
        return phi

    def to_base(self, phi: np.ndarray) -> np.ndarray:
        """Base parameters beta = K phi of standard parameters phi (..., p)."""
        return self._check(phi, self.num_params, 'parameter vector') @ self.K.T

    def base_regressor(self, Y: np.ndarray) -> np.ndarray:
        """The base regressor Y[..., base_index]: Y phi = base_regressor(Y) beta."""
        return self._check(Y, self.num_params, 'regressor')[..., self.base_index]

    def closest_standard(self, beta: np.ndarray, phi_ref: np.ndarray) -> np.ndarray:
        """The standard parameters phi with K phi = beta closest (Euclidean) to phi_ref."""
        beta = self._check(beta, self.num_base, 'base parameter vector')
        phi_ref = self._check(phi_ref, self.num_params, 'reference parameter vector')
        if self._pinv is None:
            self._pinv = np.linalg.pinv(self.K)
        return phi_ref + (beta - phi_ref @ self.K.T) @ self._pinv.T

    def combination(self, terms: Mapping[str, float]) -> np.ndarray:
        """Weights w with w @ beta = sum(coef * phi[name]) for every phi reproducing beta;
        IdentificationError when the combination is not identifiable."""
        c = np.zeros(self.num_params)
        for name, coef in terms.items():
            if name not in self.param_names:
                raise IdentificationError(f'unknown parameter {name!r}')
            c[self.param_names.index(name)] = coef
        w = np.linalg.lstsq(self.K.T, c, rcond=None)[0]
        if np.linalg.norm(self.K.T @ w - c) > 1e-8 * max(1.0, float(np.linalg.norm(c))):
            raise IdentificationError(f'{format_expression(dict(terms))} is not identifiable')
        return w

    # -- report -----------------------------------------------------------------------------------
    def to_dict(self, phi_model: np.ndarray | None = None) -> dict:
        """The JSON object of ``structure --json``; values from ``phi_model`` (default: the
        robot's own parameters, when known)."""
        phi = self.phi_model if phi_model is None else phi_model
        values = [None] * self.num_base if phi is None else self.to_base(phi).tolist()
        return {
            'robot': self.robot,
            'joints': self.joints,
            'parameters': self.param_names,
            'num_params': self.num_params,
            'num_base': self.num_base,
            'identifiable': self.identifiable,
            'unidentifiable': self.unidentifiable,
            'combined': self.combined,
            'base_parameters': [
                {'name': n, 'expression': e, 'terms': t, 'value': v}
                for n, e, t, v in zip(self.names, self.expressions, self.terms, values)],
        }
