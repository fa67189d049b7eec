"""Normal equations against explicit stacked least squares (numpy), merged and forgotten."""
import numpy as np
import pytest

from identification_node.errors import IdentificationError
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.estimation.normal_equations import NormalEquations


def data(rng, N=200, n=3, p=5):
    Y = rng.normal(size=(N, n, p))
    theta = rng.normal(size=p)
    return Y, Y @ theta + 0.1 * rng.normal(size=(N, n))


def test_split_merges_exactly_and_solves_like_lstsq():
    rng = np.random.default_rng(0)
    Y, tau = data(rng)
    whole = NormalEquations.from_rows(Y, tau)
    merged = NormalEquations.from_rows(Y[:70], tau[:70]) + NormalEquations.from_rows(
        Y[70:], tau[70:])
    np.testing.assert_allclose(merged.augmented, whole.augmented, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(merged.count, [200.0] * 3)
    w = np.array([1.0, 4.0, 0.25])
    G, b, c = whole.combined(w)
    theta = np.linalg.solve(G, b)
    ref = np.linalg.lstsq((Y * np.sqrt(w)[:, None]).reshape(-1, 5),
                          (tau * np.sqrt(w)).ravel(), rcond=None)[0]
    np.testing.assert_allclose(theta, ref, rtol=1e-10)
    np.testing.assert_allclose(whole.rss(ref), ((tau - Y @ ref) ** 2).sum(axis=0), rtol=1e-9)
    assert c == pytest.approx((w * tau ** 2).sum())


def test_estimators_expose_their_data_sums():
    rng = np.random.default_rng(1)
    Y, tau = data(rng)
    ref = NormalEquations.from_rows(Y, tau)
    rls = RecursiveLeastSquares(5)
    rls.update(Y, tau)
    stats = ResidualStatistics(5, 3, block=10)
    stats.add(Y, tau)
    for ne in (rls.normal_equations(), stats.normal_equations()):
        np.testing.assert_allclose(ne.augmented, ref.augmented, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(ne.count, ref.count)
    lam = 0.99
    rls = RecursiveLeastSquares(5, forgetting=lam)
    rls.update(Y, tau)
    decay = lam ** np.arange(len(Y) - 1, -1, -1)
    forgotten = NormalEquations.from_rows(Y * np.sqrt(decay)[:, None, None],
                                          tau * np.sqrt(decay)[:, None])
    np.testing.assert_allclose(rls.normal_equations().augmented, forgotten.augmented,
                               rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(rls.normal_equations().count, [decay.sum()] * 3)


def test_shapes_are_checked():
    with pytest.raises(IdentificationError):
        NormalEquations(np.zeros((2, 3, 4)), np.zeros(2))
    with pytest.raises(IdentificationError):
        NormalEquations.zeros(3, 2) + NormalEquations.zeros(4, 2)
