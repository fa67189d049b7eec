"""Missing model terms: torque residuals that correlate with sign(qd), qd or q, or do not
average to zero.

Per joint, sums over the equations fitted of a few features f (1, sign(qd), qd, q) times the
rows [Yb | tau] and times each other give, for any estimate theta, the partial correlation of
the residual r = tau - Yb theta with each feature given the others (with the residual sum of
squares the estimator keeps already), in constant memory, added batch by batch. A term the
model has (fc for sign(qd), fv for qd, fo for the mean) leaves the residual orthogonal to its
feature, so only missing ones can correlate; the partial correlation names the feature that
explains the residual, not one merely correlated with it along the trajectory. Units: the
rows' own (N m, rad, rad/s); correlations are dimensionless.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from identification_node.model.coulomb import coulomb_sign

FEATURES = ('1', 'sign(qd)', 'qd', 'q')
# feature: (the model's term that removes it, the likely missing term named in the warning)
TERMS = {
    'sign(qd)': ('fc', 'Coulomb friction (fc) missing?'),
    'qd': ('fv', 'viscous friction (fv) missing?'),
    'q': (None, 'a position-dependent torque (spring, cable, gravity compensator) missing?'),
}
MIN_CORRELATION = 0.25   # |r| above this warns; noise on a correct model stays far below
MIN_OFFSET = 0.25        # |mean residual| / residual RMS above this warns (no fo)
MIN_EQUATIONS = 100      # fewer equations of a joint: no warning (too little to judge)


def features(q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """(N, n, 4): 1, sign(qd), qd, q of each sample and joint (FEATURES' order)."""
    return np.stack([np.ones_like(qd), coulomb_sign(qd), qd, q], axis=-1)


class ModelTermStatistics:
    """Sums over equations of the features times the rows [Yb | tau] (n joints, c = b + 1
    columns) and times each other."""

    def __init__(self, num_joints: int, num_columns: int):
        self.n, self.c = int(num_joints), int(num_columns)
        self.reset()

    def reset(self) -> None:
        k = len(FEATURES)
        self.cross = np.zeros((self.n, k, self.c))   # sum f_k [Yb | tau]
        self.gram = np.zeros((self.n, k, k))         # sum f_k f_l (f_0 = 1: sums, weight)
        self.count = np.zeros(self.n)                # equations per joint

    def add(self, feats: np.ndarray, rows: np.ndarray) -> None:
        """Features (N, n, 4) of rows (N, n, c), all zero for an equation left out. Rows
        weighted by s (the fit's scaled equations) take features weighted by s too, the
        first one s itself: the correlations are then the fit's weighted ones."""
        if not len(rows):
            return
        f = feats.transpose(1, 2, 0)   # BLAS gemm per joint (einsum would not use BLAS)
        self.cross += f @ rows.transpose(1, 0, 2)
        self.gram += f @ feats.transpose(1, 0, 2)
        self.count += np.count_nonzero(feats[:, :, 0], axis=0)

    def __add__(self, other: ModelTermStatistics) -> ModelTermStatistics:
        out = ModelTermStatistics(self.n, self.c)
        out.cross, out.gram = self.cross + other.cross, self.gram + other.gram
        out.count = self.count + other.count
        return out

    def correlations(self, theta: np.ndarray, rss: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) partial correlation of the residual with each of sign(qd), qd and q given
        the other two (a feature that does not vary: 0), and (n,) the residual's mean over
        its RMS, for the estimate theta (b,) whose per-joint residual sum of squares over
        the same equations is ``rss`` (n,); NaN for a joint without equations."""
        a = np.append(-np.asarray(theta, dtype=float), 1.0)
        rss = np.asarray(rss, dtype=float)
        N = np.maximum(self.gram[:, 0, 0], 1e-300)   # the total weight (unweighted: count)
        s_fr = self.cross @ a                          # (n, k): sum f r; k = 0: sum r
        k = len(FEATURES)
        # sums of [f_1 .. f_3, r] products, then their covariance matrix about the means
        S = np.zeros((self.n, k, k))
        S[:, :k - 1, :k - 1] = self.gram[:, 1:, 1:]
        S[:, :k - 1, k - 1] = S[:, k - 1, :k - 1] = s_fr[:, 1:]
        S[:, k - 1, k - 1] = rss
        mean = np.concatenate([self.gram[:, 0, 1:], s_fr[:, :1]], axis=1) / N[:, None]
        C = S / N[:, None, None] - mean[:, :, None] * mean[:, None, :]
        d = np.diagonal(C, axis1=1, axis2=2)
        flat = d <= 1e-12 * np.maximum(np.diagonal(S, axis1=1, axis2=2) / N[:, None], 1e-300)
        with np.errstate(invalid='ignore', divide='ignore', over='ignore'):   # joints masked
            R = C / np.sqrt(d[:, :, None] * d[:, None, :])
            R = np.where(flat[:, :, None] | flat[:, None, :], 0.0, R)
            R[:, np.arange(k), np.arange(k)] = 1.0
            P = np.linalg.pinv(R)
            partial = -P[:, :k - 1, k - 1] / np.sqrt(P[:, np.arange(k - 1), np.arange(k - 1)]
                                                     * P[:, k - 1, k - 1][:, None])
            offset = (s_fr[:, 0] / N) / np.sqrt(rss / N)
        partial = np.where(flat[:, :k - 1], 0.0, np.clip(partial, -1.0, 1.0))
        ok = (self.count > 0) & ~flat[:, k - 1]
        return np.where(ok[:, None], partial, np.nan), np.where(ok, offset, np.nan)


def missing_term_warnings(stats: ModelTermStatistics | None, theta: np.ndarray,
                          rss: np.ndarray, joint_names: Sequence[str],
                          extras: Sequence[str]) -> list[str]:
    """Warnings naming the likely missing term of each joint whose residual correlates with
    sign(qd), qd or q beyond MIN_CORRELATION, or whose mean is MIN_OFFSET of its RMS without
    an offset column, e.g. "joint3: residual correlates with sign(qd) (r=0.60): Coulomb
    friction (fc) missing?". Terms the model has are not tested (their residual is orthogonal
    to them by construction); q is named only when no friction term is (a missing friction
    term biases the gravity terms, which depend on q)."""
    if stats is None:
        return []
    r, offset = stats.correlations(theta, rss)
    out = []
    for j, name in enumerate(joint_names):
        if stats.count[j] < MIN_EQUATIONS:
            continue
        found = [(feature, r[j, k]) for k, feature in enumerate(FEATURES[1:])
                 if TERMS[feature][0] not in extras and abs(r[j, k]) > MIN_CORRELATION]
        if len(found) > 1:   # missing friction biases the gravity terms, which depend on q
            found = [f for f in found if f[0] != 'q']
        out += [f'{name}: residual correlates with {feature} (r={value:.2f}): '
                f'{TERMS[feature][1]}' for feature, value in found]
        if 'fo' not in extras and abs(offset[j]) > MIN_OFFSET:
            out.append(f'{name}: residual mean is {offset[j]:.2f} of its RMS: torque offset '
                       '(fo) missing?')
    return out
