"""Sequential detection of a payload change in the torque residual of the current model.

A generalised likelihood ratio on a moving window (a matched-subspace test): over the last
``window`` seconds, the residual e = tau - Y phi_arm - Y_p phi_payload (N m) is fitted by a
change delta of the payload's leading parameters (the columns X: mass and first moments,
whose gravity torque dominates), each joint j weighted by 1 / its noise variance s_j^2:

    G = sum_k sum_j X_kj' X_kj / s_j^2,  b = sum_k sum_j X_kj' e_kj / s_j^2,
    delta = G^+ b,  T = b' G^+ b   (chi-square, rank G degrees of freedom, while nothing
    changed),  z = delta_0 / sqrt(G^+_00)  (the mass change in its standard deviations).

s_j^2 is the window's mean square residual left by its fitted change (weighted by the
segment's noise level; scaled from the smoothed samples' variance to the long-run variance
the sums average), never below the segment's noise level: the residual grows with the
motion (errors in variables, model errors), and a test normalised by a quiet segment's noise
would flag every faster move, while a change is what its own fit explains. (The window
before, once used, holds the change itself a window after its onset: the test went deaf
before the conditions had held ``confirm`` s.)

A change is declared when T exceeds ``threshold``, z exceeds ``min_z``, the mass change
|delta_0| exceeds ``min_change`` (kg) and the window determines it to DETERMINED *
``min_change`` (a model error can masquerade as a large change of a nearly unobservable
mass: the MIT arm's last link). A quarter of ``min_change`` held a clear 2 kg place back by
0.8 s at 250 Hz, where a window holds few samples. Significance alone would flag any small
mismatch of the arm model, so ``min_change`` is the detection threshold in kg. The
conditions must hold for ``confirm`` s, and the latest ``recent`` s alone must show a mass
change beyond ``min_change`` of the same sign, at ``min_z / 2`` of its standard deviations:
a glitch (a stalled stream bursting out with compressed stamps, a knock) moves the window's
estimate for as long as it is inside the window, but not a sub-window after it. A gap in
the samples (a dropped joint-state stream, > ``max_gap`` s) restarts the window; it is not a
change.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from identification_node.config import Payload
from identification_node.errors import IdentificationError

DEFAULT_WINDOW = Payload.window           # s
DEFAULT_THRESHOLD = Payload.threshold     # chi-square statistic (4 dof: p ~ 4e-10 per window)
DEFAULT_MIN_Z = Payload.min_z             # standard deviations of the mass change
DEFAULT_MIN_CHANGE = Payload.min_change   # kg
DEFAULT_MIN_FILL = 0.5      # fraction of the window needed before testing
DEFAULT_CONFIRM = Payload.confirm         # s the conditions must hold
DEFAULT_RECENT = 0.05      # s: the latest sub-window that must show the change alone
DETERMINED = 0.5            # the window must know the mass change to this * min_change


@dataclass(frozen=True)
class Detection:
    """A detected change: ``stamp`` (s) of the sample that crossed the thresholds, the
    estimated ``onset`` (s), the window's statistic and parameter change ``delta``."""
    stamp: float
    onset: float
    statistic: float
    delta: np.ndarray


class WindowedGLR:
    """The moving-window GLR of the module docstring. ``noise_scale``: long-run over sample
    variance of the residuals (1 / the smoother's noise gain for smoothed white noise; a
    value per joint may be set). ``push`` samples in time order;
    after a detection it stays silent until ``reset``."""

    def __init__(self, window: float = DEFAULT_WINDOW, threshold: float = DEFAULT_THRESHOLD,
                 min_change: float = DEFAULT_MIN_CHANGE, max_gap: float = 0.05,
                 min_fill: float = DEFAULT_MIN_FILL, min_z: float = DEFAULT_MIN_Z,
                 noise_scale: float = 1.0, confirm: float = DEFAULT_CONFIRM,
                 recent: float = DEFAULT_RECENT):
        for name, value, ok in (('window', window, window > 0),
                                ('threshold', threshold, threshold > 0),
                                ('min_change', min_change, min_change >= 0),
                                ('max_gap', max_gap, max_gap > 0),
                                ('min_fill', min_fill, 0 <= min_fill <= 1),
                                ('min_z', min_z, min_z >= 0),
                                ('noise_scale', noise_scale, noise_scale > 0),
                                ('confirm', confirm, confirm >= 0),
                                ('recent', recent, 0 < recent <= window)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and ok):
                raise IdentificationError(f'change detection {name} = {value!r} is out of range')
        self.window, self.threshold = float(window), float(threshold)
        self.min_change, self.max_gap, self.min_fill = float(min_change), float(max_gap), min_fill
        self.min_z = float(min_z)
        self.noise_scale: float | np.ndarray = float(noise_scale)   # or per joint (n,)
        self.confirm, self.recent = float(confirm), float(recent)
        self.statistic = 0.0      # the latest T, for diagnostics
        self.gaps = 0
        self.reset()

    def reset(self) -> None:
        """Empty the window and arm the detector."""
        self._clear()
        self.armed = True

    def _clear(self) -> None:
        self._t = np.empty(0)
        self._S: np.ndarray | None = None   # prefix sums of X'X, X'e, e^2 of every joint
        self._d0 = np.empty(0)
        self._since = -math.inf   # since when the change conditions have held

    def push(self, t: np.ndarray, X: np.ndarray, e: np.ndarray, noise_variance: np.ndarray
             ) -> Detection | None:
        """Samples at stamps t (N,) s with columns X (N, n, k), residuals e (N, n) and the
        segment's noise variance per joint (n,): the first change detected, if any."""
        t = np.asarray(t, dtype=float)
        if not self.armed or len(t) == 0:
            return None
        N, n, k = X.shape
        rows = np.concatenate([np.einsum('snk,snl->snkl', X, X).reshape(N, -1),
                               np.einsum('snk,sn->snk', X, e).reshape(N, -1), e * e], axis=1)
        floor = np.asarray(noise_variance, dtype=float)
        prev = self._t[-1] if len(self._t) else -math.inf
        # a gap (or a restarted stream) restarts the window: new segments start at the cuts
        dt = np.diff(np.concatenate([[prev], t]))
        cuts = np.flatnonzero((dt > self.max_gap) | (dt <= 0))
        if prev == -math.inf:
            cuts = cuts[cuts > 0]
        bounds = sorted({0, *cuts.tolist(), len(t)})
        for a, b in zip(bounds[:-1], bounds[1:]):
            if a in cuts:
                self.gaps += 1
                self._clear()
            found = self._segment(t[a:b], rows[a:b], n, k, floor)
            if found is not None:
                return found
        return None

    def _segment(self, t: np.ndarray, rows: np.ndarray, n: int, k: int, floor: np.ndarray
                 ) -> Detection | None:
        if len(t) == 0:
            return None
        nb = len(self._t)
        tt = np.concatenate([self._t, t])
        # prefix sums of the rows: S[i] sums the samples before i (kept from call to call)
        base = np.zeros((1, rows.shape[1])) if self._S is None else self._S
        S = np.concatenate([base, base[-1] + np.cumsum(rows, axis=0)])
        idx = np.arange(nb, len(tt))
        first = np.searchsorted(tt, tt[idx] - self.window, side='right')
        W = S[idx + 1] - S[first]
        M = len(idx)
        G = W[:, :n * k * k].reshape(M, n, k, k)
        b = W[:, n * k * k:n * k * (k + 1)].reshape(M, n, k)
        # the window's own noise once the change it tests is taken out: a change explains
        # its residual, the model noise of a fast motion does not
        w0 = np.broadcast_to(1.0 / floor, (M, n))
        d_0, _, _ = _solve(np.einsum('mj,mjkl->mkl', w0, G), np.einsum('mj,mjk->mk', w0, b))
        rss = (W[:, n * k * (k + 1):] - 2.0 * np.einsum('mk,mjk->mj', d_0, b)
               + np.einsum('mk,mjkl,ml->mj', d_0, G, d_0))
        count = (idx + 1 - first)[:, None].astype(float)
        var = np.maximum(rss, 0.0) / count * self.noise_scale
        w = 1.0 / np.maximum(var, floor)
        delta, T, sd0 = _solve(np.einsum('mj,mjkl->mkl', w, G), np.einsum('mj,mjk->mk', w, b))
        d0 = delta[:, 0]
        filled = tt[idx] - tt[0] >= self.min_fill * self.window
        with np.errstate(divide='ignore', invalid='ignore'):
            z = np.where(sd0 > 0, np.abs(d0) / sd0, 0.0)
        held = (filled & (T > self.threshold) & (z > self.min_z)
                & (np.abs(d0) > self.min_change) & (sd0 <= DETERMINED * self.min_change))
        # since when each sample's condition has held without a break (carried across calls)
        carried = np.isfinite(self._since)
        begins = held & ~np.concatenate([[carried], held[:-1]])
        marks = np.where(begins, tt[idx], -np.inf)
        if carried and held[0]:
            marks[0] = self._since
        start = np.maximum.accumulate(marks)
        start = np.where(held, start, np.nan)
        # the latest sub-window alone must show the change too: a glitch (a stalled and
        # bursting stream, a knock) moves the whole window's estimate while it is inside it
        recent = np.searchsorted(tt, tt[idx] - self.recent, side='right')
        Wr = S[idx + 1] - S[recent]
        Gr = Wr[:, :n * k * k].reshape(M, n, k, k)
        br = Wr[:, n * k * k:n * k * (k + 1)].reshape(M, n, k)
        dr, _, sdr = _solve(np.einsum('mj,mjkl->mkl', w, Gr), np.einsum('mj,mjk->mk', w, br))
        alarm = (held & (tt[idx] - start >= self.confirm)
                 & (np.sign(dr[:, 0]) == np.sign(d0)) & (np.abs(dr[:, 0]) > self.min_change)
                 & (np.abs(dr[:, 0]) > 0.5 * self.min_z * sdr))
        self.statistic = float(T[-1])
        d0_all = np.concatenate([self._d0, d0])
        if alarm.any():
            i = int(np.argmax(alarm))
            ti, crossed = float(tt[idx[i]]), float(start[i])
            # The window's estimate ramps up from the onset: it crossed half the threshold
            # halfway to crossing it.
            j = int(np.searchsorted(tt, crossed))
            below = np.flatnonzero(np.abs(d0_all[:j]) <= 0.5 * self.min_change)
            half = float(tt[below[-1] + 1]) if len(below) else crossed - self.window
            onset = min(crossed, max(crossed - self.window, 2.0 * half - crossed))
            self.armed = False
            return Detection(ti, onset, float(T[i]), delta[i].copy())
        self._since = float(start[-1]) if held[-1] else -math.inf
        keep = np.searchsorted(tt, tt[-1] - 2 * self.window, side='right')
        keep = max(0, min(keep, len(tt) - 1))
        self._t, self._S, self._d0 = tt[keep:], S[keep:] - S[keep], d0_all[keep:]
        return None


def _solve(G: np.ndarray, b: np.ndarray, rcond: float = 1e-9
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """delta = G^+ b, T = b' G^+ b and sqrt(G^+_00) for a stack of symmetric PSD G (M, k, k),
    b (M, k), in diagonally scaled coordinates with eigenvalues below rcond * the largest
    dropped (sqrt(G^+_00) inf where the first parameter is in the dropped directions)."""
    d = np.sqrt(np.maximum(np.einsum('mkk->mk', G), 0.0))
    d = np.where(d > 0, d, 1.0)
    Gs = G / (d[:, :, None] * d[:, None, :])
    lam, V = np.linalg.eigh(Gs)
    kept = lam > rcond * lam[:, -1:]
    inv = np.where(kept, 1.0 / np.where(lam > 0, lam, 1.0), 0.0)
    bs = b / d
    proj = np.einsum('mkl,mk->ml', V, bs) * inv
    xs = np.einsum('mkl,ml->mk', V, proj)
    var0 = np.einsum('ml,ml->m', V[:, 0, :] ** 2, inv) / d[:, 0] ** 2
    dropped = np.einsum('ml,ml->m', V[:, 0, :] ** 2, ~kept) > 1e-6
    sd0 = np.where(dropped, np.inf, np.sqrt(var0))
    return xs / d, np.einsum('mk,mk->m', bs, xs), sd0
