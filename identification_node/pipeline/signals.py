"""Signal processing for identification data: smoothing, derivatives, filtering, averaging.

:class:`FixedLagSmoother` is the online path: a streaming local polynomial (Savitzky-Golay
style) least-squares fit over 2L+1 samples, evaluated at the window centre. It uses the actual
time stamps, so jitter and irregular sampling need no resampling. The centre of a window is known
only once its last sample arrived: outputs lag the newest input by L samples (L / rate seconds);
the estimator must pair them with the other signals at the returned centre stamps. Windows
whose stamps are uniform (to 1e-9 of the step and the stamps' float rounding) take the fit's
fixed weights (Savitzky-Golay), all of them in one matrix product.

Frequency response (uniform sampling): the fit is a linear FIR filter, symmetric about the
centre, so it has zero phase relative to the centre stamp (pure delay of L samples), unit gain
at DC and, for the derivatives, the ideal gains j w and -w^2 at low frequency. It passes low
frequencies nearly unchanged and attenuates above roughly (order + 1) / (3.2 L - 4.6) times the
Nyquist frequency (Schafer 2011, good for L >~ 10); :meth:`FixedLagSmoother.frequency_response`
gives the exact gains.

Its bandwidth is specified in Hz: :func:`smoother_cutoff` is the exact -3 dB frequency of the
value output of a window at a sampling rate, :func:`half_window_for_cutoff` the half window
whose cut-off is nearest a given one (at least MIN_HALF_WINDOW samples, so the cubic fit stays
well-posed at low rates). Long windows (more than _FFT_TAPS samples) of uniform stamps are
applied by FFT convolution (the same weights, O(log K) per sample instead of O(K)); those of
stamps off their grid are fitted from sliding sums (O(1) per sample).

The rest are offline helpers on whole arrays with samples along axis 0.
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
import scipy.fft as sp_fft
import scipy.signal as sps

from identification_node.errors import IdentificationError
from identification_node.model.coulomb import coulomb_sign

_BLOCK = 4096   # windows per batched solve: bounds memory for long offline calls
# A window counts as uniformly sampled when its stamp steps differ by at most this fraction of
# the step (its centred, scaled stamps then differ from k / L by < 2e-9, far below the
# nanosecond quantisation of stamps: 1e-9 s / 1 ms = 1e-6) plus the rounding of the stamps as
# floats (which the general fit sees as well).
_UNIFORM_TOL = 1e-9
_FEW = 64       # up to this many windows a batch is not split into uniform and jittered runs
_FFT_TAPS = 129  # longer windows: by FFT convolution (uniform stamps) or sliding sums
_GATHER = 1 << 21   # floats gathered at most per block of jittered windows (memory bound)
MIN_HALF_WINDOW = 4   # samples: the shortest half window a cut-off maps to (9-sample fit)


def _as_samples(x: np.ndarray, name: str, finite: bool = True) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim not in (1, 2) or x.shape[0] == 0:
        raise IdentificationError(f'{name} has shape {x.shape}; expected (N,) or (N, c)')
    if finite and not np.isfinite(x).all():
        k = int(np.argwhere(~np.isfinite(x))[0][0])
        raise IdentificationError(f'{name} contains NaN or inf (first at sample {k})')
    return x


def _stamps(t: np.ndarray, n: int) -> np.ndarray:
    t = np.asarray(t, dtype=float).reshape(-1)
    if t.shape[0] != n:
        raise IdentificationError(f'{t.shape[0]} time stamps for {n} samples')
    if not np.isfinite(t).all():
        raise IdentificationError('time stamps contain NaN or inf')
    d = np.diff(t)
    if (d <= 0).any():
        k = int(np.argmax(d <= 0)) + 1
        raise IdentificationError(
            f'time stamps must be strictly increasing (sample {k}: {t[k - 1]!r} -> {t[k]!r})')
    return t


def smoothing_noise_gain(half_window: int, order: int) -> float:
    """Sum of squared weights of the centre value of a local polynomial fit of ``order`` over
    2 * half_window + 1 uniform samples: white noise of variance s^2 leaves with variance
    gain * s^2, while slow signals (and the low-frequency noise an estimate averages) pass with
    gain 1. Least squares on smoothed data thus reports a residual variance ``gain`` times too
    small for the estimate's covariance."""
    u = np.arange(-half_window, half_window + 1, dtype=float)
    V = np.vander(u, order + 1, increasing=True)
    return float(np.linalg.inv(V.T @ V)[0, 0])


def value_weights(half_window: int, order: int) -> np.ndarray:
    """(2L + 1,): weights of the centre value of a local polynomial fit of ``order`` over
    2 * half_window + 1 uniform samples (FixedLagSmoother's value on a uniform window)."""
    u = np.arange(-half_window, half_window + 1, dtype=float)
    V = np.vander(u, order + 1, increasing=True)
    return np.linalg.solve(V.T @ V, V.T)[0]


@functools.lru_cache(maxsize=64)
def _cumulative_value_weights(half_window: int, order: int) -> np.ndarray:
    """(L + 1,) read-only: cum[k] the sum of the value weights of i < k - L (k <= L), the
    weights made exactly symmetric; once per window (every run asks)."""
    w = value_weights(half_window, order)
    w = 0.5 * (w + w[::-1])   # symmetric in exact arithmetic: so in rounding too
    cum = np.concatenate([[0.0], np.cumsum(w[:half_window])])
    cum.flags.writeable = False
    return cum


def smoothed_sign(v: np.ndarray, a: np.ndarray, half_window: int, order: int,
                  period: float) -> np.ndarray:
    """What the smoother makes of sign(v(t)) at the window centre, for a velocity crossing
    zero linearly within the window: sum_i w_i sign(v + a i period) over i = -L..L (value
    weights w, value_weights), from the smoothed velocity v and acceleration a (same shape,
    rad/s and rad/s^2) and the sample period (s). Equal to sign(v) where no reversal lies in
    the window, 0 at rest (coulomb_sign); a Coulomb column of it is what the smoothed torque
    holds of sign friction."""
    L = int(half_window)
    cum = _cumulative_value_weights(L, int(order))
    with np.errstate(divide='ignore', invalid='ignore'):
        # |x|, x the zero crossing in samples from the centre; none within reach: L + 1
        x = np.fmin(np.abs(v / (a * period)), L + 1.0)
    # the samples of the other sign, i < x for x < 0 and i > x for x >= 0: by the weights'
    # symmetry, those of i < -|x| either way
    other = cum[np.maximum(L - np.floor(x), 0).astype(np.int64)]
    return coulomb_sign(v) * (1.0 - 2.0 * other)


@functools.lru_cache(maxsize=4096)
def _relative_cutoff(half_window: int, order: int) -> float:
    """-3 dB frequency of the value output of a uniform window, in cycles per sample."""
    L = int(half_window)
    k = np.arange(-L, L + 1) / L
    V = np.vander(k, order + 1, increasing=True)
    w = np.linalg.solve(V.T @ V, V.T)[0]                     # value weights (symmetric)
    u = np.arange(0, L + 1)

    def gain(f: float) -> float:
        return float(w[L:] @ np.cos(2 * np.pi * f * u) * 2 - w[L])

    target = 1 / math.sqrt(2)
    grid = np.linspace(0, 0.5, 16 * (L + 1) + 1)[1:]
    g = 2 * np.cos(2 * np.pi * np.outer(grid, u)) @ w[L:] - w[L]
    below = np.flatnonzero(g < target)
    if below.size == 0:
        return 0.5
    hi = float(grid[below[0]])
    lo = float(grid[below[0] - 1]) if below[0] > 0 else 0.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gain(mid) >= target else (lo, mid)
    return 0.5 * (lo + hi)


def smoother_cutoff(half_window: int, order: int, rate: float) -> float:
    """The -3 dB frequency (Hz) of the smoother's value output (local polynomial fit of
    ``order`` over 2 half_window + 1 samples) at a uniform sampling ``rate`` (Hz)."""
    if not rate > 0:
        raise IdentificationError(f'rate must be > 0 Hz, got {rate!r}')
    return _relative_cutoff(int(half_window), int(order)) * float(rate)


def half_window_for_cutoff(cutoff: float, rate: float, order: int,
                           minimum: int = MIN_HALF_WINDOW) -> int:
    """The half window (samples, >= ``minimum`` and >= order) whose -3 dB cut-off at
    ``rate`` is nearest ``cutoff`` (both Hz; nearest in log frequency)."""
    if not (math.isfinite(cutoff) and cutoff > 0 and math.isfinite(rate) and rate > 0):
        raise IdentificationError(f'need cutoff > 0 and rate > 0 Hz, got {cutoff!r}, {rate!r}')
    low = max(int(minimum), int(order), 1)
    # Schafer (2011): cut-off ~ (order + 1) / (3.2 L - 4.6) times Nyquist; then, the cut-off
    # being nearly proportional to 1 / L, a few corrections and a look at the neighbours
    guess = ((order + 1) * rate / (2.0 * cutoff) + 4.6) / 3.2
    if not guess < 1e6:
        raise IdentificationError(f'cutoff {cutoff} Hz is too low for rate {rate} Hz')
    L = max(low, int(round(guess)))
    for _ in range(4):
        L = max(low, int(round(L * smoother_cutoff(L, order, rate) / cutoff)))
    return min(range(max(low, L - 2), L + 3),
               key=lambda h: abs(math.log(smoother_cutoff(h, order, rate) / cutoff)))


class FixedLagSmoother:
    """Streaming local polynomial fit: value, first and second time derivative of c channels.

    half_window L (window 2L+1 samples), polynomial ``order`` (2 or 3 usual, up to 4, at most
    2L), ``max_gap`` (s): a larger stamp gap restarts the window instead of fitting across it.
    """

    def __init__(self, num_channels: int, half_window: int = 10, order: int = 3,
                 max_gap: float = np.inf):
        for name, v, lo in (('num_channels', num_channels, 1), ('half_window', half_window, 1),
                            ('order', order, 2)):
            if isinstance(v, bool) or int(v) != v or v < lo:
                raise IdentificationError(f'{name} must be an integer >= {lo}, got {v!r}')
        if order > 4 or order > 2 * half_window:
            raise IdentificationError(
                f'order must be <= 4 and <= 2 * half_window ({2 * half_window}), got {order}')
        if not max_gap > 0:
            raise IdentificationError(f'max_gap must be > 0 s, got {max_gap!r}')
        self.num_channels = int(num_channels)
        self.half_window = int(half_window)
        self.order = int(order)
        self.max_gap = float(max_gap)
        p = np.arange(self.order + 1)
        self._hankel = p[:, None] + p[None, :]
        self._offsets = np.arange(2 * self.half_window + 1)
        # Value, first and second derivative weights (in scaled time) of a uniform window.
        k = np.arange(-self.half_window, self.half_window + 1) / self.half_window
        gram, powers = self._normal(k[None, :])
        self._uniform_weights = np.linalg.solve(gram, powers)[0, :3]             # (3, K)
        self._spectrum: tuple[int, np.ndarray] | None = None   # (FFT length, _spectra)
        m = np.arange(2 * self.order + 1)    # _fit_long's binomial coefficients C(m, l)
        self._binomial = np.array([[math.comb(i, j) for j in m] for i in m], dtype=float)
        self._binomial_powers = np.clip(m[:, None] - m[None, :], 0, None)    # m - l (>= 0)
        self.reset()

    @property
    def delay_samples(self) -> int:
        """Output lag behind the newest input, in samples (= half_window)."""
        return self.half_window

    def delay(self, rate: float) -> float:
        """Output lag in seconds at a sampling rate (Hz)."""
        if not rate > 0:
            raise IdentificationError(f'rate must be > 0 Hz, got {rate!r}')
        return self.half_window / float(rate)

    @property
    def noise_gain(self) -> float:
        """Variance of smoothed over raw white noise for the value output on a uniform grid
        (the sum of the squared filter weights); see :func:`smoothing_noise_gain`."""
        return smoothing_noise_gain(self.half_window, self.order)

    def reset(self) -> None:
        """Forget the buffered samples (next outputs come 2L samples after new data starts)."""
        self._t = np.zeros(0)
        self._x = np.zeros((0, self.num_channels))

    def _empty(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        z = np.zeros((0, self.num_channels))
        return np.zeros(0), z, z.copy(), z.copy()

    def push(self, t: np.ndarray, x: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Add samples t (N,) s, x (N, c); return (t_c (M,), x (M, c), xd (M, c), xdd (M, c))
        for every window centre completed by them (M may be 0)."""
        x = np.asarray(x, dtype=float)
        if x.ndim == 1 and np.ndim(t) == 0:
            x = x[None]
        if x.ndim != 2 or x.shape[1] != self.num_channels:
            raise IdentificationError(
                f'samples have shape {x.shape}; expected (N, {self.num_channels})')
        t = _stamps(t, x.shape[0])
        if x.shape[0] == 0:
            return self._empty()
        if not np.isfinite(x).all():
            k = int(np.argwhere(~np.isfinite(x))[0][0])
            raise IdentificationError(f'samples contain NaN or inf (first at sample {k})')
        if self._t.size and t[0] <= self._t[-1]:
            raise IdentificationError(
                f'time stamp {t[0]!r} not after the previous one {self._t[-1]!r} '
                '(call reset() when time restarts)')
        return self.push_checked(t, x)

    def push_checked(self, t: np.ndarray, x: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``push`` without its checks, for callers that validated already: t (N,) float
        strictly increasing past the stamps pushed before, x (N, c) finite floats, N >= 1."""
        T = np.concatenate([self._t, t])
        X = np.concatenate([self._x, x])
        L, K = self.half_window, 2 * self.half_window + 1
        d = T[1:] - T[:-1]
        starts = np.arange(max(T.size - K + 1, 0))
        last = 0                                             # first sample of the last segment
        if d.size and d.max() > self.max_gap:
            seg = np.concatenate([[0], np.cumsum(d > self.max_gap)])  # segment id per sample
            last = int(np.searchsorted(seg, seg[-1]))
            starts = starts[seg[starts] == seg[starts + K - 1]]  # windows not spanning a gap
        self._t, self._x = T[max(last, T.size - 2 * L):], X[max(last, T.size - 2 * L):]
        if starts.size == 0:
            return self._empty()
        out = []
        block = self._block
        for run, uniform in self._runs(T, d, starts):
            if uniform and self._long:
                out.append(self._fit_fft(T, X, int(run[0]), run.size))
                continue
            for i in range(0, run.size, block):
                out.append(self._fit_uniform(T, X, int(run[i]), min(block, run.size - i))
                           if uniform else self._fit(T, X, run[i:i + block]))
        if len(out) == 1:
            return out[0]
        t_c, x_c, xd_c, xdd_c = (np.concatenate(parts) for parts in zip(*out))
        return t_c, x_c, xd_c, xdd_c

    @property
    def _long(self) -> bool:
        """Whether the window is longer than _FFT_TAPS samples (fitted by FFT or from
        sliding sums)."""
        return 2 * self.half_window + 1 > _FFT_TAPS

    @property
    def _block(self) -> int:
        """Windows per batched solve: _BLOCK, fewer for long windows (memory)."""
        return max(1, min(_BLOCK, _GATHER // ((2 * self.half_window + 1) * self.num_channels)))

    def fit_at(self, t: np.ndarray, x: np.ndarray, centres: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fit (value, first and second derivative, each (M, c)) of the windows centred
        at the sample indices ``centres`` (M,) of t (N,) s, x (N, c), whatever the stamps'
        spacing; every centre needs half_window samples on either side. Stateless (the
        streaming buffer is not touched): for choosing a window on recorded samples."""
        x = _as_samples(x, 'x')
        t = _stamps(t, x.shape[0])
        x = x.reshape(x.shape[0], -1)
        starts = np.asarray(centres, dtype=np.int64) - self.half_window
        if starts.size and (starts.min() < 0 or starts.max() + 2 * self.half_window >= t.size):
            raise IdentificationError('a window centre lies within half a window of the ends')
        d = np.diff(t)
        rounding = 8 * np.finfo(float).eps * max(abs(t[0]), abs(t[-1]))
        uniform = d.size > 0 and d.max() - d.min() <= _UNIFORM_TOL * d.min() + rounding
        if uniform and self._long and starts.size:
            lo, span = int(starts.min()), int(starts.max() - starts.min()) + 1
            if starts.size * (2 * self.half_window + 1) > 8 * (span + 2 * self.half_window):
                # many long windows: all those of their span by FFT cost less than gathering
                _, value, first, second = self._fit_fft(t, x, lo, span)
                return value[starts - lo], first[starts - lo], second[starts - lo]
        parts = [self._fit_at_uniform(t, x, starts[i:i + self._block]) if uniform
                 else self._fit(t, x, starts[i:i + self._block])[1:]
                 for i in range(0, starts.size, self._block)] or [
                     (np.zeros((0, x.shape[1])),) * 3]
        value, first, second = (np.concatenate(p) for p in zip(*parts))
        return value, first, second

    def _fit_at_uniform(self, t: np.ndarray, x: np.ndarray, starts: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """fit_at's windows starting at ``starts`` of uniform stamps: the fixed weights."""
        idx = starts[:, None] + self._offsets
        coef = np.tensordot(self._uniform_weights, x[idx], axes=([1], [1]))   # (3, B, c)
        h = (0.5 * (t[idx[:, -1]] - t[idx[:, 0]]))[:, None]
        return coef[0], coef[1] / h, 2.0 * coef[2] / (h * h)

    def _runs(self, T: np.ndarray, d: np.ndarray, starts: np.ndarray
              ) -> list[tuple[np.ndarray, bool]]:
        """``starts`` split into runs of consecutive windows that all are, or all are not,
        uniformly sampled (within _UNIFORM_TOL); d = diff(T). A few windows with jittered
        stamps among them are all fitted in general (the fixed weights only save time)."""
        K = 2 * self.half_window + 1
        rounding = 8 * np.finfo(float).eps * max(abs(T[0]), abs(T[-1]))
        if d.max() - d.min() <= _UNIFORM_TOL * d.min() + rounding:   # usual: all uniform
            if starts[-1] - starts[0] == starts.size - 1:
                return [(starts, True)]
            uniform = np.ones(starts.size, dtype=bool)
        elif starts.size <= _FEW:
            return [(starts, False)]
        else:
            steps = np.lib.stride_tricks.sliding_window_view(d, K - 1)
            uniform = np.empty(starts.size, dtype=bool)
            for i in range(0, starts.size, _BLOCK):
                win = steps[starts[i:i + _BLOCK]]
                lo = win.min(axis=1)
                uniform[i:i + _BLOCK] = win.max(axis=1) - lo <= _UNIFORM_TOL * lo + rounding
        cuts = np.flatnonzero((np.diff(starts) != 1) | (uniform[1:] != uniform[:-1])) + 1
        return [(run, bool(uniform[run_start]))
                for run, run_start in zip(np.split(starts, cuts), np.r_[0, cuts])]

    def _fit_uniform(self, T: np.ndarray, X: np.ndarray, first: int, count: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``_fit`` of the ``count`` uniformly sampled windows starting at sample ``first``:
        fixed Savitzky-Golay weights, all windows in one BLAS product with the (window offset,
        sample x channel) Hankel matrix of X."""
        L, K, c = self.half_window, 2 * self.half_window + 1, X.shape[1]
        X = np.ascontiguousarray(X[first:first + count + K - 1])
        view = np.ndarray((K, count * c), X.dtype, X, 0, X.strides)   # row j: X[j:j + count]
        # a copy: BLAS takes no overlapping rows, and numpy's own loop is slower than copying
        coef = (self._uniform_weights @ view.copy()).reshape(3, count, c)
        h = 0.5 * (T[first + K - 1:first + K - 1 + count] - T[first:first + count])
        return (T[first + L:first + L + count], coef[0], coef[1] / h[:, None],
                2.0 * coef[2] / (h * h)[:, None])

    def _fit_fft(self, T: np.ndarray, X: np.ndarray, first: int, count: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``_fit_uniform`` by FFT convolution (overlap-save, blocks of up to _BLOCK windows):
        each block's samples transformed once for the three weights' spectra."""
        L, K = self.half_window, 2 * self.half_window + 1
        step = min(count, max(_BLOCK, K))
        n = sp_fft.next_fast_len(step + K - 1, real=True)
        spectra = self._spectra(n)                                        # (3, n // 2 + 1)
        coef = np.empty((3, count, X.shape[1]))
        for a in range(0, count, step):
            b = min(count, a + step)
            seg = sp_fft.rfft(X[first + a:first + b + K - 1], n, axis=0)
            # circular correlation: its first b - a values are the full windows' (n >= b-a+K-1)
            coef[:, a:b] = sp_fft.irfft(seg * spectra[:, :, None], n, axis=1)[:, :b - a]
        h = (0.5 * (T[first + K - 1:first + K - 1 + count] - T[first:first + count]))[:, None]
        return (T[first + L:first + L + count], coef[0], coef[1] / h, 2.0 * coef[2] / (h * h))

    def _spectra(self, n: int) -> np.ndarray:
        """Conjugate spectra (3, n // 2 + 1) of the uniform weights at FFT length n (cached):
        multiplying a block's spectrum by them correlates it with the weights."""
        if self._spectrum is None or self._spectrum[0] != n:
            self._spectrum = n, np.conj(sp_fft.rfft(self._uniform_weights, n, axis=1))
        return self._spectrum[1]

    def _normal(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gram matrices (B, p, p) and Vandermonde rows (B, p, K) of the least-squares fit of
        a polynomial in u (centred, scaled time) over each window: gram c = powers @ v."""
        powers = np.empty((u.shape[0], 2 * self.order + 1, u.shape[1]))
        powers[:, 0] = 1.0
        powers[:, 1:] = u[:, None, :]
        np.cumprod(powers, axis=1, out=powers)     # products, not float pow: 10x faster
        gram = powers.sum(axis=2)[:, self._hankel]
        return gram, powers[:, :self.order + 1]

    def _fit(self, T: np.ndarray, X: np.ndarray, starts: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The least-squares fit of the windows starting at ``starts`` (increasing), whatever
        the stamps' spacing: (centre stamps, value, first and second derivative)."""
        if self._long and starts.size:
            return self._fit_long(T, X, starts)
        L = self.half_window
        idx = starts[:, None] + self._offsets
        tw = T[idx]
        tc = tw[:, L]
        h = 0.5 * (tw[:, -1] - tw[:, 0])
        u = (tw - tc[:, None]) / h[:, None]
        gram, powers = self._normal(u)
        coef = np.linalg.solve(gram, powers @ X[idx])                           # (B, p, c)
        return (tc, coef[:, 0], coef[:, 1] / h[:, None],
                2.0 * coef[:, 2] / (h * h)[:, None])

    def _fit_long(self, T: np.ndarray, X: np.ndarray, starts: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``_fit`` of long windows from sliding sums, O(order) per window and channel instead
        of O(K): per group of windows starting within half a window of each other, the power
        sums of v = (t - r) / H (r, H: the group's samples' centre and half span) and their
        products with x, summed over each window as differences of cumulative sums, then
        moved to each window's u = (t - t_c) / h by the binomial theorem (|v|, |u| <= 1
        within a group: little cancellation)."""
        L, K, p = self.half_window, 2 * self.half_window + 1, self.order
        out = []
        for group in np.split(starts, np.flatnonzero(np.diff(starts // L)) + 1):
            lo, hi = int(group[0]), int(group[-1]) + K
            t, x = T[lo:hi], X[lo:hi] - X[lo]
            r, H = 0.5 * (t[0] + t[-1]), 0.5 * (t[-1] - t[0])
            v = np.empty((2 * p + 1, hi - lo))
            v[0] = 1.0
            v[1:] = (t - r) / H
            np.cumprod(v, axis=0, out=v)
            cum = np.zeros((2 * p + 1, hi - lo + 1))
            np.cumsum(v, axis=1, out=cum[:, 1:])
            cum_x = np.zeros((p + 1, hi - lo + 1, x.shape[1]))
            np.cumsum(v[:p + 1, :, None] * x, axis=1, out=cum_x[:, 1:])
            a = group - lo
            sums = cum[:, a + K] - cum[:, a]                                 # (2p+1, B)
            sums_x = cum_x[:, a + K] - cum_x[:, a]                           # (p+1, B, c)
            tc, h = t[a + L], 0.5 * (t[a + K - 1] - t[a])
            # u^m = (H / h)^m sum_l C(m, l) v^l (-(tc - r) / H)^(m - l)
            shift = (-(tc - r) / H)[:, None, None] ** self._binomial_powers * self._binomial
            shift *= ((H / h)[:, None] ** np.arange(2 * p + 1))[:, :, None]   # (B, m, l)
            gram = np.einsum('bml,lb->bm', shift, sums)[:, self._hankel]
            moments = np.einsum('bml,lbc->bmc', shift[:, :p + 1, :p + 1], sums_x)
            coef = np.linalg.solve(gram, moments)
            out.append((tc, coef[:, 0] + X[lo], coef[:, 1] / h[:, None],
                        2.0 * coef[:, 2] / (h * h)[:, None]))
        tc, value, first, second = (np.concatenate(part) for part in zip(*out))
        return tc, value, first, second

    def frequency_response(self, freq: np.ndarray, rate: float
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Complex gains (value, first, second derivative) at frequencies freq (Hz) for uniform
        sampling at ``rate``, relative to the window centre (the real output is additionally
        delayed by L samples). Ideal: 1, j w, -w^2."""
        if not rate > 0:
            raise IdentificationError(f'rate must be > 0 Hz, got {rate!r}')
        L = self.half_window
        k = np.arange(-L, L + 1)
        g = self._uniform_weights * (np.array([1.0, rate / L, 2.0 * (rate / L) ** 2]))[:, None]
        e = np.exp(2j * np.pi * np.asarray(freq, dtype=float)[..., None] * k / rate)
        return e @ g[0], e @ g[1], e @ g[2]


# -- offline helpers ------------------------------------------------------------------------------
def zero_phase_lowpass(x: np.ndarray, rate: float, cutoff: float, order: int = 4) -> np.ndarray:
    """Butterworth low-pass run forwards and backwards along axis 0 (no delay, squared gain).

    x (N,) or (N, c) uniformly sampled at ``rate`` Hz; ``cutoff`` in Hz below rate / 2.
    """
    x = _as_samples(x, 'x')
    if not rate > 0 or not 0 < cutoff < 0.5 * rate:
        raise IdentificationError(
            f'cutoff must be in (0, rate/2) with rate > 0; got cutoff {cutoff!r} Hz, '
            f'rate {rate!r} Hz')
    if isinstance(order, bool) or int(order) != order or order < 1:
        raise IdentificationError(f'filter order must be an integer >= 1, got {order!r}')
    sos = sps.butter(int(order), cutoff, fs=rate, output='sos')
    try:
        return sps.sosfiltfilt(sos, x, axis=0)
    except ValueError as exc:
        raise IdentificationError(
            f'{x.shape[0]} samples are too few for a zero-phase filter of order {order}: {exc}'
        ) from None


def decimate(x: np.ndarray, factor: int, order: int = 8) -> np.ndarray:
    """Every ``factor``-th sample of x (N,) or (N, c) after a zero-phase Butterworth low-pass at
    0.8 times the new Nyquist frequency (anti-aliasing). Slice the stamps with t[::factor]."""
    if isinstance(factor, bool) or int(factor) != factor or factor < 1:
        raise IdentificationError(f'decimation factor must be an integer >= 1, got {factor!r}')
    x = _as_samples(x, 'x')
    if factor == 1:
        return x.copy()
    return zero_phase_lowpass(x, 1.0, 0.4 / factor, order)[::int(factor)]


def central_derivatives(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and second time derivatives of x (N,) or (N, c) at stamps t (N,), by 3-point
    formulas valid for irregular stamps (exact for quadratics; second derivative at the two ends
    copied from their neighbours). Noisy: smooth first."""
    x = _as_samples(x, 'x')
    t = _stamps(t, x.shape[0])
    if t.size < 3:
        raise IdentificationError(f'need at least 3 samples for derivatives, got {t.size}')
    xd = np.gradient(x, t, axis=0, edge_order=2)
    h = np.diff(t).reshape((-1,) + (1,) * (x.ndim - 1))
    slope = np.diff(x, axis=0) / h
    xdd = np.empty_like(x)
    xdd[1:-1] = 2.0 * (slope[1:] - slope[:-1]) / (h[1:] + h[:-1])
    xdd[0], xdd[-1] = xdd[1], xdd[-2]
    return xd, xdd


class PeriodAverage(NamedTuple):
    """Result of :func:`period_average`. Arrays have one row per phase bin."""

    t: np.ndarray        # (n,) phase times from the first sample, s
    mean: np.ndarray     # (n,) or (n, c): average over the periods
    var: np.ndarray      # (n,) or (n, c): per-sample noise variance (ddof=1); of the mean: /counts
    counts: np.ndarray   # (n,) samples averaged per bin
    periods: int         # whole periods used


def period_average(t: np.ndarray, x: np.ndarray, period: float) -> PeriodAverage:
    """Average a periodic signal over its whole periods (Radkhah et al., section II.C).

    Samples are put in n = round(period / median step) phase bins by their stamp, so jitter and
    dropped samples are fine; samples after the last whole period are ignored. With an integer
    number of samples per period each bin holds one sample per period; otherwise a bin spans up
    to one step of phase, which adds (slope * step)^2 / 12 to the variance.
    """
    x = _as_samples(x, 'x')
    t = _stamps(t, x.shape[0])
    if not period > 0 or not np.isfinite(period):
        raise IdentificationError(f'period must be a positive number of seconds, got {period!r}')
    if t.size < 4:
        raise IdentificationError(f'need at least two periods of samples, got {t.size} samples')
    n = int(round(period / float(np.median(np.diff(t)))))
    if n < 2:
        raise IdentificationError(
            f'period {period} s is shorter than two sampling steps')
    b = np.rint((t - t[0]) * (n / period)).astype(np.int64)    # global phase-bin index
    periods = int((b[-1] + 1) // n)
    if periods < 2:
        raise IdentificationError(
            f'data span {t[-1] - t[0]:.6g} s holds {periods} whole period(s) of {period} s; '
            'need at least 2 to estimate the noise')
    keep = b < periods * n
    k, xs = b[keep] % n, x[keep]
    counts = np.bincount(k, minlength=n)
    if counts.min() < 2:
        raise IdentificationError(
            f'phase bin {int(np.argmin(counts))} of {n} holds fewer than 2 samples '
            '(too many dropped samples?)')
    shape = (n,) + x.shape[1:]
    cnt = counts.reshape((n,) + (1,) * (x.ndim - 1))
    mean = np.zeros(shape)
    np.add.at(mean, k, xs)
    mean /= cnt
    var = np.zeros(shape)
    np.add.at(var, k, (xs - mean[k]) ** 2)
    var /= cnt - 1
    return PeriodAverage(np.arange(n) * (period / n), mean, var, counts, periods)
