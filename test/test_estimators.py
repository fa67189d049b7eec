"""Estimators against independent truth: simulations with known parameters and Gaussian noise,
numpy's lstsq / explicit normal equations, closed forms of weighted and ridge least squares."""
import numpy as np
import pytest
import scipy.linalg as sl
from scipy.stats import chi2

from identification_node.errors import IdentificationError
from identification_node.estimation.batch import (LeastSquares, RidgeRegression,
                                                  WeightedLeastSquares)
from identification_node.estimation.lsq import Estimate
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.model.robot import load_robot


# -- fixtures ---------------------------------------------------------------------------------
def sines_trajectory(n, num, period, rng, harmonics=3, amplitude=1.0):
    """q, qd, qdd (num, n): per joint a sum of sines/cosines with a common period (s)."""
    t = np.arange(num) * (period / num)
    w = 2 * np.pi / period
    q, qd, qdd = (np.zeros((num, n)) for _ in range(3))
    for j in range(n):
        for k in range(1, harmonics + 1):
            a, b = rng.normal(size=2) * amplitude / k
            s, c = np.sin(k * w * t), np.cos(k * w * t)
            q[:, j] += a * s + b * c
            qd[:, j] += k * w * (a * c - b * s)
            qdd[:, j] -= (k * w) ** 2 * (a * s + b * c)
    return q, qd, qdd


def base_columns(Y, tol=1e-9):
    """Sorted independent columns of the stacked regressor (QR with column pivoting)."""
    A = Y.reshape(-1, Y.shape[-1])
    R, piv = sl.qr(A, mode='r', pivoting=True)
    d = np.abs(np.diag(R))
    return np.sort(piv[:int(np.sum(d > tol * d[0]))])


@pytest.fixture(scope='module')
def mit():
    """MIT arm: full regressor K (N, 3, 30) on an exciting trajectory, base columns, true base
    parameters beta (tau = K[..., base] @ beta = K @ phi_model) and the base map."""
    robot = load_robot('mit_dd_arm')
    rng = np.random.default_rng(7)
    qr_, qdr, qddr = (rng.uniform(-3, 3, size=(300, robot.dof)) for _ in range(3))
    base = base_columns(robot.regressor(qr_, qdr, qddr))
    K = robot.regressor(*sines_trajectory(robot.dof, 300, 6.0, rng))
    A, Ab = K.reshape(-1, 30), K[..., base].reshape(-1, len(base))
    beta = np.linalg.lstsq(Ab, A @ robot.phi_model, rcond=None)[0]
    # base map: beta = T phi, T[:, base] = I and dependent columns A_dep = A_b alpha
    T = np.linalg.lstsq(Ab, A, rcond=None)[0]
    return dict(robot=robot, base=base, K=K, Yb=K[..., base], beta=beta, T=T)


def noisy(Y, theta, sigma, rng):
    return Y @ theta + rng.normal(size=Y.shape[:2]) * sigma


def lstsq_reference(Y, tau):
    """theta and its covariance from numpy's lstsq on the stacked rows."""
    N, n, p = Y.shape
    A, b = Y.reshape(-1, p), tau.ravel()
    theta = np.linalg.lstsq(A, b, rcond=None)[0]
    s2 = np.sum((b - A @ theta) ** 2) / (N * n - p)
    return theta, s2 * np.linalg.inv(A.T @ A)


def nees(err, cov):
    return float(err @ np.linalg.solve(cov, err))


def chi2_bounds(trials, p, alpha=1e-3):
    """Bounds on the mean NEES of `trials` independent p-dimensional errors."""
    dof = trials * p
    return chi2.ppf(alpha / 2, dof) / trials, chi2.ppf(1 - alpha / 2, dof) / trials


def assert_estimates_equal(a: Estimate, b: Estimate, rtol=1e-9):
    np.testing.assert_allclose(a.theta, b.theta, rtol=rtol, atol=rtol * np.abs(b.theta).max())
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=rtol,
                               atol=rtol * np.abs(b.covariance).max())
    np.testing.assert_allclose(a.noise_variance, b.noise_variance, rtol=rtol)
    np.testing.assert_allclose(a.rss, b.rss, rtol=rtol)
    assert a.num_samples == b.num_samples


# -- fixture sanity ---------------------------------------------------------------------------
def test_mit_arm_has_15_base_parameters(mit):
    assert len(mit['base']) == 15
    tau = mit['K'] @ mit['robot'].phi_model
    np.testing.assert_allclose(mit['Yb'] @ mit['beta'], tau, atol=1e-9 * np.abs(tau).max())


# -- ordinary least squares -------------------------------------------------------------------
def test_least_squares_matches_lstsq_and_is_within_3_sigma(mit):
    rng = np.random.default_rng(1)
    Y, sigma = mit['Yb'], 0.5
    tau = noisy(Y, mit['beta'], sigma, rng)
    ls = LeastSquares(15, 3)
    ls.add(Y, tau)
    est = ls.solve()
    theta_ref, cov_ref = lstsq_reference(Y, tau)
    np.testing.assert_allclose(est.theta, theta_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(est.covariance, cov_ref, rtol=1e-7, atol=1e-12 * cov_ref.max())
    np.testing.assert_array_less(np.abs(est.theta - mit['beta']), 3 * est.stddev)
    np.testing.assert_allclose(est.stddev, np.sqrt(np.diag(cov_ref)), rtol=1e-7)
    np.testing.assert_allclose(est.rel_stddev, 100 * est.stddev / np.abs(est.theta))
    assert est.noise_variance.shape == (3,)
    np.testing.assert_allclose(est.noise_variance, sigma ** 2, rtol=0.25)
    np.testing.assert_allclose(est.rss, np.sum((tau - Y @ est.theta) ** 2), rtol=1e-10)
    np.testing.assert_allclose(est.predict(Y), Y @ est.theta)
    assert est.num_samples == Y.shape[0]


@pytest.mark.parametrize('case', ['mit', 'random'])
def test_least_squares_covariance_is_honest(mit, case):
    """Mean normalized estimation error squared over repeated noise draws ~ p."""
    rng = np.random.default_rng(2)
    if case == 'mit':
        Y, theta = mit['Yb'], mit['beta']
    else:
        Y = rng.normal(size=(120, 4, 12)) * np.logspace(-1, 1, 12)
        theta = rng.normal(size=12)
    p, trials = Y.shape[2], 150
    values = []
    for _ in range(trials):
        ls = LeastSquares(p, Y.shape[1])
        ls.add(Y, noisy(Y, theta, 0.3, rng))
        est = ls.solve()
        values.append(nees(est.theta - theta, est.covariance))
    lo, hi = chi2_bounds(trials, p)
    assert lo < np.mean(values) < hi


def test_chunked_one_shot_and_merged_agree(mit):
    rng = np.random.default_rng(3)
    Y = np.concatenate([mit['Yb']] * 20)  # 6000 samples: more than one internal chunk
    tau = noisy(Y, mit['beta'], 0.5, rng)
    for cls, extra in ((LeastSquares, {}), (WeightedLeastSquares, {})):
        one = cls(15, 3, **extra)
        one.add(Y, tau)
        chunked = cls(15, 3, **extra)
        cuts = np.sort(rng.choice(np.arange(1, len(Y)), 7, replace=False))
        for part_Y, part_tau in zip(np.split(Y, cuts), np.split(tau, cuts)):
            chunked.add(part_Y, part_tau)
        first, second = cls(15, 3, **extra), cls(15, 3, **extra)
        first.add(Y[:2500], tau[:2500])
        second.add(Y[2500:], tau[2500:])
        merged = first.merge(second)
        assert merged is first
        ref = one.solve()
        assert_estimates_equal(chunked.solve(), ref)
        assert_estimates_equal(merged.solve(), ref)
        if cls is LeastSquares:
            theta_ref, cov_ref = lstsq_reference(Y, tau)
            np.testing.assert_allclose(ref.theta, theta_ref, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(ref.covariance, cov_ref, rtol=1e-7, atol=1e-12)


# -- weighted least squares -------------------------------------------------------------------
def test_weighted_least_squares_unequal_joint_noise(mit):
    rng = np.random.default_rng(4)
    Y, beta = mit['Yb'], mit['beta']
    sigma = np.array([0.05, 0.5, 2.0])
    trials = 120
    nees_wls, err_wls, err_ols, var = [], [], [], []
    for _ in range(trials):
        tau = noisy(Y, beta, sigma, rng)
        wls, ols = WeightedLeastSquares(15, 3), LeastSquares(15, 3)
        wls.add(Y, tau)
        ols.add(Y, tau)
        w, o = wls.solve(), ols.solve()
        P_inv = np.linalg.inv(w.covariance)
        nees_wls.append(nees(w.theta - beta, w.covariance))
        # both errors measured in the metric of the (honest) WLS covariance
        err_wls.append((w.theta - beta) @ P_inv @ (w.theta - beta))
        err_ols.append((o.theta - beta) @ P_inv @ (o.theta - beta))
        var.append(w.noise_variance)
    var = np.array(var)
    np.testing.assert_allclose(var.mean(axis=0), sigma ** 2, rtol=0.05)
    np.testing.assert_allclose(var, np.broadcast_to(sigma ** 2, var.shape), rtol=0.35)
    lo, hi = chi2_bounds(trials, 15)
    assert lo < np.mean(nees_wls) < hi
    assert np.mean(err_ols) > 3 * np.mean(err_wls)


def test_weighted_least_squares_is_eq6_with_its_variances(mit):
    """theta = (A' S^-1 A)^-1 A' S^-1 tau, covariance (A' S^-1 A)^-1 with S = diag(sigma_j^2)
    from the estimate, and sigma_j^2 reproduces from the residuals (fixed point)."""
    rng = np.random.default_rng(5)
    Y = mit['Yb']
    tau = noisy(Y, mit['beta'], np.array([2.0, 0.1, 0.7]), rng)
    wls = WeightedLeastSquares(15, 3)
    wls.add(Y, tau)
    est = wls.solve()
    A, b = Y.reshape(-1, 15), tau.ravel()
    s_inv = np.tile(1.0 / est.noise_variance, Y.shape[0])
    info = A.T @ (s_inv[:, None] * A)
    theta = np.linalg.solve(info, A.T @ (s_inv * b))
    np.testing.assert_allclose(est.theta, theta, rtol=1e-7)
    np.testing.assert_allclose(est.covariance, np.linalg.inv(info), rtol=1e-6)
    # fixed point with leverage-corrected degrees of freedom
    res = (tau - Y @ theta) ** 2
    lev = np.array([np.trace(np.linalg.solve(info, Y[:, j].T @ Y[:, j])) / est.noise_variance[j]
                    for j in range(3)])
    np.testing.assert_allclose(est.noise_variance, res.sum(axis=0) / (len(Y) - lev), rtol=1e-6)
    assert np.isclose(lev.sum(), 15)


def test_weighted_least_squares_noise_free_data_is_exact(mit):
    wls = WeightedLeastSquares(15, 3)
    wls.add(mit['Yb'], mit['Yb'] @ mit['beta'])
    est = wls.solve()
    np.testing.assert_allclose(est.theta, mit['beta'], rtol=1e-8, atol=1e-12)
    assert np.all(np.isfinite(est.covariance)) and np.all(np.isfinite(est.noise_variance))


# -- ridge regression -------------------------------------------------------------------------
def test_ridge_matches_closed_form_on_rank_deficient_data():
    rng = np.random.default_rng(6)
    Y = rng.normal(size=(80, 2, 9))
    Y[..., 8] = Y[..., 0] - 2 * Y[..., 3]  # rank 8
    Y[..., 5] = 0.0                        # rank 7
    tau = noisy(Y, rng.normal(size=9), 0.1, rng)
    d = 0.7
    ridge = RidgeRegression(9, 2, d)
    ridge.add(Y[:50], tau[:50])
    ridge.add(Y[50:], tau[50:])
    est = ridge.solve()
    A, b = Y.reshape(-1, 9), tau.ravel()
    G = np.linalg.inv(A.T @ A + d * np.eye(9))
    psi = G @ A.T @ b
    np.testing.assert_allclose(est.theta, psi, rtol=1e-9, atol=1e-12)
    assert est.theta[5] == pytest.approx(0.0, abs=1e-14)
    dof = len(b) - np.trace(G @ A.T @ A)
    s2 = np.sum((b - A @ psi) ** 2) / dof
    np.testing.assert_allclose(est.covariance, s2 * G @ A.T @ A @ G, rtol=1e-8, atol=1e-14)


def test_ridge_with_small_d_agrees_with_base_least_squares(mit):
    """An/Atkeson/Hollerbach: ridge on the full 30-parameter regressor with d << the smallest
    nonzero eigenvalue of K'K gives the base least-squares estimate on the identifiable part."""
    rng = np.random.default_rng(8)
    K, Yb = mit['K'], mit['Yb']
    tau = noisy(Yb, mit['beta'], 0.5, rng)
    ls = LeastSquares(15, 3)
    ls.add(Yb, tau)
    base = ls.solve()
    A = K.reshape(-1, 30)
    eig = np.linalg.eigvalsh(A.T @ A)
    lam_min = eig[-15]  # 15 nonzero eigenvalues
    assert eig[-16] < 1e-9 * lam_min
    for d, close in ((1e-6 * lam_min, True), (100 * lam_min, False)):
        ridge = RidgeRegression(30, 3, d)
        ridge.add(K, tau)
        psi = ridge.solve().theta
        diff = np.abs(mit['T'] @ psi - base.theta) / base.stddev
        pred = np.abs(K @ psi - Yb @ base.theta).max()
        if close:
            assert diff.max() < 1e-3
            assert pred < 1e-3 * 0.5
            # the unidentifiable parameters of link 1 (no column at all) stay at 0
            assert np.all(psi[:9] == 0.0)
        else:
            assert diff.max() > 1.0


# -- recursive least squares ------------------------------------------------------------------
def test_rls_without_forgetting_equals_least_squares(mit):
    rng = np.random.default_rng(9)
    Y = np.concatenate([mit['Yb']] * 20)
    tau = noisy(Y, mit['beta'], 0.5, rng)
    ls = LeastSquares(15, 3)
    ls.add(Y, tau)
    rls = RecursiveLeastSquares(15)
    cuts = [1, 7, 300, 301, 5000]  # includes a batch larger than one internal chunk
    for part_Y, part_tau in zip(np.split(Y, cuts), np.split(tau, cuts)):
        rls.update(part_Y, part_tau)
    ref = ls.solve()
    assert_estimates_equal(rls.estimate(), ref)
    assert_estimates_equal(rls.snapshot(), ref)
    np.testing.assert_allclose(rls.covariance, ref.covariance, rtol=1e-9,
                               atol=1e-9 * ref.covariance.max())
    np.testing.assert_allclose(rls.information, ls.information, rtol=1e-9,
                               atol=1e-9 * np.abs(ls.information).max())
    np.testing.assert_allclose(rls.residual_rms,
                               np.sqrt(np.mean((tau - Y @ ref.theta) ** 2, axis=0)), rtol=1e-9)
    assert rls.num_samples == len(Y) and rls.rank == 15


def test_rls_batch_forgetting_equals_exponentially_weighted_least_squares(mit):
    """One vectorised batch == sample-by-sample updates == lstsq with weights lam^(N-1-k)."""
    rng = np.random.default_rng(10)
    Y = mit['Yb'][:200]
    tau = noisy(Y, mit['beta'], 0.5, rng)
    lam = 0.98
    batch = RecursiveLeastSquares(15, lam, min_information=0.0)
    batch.update(Y[:20], tau[:20])
    batch.update(Y[20:], tau[20:])
    single = RecursiveLeastSquares(15, lam, min_information=0.0)
    for k in range(len(Y)):
        single.update(Y[k], tau[k])
    w = np.sqrt(lam ** np.arange(len(Y) - 1, -1, -1))
    A = (w[:, None, None] * Y).reshape(-1, 15)
    theta = np.linalg.lstsq(A, (w[:, None] * tau).ravel(), rcond=None)[0]
    np.testing.assert_allclose(batch.theta, theta, rtol=1e-8)
    np.testing.assert_allclose(single.theta, theta, rtol=1e-8)
    np.testing.assert_allclose(batch.information, A.T @ A, rtol=1e-9,
                               atol=1e-10 * np.abs(A.T @ A).max())
    rms = np.sqrt(np.sum(w[:, None] ** 2 * (tau - Y @ theta) ** 2, axis=0) / np.sum(w ** 2))
    np.testing.assert_allclose(batch.residual_rms, rms, rtol=1e-8)
    # a batch longer than the internal QR chunk, after some earlier data
    lam = 0.9995
    Y = np.concatenate([mit['Yb']] * 20)
    tau = noisy(Y, mit['beta'], 0.5, rng)
    rls = RecursiveLeastSquares(15, lam, min_information=0.0)
    rls.update(Y[:1000], tau[:1000])
    rls.update(Y[1000:], tau[1000:])
    w = np.sqrt(lam ** np.arange(len(Y) - 1, -1, -1))
    A = (w[:, None, None] * Y).reshape(-1, 15)
    theta = np.linalg.lstsq(A, (w[:, None] * tau).ravel(), rcond=None)[0]
    np.testing.assert_allclose(rls.theta, theta, rtol=1e-8)


def test_rls_weights_equal_scaled_rows(mit):
    rng = np.random.default_rng(11)
    Y = mit['Yb']
    sigma = np.array([0.1, 1.0, 3.0])
    tau = noisy(Y, mit['beta'], sigma, rng)
    rls = RecursiveLeastSquares(15)
    rls.update(Y, tau, weights=1 / sigma ** 2)
    s = 1 / sigma
    A = (Y * s[None, :, None]).reshape(-1, 15)
    theta = np.linalg.lstsq(A, (tau * s).ravel(), rcond=None)[0]
    np.testing.assert_allclose(rls.theta, theta, rtol=1e-9)
    # with inverse-variance weights the weighted residuals have unit variance
    assert 0.85 < rls.noise_variance < 1.15
    lo, hi = chi2_bounds(1, 15, 1e-3)
    assert lo < nees(rls.theta - mit['beta'], rls.covariance) < hi


def test_rls_forgetting_tracks_a_parameter_step(mit):
    rng = np.random.default_rng(12)
    Y = np.concatenate([mit['Yb']] * 10)
    beta1 = mit['beta']
    beta2 = beta1 * (1 + 0.3 * rng.choice([-1, 1], size=15))
    tracking, plain = RecursiveLeastSquares(15, 0.99), RecursiveLeastSquares(15, 1.0)
    for beta in (beta1, beta2):
        for k in range(0, len(Y), 500):
            tau = noisy(Y[k:k + 500], beta, 0.5, rng)
            tracking.update(Y[k:k + 500], tau)
            plain.update(Y[k:k + 500], tau)
    est = tracking.estimate()
    np.testing.assert_array_less(np.abs(est.theta - beta2), 4 * est.stddev)
    assert np.all(np.isfinite(est.stddev))
    assert np.max(np.abs(plain.theta - beta2) / plain.stddev) > 20


def test_rls_before_excitation_is_minimum_norm_and_finite(mit):
    """Arm at rest (gravity only): rank deficient; theta is the column-scaled minimum-norm
    least-squares solution, finite; parameters not determined get infinite stddev."""
    robot, base = mit['robot'], mit['base']
    rng = np.random.default_rng(13)
    q = rng.uniform(-3, 3, size=(50, 3))
    Y = robot.regressor(q, np.zeros_like(q), np.zeros_like(q))[..., base]
    tau = noisy(Y, mit['beta'], 0.1, rng)
    rls = RecursiveLeastSquares(15)
    assert np.all(rls.theta == 0) and rls.rank == 0
    assert np.all(np.isinf(rls.stddev))
    rls.update(Y, tau)
    A, b = Y.reshape(-1, 15), tau.ravel()
    rank = np.linalg.matrix_rank(A)
    assert 0 < rls.rank == rank < 15
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1
    theta = np.linalg.lstsq(A / scale, b, rcond=None)[0] / scale
    np.testing.assert_allclose(rls.theta, theta, rtol=1e-7, atol=1e-9)
    est = rls.estimate()
    for field in ('theta', 'stddev', 'rel_stddev', 'noise_variance'):
        assert not np.any(np.isnan(getattr(est, field))), field
    assert not np.any(np.isnan(est.covariance))
    assert np.any(np.isinf(est.stddev)) and np.any(np.isfinite(est.stddev))
    # the determined combinations: gravity torques are predicted
    np.testing.assert_allclose(Y @ est.theta, Y @ mit['beta'], atol=0.1)
    rls.update(mit['Yb'], noisy(mit['Yb'], mit['beta'], 0.1, rng))
    assert rls.rank == 15 and np.all(np.isfinite(rls.stddev))


def test_rls_stabilised_forgetting_bounds_information_and_keeps_estimate(mit):
    robot, base = mit['robot'], mit['base']
    rng = np.random.default_rng(14)
    lam, m = 0.99, 1e-4
    rls = RecursiveLeastSquares(15, lam, min_information=m)
    unstabilised = RecursiveLeastSquares(15, lam, min_information=0.0)
    Y = np.concatenate([mit['Yb']] * 5)
    for r in (rls, unstabilised):
        r.update(Y, noisy(Y, mit['beta'], 0.5, rng))
    before = rls.estimate()
    q = np.tile([0.3, -0.5, 1.0], (10000, 1))  # at rest: gravity rows of one posture only
    Yr = robot.regressor(q, np.zeros_like(q), np.zeros_like(q))[..., base]
    for k in range(0, 10000, 1000):
        tau = noisy(Yr[k:k + 1000], mit['beta'], 0.5, rng)
        for r in (rls, unstabilised):
            r.update(Yr[k:k + 1000], tau)
        total = rls.num_samples
        assert rls.min_eigenvalue >= (1 - lam ** total) * m * (1 - 1e-9)
        cov = rls.covariance
        np.linalg.cholesky(cov)
        # covariance bounded by sigma^2 / min information
        bound = rls.noise_variance / ((1 - lam ** total) * m)
        assert np.linalg.eigvalsh(cov).max() <= bound * (1 + 1e-9)
    # unexcited directions stay where the exciting data put them
    np.testing.assert_array_less(np.abs(rls.theta - mit['beta']), 4 * before.stddev)
    # plain exponential forgetting loses them: information underflows, rank drops, drift
    assert unstabilised.rank < 15
    assert np.max(np.abs(unstabilised.theta - mit['beta']) / before.stddev) > 10
    assert not np.any(np.isnan(unstabilised.estimate().covariance))


def test_rls_reset_and_num_joints():
    rng = np.random.default_rng(15)
    Y = rng.normal(size=(40, 2, 5))
    tau = Y @ np.arange(1.0, 6.0)
    rls = RecursiveLeastSquares(5, 0.95)
    assert rls.num_joints is None and rls.residual_rms.shape == (0,)
    rls.update(Y, tau)
    assert rls.num_joints == 2
    np.testing.assert_allclose(rls.theta, np.arange(1.0, 6.0), rtol=1e-6)
    rls.reset()
    assert rls.num_samples == 0 and np.all(rls.theta == 0) and rls.num_joints == 2
    with pytest.raises(IdentificationError, match='expected'):
        rls.update(rng.normal(size=(4, 3, 5)), np.zeros((4, 3)))


def test_rls_prior():
    theta0 = np.array([1.0, -2.0, 3.0])
    rls = RecursiveLeastSquares(3, prior_information=np.diag([4.0, 4.0, 4.0]), theta0=theta0)
    np.testing.assert_allclose(rls.theta, theta0)
    np.testing.assert_allclose(rls.information, 4 * np.eye(3))
    Y = np.array([[[1.0, 0.0, 0.0]]])
    rls.update(Y, np.array([[5.0]]))
    # (4 * 1 + 1 * 5) / (4 + 1) for the observed parameter, others unchanged
    np.testing.assert_allclose(rls.theta, [9 / 5, -2.0, 3.0])


# -- errors -----------------------------------------------------------------------------------
def test_errors_for_bad_input(mit):
    ls = LeastSquares(15, 3)
    with pytest.raises(IdentificationError, match='no samples'):
        ls.solve()
    ls.add(mit['Yb'][:4], mit['Yb'][:4] @ mit['beta'])
    with pytest.raises(IdentificationError, match=r'not enough excitation: .*\(rank 12 < 15\)'):
        ls.solve()
    full = LeastSquares(30, 3)
    full.add(mit['K'], mit['K'] @ mit['robot'].phi_model)
    with pytest.raises(IdentificationError, match=r'not enough excitation: .*\(rank 15 < 30\)'):
        full.solve()
    exact = LeastSquares(15, 3)
    exact.add(mit['Yb'][:5], mit['Yb'][:5] @ mit['beta'])
    with pytest.raises(IdentificationError, match='not enough samples'):
        exact.solve()
    Y, tau = mit['Yb'][:10].copy(), mit['Yb'][:10] @ mit['beta']
    Y[6, 1, 2] = np.nan
    for est in (LeastSquares(15, 3), WeightedLeastSquares(15, 3), RidgeRegression(15, 3, 1.0)):
        with pytest.raises(IdentificationError, match='NaN or inf .*sample 6'):
            est.add(Y, tau)
    tau[3, 0] = np.inf
    with pytest.raises(IdentificationError, match='torques contain'):
        RecursiveLeastSquares(15).update(mit['Yb'][:10], tau)
    with pytest.raises(IdentificationError, match='shape'):
        LeastSquares(15, 3).add(mit['Yb'][:10], tau[:9])
    with pytest.raises(IdentificationError, match='shape'):
        LeastSquares(14, 3).add(mit['Yb'][:10], tau)
    with pytest.raises(IdentificationError, match='numeric'):
        LeastSquares(2, 1).add([[['a', 'b']]], [[1.0]])
    with pytest.raises(IdentificationError, match='different size'):
        LeastSquares(15, 3).merge(LeastSquares(15, 2))
    for bad in (0.0, 1.5, np.nan, -0.1):
        with pytest.raises(IdentificationError, match='forgetting'):
            RecursiveLeastSquares(15, bad)
    with pytest.raises(IdentificationError, match='min_information'):
        RecursiveLeastSquares(3, 0.9, min_information=-1.0)
    with pytest.raises(IdentificationError, match='min_information'):
        RecursiveLeastSquares(3, 0.9, min_information=np.diag([1.0, -1.0, 1.0]))
    for bad in (0.0, -1.0, np.inf):
        with pytest.raises(IdentificationError, match='ridge'):
            RidgeRegression(3, 1, bad)
    with pytest.raises(IdentificationError, match='num_params'):
        LeastSquares(0, 3)
    with pytest.raises(IdentificationError, match='weights'):
        RecursiveLeastSquares(15).update(mit['Yb'][:10], mit['Yb'][:10] @ mit['beta'],
                                         weights=-np.ones(3))


def test_residual_statistics_for_any_theta_and_long_run_variance():
    from identification_node.estimation.residuals import MIN_BLOCKS, ResidualStatistics
    rng = np.random.default_rng(11)
    N, n, p, m = 60000, 2, 3, 9
    Y = rng.standard_normal((N, n, p))
    theta = np.array([1.0, -2.0, 0.5])
    # Residuals: white noise through a moving average of m samples (correlated, like a smoother)
    h = np.full(m, 1.0 / m)
    white = rng.standard_normal((N + m - 1, n))
    e = np.stack([np.convolve(white[:, j], h, mode='valid') for j in range(n)], axis=1)
    tau = Y @ theta + e
    stats = ResidualStatistics(p, n, block=8 * m)
    for start in range(0, N, 777):   # uneven chunks: blocks straddle them
        stats.add(Y[start:start + 777], tau[start:start + 777])
    other = rng.standard_normal(p)
    np.testing.assert_allclose(stats.rss(other), ((tau - Y @ other) ** 2).sum(axis=0),
                               rtol=1e-9)
    assert stats.blocks == N // (8 * m)
    # Sample variance sigma^2 sum(h^2) = 1/m; long-run variance sigma^2 (sum h)^2 = 1.
    np.testing.assert_allclose(stats.variance(theta), 1.0 / m, rtol=0.03)
    np.testing.assert_allclose(stats.long_run_variance(theta), 1.0, rtol=0.2)
    direct = 100 * np.linalg.norm(e, axis=0) / np.linalg.norm(tau, axis=0)
    np.testing.assert_allclose(stats.relative_error(theta), direct, rtol=1e-6)
    # The noise level: the larger of the white raw noise (variance times the smoother's
    # 1 / gain, here m) and the long-run variance; white alone before MIN_BLOCKS blocks.
    long_run, var = stats.long_run_variance(theta), stats.variance(theta)
    for white_scale in (m / 4, m, 4 * m):
        np.testing.assert_allclose(stats.noise_variance(theta, white_scale),
                                   np.fmax(var * white_scale, long_run), rtol=1e-12)
    np.testing.assert_allclose(stats.noise_variance(theta, 4 * m), 4.0, rtol=0.05)
    np.testing.assert_allclose(stats.noise_variance(theta, m / 4), 1.0, rtol=0.2)
    few = ResidualStatistics(p, n, block=8 * m)
    few.add(Y[:8 * m * (MIN_BLOCKS - 1)], tau[:8 * m * (MIN_BLOCKS - 1)])
    np.testing.assert_allclose(few.noise_variance(theta, m / 4),
                               few.variance(theta) * m / 4, rtol=1e-12)


# -- RLS update paths: information form (Cholesky) and QR --------------------------------------
def _count_qr(monkeypatch):
    import identification_node.estimation.rls as est
    calls = []
    qr = est.qr_r
    monkeypatch.setattr(est, 'qr_r', lambda a: calls.append(a.shape) or qr(a))
    return calls


@pytest.mark.parametrize('lam', [1.0, 0.995])
def test_rls_information_form_equals_qr_update_when_well_conditioned(mit, monkeypatch, lam):
    import identification_node.estimation.rls as est
    rng = np.random.default_rng(31)
    Y = np.concatenate([mit['Yb']] * 4)
    tau = noisy(Y, mit['beta'], 0.5, rng)
    w = rng.uniform(0.5, 2.0, size=tau.shape) * (rng.random(tau.shape) > 0.1)
    runs = {}
    for name, limit in (('information', est._INFORMATION_MAX_CONDITION), ('qr', 0.0)):
        monkeypatch.setattr(est, '_INFORMATION_MAX_CONDITION', limit)
        rls = RecursiveLeastSquares(15, lam)
        rls.update(Y[:300], tau[:300], w[:300])  # excites every direction
        calls = _count_qr(monkeypatch)
        for k in range(300, len(Y), 150):
            rls.update(Y[k:k + 150], tau[k:k + 150], w[k:k + 150])
        runs[name] = (rls, len(calls))
        monkeypatch.undo()
    (info, info_qr), (qr, qr_qr) = runs['information'], runs['qr']
    assert info_qr == 0 and qr_qr > 0
    np.testing.assert_allclose(info.theta, qr.theta, rtol=1e-9, atol=1e-9 * np.abs(qr.theta).max())
    for attr in ('covariance', 'information', 'data_information'):
        a, b = getattr(info, attr), getattr(qr, attr)
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.abs(b).max())
    np.testing.assert_allclose(info.residual_rms, qr.residual_rms, rtol=1e-9)
    assert_estimates_equal(info.estimate(), qr.estimate())
    if lam == 1.0:  # and both are the weighted batch least squares
        s = np.sqrt(w)
        A = (Y * s[..., None]).reshape(-1, 15)
        theta = np.linalg.lstsq(A, (tau * s).ravel(), rcond=None)[0]
        np.testing.assert_allclose(info.theta, theta, rtol=1e-9)


def test_rls_ill_conditioned_information_falls_back_to_qr(monkeypatch):
    """Two nearly equal columns: forming A'A would square a condition number of ~1e7 (normal
    equations lose ~all digits of that direction); the update must take the QR path and stay
    as accurate as batch least squares by QR."""
    rng = np.random.default_rng(32)
    N, n, p = 2000, 2, 4
    Y = rng.standard_normal((N, n, p))
    Y[:, :, 3] = Y[:, :, 2] + 1e-7 * rng.standard_normal((N, n))
    theta = np.array([1.0, -2.0, 3.0, 0.5])
    tau = Y @ theta + 1e-9 * rng.standard_normal((N, n))
    rls = RecursiveLeastSquares(p)
    rls.update(Y[:500], tau[:500])
    calls = _count_qr(monkeypatch)
    for k in range(500, N, 500):
        rls.update(Y[k:k + 500], tau[k:k + 500])
    assert calls  # the QR update ran
    A, b = Y.reshape(-1, p), tau.ravel()
    ref = np.linalg.lstsq(A, b, rcond=None)[0]
    normal = np.linalg.solve(A.T @ A, A.T @ b)
    assert np.abs(normal - ref).max() > 1e3 * np.abs(rls.theta - ref).max()
    np.testing.assert_allclose(rls.theta, ref, rtol=1e-6)


def test_rls_not_yet_excited_uses_qr_then_information_form(mit, monkeypatch):
    """Rank-deficient information (one sample) cannot be Cholesky-factored: QR; once the data
    excite every direction the cheap update takes over."""
    rng = np.random.default_rng(33)
    tau = noisy(mit['Yb'], mit['beta'], 0.5, rng)
    rls = RecursiveLeastSquares(15)
    calls = _count_qr(monkeypatch)
    rls.update(mit['Yb'][:1], tau[:1])
    assert calls and rls.rank < 15
    rls.update(mit['Yb'][1:200], tau[1:200])
    calls.clear()
    rls.update(mit['Yb'][200:], tau[200:])
    assert not calls and rls.rank == 15
