"""Fixed-lag smoother, zero-phase filtering, decimation, derivatives and period averaging."""
import numpy as np
import pytest

from identification_node.errors import IdentificationError
from identification_node.pipeline import signals
from identification_node.pipeline.signals import (FixedLagSmoother, central_derivatives, decimate,
                                                  half_window_for_cutoff, period_average,
                                                  smoother_cutoff, zero_phase_lowpass)


def _irregular_stamps(rng, n, dt=0.01, jitter=0.4, t0=3.0):
    return t0 + np.cumsum(dt * rng.uniform(1 - jitter, 1 + jitter, n))


def _poly(t, coeffs):
    """Values, first and second derivatives of polynomials (columns) at t."""
    ps = [np.polynomial.Polynomial(c) for c in coeffs]
    return (np.stack([p(t) for p in ps], 1), np.stack([p.deriv()(t) for p in ps], 1),
            np.stack([p.deriv(2)(t) for p in ps], 1))


@pytest.mark.parametrize('order,L', [(2, 3), (3, 5), (3, 1 + 1), (4, 6)])
def test_exact_on_polynomials_with_irregular_stamps(order, L):
    rng = np.random.default_rng(order * 10 + L)
    t = _irregular_stamps(rng, 200)
    coeffs = rng.normal(size=(4, order + 1))
    x, xd, xdd = _poly(t - 4.0, coeffs)
    sm = FixedLagSmoother(4, half_window=L, order=order)
    tc, v, d, dd = sm.push(t, x)
    assert tc.size == 200 - 2 * L
    np.testing.assert_array_equal(tc, t[L:-L])
    np.testing.assert_allclose(v, x[L:-L], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(d, xd[L:-L], rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(dd, xdd[L:-L], rtol=1e-5, atol=1e-5)


def test_not_exact_above_its_order():
    # A quadratic fit cannot follow a quartic: the check above is not vacuous.
    t = np.linspace(0, 1, 101)
    x = (t ** 4)[:, None]
    _, v, _, dd = FixedLagSmoother(1, half_window=10, order=2).push(t, x)
    assert np.abs(dd[:, 0] - 12 * t[10:-10] ** 2).max() > 0.01


def test_noisy_sine_derivatives():
    rng = np.random.default_rng(7)
    f, amp, sigma = 1.3, 0.8, 1e-3
    t = _irregular_stamps(rng, 4000, dt=0.002, jitter=0.2)
    w = 2 * np.pi * f
    clean = amp * np.sin(w * t)
    x = (clean + rng.normal(0, sigma, t.size))[:, None]
    tc, v, d, dd = FixedLagSmoother(1, half_window=20, order=3).push(t, x)
    rms = lambda e: np.sqrt(np.mean(e ** 2))                        # noqa: E731
    assert rms(v[:, 0] - amp * np.sin(w * tc)) < 0.5 * sigma        # smoothing reduces noise
    assert rms(d[:, 0] - amp * w * np.cos(w * tc)) < 0.01 * amp * w
    assert rms(dd[:, 0] + amp * w * w * np.sin(w * tc)) < 0.1 * amp * w * w
    # ...and beats plain finite differences of the same noisy samples by far.
    fd, _ = central_derivatives(t, x)
    assert rms(d[:, 0] - amp * w * np.cos(w * tc)) < 0.2 * rms(
        fd[20:-20, 0] - amp * w * np.cos(w * t[20:-20]))


def test_chunked_equals_one_shot():
    rng = np.random.default_rng(3)
    t = _irregular_stamps(rng, 1500)
    t[700:] += 0.5                                                  # one gap
    x = rng.normal(size=(1500, 5))
    one = FixedLagSmoother(5, half_window=8, order=3, max_gap=0.1).push(t, x)
    sm = FixedLagSmoother(5, half_window=8, order=3, max_gap=0.1)
    parts, i = [], 0
    for m in rng.integers(0, 40, 10000):
        if i >= t.size:
            break
        parts.append(sm.push(t[i:i + m], x[i:i + m]))
        i += m
    chunked = [np.concatenate(p) for p in zip(*parts)]
    assert one[0].size == 1500 - 4 * 8
    for a, b in zip(one, chunked):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13)
    # one sample at a time, scalar stamp and (c,) sample
    sm.reset()
    single = [sm.push(t[k], x[k]) for k in range(100)]
    np.testing.assert_allclose(np.concatenate([s[2] for s in single]), one[2][:100 - 16],
                               rtol=1e-13, atol=1e-13)


def test_gap_restarts_the_window():
    # Different polynomials before and after the gap: any window straddling it would be wrong.
    rng = np.random.default_rng(4)
    t1 = _irregular_stamps(rng, 60)
    t2 = _irregular_stamps(rng, 50, t0=t1[-1] + 1.0)
    a = _poly(t1 - 3, [[1, 2, -3, 0.5]])
    b = _poly(t2 - 3, [[-4, 0.5, 7, -2]])
    sm = FixedLagSmoother(1, half_window=5, order=3, max_gap=0.5)
    out1 = sm.push(t1, a[0])
    out2 = sm.push(t2, b[0])
    np.testing.assert_array_equal(out2[0], t2[5:-5])
    np.testing.assert_allclose(out1[2], a[1][5:-5], rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(out2[2], b[1][5:-5], rtol=1e-7, atol=1e-7)
    # The same stream in one call gives the same windows.
    sm.reset()
    both = sm.push(np.r_[t1, t2], np.r_[a[0], b[0]])
    np.testing.assert_array_equal(both[0], np.r_[t1[5:-5], t2[5:-5]])
    # A gap inside a short segment leaves no output for it.
    sm.reset()
    t3 = np.r_[t1[:4], t1[4:] + 2.0]
    assert sm.push(t3, a[0])[0].size == 60 - 4 - 10


def test_delay_and_validation():
    sm = FixedLagSmoother(2, half_window=7, order=2)
    assert sm.delay_samples == 7
    assert sm.delay(100.0) == pytest.approx(0.07)
    assert sm.push(np.arange(14.0), np.zeros((14, 2)))[0].size == 0   # 2L samples: none yet
    assert sm.push([14.0], np.zeros((1, 2)))[0].tolist() == [7.0]
    with pytest.raises(IdentificationError, match='not after'):
        sm.push([14.0], np.zeros((1, 2)))
    with pytest.raises(IdentificationError, match='strictly increasing'):
        sm.push([20.0, 21.0, 21.0], np.zeros((3, 2)))
    with pytest.raises(IdentificationError, match='NaN'):
        sm.push([30.0], [[0.0, np.nan]])
    with pytest.raises(IdentificationError, match=r'expected \(N, 2\)'):
        sm.push([30.0], np.zeros((1, 3)))
    with pytest.raises(IdentificationError, match='time stamps'):
        sm.push([30.0, 31.0], np.zeros((1, 2)))
    sm.reset()
    assert sm.push([0.0], np.zeros((1, 2)))[0].size == 0              # reset allows restart
    for kw in (dict(half_window=0), dict(order=1), dict(order=5), dict(half_window=1, order=3),
               dict(max_gap=0.0), dict(order=2.5)):
        with pytest.raises(IdentificationError):
            FixedLagSmoother(3, **kw)
    with pytest.raises(IdentificationError, match='rate'):
        sm.delay(0.0)


def test_frequency_response_matches_streaming_output():
    rate, f, L = 100.0, 7.0, 12
    sm = FixedLagSmoother(1, half_window=L, order=3)
    t = np.arange(400) / rate
    tc, v, d, dd = sm.push(t, np.sin(2 * np.pi * f * t)[:, None])
    h0, h1, h2 = sm.frequency_response(np.array([f]), rate)
    z = np.exp(2j * np.pi * f * tc)                                # sin = Im(z)
    np.testing.assert_allclose(v[:, 0], np.imag(h0 * z), atol=1e-10)
    np.testing.assert_allclose(d[:, 0], np.imag(h1 * z), atol=1e-8)
    np.testing.assert_allclose(dd[:, 0], np.imag(h2 * z), atol=1e-6)
    # Zero phase about the centre, unit DC gain, ideal derivative gains at low frequency.
    g0, g1, g2 = sm.frequency_response(np.array([0.0, 0.2]), rate)
    np.testing.assert_allclose(np.imag(g0), 0.0, atol=1e-12)
    assert g0[0].real == pytest.approx(1.0)
    w = 2 * np.pi * 0.2
    assert g1[1] == pytest.approx(1j * w, rel=1e-5)
    assert g2[1] == pytest.approx(-w * w, rel=1e-2)
    assert abs(sm.frequency_response(np.array([0.45 * rate]), rate)[0][0]) < 0.1


def _window_fits(t, x, L, order, centres):
    """Independent reference: numpy's polynomial least-squares fit of each window (in time
    relative to its centre), its value and derivatives at the centre."""
    out = np.empty((3, len(centres), x.shape[1]))
    for i, c in enumerate(centres):
        w = slice(c - L, c + L + 1)
        h = 0.5 * (t[c + L] - t[c - L])
        coef = np.polynomial.polynomial.polyfit((t[w] - t[c]) / h, x[w], order)
        out[:, i] = coef[0], coef[1] / h, 2 * coef[2] / h ** 2
    return out


def test_uniform_stamps_take_fixed_weights_equal_to_the_general_fit(monkeypatch):
    rng = np.random.default_rng(41)
    n, L = 3000, 10
    # stamps exact in binary (the general fit's own rounding stays ~1e-13), ~1 kHz, with a
    # jittered stretch and a gap: those windows need the general fit
    t = 4.0 + np.arange(n) * 2.0 ** -10
    t[1000:1200] += rng.uniform(-2e-4, 2e-4, 200)
    t[2000:] += 0.25
    x = np.column_stack([np.sin(3 * t), np.cos(11 * t) + 0.01 * rng.standard_normal(n), t ** 2])
    uniform_calls = []
    fast = FixedLagSmoother(3, half_window=L, order=3, max_gap=0.05)
    fit = fast._fit_uniform
    monkeypatch.setattr(fast, '_fit_uniform', lambda *a: uniform_calls.append(a[3]) or fit(*a))
    general = FixedLagSmoother(3, half_window=L, order=3, max_gap=0.05)
    monkeypatch.setattr(general, '_runs', lambda T, d, starts: [(starts, False)])
    got = [fast.push(t[k:k + 700], x[k:k + 700]) for k in range(0, n, 700)]
    want = [general.push(t[k:k + 700], x[k:k + 700]) for k in range(0, n, 700)]
    got, want = ([np.concatenate(p) for p in zip(*r)] for r in (got, want))
    assert sum(uniform_calls) > 0.8 * len(got[0])  # most windows took the fixed weights
    np.testing.assert_array_equal(got[0], want[0])
    for a, b in zip(got[1:], want[1:]):  # O(1) signals (t^2: cancellation in the fit)
        np.testing.assert_allclose(a[:, :2], b[:, :2], rtol=1e-12, atol=1e-12 * np.abs(b).max())
    centres = np.searchsorted(t, got[0])
    jittered = (centres > 1000 - L) & (centres < 1200 + L)
    for a, b in zip(got[1:], want[1:]):  # the jittered windows: the same computation
        np.testing.assert_array_equal(a[jittered], b[jittered])
    ref = _window_fits(t, x, L, 3, centres)
    for a, r, tol in zip(got[1:], ref, (1e-9, 1e-8, 1e-6)):  # polyfit's own rounding
        np.testing.assert_allclose(a, r, rtol=tol, atol=tol * np.abs(r).max())
    for r in (got, want):  # (t^2)'' = 2, to the rounding of both
        np.testing.assert_allclose(r[3][:, 2], 2.0, rtol=1e-8)


@pytest.mark.parametrize('L', [4, 10, 57, 300])
def test_cutoff_is_the_exact_3_db_frequency_and_maps_back_to_the_window(L):
    rate = 500.0
    fc = smoother_cutoff(L, 3, rate)
    sm = FixedLagSmoother(1, half_window=L, order=3)
    gain = np.abs(sm.frequency_response(np.array([0.5 * fc, fc, 1.02 * fc]), rate)[0])
    assert gain[1] == pytest.approx(1 / np.sqrt(2), abs=1e-9)
    assert gain[0] > gain[1] > gain[2]
    assert half_window_for_cutoff(fc, rate, 3) == L
    # the same window in seconds at another rate has about the same cut-off in Hz
    assert smoother_cutoff(4 * L, 3, 4 * rate) == pytest.approx(fc, rel=0.05 if L > 4 else 0.2)
    # a cut-off near Nyquist stops at the shortest well-posed window
    assert half_window_for_cutoff(0.45 * rate, rate, 3) == signals.MIN_HALF_WINDOW
    with pytest.raises(IdentificationError):
        half_window_for_cutoff(0.0, rate, 3)


def test_long_windows_by_fft_and_fit_at_equal_the_general_fit(monkeypatch):
    rng = np.random.default_rng(3)
    n, L = 3000, 150
    t = 2.0 + np.arange(n) * 2.0 ** -9
    x = np.column_stack([np.sin(3 * t), 5 + np.cos(7 * t) + 0.01 * rng.standard_normal(n)])
    fast = FixedLagSmoother(2, half_window=L, order=3)
    got = [fast.push(t[k:k + 1000], x[k:k + 1000]) for k in range(0, n, 1000)]
    got = [np.concatenate(p) for p in zip(*got)]
    monkeypatch.setattr(signals, '_FFT_TAPS', 10 ** 9)   # the fixed weights by BLAS
    want = FixedLagSmoother(2, half_window=L, order=3).push(t, x)
    np.testing.assert_array_equal(got[0], want[0])
    for a, b in zip(got[1:], want[1:]):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())
    centres = np.searchsorted(t, want[0])[::37]
    at = FixedLagSmoother(2, half_window=L, order=3).fit_at(t, x, centres)
    for a, b in zip(at, want[1:]):
        np.testing.assert_allclose(a, b[::37], rtol=1e-9, atol=1e-9 * np.abs(b).max())
    with pytest.raises(IdentificationError, match='half a window'):
        fast.fit_at(t, x, [L - 1])
    # one push of more windows than a block: overlap-save over several blocks
    monkeypatch.setattr(signals, '_FFT_TAPS', 129)
    monkeypatch.setattr(signals, '_BLOCK', 1000)
    once = FixedLagSmoother(2, half_window=L, order=3).push(t, x)
    np.testing.assert_array_equal(once[0], want[0])
    for a, b in zip(once[1:], want[1:]):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())


def test_long_windows_of_jittered_stamps_by_sliding_sums_equal_the_direct_fit(monkeypatch):
    """Stamps off their grid (a driver stamping on receipt): windows longer than _FFT_TAPS
    are fitted from sliding sums, equal to the fit of each window's samples (a push in
    chunks, one of a single window, and fit_at on scattered centres), epoch-sized stamps."""
    rng = np.random.default_rng(5)
    n, L = 6000, 200
    t = 1.7e9 + np.arange(n) * 2e-4 + rng.uniform(0.0, 5e-5, n)
    x = np.column_stack([np.sin(3 * t), 5 + np.cos(7 * t) + 0.01 * rng.standard_normal(n),
                         40 * np.sin(30 * t)])
    t -= 1.7e9    # epoch-sized stamps rounded as the pipeline's; then relative, as it passes
    sliding = FixedLagSmoother(3, half_window=L, order=3)
    pushes = [sliding.push(t[k:k + m], x[k:k + m])
              for k, m in zip([0, 1500, 1550, 1551, 4000], [1500, 50, 1, 2449, 2000])]
    got = [np.concatenate(p) for p in zip(*pushes)]
    centres = np.sort(rng.choice(np.arange(L, n - L), 300, replace=False))
    at = FixedLagSmoother(3, half_window=L, order=3).fit_at(t, x, centres)
    monkeypatch.setattr(signals, '_FFT_TAPS', 10 ** 9)   # every window's samples gathered
    direct = FixedLagSmoother(3, half_window=L, order=3)
    want = direct.push(t, x)
    np.testing.assert_array_equal(got[0], want[0])
    for a, b in zip(got[1:], want[1:]):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())
    for a, b in zip(at, direct.fit_at(t, x, centres)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())


def test_fit_at_many_long_windows_by_fft_equals_each_windows_polynomial_fit(monkeypatch):
    """The smoother's choice fits 500 scattered long windows (uniform stamps): every window
    of their span by FFT, picked at the centres, equals each window's own least-squares
    cubic (numpy.polynomial), value and derivatives, from a late start too."""
    rng = np.random.default_rng(7)
    n, L = 5000, 400
    for t0 in (0.0, 1000.0):
        t = t0 + np.arange(n) * 1e-3
        x = np.column_stack([np.sin(3 * (t - t0)), 5 + 0.01 * rng.standard_normal(n)])
        centres = np.sort(rng.choice(np.arange(L, n - L), 500, replace=False))
        smoother = FixedLagSmoother(2, half_window=L, order=3)
        monkeypatch.setattr(smoother, '_fit_at_uniform', None)   # not the gathering path
        value, first, second = smoother.fit_at(t, x, centres)
        for i in rng.choice(len(centres), 12, replace=False):
            c = centres[i]
            u = t[c - L:c + L + 1] - t[c]
            for j in range(2):
                p = np.polynomial.Polynomial.fit(u, x[c - L:c + L + 1, j], 3, domain=[-1, 1])
                want = [p(0.0), p.deriv(1)(0.0), p.deriv(2)(0.0)]
                scale = [1.0, 3.0, 9.0]
                for got, w, s in zip((value, first, second), want, scale):
                    assert abs(got[i, j] - w) <= 1e-8 * s, (t0, c, j, got[i, j], w)


def test_long_uniform_push_in_blocks_equals_chunked_pushes():
    t = np.arange(9000) * 2.0 ** -10  # more windows than one block of the fixed-weight fit
    x = np.column_stack([np.sin(2 * t), np.cos(5 * t)])
    one = FixedLagSmoother(2, half_window=10, order=3).push(t, x)
    sm = FixedLagSmoother(2, half_window=10, order=3)
    parts = [sm.push(t[k:k + 1000], x[k:k + 1000]) for k in range(0, 9000, 1000)]
    for a, b in zip(one, (np.concatenate(p) for p in zip(*parts))):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    assert len(one[0]) == 9000 - 20


def test_uniformity_tolerance_is_relative_to_the_step_and_the_stamp_rounding(monkeypatch):
    L, n = 5, 400
    sm = FixedLagSmoother(1, half_window=L, order=2)
    starts = np.arange(n - 2 * L)
    # 10 days of seconds at 1 kHz: float rounding of the stamps (~1e-10 s) is uniform
    t = 864000.0 + np.arange(n) * 1e-3
    assert all(u for _, u in sm._runs(t, np.diff(t), starts))
    t = np.arange(n) * 1e-3
    t[200] += 1e-11  # 1e-8 of a step: not uniform around it
    runs = sm._runs(t, np.diff(t), starts)
    assert [u for _, u in runs] == [True, False, True]
    # a few windows with jitter among them are fitted in general, all of them
    assert [u for _, u in sm._runs(t, np.diff(t), starts[150:200])] == [False]
    assert np.array_equal(runs[1][0], np.arange(200 - 2 * L, 201))


def test_zero_phase_lowpass_has_no_delay():
    rate = 1000.0
    t = np.arange(4000) / rate
    slow = np.sin(2 * np.pi * 2.0 * t)
    x = np.stack([slow + 0.3 * np.sin(2 * np.pi * 200.0 * t), -slow], 1)
    y = zero_phase_lowpass(x, rate, cutoff=20.0, order=4)
    mid = slice(500, -500)
    # One sample of delay would give an error of 2 pi 2 / 1000 = 1.3e-2.
    np.testing.assert_allclose(y[mid, 0], slow[mid], atol=1e-4)
    np.testing.assert_allclose(y[mid, 1], -slow[mid], atol=1e-4)
    assert zero_phase_lowpass(slow, rate, 20.0).shape == slow.shape
    with pytest.raises(IdentificationError, match='cutoff'):
        zero_phase_lowpass(x, rate, cutoff=600.0)
    with pytest.raises(IdentificationError, match='too few'):
        zero_phase_lowpass(x[:10], rate, cutoff=20.0)
    with pytest.raises(IdentificationError, match='NaN'):
        zero_phase_lowpass(np.r_[slow[:100], np.nan], rate, 20.0)


def test_decimate_removes_aliases():
    rate, factor = 1000.0, 10
    t = np.arange(5000) / rate
    slow = np.cos(2 * np.pi * 1.5 * t)
    fast = 0.5 * np.sin(2 * np.pi * 190.0 * t)     # would alias to 10 Hz at 100 Hz
    y = decimate(np.stack([slow + fast, slow], 1), factor)
    assert y.shape == (500, 2)
    np.testing.assert_allclose(y[30:-30, 0], slow[::factor][30:-30], atol=2e-3)
    np.testing.assert_allclose(decimate(slow, 1), slow)
    with pytest.raises(IdentificationError, match='factor'):
        decimate(slow, 0)


def test_central_derivatives_exact_on_quadratics():
    rng = np.random.default_rng(9)
    t = _irregular_stamps(rng, 50, jitter=0.6)
    x, xd, xdd = _poly(t - 3.2, rng.normal(size=(3, 3)))
    d, dd = central_derivatives(t, x)
    np.testing.assert_allclose(d, xd, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(dd, xdd, rtol=1e-6, atol=1e-6)
    with pytest.raises(IdentificationError, match='increasing'):
        central_derivatives(t[::-1], x)


def test_period_average_recovers_signal_and_noise():
    rng = np.random.default_rng(11)
    rate, period, periods = 100.0, 2.0, 30
    n = int(rate * period)
    t = np.arange(n * periods + 37) / rate + rng.uniform(-0.1, 0.1, n * periods + 37) / rate
    sig = np.stack([np.sin(2 * np.pi * t / period) + 0.3 * np.cos(6 * np.pi * t / period),
                    2.0 * np.sin(4 * np.pi * t / period + 1.0)], 1)
    sigma = np.array([0.05, 0.2])
    x = sig + rng.normal(size=sig.shape) * sigma
    drop = rng.choice(x.shape[0], 40, replace=False)         # dropped messages
    t, x, sig = np.delete(t, drop), np.delete(x, drop, 0), np.delete(sig, drop, 0)
    res = period_average(t, x, period)
    assert res.periods == periods
    assert res.mean.shape == res.var.shape == (n, 2)
    assert res.counts.sum() == np.sum(t - t[0] < periods * period - 0.5 / rate)
    # Per-bin variance estimates with ~29 degrees of freedom, averaged over 200 bins: ~2 %.
    np.testing.assert_allclose(res.var.mean(axis=0), sigma ** 2, rtol=0.1)
    truth = np.stack([np.sin(2 * np.pi * (res.t + t[0]) / period)
                      + 0.3 * np.cos(6 * np.pi * (res.t + t[0]) / period),
                      2.0 * np.sin(4 * np.pi * (res.t + t[0]) / period + 1.0)], 1)
    err = (res.mean - truth) / (sigma / np.sqrt(res.counts[:, None]))
    assert np.sqrt(np.mean(err ** 2)) < 1.5          # ~1 if the mean is unbiased (+ jitter)
    one = period_average(t, x[:, 1], period)         # 1-D in, 1-D out
    np.testing.assert_allclose(one.var, res.var[:, 1])


def test_period_average_errors():
    t = np.arange(300) / 100.0
    with pytest.raises(IdentificationError, match='whole period'):
        period_average(t, np.sin(t), 2.0)
    with pytest.raises(IdentificationError, match='period'):
        period_average(t, np.sin(t), -1.0)
    with pytest.raises(IdentificationError, match='fewer than 2'):
        period_average(np.delete(t, [5, 105]), np.delete(np.sin(t), [5, 105]), 1.0)


@pytest.mark.parametrize('order,L', [(3, 5), (3, 40), (2, 12)])
def test_smoothed_sign_is_what_the_smoother_makes_of_sign_friction(order, L):
    """The Coulomb column at reversals: the smoother run on sign(v(t)) of a velocity that
    crosses zero (a cosine, so v is not exactly linear in the window) against
    signals.smoothed_sign of the smoothed v and a at the centres."""
    rate = 100.0 if L < 20 else 1000.0
    t = np.arange(int(6 * rate)) / rate
    v = 0.8 * np.cos(2 * np.pi * 0.3 * t) + 0.05          # rad/s, 3 reversals
    a = -0.8 * 2 * np.pi * 0.3 * np.sin(2 * np.pi * 0.3 * t)
    tc, smoothed, _, _ = FixedLagSmoother(1, half_window=L, order=order).push(
        t, np.sign(v)[:, None])
    idx = np.round(tc * rate).astype(int)
    column = signals.smoothed_sign(v[idx], a[idx], L, order, 1 / rate)
    crossing = np.abs(np.sign(v[idx]) - smoothed[:, 0]) > 1e-9   # reversal in the window
    assert crossing.sum() > 3 * L     # the test looks at reversals
    error = np.abs(column - smoothed[:, 0])
    # the linearised crossing may fall a sample off where v curves: one sample's weight, twice
    assert error.max() < 2.5 * np.abs(signals.value_weights(L, order)).max()
    assert error[crossing].mean() < 0.02
    assert np.abs(np.sign(v[idx]) - smoothed[:, 0])[crossing].max() > 0.5   # sign(qd) is not


@pytest.mark.parametrize('order,L', [(3, 4), (2, 19), (3, 100)])
def test_smoothed_sign_is_its_weighted_sum(order, L):
    """signals.smoothed_sign against its definition, sum_i w_i sign(v + a i period) over the
    window's value weights, for crossings anywhere in and beyond the window (none on a
    sample), velocities at rest and accelerations of 0 and inf."""
    rng = np.random.default_rng(L)
    period, M = 1e-3, 4000
    a = rng.normal(0.0, 10.0, M)
    x = rng.uniform(-L - 3, L + 3, M)            # the crossing, in samples from the centre
    x[np.abs(x - np.round(x)) < 1e-6] += 0.5     # not on a sample
    v = -x * a * period
    v[:20], a[20:40], a[40:50] = 0.0, 0.0, np.inf
    i = np.arange(-L, L + 1)
    with np.errstate(invalid='ignore'):
        inside = np.where(i == 0, v[:, None], v[:, None] + a[:, None] * i * period)
    expected = np.where(np.abs(v[:, None]) > 1e-9, np.sign(inside), 0.0) @ signals.value_weights(
        L, order)
    got = signals.smoothed_sign(v, a, L, order, period)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


def test_a_joint_at_rest_has_no_coulomb_sign():
    """A joint held still (constant position) under jittered stamps: the smoother's velocity is
    rounding noise, of both signs, whose np.sign flips the Coulomb column of a resting joint at
    random (the TX40's held-out joint 3, 45 % of its samples); coulomb_sign, the regressor's
    fc column and the smoothed sign are 0 there, and 1 for the moving joint."""
    from identification_node.model.coulomb import REST_SPEED, coulomb_sign
    from identification_node.model.robot import load_robot
    L = 20   # a window fitted in general (jittered stamps, not long): rounding in its slope
    rng = np.random.default_rng(5)
    t = np.arange(3000) * 2e-4 + rng.uniform(-2.4e-7, 2.4e-7, 3000)
    q = np.column_stack([np.full(3000, 0.7311), np.sin(3.0 * t)])
    sm = FixedLagSmoother(2, half_window=L, order=2)
    _, x, xd, xdd = sm.push(t, q)
    rest = np.abs(xd[:, 0])
    assert 0 < rest.max() <= REST_SPEED and len(np.unique(np.sign(xd[:, 0]))) > 1
    assert not coulomb_sign(xd[:, 0]).any()
    sign = signals.smoothed_sign(xd, xdd, L, 2, 2e-4)
    assert not sign[:, 0].any() and np.mean(sign[:, 1] != 0) > 0.99
    robot = load_robot('mit_dd_arm', ['joint1', 'joint2'], extras=['fc'])
    Y = robot.regressor(x, xd, xdd)
    fc = [robot.param_index(f'{j}.fc') for j in robot.joint_names]
    assert not Y[:, 0, fc[0]].any()
    np.testing.assert_array_equal(Y[:, 1, fc[1]], np.sign(xd[:, 1]))
