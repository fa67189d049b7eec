"""Residual statistics of any parameter vector from constant-memory per-joint sums: per
sample, and over blocks of consecutive samples (long-run variance of correlated residuals).

Data are regressor rows grouped per sample: ``Y`` (N, n, p) and measured joint torques ``tau``
(N, n) with tau ~ Y @ theta (SI units of the regressor columns; p parameters, n joints).
"""
from __future__ import annotations

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.lsq import (CHUNK, check_count, check_data, sample_rows,
                                                row_information)
from identification_node.estimation.normal_equations import NormalEquations

MIN_BLOCKS = 10   # complete blocks before their long-run variance is trusted


class ResidualStatistics:
    """Per-joint sums giving, for ANY parameter vector theta, the residuals tau - Y theta's sum
    of squares sample by sample and over blocks of ``block`` consecutive samples, in constant
    memory. The block sums give the long-run (zero-frequency) variance of correlated residuals,
    such as smoothed noise: the variance that least squares actually averages.
    """

    def __init__(self, num_params: int, num_joints: int, block: int):
        self.p, self.n = check_count('num_params', num_params), check_count(
            'num_joints', num_joints)
        self.block = check_count('block', block)
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
        Y, tau = check_data(Y, tau, self.p, self.n)
        for start in range(0, len(tau), CHUNK):
            self.add_rows(sample_rows(Y[start:start + CHUNK], tau[start:start + CHUNK]))

    def add_rows(self, rows: np.ndarray, information: np.ndarray | None = None) -> None:
        """``add`` on trusted data (finite, shapes right: not checked): rows (N, n, p+1) =
        [Y_j | tau_j] of each sample and joint in time order (sample_rows), ``information``
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
        # (gram @ theta) @ theta: BLAS products, 3x faster than the three-operand einsum
        return np.maximum(sq - 2 * cross @ theta + (gram @ theta) @ theta, 0.0)

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

    def noise_variance(self, theta: np.ndarray, white_scale: float) -> np.ndarray:
        """Per-joint variance of the residual noise an estimate averages (N m)^2, for residuals
        of data smoothed with white-noise gain 1 / ``white_scale``
        (signals.smoothing_noise_gain): the larger of the white raw noise that explains their
        variance and, once MIN_BLOCKS blocks are in, their long-run variance. The long-run
        variance is right for noise, but blind to what a fit leaves at the motion's
        frequencies: the smoother's bias on the signals and the derivatives' noise in the
        regressor. The white model counts those, conservatively."""
        white = self.variance(theta) * white_scale
        if self.blocks < MIN_BLOCKS:
            return white
        return np.fmax(white, self.long_run_variance(theta))

    def relative_error(self, theta: np.ndarray) -> np.ndarray:
        """Per-joint 100 ||tau - Y theta|| / ||tau|| (percent)."""
        with np.errstate(invalid='ignore', divide='ignore'):
            return 100.0 * np.sqrt(self.rss(theta) / self.sq)
