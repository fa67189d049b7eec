"""Sequential detection of a payload change in the torque residual of the current model.

A generalised likelihood ratio on a moving window (a matched-subspace test): over the last
``window`` seconds, the residual e = tau - Y phi_arm - Y_p phi_payload (N m), each joint
normalised by its long-run noise variance (weights w_j), is fitted by a change delta of the
payload's leading parameters (the columns X: mass and first moments, whose gravity torque
dominates),

    G = sum_k sum_j w_j X_kj' X_kj,  b = sum_k sum_j w_j X_kj' e_kj,  delta = G^+ b,
    T = b' G^+ b   (chi-square with rank G degrees of freedom while nothing changed).

A change is declared when T exceeds ``threshold`` and the window's mass change |delta_0|
exceeds ``min_change`` (kg): significance alone would flag any small mismatch of the arm
model, so ``min_change`` is the detection threshold in kg. A gap in the samples (a dropped
joint-state stream, > ``max_gap`` s) restarts the window; it is not a change.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import IdentificationError

DEFAULT_WINDOW = 0.25       # s
DEFAULT_THRESHOLD = 50.0    # chi-square statistic (4 dof: p ~ 4e-10 per window)
DEFAULT_MIN_CHANGE = 0.2    # kg
DEFAULT_MIN_FILL = 0.5      # fraction of the window needed before testing


@dataclass(frozen=True)
class Detection:
    """A detected change: ``stamp`` (s) of the sample that crossed the thresholds, the
    estimated ``onset`` (s), the window's statistic and parameter change ``delta``."""
    stamp: float
    onset: float
    statistic: float
    delta: np.ndarray


class WindowedGLR:
    """The moving-window GLR of the module docstring. ``push`` samples in time order;
    after a detection it stays silent until ``reset``."""

    def __init__(self, window: float = DEFAULT_WINDOW, threshold: float = DEFAULT_THRESHOLD,
                 min_change: float = DEFAULT_MIN_CHANGE, max_gap: float = 0.05,
                 min_fill: float = DEFAULT_MIN_FILL):
        for name, value, ok in (('window', window, window > 0),
                                ('threshold', threshold, threshold > 0),
                                ('min_change', min_change, min_change >= 0),
                                ('max_gap', max_gap, max_gap > 0),
                                ('min_fill', min_fill, 0 <= min_fill <= 1)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and ok):
                raise IdentificationError(f'change detection {name} = {value!r} is out of range')
        self.window, self.threshold = float(window), float(threshold)
        self.min_change, self.max_gap, self.min_fill = float(min_change), float(max_gap), min_fill
        self.statistic = 0.0      # the latest T, for diagnostics
        self.reset()

    def reset(self) -> None:
        """Empty the window and arm the detector."""
        self._t = np.empty(0)
        self._A: np.ndarray | None = None
        self._c: np.ndarray | None = None
        self._d0 = np.empty(0)
        self.armed = True
        self.gaps = 0

    def push(self, t: np.ndarray, X: np.ndarray, e: np.ndarray, w: np.ndarray
             ) -> Detection | None:
        """Samples at stamps t (N,) s with columns X (N, n, k), residuals e (N, n) and joint
        weights w (n,): the first change detected among them, if any."""
        t = np.asarray(t, dtype=float)
        if not self.armed or len(t) == 0:
            return None
        w = np.asarray(w, dtype=float)
        A = np.einsum('snk,n,snl->skl', X, w, X)
        c = np.einsum('snk,n,sn->sk', X, w, e)
        prev = self._t[-1] if len(self._t) else -math.inf
        # a gap restarts the window: new segments start at the cuts
        cuts = np.flatnonzero(np.diff(np.concatenate([[prev], t])) > self.max_gap)
        if prev == -math.inf:
            cuts = cuts[cuts > 0]
        bounds = sorted({0, *cuts.tolist(), len(t)})
        for a, b in zip(bounds[:-1], bounds[1:]):
            if a in cuts:
                self.gaps += 1
                self._t, self._A, self._c, self._d0 = np.empty(0), None, None, np.empty(0)
            found = self._segment(t[a:b], A[a:b], c[a:b])
            if found is not None:
                return found
        return None

    def _segment(self, t: np.ndarray, A: np.ndarray, c: np.ndarray) -> Detection | None:
        if len(t) == 0:
            return None
        nb = len(self._t)
        tt = np.concatenate([self._t, t])
        AA = A if self._A is None else np.concatenate([self._A, A])
        cc = c if self._c is None else np.concatenate([self._c, c])
        k = A.shape[1]
        SA = np.concatenate([np.zeros((1, k, k)), np.cumsum(AA, axis=0)])
        Sc = np.concatenate([np.zeros((1, k)), np.cumsum(cc, axis=0)])
        idx = np.arange(nb, len(tt))
        first = np.searchsorted(tt, tt[idx] - self.window, side='right')
        G = SA[idx + 1] - SA[first]
        b = Sc[idx + 1] - Sc[first]
        delta, T = _solve(G, b)
        d0 = delta[:, 0]
        filled = tt[idx] - tt[0] >= self.min_fill * self.window
        alarm = filled & (T > self.threshold) & (np.abs(d0) > self.min_change)
        self.statistic = float(T[-1])
        d0_all = np.concatenate([self._d0, d0])
        if alarm.any():
            i = int(np.argmax(alarm))
            ti = float(tt[idx[i]])
            # The window's estimate ramps up from the onset: it crossed half the threshold
            # halfway there.
            below = np.flatnonzero(np.abs(d0_all[:nb + i]) <= 0.5 * self.min_change)
            half = float(tt[below[-1] + 1]) if len(below) else ti - self.window
            onset = min(ti, max(ti - self.window, 2.0 * half - ti))
            self.armed = False
            return Detection(ti, onset, float(T[i]), delta[i].copy())
        keep = np.searchsorted(tt, tt[-1] - self.window, side='right')
        keep = max(0, min(keep, len(tt) - 1))
        self._t, self._A, self._c, self._d0 = tt[keep:], AA[keep:], cc[keep:], d0_all[keep:]
        return None


def _solve(G: np.ndarray, b: np.ndarray, rcond: float = 1e-9
           ) -> tuple[np.ndarray, np.ndarray]:
    """delta = G^+ b and T = b' G^+ b for a stack of symmetric PSD G (M, k, k), b (M, k),
    in diagonally scaled coordinates with eigenvalues below rcond * the largest dropped."""
    d = np.sqrt(np.maximum(np.einsum('mkk->mk', G), 0.0))
    d = np.where(d > 0, d, 1.0)
    Gs = G / (d[:, :, None] * d[:, None, :])
    lam, V = np.linalg.eigh(Gs)
    inv = np.where(lam > rcond * lam[:, -1:], 1.0 / np.where(lam > 0, lam, 1.0), 0.0)
    bs = b / d
    proj = np.einsum('mkl,mk->ml', V, bs) * inv
    xs = np.einsum('mkl,ml->mk', V, proj)
    return xs / d, np.einsum('mk,mk->m', bs, xs)
