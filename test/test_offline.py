"""Offline (batch) identification: periodic averaging, zero-phase filtering, weighted least
squares on masked equations, and validation on held-out bags."""
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from identification_node.bags.reader import iter_joint_states, open_bag
from identification_node.bags.writer import BagWriter
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.estimation.batch import weighted_solve
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.batch import rows as batch
from identification_node.pipeline.signals import half_window_for_cutoff
from identification_node.batch.rows import BatchOptions, fourier_fit
from identification_node.batch.samples import BagSamples, Stream, read_samples
from identification_node.batch.solve import identify_samples, offline_identify
from identification_node.replay.stream import identify_bag
from identification_node.pipeline.signals import central_derivatives, zero_phase_lowpass
from identification_node.settings import Settings, read_parameter_file
from test_bags import BAGS, true_base_parameters
from identification_node.replay.validation import bag_error
from identification_node.replay.stream import replay_identify
from identification_node.replay.validation import evaluation_settings

REPO = Path(__file__).resolve().parents[1]
NOISE = np.array([0.8, 0.4, 0.2])      # N m, per joint of the MIT arm


def config_settings(config):
    return Settings.from_dict(read_parameter_file(REPO / 'config' / config))


@pytest.fixture(scope='module')
def mit():
    return load_robot('mit_dd_arm')


@pytest.fixture(scope='module')
def mit_settings():
    return Settings.from_dict({'robot': 'mit_dd_arm'})


def true_base(bag, names):
    return true_base_parameters(Path(bag).name, names)


def simulate(robot, trajectory, duration, rate=1000.0, seed=0, phi=None, noise=NOISE):
    """Perfectly tracked motion with encoder quantisation, velocity noise and per-joint torque
    noise: (t, q, qd, tau)."""
    t = np.arange(int(round(duration * rate))) / rate
    sim = simulate_kinematic(robot, phi, trajectory, t,
                             SensorNoise(encoder_counts=65536, velocity_std=0.001), seed=seed)
    rng = np.random.default_rng(seed + 1000)
    return t, sim.q_meas, sim.qd_meas, sim.tau + noise * rng.standard_normal(sim.tau.shape)


def write_bag(path, robot, t, q, qd, tau, description=True, names=None):
    with BagWriter(path) as bag:
        if description:
            bag.write_string('/robot_description', 0, robot.description)
        for k in range(len(t)):
            ns = int(round(t[k] * 1e9))
            bag.write_joint_state('/joint_states', ns, ns * 1e-9, names or robot.joint_names,
                                  q[k], qd[k], tau[k])
    return path


def samples_of(t, q, qd, tau):
    return BagSamples('sim', [Stream(np.round(t * 1e9).astype(np.int64), q, qd, tau)],
                      len(t), {}, True)


# -- the bundled bags -----------------------------------------------------------------------------
@pytest.mark.parametrize('bag', sorted(BAGS))
def test_batch_identification_of_the_bundled_bags_recovers_the_truth(bag):
    s = config_settings(BAGS[bag])
    ident = offline_identify(REPO / 'bags' / bag, s, s.load_robot())
    z = (ident.theta - true_base(REPO / 'bags' / bag, ident.base.names)) / ident.stddev
    # 15 to 48 parameters: 4 sigma each keeps the family-wise false alarm rate below 0.5 %.
    assert np.all(np.abs(z) < 4), dict(zip(ident.base.names, z.round(2)))
    assert np.sqrt(np.mean(z ** 2)) < 2.0
    assert ident.method == 'batch' and ident.processing == 'filtered'
    assert ident.converged and not ident.rejected
    assert ident.details['rate_hz'] == [1000.0]
    # the cut-off chosen from the bag's first 5 s of motion, the decimation following it
    assert ident.details['cutoff_source'] == 'automatic'
    assert ident.details['decimation'] == [int(1000.0 / (2 * ident.details['cutoff_hz']))]
    assert ident.history[-1].num_samples == ident.num_samples
    if 'fc' in ident.robot.extras:   # velocity reversals of the CRS arm are left out
        assert ident.details['excluded_equations'] > 0
        assert sum(ident.details['excluded_per_joint'].values()) == \
            ident.details['excluded_equations']
    assert ident.warnings == []      # a right model flags no missing term


def test_read_samples_are_the_bags_joint_states():
    s = config_settings('crs_a465.yaml')
    robot = s.load_robot()
    bag = REPO / 'bags' / 'crs_a465_fourier'
    samples = read_samples(bag, s, robot)
    with open_bag(bag) as reader:
        recs = [r for _, _, r in iter_joint_states(reader, ['/joint_states'])]
    idx = [list(recs[0].names).index(j) for j in robot.joint_names]
    (stream,) = samples.streams
    np.testing.assert_array_equal(stream.stamps_ns, [r.stamp_ns for r in recs])
    np.testing.assert_array_equal(stream.q, [r.position[idx] for r in recs])
    np.testing.assert_array_equal(stream.qd, [r.velocity[idx] for r in recs])
    np.testing.assert_array_equal(stream.tau, [r.effort[idx] for r in recs])
    assert samples.velocity_measured and samples.messages == len(recs)


# -- weighted least squares -----------------------------------------------------------------------
def random_problem(seed, N=400, n=3, p=6):
    rng = np.random.default_rng(seed)
    Y = rng.standard_normal((N, n, p))
    theta = rng.standard_normal(p)
    tau = Y @ theta + np.array([0.1, 1.0, 3.0])[:n] * rng.standard_normal((N, n))
    return Y, tau


def test_weighted_solve_leaves_masked_equations_out():
    # Reference: feasible GLS on the stacked equations that remain, written out directly.
    Y, tau = random_problem(1)
    mask = np.random.default_rng(2).random(tau.shape) > 0.3
    stats = ResidualStatistics(6, 3, 8)
    stats.add(Y * mask[..., None], tau * mask)
    fit = weighted_solve(NormalEquations(stats.normal_equations().augmented, mask.sum(axis=0)))
    w = np.ones(3)
    for _ in range(50):
        rows = [(Y[mask[:, j], j] * np.sqrt(w[j]), tau[mask[:, j], j] * np.sqrt(w[j]))
                for j in range(3)]
        A = np.vstack([r[0] for r in rows])
        theta = np.linalg.lstsq(A, np.concatenate([r[1] for r in rows]), rcond=None)[0]
        P = np.linalg.inv(A.T @ A)
        lev = [np.trace(P @ (r[0].T @ r[0])) for r in rows]
        rss = [np.sum((tau[mask[:, j], j] - Y[mask[:, j], j] @ theta) ** 2) for j in range(3)]
        w = 1.0 / (np.array(rss) / (mask.sum(axis=0) - np.array(lev)))
    np.testing.assert_allclose(fit.theta, theta, rtol=1e-8)
    np.testing.assert_allclose(fit.covariance, P, rtol=1e-6)
    np.testing.assert_allclose(fit.noise_variance, 1.0 / w, rtol=1e-6)


def test_weighted_solve_refuses_unexcited_data():
    Y, tau = random_problem(3)
    Y[..., 5] = Y[..., 4]        # two parameters the data cannot tell apart
    stats = ResidualStatistics(6, 3, 8)
    stats.add(Y, tau)
    with pytest.raises(IdentificationError, match='excitation'):
        weighted_solve(stats.normal_equations())


# -- periodic averaging ---------------------------------------------------------------------------
def test_fourier_fit_gives_the_analytic_derivatives(mit):
    traj = FourierTrajectory.random(mit, harmonics=5, period=2.0, seed=4)
    t = np.arange(1000) * 2.0 / 1000
    q, qd, qdd = traj.sample(t)
    quantum = 2 * np.pi / 65536
    value, first, second, used = fourier_fit(quantum * np.round(q / quantum), 2.0, 40)
    assert used.tolist() == [5, 5, 5]      # the quantisation noise harmonics are left out
    np.testing.assert_allclose(value, q, atol=3e-5)
    np.testing.assert_allclose(first, qd, atol=3e-4 * np.abs(qd).max())
    np.testing.assert_allclose(second, qdd, atol=3e-3 * np.abs(qdd).max())
    exact = fourier_fit(q, 2.0, 40, harmonics=7)
    assert exact[3].tolist() == [7, 7, 7]
    for got, want in zip(exact[:3], (q, qd, qdd)):
        np.testing.assert_allclose(got, want, atol=1e-9 * np.abs(want).max())


@pytest.fixture(scope='module')
def periodic_bag(tmp_path_factory, mit):
    """Six whole periods of a 2 s Fourier excitation at 500 Hz, with the trajectory file."""
    traj = FourierTrajectory.random(mit, period=2.0, seed=3)
    t, q, qd, tau = simulate(mit, traj, 12.0, rate=500.0, seed=5)
    path = tmp_path_factory.mktemp('periodic')
    (path / 'traj.yaml').write_text(yaml.safe_dump(traj.to_dict()))
    return write_bag(path / 'bag', mit, t, q, qd, tau)


def test_periodic_averaging_recovers_noise_variances_and_parameters(periodic_bag, mit,
                                                                    mit_settings):
    ident = offline_identify(periodic_bag, mit_settings, mit, BatchOptions(period=2.0))
    d = ident.details
    assert ident.processing == 'periodic'
    assert (d['periods'], d['bins'], d['samples_averaged']) == (6, 1000, 6000)
    assert d['harmonics'] == [5, 5, 5]
    # 1000 bins x 5 degrees of freedom: the noise std is known to about 1 %.
    np.testing.assert_allclose(d['torque_noise_std'], NOISE, rtol=0.05)
    np.testing.assert_allclose(ident.noise_variance, NOISE ** 2 / 6, rtol=0.1)
    assert 0.85 < d['fit_ratio'] < 1.15
    z = (ident.theta - ident.base.to_base(mit.phi_model)) / ident.stddev
    assert np.all(np.abs(z) < 4) and np.sqrt(np.mean(z ** 2)) < 2
    # The history averages the first 2, 3, ... periods; the stddev shrinks with them.
    assert [c.num_samples for c in ident.history] == [2000, 3000, 4000, 5000, 6000]
    assert np.all(ident.history[0].stddev > ident.history[-1].stddev)


def test_the_trajectory_file_gives_the_period(periodic_bag, capsys):
    traj = str(periodic_bag.parent / 'traj.yaml')
    assert main(['identify', str(periodic_bag), '--robot', 'mit_dd_arm', '--trajectory', traj,
                 '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['method'] == 'batch' and doc['processing']['processing'] == 'periodic'
    assert doc['processing']['period_s'] == 2.0 and doc['processing']['periods'] == 6
    assert main(['identify', str(periodic_bag), '--robot', 'mit_dd_arm', '--trajectory', traj,
                 '--period', '3']) == 2
    assert '--period 3.0 s differs' in capsys.readouterr().err


def test_periodic_averaging_needs_two_periods(periodic_bag, mit, mit_settings):
    with pytest.raises(IdentificationError, match='need at least 2'):
        offline_identify(periodic_bag, mit_settings, mit, BatchOptions(period=7.0))


@pytest.mark.slow
@pytest.mark.parametrize('options, period', [(BatchOptions(), 4.0),
                                             (BatchOptions(period=2.0), 2.0)])
def test_the_covariance_is_honest_over_noise_realisations(mit, mit_settings, options, period):
    # 20 noise realisations of one motion: the spread of the estimates matches the reported
    # standard deviations (mean z^2 = 1; a covariance off by 2x in variance fails).
    traj = FourierTrajectory.random(mit, period=period, seed=3)
    t = np.arange(4000) / 1000.0
    sim = simulate_kinematic(mit, None, traj, t, SensorNoise(encoder_counts=65536), seed=0)
    base = mit_settings.build(mit).base
    true = base.to_base(mit.phi_model)
    zs = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        qd = sim.qd + 0.001 * rng.standard_normal(sim.qd.shape)
        tau = sim.tau + NOISE * rng.standard_normal(sim.tau.shape)
        ident = identify_samples(samples_of(t, sim.q_meas, qd, tau), mit_settings, mit, base,
                                 options)
        zs.append((ident.theta - true) / ident.stddev)
    assert 0.5 < np.mean(np.square(zs)) < 2.0, np.mean(np.square(zs), axis=0)


# -- zero-phase filtering -------------------------------------------------------------------------
def test_filtered_rows_are_the_parallel_filtered_regressor(mit, mit_settings, monkeypatch):
    # Independent: filter the whole segment at once (no chunks) and pick the rows.
    traj = FourierTrajectory.random(mit, period=4.0, seed=1)
    t, q, qd, tau = simulate(mit, traj, 3.0)
    base = mit_settings.build(mit).base
    monkeypatch.setattr(batch, 'CHUNK', 300)       # many chunks with overlaps
    info, rows = batch.batch_rows(samples_of(t, q, qd, tau), mit_settings, mit, base,
                                  BatchOptions(cutoff=15.0, decimation=10))
    rows = list(rows)
    assert len(rows) > 5 and info['rows'] == sum(len(r) for r in rows)
    stamps = np.concatenate([r.stamps_ns for r in rows])
    got_Y = np.concatenate([r.regressor for r in rows])
    got_tau = np.concatenate([r.tau for r in rows])
    qf = zero_phase_lowpass(q, 1000.0, 15.0)
    qdf = zero_phase_lowpass(qd, 1000.0, 15.0)
    qddf = central_derivatives(t, qdf)[0]
    Yb = base.base_regressor(mit.regressor(qf, qdf, qddf))
    Yf = zero_phase_lowpass(Yb.reshape(len(t), -1), 1000.0, 15.0).reshape(Yb.shape)
    trim = int(np.ceil(3 * 1000 / 15))
    picks = np.arange(trim, len(t) - trim, 10)
    np.testing.assert_array_equal(stamps, np.round(t[picks] * 1e9).astype(np.int64))
    scale = np.maximum(np.abs(Yf).max(axis=0), 1e-6 * np.abs(Yf).max())  # per column
    np.testing.assert_allclose(got_Y / scale, Yf[picks] / scale, atol=1e-8)
    np.testing.assert_allclose(got_tau, zero_phase_lowpass(tau, 1000.0, 15.0)[picks],
                               atol=1e-8 * np.abs(tau).max())


def test_gaps_split_segments_and_jitter_is_resampled(mit, mit_settings):
    traj = FourierTrajectory.random(mit, period=4.0, seed=1)
    t, q, qd, tau = simulate(mit, traj, 6.0, seed=2)
    rng = np.random.default_rng(0)
    t = t + rng.uniform(-5e-5, 5e-5, len(t))           # 5 % jitter
    keep = (t < 2.5) | (t > 2.7)                         # a 0.2 s gap
    ident = identify_samples(samples_of(t[keep], q[keep], qd[keep], tau[keep]), mit_settings,
                             mit, mit_settings.build(mit).base, BatchOptions())
    assert ident.details['segments'] == 2 and ident.details['resampled_segments'] == 2
    z = (ident.theta - ident.base.to_base(mit.phi_model)) / ident.stddev
    assert np.all(np.abs(z) < 4)


def test_bad_batch_options_give_clear_errors(periodic_bag, mit, mit_settings, capsys):
    with pytest.raises(IdentificationError, match='below half the sampling rate'):
        offline_identify(periodic_bag, mit_settings, mit, BatchOptions(cutoff=300.0))
    with pytest.raises(IdentificationError, match='alias'):
        offline_identify(periodic_bag, mit_settings, mit, BatchOptions(decimation=20))
    bag = str(periodic_bag)
    for args, words in ((['--method', 'rls', '--cutoff', '5'], 'only apply to --method batch'),
                        (['--harmonics', '3'], '--harmonics needs --period'),
                        (['--period', '-1'], 'period must be > 0')):
        assert main(['identify', bag, '--robot', 'mit_dd_arm'] + args) == 2
        assert words in capsys.readouterr().err


# -- validation on a held-out bag -----------------------------------------------------------------
@pytest.fixture(scope='module')
def validation_bags(tmp_path_factory, mit):
    """Training and test bags of the MIT arm, and a test bag of an arm whose true parameters
    differ from the model's (link 3 heavier, link 2 more inertia)."""
    path = tmp_path_factory.mktemp('validation')
    wrong = mit.phi_model.copy()
    for name, factor in (('link3.m', 1.3), ('link3.mz', 1.3), ('link2.Izz', 1.5),
                         ('link3.Izz', 1.4)):
        wrong[mit.param_index(name)] *= factor
    bags = {}
    for name, seed, phi in (('train', 1, None), ('test', 2, None), ('wrong', 2, wrong)):
        traj = FourierTrajectory.random(mit, period=4.0, seed=seed)
        bags[name] = write_bag(path / name, mit, *simulate(mit, traj, 4.0, seed=seed, phi=phi))
    return bags


@pytest.mark.parametrize('method', ['batch', 'rls'])
def test_validation_error_is_close_to_training_and_grows_with_wrong_parameters(
        validation_bags, mit, mit_settings, method):
    train = validation_bags['train']
    ident = (offline_identify(train, mit_settings, mit) if method == 'batch'
             else replay_identify(train, mit_settings, mit))
    trained = bag_error(ident, train, mit_settings, training=True).relative_error
    same = bag_error(ident, validation_bags['test'], mit_settings)
    wrong = bag_error(ident, validation_bags['wrong'], mit_settings)
    # every sample but the smoother's first and last half windows, whatever the method (the
    # smoother the fit used: the bag is processed as the training bag was)
    half = evaluation_settings(mit_settings, ident).build(mit).row_builder.half_window
    assert same.num_samples == 4000 - 2 * half
    # Another motion has other torques: the relative errors are alike, not equal ...
    assert np.all((same.relative_error > 0.4 * trained) & (same.relative_error < 2.5 * trained))
    # ... and as small as the truth's (the model's own parameters simulated the test bag).
    np.testing.assert_allclose(same.relative_error, same.errors['model'].per_joint, rtol=0.2)
    assert np.all(wrong.relative_error > 2 * same.relative_error), \
        (wrong.relative_error, same.relative_error)


def test_validate_cli_reports_the_held_out_error(validation_bags, mit, mit_settings, capsys):
    train, test = (str(validation_bags[k]) for k in ('train', 'test'))
    assert main(['identify', train, '--robot', 'mit_dd_arm', '--method', 'batch',
                 '--validate', test, '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    (v,) = doc['validation']
    # the smoother's edges: the smoother of the fit's cut-off (evaluation_settings)
    half = half_window_for_cutoff(doc['processing']['cutoff_hz'],
                                  doc['processing']['rate_hz'][0], 3)
    assert v['bag'] == test and v['num_samples'] == 4000 - 2 * half
    assert set(v['estimate']['per_joint']) == {'joint1', 'joint2', 'joint3'}
    assert all(0 < e < 10 for e in v['estimate']['per_joint'].values())
    # Validating on the training bag itself gives the training error exactly.
    assert main(['identify', train, '--robot', 'mit_dd_arm', '--method', 'batch',
                 '--validate', train, '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['validation'][0]['estimate'] == doc['training_error']['estimate']


def test_validation_bag_of_another_robot_is_refused(validation_bags, tmp_path, mit, capsys):
    train = str(validation_bags['train'])
    crs = str(REPO / 'bags' / 'crs_a465_fourier')   # has joint1..3 too, but is another arm
    assert main(['identify', train, '--robot', 'mit_dd_arm', '--validate', crs]) == 2
    err = capsys.readouterr().err
    assert 'validation bag' in err and 'another robot' in err and 'Traceback' not in err
    # Without a robot description: other joint names, no usable sample.
    t, q, qd, tau = simulate(mit, FourierTrajectory.random(mit, period=4.0), 0.5)
    other = write_bag(tmp_path / 'other', mit, t, q, qd, tau, description=False,
                      names=['a', 'b', 'c'])
    for method in ('rls', 'batch'):
        assert main(['identify', train, '--robot', 'mit_dd_arm', '--method', method,
                     '--validate', str(other)]) == 2
        err = capsys.readouterr().err
        assert err.startswith('error: validation bag') and 'missing_joints' in err


def test_rls_identification_matches_the_replay(validation_bags, mit, mit_settings):
    bag = validation_bags['train']
    ident = replay_identify(bag, mit_settings, mit)
    est = identify_bag(bag, mit_settings, mit).pipeline.estimate()
    np.testing.assert_array_equal(ident.theta, est.values)
    np.testing.assert_array_equal(ident.stddev, est.stddev)
    assert ident.num_samples == est.num_samples and ident.series is not None
