"""The information form every solver reads: per-joint normal equations of tau_j = Y_j theta.

For joint j over a set of samples (weighted, forgotten or not):

    A_j = sum_k [Y_jk | tau_jk]' [Y_jk | tau_jk]   (p+1, p+1),  count_j = sum of row weights,

so that ||tau_j - Y_j theta||^2 = v' A_j v with v = [theta, -1]. These sums are sufficient
statistics: the batch and recursive estimators, the physically consistent solve, the payload
fit and the fleet reduction all read them, and sets of samples merge exactly by addition.
theta is in the estimator's parameter order (base parameters, see identifiability).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identification_node.errors import IdentificationError


@dataclass(frozen=True)
class NormalEquations:
    """Per-joint augmented information ``augmented`` (n, p+1, p+1) and row counts ``count``
    (n,) of tau_j = Y_j theta (units: those of Y and tau squared)."""

    augmented: np.ndarray
    count: np.ndarray

    def __post_init__(self) -> None:
        a, c = np.asarray(self.augmented, dtype=float), np.asarray(self.count, dtype=float)
        if a.ndim != 3 or a.shape[1] != a.shape[2] or a.shape[1] < 2 or c.shape != a.shape[:1]:
            raise IdentificationError(
                f'normal equations need augmented (n, p+1, p+1) and count (n,), '
                f'got {a.shape} and {c.shape}')
        object.__setattr__(self, 'augmented', a)
        object.__setattr__(self, 'count', c)

    @classmethod
    def zeros(cls, num_params: int, num_joints: int) -> NormalEquations:
        return cls(np.zeros((num_joints, num_params + 1, num_params + 1)), np.zeros(num_joints))

    @classmethod
    def from_rows(cls, Y: np.ndarray, tau: np.ndarray) -> NormalEquations:
        """From regressor rows Y (N, n, p) and torques tau (N, n)."""
        Y, tau = np.asarray(Y, dtype=float), np.asarray(tau, dtype=float)
        if Y.ndim != 3 or tau.shape != Y.shape[:2]:
            raise IdentificationError(
                f'Y must be (N, n, p) and tau (N, n), got {Y.shape} and {tau.shape}')
        rows = np.concatenate([Y, tau[:, :, None]], axis=2)
        return cls(np.einsum('kjp,kjq->jpq', rows, rows), np.full(Y.shape[1], float(len(Y))))

    @property
    def num_params(self) -> int:
        return self.augmented.shape[1] - 1

    @property
    def num_joints(self) -> int:
        return self.augmented.shape[0]

    gram = property(lambda self: self.augmented[:, :-1, :-1], doc="sum Y_j'Y_j (n, p, p)")
    cross = property(lambda self: self.augmented[:, :-1, -1], doc="sum Y_j'tau_j (n, p)")
    sq = property(lambda self: self.augmented[:, -1, -1], doc='sum tau_j^2 (n,)')

    def __add__(self, other: NormalEquations) -> NormalEquations:
        if self.augmented.shape != other.augmented.shape:
            raise IdentificationError(
                f'cannot merge normal equations of shapes {self.augmented.shape} and '
                f'{other.augmented.shape}')
        return NormalEquations(self.augmented + other.augmented, self.count + other.count)

    def scaled(self, factor: float) -> NormalEquations:
        """Every sum times ``factor`` (forgetting)."""
        return NormalEquations(self.augmented * factor, self.count * factor)

    def combined(self, weights: np.ndarray | float = 1.0
                 ) -> tuple[np.ndarray, np.ndarray, float]:
        """sum_j w_j A_j split as (Y'WY (p, p), Y'W tau (p,), tau'W tau): the weighted least
        squares objective is theta'G theta - 2 b'theta + c. ``weights`` per joint (n,), e.g.
        inverse noise variances."""
        w = np.broadcast_to(np.asarray(weights, dtype=float), (self.num_joints,))
        A = np.einsum('j,jpq->pq', w, self.augmented)
        return A[:-1, :-1], A[:-1, -1], float(A[-1, -1])

    def rss(self, theta: np.ndarray) -> np.ndarray:
        """Per-joint residual sum of squares ||tau_j - Y_j theta||^2 (n,)."""
        v = np.append(np.asarray(theta, dtype=float), -1.0)
        return np.maximum(np.einsum('p,jpq,q->j', v, self.augmented, v), 0.0)
