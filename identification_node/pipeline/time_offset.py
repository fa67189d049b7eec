"""Stage 6b, the time alignment check: does the torque belong to the motion it is paired with?

Motor currents and joint states often come from two drivers with two clocks; a torque
stamped late or early by a fraction of a second is paired with the wrong motion, and the
estimate is silently wrong. The check fits the base regressor rows Yb(t) of the motion to
the torque shifted in time, tau(t + s), by least squares for every shift s within
``search`` seconds, and takes the shift of the smallest residual, each joint weighted by its
noise floor (the smallest residual its own fit reaches at any shift): the offset by which the
torque is late (s > 0: the torque's stamps are s too late against the joint states; the same
holds for an effort carried in the joint states themselves). Model-free: the parameters are
refitted at each shift, so it does not trust the description's inertials.

The streaming pipeline buffers the rows of the first ``seconds`` of used samples of a stream
(decimated to about RATE Hz) and estimates once, searching at most an eighth of what it
has. An offset beyond ``warn`` seconds whose shift explains the torque better (residual RMS
at zero shift more than SIGNIFICANCE times the best one) is warned of, one beyond ``refuse``
seconds refused (identify exits 2; the node reports an error). The sums over shifts are
correlations, summed in blocks of BLOCK rows (OffsetSums) as the rows arrive, so that no
processing run of a live stream does the whole check at once.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

RATE = 250.0           # Hz the buffered rows are decimated to (lag resolution 4 ms)
SIGNIFICANCE = 1.05    # residual RMS ratio (zero shift / best shift) needed to report
NOISE_FLOOR = 1e-6     # a joint's noise floor at least this fraction of its torque's RMS
BLOCK = 128            # rows correlated at a time (about 0.5 s; 2 ms of CPU for 7 joints)


@dataclass(frozen=True)
class TimeOffset:
    """The estimated offset (s; > 0: the torque is late), the residual RMS of the fit at zero
    shift and at the best one (per joint in units of its noise floor), the seconds of data
    and the +- seconds searched; ``level`` 0 fine, 1 warned of, 2 refused."""
    offset: float
    rms_aligned: float
    rms_best: float
    seconds: float
    search: float
    level: int = 0

    @property
    def ratio(self) -> float:
        return self.rms_aligned / self.rms_best if self.rms_best > 0 else math.inf

    def describe(self) -> str:
        late = 'late' if self.offset > 0 else 'early'
        return (f'the torque is {abs(self.offset):.3f} s {late} against the joint states: the '
                f'motion explains it {self.ratio:.2f}x better (residual RMS) shifted by '
                f'{self.offset:+.3f} s (time_offset.warn/refuse; estimated on '
                f'{self.seconds:.1f} s); check the stamps of the current or effort stream')

    def document(self) -> dict:
        return {'offset_s': self.offset, 'residual_ratio': self.ratio,
                'seconds': self.seconds, 'search_s': self.search,
                'level': ('ok', 'warning', 'refused')[self.level]}


class OffsetSums:
    """The sums of the fit at every shift, gathered over the first rows of an evenly sampled
    run: for ``lags`` L, the centre row i (the run's row L + i) against the torque at rows
    i .. i + 2L. ``A`` (n, b, b): each joint's normal matrix; ``cross`` (n, 2L + 1, b): its
    right-hand side at each shift; ``done``: the centre rows summed."""

    def __init__(self, lags: int, n: int, b: int):
        self.lags, self.done = int(lags), 0
        self.A = np.zeros((n, b, b))
        self.cross = np.zeros((n, 2 * self.lags + 1, b))

    def add(self, rows: np.ndarray, tau: np.ndarray, upto: int) -> None:
        """Sum centre rows ``done`` .. ``upto`` of the run whose rows (M, n, b) and torque
        (M, n) start with ``rows`` and ``tau`` (M >= upto + 2L), BLOCK rows at a time."""
        L, S = self.lags, 2 * self.lags + 1
        while self.done < upto:
            i0, i1 = self.done, min(upto, self.done + BLOCK)
            centre = rows[L + i0:L + i1]                          # (B, n, b)
            torque = np.ascontiguousarray(tau[i0:i1 + 2 * L].T)   # (n, B + 2L)
            shifts = np.arange(S)[:, None] + np.arange(i1 - i0)   # (S, B): tau at i + shift
            for j in range(len(torque)):   # per joint: one matrix product (BLAS)
                self.cross[j] += torque[j][shifts] @ centre[:, j]
            self.A += centre.transpose(1, 2, 0) @ centre.transpose(1, 0, 2)
            self.done = i1


def estimate_offset(rows: np.ndarray, tau: np.ndarray, dt: float, search: float,
                    warn: float = 0.0, refuse: float = math.inf,
                    sums: OffsetSums | None = None) -> TimeOffset | None:
    """The offset of ``tau`` (M, n) against the motion of the base regressor ``rows``
    (M, n, b), sampled evenly every ``dt`` s, searched within +-``search`` s, with its level
    against ``warn`` and ``refuse`` (s; warn 0: level 0); None when there are too few samples
    for that search (fewer than 4 search spans and 2b rows). ``sums``: those of the first
    centre rows, already gathered for this search (continued here)."""
    M, n, b = rows.shape
    L = int(search / dt)
    if L < 1 or M - 2 * L < max(2 * b, 2 * L):
        return None
    Mc = M - 2 * L
    if sums is None or sums.lags != L or sums.done > Mc:
        sums = OffsetSums(L, n, b)
    sums.add(rows, tau, Mc)
    A, cross = sums.A, sums.cross
    sq = np.concatenate([np.zeros((1, n)), np.cumsum(tau ** 2, axis=0)])
    energy = sq[Mc:Mc + 2 * L + 1] - sq[:2 * L + 1]          # (2L+1, n): sum of tau^2
    # Each joint weighted by its noise floor, the best its own fit reaches at any shift (a
    # joint whose torque is mostly noise must not outweigh the others' misfit)
    rms = np.sqrt(np.mean(tau ** 2, axis=0))
    own = [_rss(A[j], cross[j], energy[:, j]) for j in range(n)]
    floor = np.array([r.min() / max(Mc - rank, 1) for r, rank in own])
    sigma = np.sqrt(np.maximum(floor, (NOISE_FLOOR * rms) ** 2))
    weight = np.divide(1.0, sigma ** 2, out=np.zeros(n), where=rms > 0)
    rss, _ = _rss(np.einsum('j,jkl->kl', weight, A), np.einsum('j,jsk->sk', weight, cross),
                  energy @ weight)
    k = int(np.argmin(rss))
    shift = float(k - L)
    if 0 < k < 2 * L:   # parabola through the minimum and its neighbours
        curve = rss[k - 1] - 2 * rss[k] + rss[k + 1]
        if curve > 0:
            shift += 0.5 * float(rss[k - 1] - rss[k + 1]) / curve
    residual = np.sqrt(rss / (Mc * max(int(np.count_nonzero(weight)), 1)))
    found = TimeOffset(float(shift * dt), float(residual[L]), float(residual[k]),
                       float(M * dt), float(L * dt))
    if warn > 0 and found.ratio > SIGNIFICANCE and abs(found.offset) > warn:
        return replace(found, level=2 if abs(found.offset) > refuse else 1)
    return found


def _rss(A: np.ndarray, cross: np.ndarray, energy: np.ndarray) -> tuple[np.ndarray, int]:
    """(residual sum of squares at each shift (S,), rank) of the least squares with normal
    matrix ``A`` (b, b), right-hand sides ``cross`` (S, b) and sums of squares ``energy``."""
    w, V = np.linalg.eigh(A)
    keep = w > max(w.max(initial=0.0), 0.0) * 1e-10
    proj = (cross @ V[:, keep]) / np.sqrt(w[keep])
    return np.maximum(energy - (proj ** 2).sum(axis=1), 0.0), int(keep.sum())


class TimeOffsetCheck:
    """Buffers the rows of a stream's first ``seconds`` of used samples and estimates the
    offset once (``result``); ``finish`` estimates on what is buffered (end of a bag).
    While the buffer is one evenly sampled run, its sums are gathered as the rows arrive
    (OffsetSums). ``warn`` 0: no check."""

    def __init__(self, warn: float, refuse: float, seconds: float, search: float):
        self.warn, self.refuse = float(warn), float(refuse)
        self.seconds, self.search = float(seconds), float(search)
        self.reset()

    def reset(self) -> None:
        self.result: TimeOffset | None = None
        self.restart()

    def restart(self) -> None:
        """A new stream: what is buffered no longer continues (a result stays)."""
        self._t = np.empty(0)
        self._rows = np.empty((0, 0, 0))
        self._tau = np.empty((0, 0))
        self._count, self._even = 0, True
        self._step, self._dt, self._next = 0, 0.0, -math.inf
        self._sums: OffsetSums | None = None

    @property
    def active(self) -> bool:
        return self.warn > 0 and self.result is None

    @property
    def _spacing(self) -> float:
        """s between the buffered (decimated) rows."""
        return self._step * self._dt

    def add(self, t: np.ndarray, rows: np.ndarray, tau: np.ndarray,
            terms: np.ndarray | None = None) -> None:
        """Used samples at t (M,) s: base regressor rows (M, n, b) and torque (M, n);
        ``terms`` (M, n, k): per-joint terms fitted beside the rows, each in its own joint's
        equation (1, sign(qd), qd: an offset or friction the model lacks would otherwise be
        partly fitted by a shift of the torque)."""
        if not self.active or not len(t):
            return
        if not self._step:   # decimation step from the stream's own rate
            if len(t) < 2:
                return
            dt = float(np.median(np.diff(t)))
            if not dt > 0:
                return
            self._step, self._dt = max(1, int(round(1.0 / (RATE * dt)))), dt
        pick = np.flatnonzero(t >= self._next - 0.5 * self._dt)[::self._step]
        if len(pick):   # every step-th sample, continued across batches
            self._next = t[pick[-1]] + self._spacing
            rows = rows[pick]
            if terms is not None:
                M, n, k = len(pick), *terms.shape[1:]
                own = terms[pick][:, :, None, :] * np.eye(n)[None, :, :, None]  # (M, n, n, k)
                rows = np.concatenate([rows, own.reshape(M, n, n * k)], axis=2)
            self._append(t[pick], rows, tau[pick])
            if self._t[self._count - 1] - self._t[0] >= self.seconds:
                self.finish()
            else:
                self._gather()

    def finish(self) -> None:
        """Estimate from what is buffered: its longest evenly sampled run, searched within
        +-search s or an eighth of the run (the fit keeps 3/4 of it)."""
        if not self.active or not self._count:
            return
        t, dt = self._t[:self._count], self._spacing
        cuts = np.r_[0, np.flatnonzero(np.diff(t) > 1.5 * dt) + 1, len(t)]
        k = int(np.argmax(np.diff(cuts)))
        run = slice(cuts[k], cuts[k + 1])
        span = (cuts[k + 1] - cuts[k]) * dt
        self.result = estimate_offset(self._rows[run], self._tau[run], dt,
                                      min(self.search, span / 8), self.warn, self.refuse,
                                      self._sums if run.start == 0 else None)
        self.restart()

    def _append(self, t: np.ndarray, rows: np.ndarray, tau: np.ndarray) -> None:
        """Decimated rows onto the buffer (grown by doubling)."""
        dt = self._spacing
        if self._count and rows.shape[1:] != self._rows.shape[1:]:
            self._count, self._sums = 0, None   # other columns: the buffer starts anew
        count, end = self._count, self._count + len(t)
        if end > len(self._t) or not count:
            # room for ``seconds`` and the rows of the batch that completes them
            size = max(end, 2 * len(self._t), int(self.seconds / dt) + 64)
            grown = [np.empty((size, *a.shape[1:])) for a in (t, rows, tau)]
            if count:
                for new, old in zip(grown, (self._t, self._rows, self._tau)):
                    new[:count] = old[:count]
            self._t, self._rows, self._tau = grown
        self._t[count:end], self._rows[count:end], self._tau[count:end] = t, rows, tau
        if count == 0:
            self._even = True
        joined = self._t[max(count - 1, 0):end]
        if len(joined) > 1 and np.diff(joined).max() > 1.5 * dt:
            self._even, self._sums = False, None   # finish fits the longest run anew
        self._count = end

    def _gather(self) -> None:
        """Sum the complete blocks of centre rows whose torque is buffered up to the largest
        shift, for the search finish will make on a full buffer (``seconds`` of one evenly
        sampled run; none when that search depends on how long the run will be)."""
        dt = self._spacing
        lags = int(self.search / dt)
        if not self._even or lags < 1 or self.search > self.seconds / 8:
            return
        ready = self._count - 2 * lags          # centre rows with all their shifts
        if self._sums is None:
            if ready < BLOCK:
                return
            self._sums = OffsetSums(lags, *self._rows.shape[1:])
        upto = self._sums.done + (ready - self._sums.done) // BLOCK * BLOCK
        if upto > self._sums.done:
            self._sums.add(self._rows, self._tau, upto)
