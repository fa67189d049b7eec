"""Soak test of the square-root-information RLS: 10^6 samples of the MIT arm's base regressor
with long stretches at rest (gravity rows only), with and without forgetting."""
import numpy as np
import pytest
import scipy.linalg as sl

from identification_node.estimation.batch import LeastSquares
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.model.robot import load_robot
from test_estimators import sines_trajectory

pytestmark = pytest.mark.slow

BATCH = 1000
SIGMA = 0.5  # N m torque noise
# (kind, number of batches): 10^6 samples, 4 * 10^5 of them at rest
SCHEDULE = (('move', 250), ('rest', 200), ('move', 250), ('rest', 200), ('move', 100))


@pytest.fixture(scope='module')
def data():
    """One trajectory period (1000 samples, 10 s) and the rest posture, as base regressor rows,
    and the true base parameters of the MIT arm's model."""
    robot = load_robot('mit_dd_arm')
    rng = np.random.default_rng(21)
    Yr = robot.regressor(*(rng.uniform(-3, 3, size=(300, 3)) for _ in range(3)))
    R, piv = sl.qr(Yr.reshape(-1, 30), mode='r', pivoting=True)
    d = np.abs(np.diag(R))
    base = np.sort(piv[:int(np.sum(d > 1e-9 * d[0]))])
    assert len(base) == 15
    K = robot.regressor(*sines_trajectory(3, BATCH, 10.0, rng))
    A = K.reshape(-1, 30)
    beta = np.linalg.lstsq(A[:, base], A @ robot.phi_model, rcond=None)[0]
    q_rest = np.array([[0.4, -0.8, 1.2]])
    rest = robot.regressor(q_rest, np.zeros((1, 3)), np.zeros((1, 3)))[..., base]
    return dict(move=K[..., base], rest=np.broadcast_to(rest, (BATCH, 3, 15)), beta=beta)


def batches(data, rng):
    for kind, count in SCHEDULE:
        Y = data[kind]
        for _ in range(count):
            yield kind, Y, Y @ data['beta'] + SIGMA * rng.normal(size=(BATCH, 3))


def test_soak_forgetting_stays_bounded_and_no_forgetting_equals_batch(data):
    lam, m = 0.999, 1e-4
    stabilised = RecursiveLeastSquares(15, lam, min_information=m)
    plain = RecursiveLeastSquares(15, 1.0)
    ls = LeastSquares(15, 3)
    info, moment = np.zeros((15, 15)), np.zeros(15)  # normal equations: independent reference
    rng = np.random.default_rng(22)
    last_kind, at_rest_start = None, None
    for kind, Y, tau in batches(data, rng):
        if kind == 'rest' and last_kind == 'move':
            at_rest_start = stabilised.estimate()
        if kind == 'move' and last_kind == 'rest':
            # a long rest did not move the estimate in the unexcited directions
            drift = np.abs(stabilised.theta - at_rest_start.theta) / at_rest_start.stddev
            assert drift.max() < 4
        last_kind = kind
        stabilised.update(Y, tau)
        plain.update(Y, tau)
        ls.add(Y, tau)
        A = Y.reshape(-1, 15)
        info += A.T @ A
        moment += A.T @ tau.ravel()

        k = stabilised.num_samples
        theta, cov = stabilised.theta, stabilised.covariance
        assert np.all(np.isfinite(theta))
        np.testing.assert_array_equal(cov, cov.T)
        np.linalg.cholesky(cov)
        ev = np.linalg.eigvalsh(cov)
        floor = (1 - lam ** k) * m
        assert ev[0] > 0
        assert ev[-1] <= stabilised.noise_variance / floor * (1 + 1e-9)  # no wind-up
        assert stabilised.min_eigenvalue >= floor * (1 - 1e-9)
    assert plain.num_samples == 10 ** 6

    ref = ls.solve()
    est = plain.estimate()
    np.testing.assert_allclose(est.theta, ref.theta, rtol=1e-9,
                               atol=1e-9 * np.abs(ref.theta).max())
    np.testing.assert_allclose(est.covariance, ref.covariance, rtol=1e-8,
                               atol=1e-9 * np.abs(ref.covariance).max())
    theta_ne = np.linalg.solve(info, moment)
    assert np.linalg.norm(est.theta - theta_ne) <= 1e-6 * np.linalg.norm(theta_ne)
    np.testing.assert_allclose(est.noise_variance, SIGMA ** 2, rtol=0.01)
    # both end after an exciting stretch: honest within a few standard deviations
    for e in (est, stabilised.estimate()):
        assert np.all(np.abs(e.theta - data['beta']) < 4 * e.stddev)


def naive_rls(P, theta, Y, tau, lam):
    """Textbook covariance-form RLS with exponential forgetting, sample by sample."""
    eye = np.eye(Y.shape[1])
    with np.errstate(all='ignore'):  # it overflows: that is the point
        for Yk, tk in zip(Y, tau):
            PYt = P @ Yk.T
            gain = np.linalg.solve(lam * eye + Yk @ PYt, PYt.T).T
            theta = theta + gain @ (tk - Yk @ theta)
            P = (P - gain @ PYt.T) / lam
    return P, theta


def test_naive_covariance_rls_winds_up_where_square_root_form_does_not(data):
    """Demonstration that the problem is real: the covariance form divides P by lambda every
    sample, so at rest it grows as lambda^-k in the unexcited directions (here by ~e^30)."""
    lam, m, rest = 0.999, 1e-4, 30000
    rng = np.random.default_rng(23)
    Y = data['move']
    tau = Y @ data['beta'] + SIGMA * rng.normal(size=(BATCH, 3))
    P, theta = naive_rls(1e3 * np.eye(15), np.zeros(15), Y, tau, lam)
    rls = RecursiveLeastSquares(15, lam, min_information=m)
    rls.update(Y, tau)
    grown_naive = np.linalg.eigvalsh(P)[-1]
    inv_info = np.linalg.inv(rls.information)
    grown_sqrt = np.linalg.eigvalsh(inv_info)[-1]

    Yr = data['rest'][:1]
    Yr = np.broadcast_to(Yr, (rest, 3, 15))
    tau_r = Yr @ data['beta'] + SIGMA * rng.normal(size=(rest, 3))
    P, _ = naive_rls(P, theta, Yr, tau_r, lam)
    for k in range(0, rest, BATCH):
        rls.update(Yr[k:k + BATCH], tau_r[k:k + BATCH])
    ev = np.linalg.eigvalsh(0.5 * (P + P.T)) if np.all(np.isfinite(P)) else None
    naive_failed = ev is None or ev[0] < 0 or ev[-1] > 1e10 * grown_naive
    assert naive_failed
    ev_sqrt = np.linalg.eigvalsh(np.linalg.inv(rls.information))
    assert 0 < ev_sqrt[0] and ev_sqrt[-1] <= 1 / ((1 - lam ** rls.num_samples) * m) * (1 + 1e-9)
    assert ev_sqrt[-1] < 1e10 * grown_sqrt
