"""Excitation design: criteria, limits, the paper's initial guess and Table I, SLSQP results
checked on fine grids (torques by pinocchio's RNEA), a simulated identification, and the CLI."""
import math
import re

import numpy as np
import pytest
import yaml

from identification_node.bags.reader import BagReader, iter_messages
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.estimation.batch import LeastSquares
from identification_node.excitation.criteria import (CRITERIA, condition_number, criterion_value,
                                                     d_optimality)
from identification_node.excitation import design as ex
from identification_node.excitation.export import trajectory_to_joint_trajectory
from identification_node.excitation.framing import DEFAULT_PERIODS
from identification_node.excitation.initial_guess import (VERIFY_RATIO, fourier_basis,
                                                          initial_trajectory, least_squares_guess,
                                                          scale_to_limits, shrink_into_limits,
                                                          table1_trajectory, to_x)
from identification_node.excitation.limits import (LIMIT_KINDS, ExcitationLimits, limit_ratios,
                                                   load_limits)
from identification_node.excitation.problem import DesignProblem
from identification_node.excitation.sampled import SampledTrajectory
from identification_node.excitation.trajectories import (FourierTrajectory, FramedTrajectory,
                                                         load_trajectory)
from identification_node.excitation.trajectory_base import check_limits
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.wire.cdr import JOINT_TRAJECTORY

FINE = 20001  # kinematic check points over one period
FINE_TORQUE = 3001


@pytest.fixture(scope='module')
def crs():
    robot = load_robot('crs_a465')
    return robot, BaseParameters.from_robot(robot)


@pytest.fixture(scope='module')
def crs_results(crs):
    robot, base = crs
    return {c: ex.optimize_excitation(robot, 5, 10.0, c, base=base, maxiter=20)
            for c in CRITERIA}


def assert_within_limits(traj, robot, limits):
    """Every limit on a fine grid; torques from pinocchio's RNEA (not the regressor)."""
    t = np.linspace(0.0, traj.period, FINE)
    q, qd, qdd = traj.sample(t)
    lo, hi = limits.position_limits.T
    assert np.all(q >= lo) and np.all(q <= hi)
    assert np.all(np.abs(qd) <= limits.velocity_limits)
    assert np.all(np.abs(qdd) <= limits.acceleration_limits)
    k = np.linspace(0, FINE - 1, FINE_TORQUE).astype(int)
    tau = robot.rnea(q[k], qd[k], qdd[k])
    assert np.all(np.abs(tau) <= limits.effort_limits)
    assert check_limits(traj, limits, t)['position'] <= 1.0


# -- building blocks ---------------------------------------------------------------------------
def test_fourier_basis_matches_trajectory_sample():
    rng = np.random.default_rng(3)
    traj = FourierTrajectory(rng.normal(size=(2, 4)), rng.normal(size=(2, 4)), [0.3, -1.0], 3.0)
    t = rng.uniform(0, 7, 50)
    Bq, Bv, Ba = fourier_basis(t, 4, 3.0)
    X = to_x(traj).reshape(2, -1).T
    for B, ref in zip((Bq, Bv, Ba), traj.sample(t)):
        np.testing.assert_allclose(B @ X, ref, atol=1e-12)


def test_criteria_closed_form():
    rng = np.random.default_rng(0)
    U = np.linalg.qr(rng.normal(size=(40, 5)))[0]
    V = np.linalg.qr(rng.normal(size=(5, 5)))[0]
    s = np.array([9.0, 4.0, 2.0, 1.5, 0.5])
    W = U @ np.diag(s) @ V.T
    assert condition_number(W) == pytest.approx(18.0)
    assert d_optimality(W) == pytest.approx(-2 * np.log(s).sum())
    scaled = W / np.linalg.norm(W, axis=0)
    sv = np.linalg.svd(scaled, compute_uv=False)
    assert condition_number(W, scaled=True) == pytest.approx(sv[0] / sv[-1])
    # noise weights: information sum_j W_j'W_j / sigma_j^2
    Y = rng.normal(size=(30, 2, 4))
    sigma = np.array([0.5, 2.0])
    info = sum(Y[:, j].T @ Y[:, j] / sigma[j] ** 2 for j in range(2))
    assert d_optimality(Y, sigma) == pytest.approx(-np.linalg.slogdet(info)[1])
    assert condition_number(np.c_[W, np.zeros(40)]) == math.inf
    with pytest.raises(IdentificationError, match='noise_std'):
        d_optimality(Y, [1.0, -1.0])


@pytest.mark.parametrize('criterion', CRITERIA)
def test_design_gradients_match_finite_differences(mit, criterion):
    robot, base = mit
    limits = ExcitationLimits.from_robot(robot)
    design = DesignProblem(robot, base, limits, 3, 2.0, 40, criterion, [1.0, 2.0, 0.5], 1.0)
    x = to_x(initial_trajectory(robot, None, limits, 3, 2.0, 1))
    grad, J = design.gradient(x)
    cjac = design.constraint_jac(x)
    rng = np.random.default_rng(2)
    for _ in range(3):
        v, h = rng.normal(size=x.size), 1e-5
        (fp, tp), (fm, tm) = design.value(x + h * v), design.value(x - h * v)
        assert (fp - fm) / (2 * h) == pytest.approx(grad @ v, rel=1e-4, abs=1e-6)
        np.testing.assert_allclose((tp - tm) / (2 * h), J @ v, rtol=1e-4,
                                   atol=1e-4 * np.abs(J @ v).max())
        dc = (design.constraint(x + h * v) - design.constraint(x - h * v)) / (2 * h)
        np.testing.assert_allclose(dc, cjac @ v, atol=1e-5)


def test_least_squares_guess_solves_the_papers_normal_equations(crs):
    robot, _ = crs
    limits = ExcitationLimits.from_robot(robot)
    guess = least_squares_guess(limits, 5, 10.0, seed=4, num_points=100)
    # regenerate the random targets: A delta - qd is orthogonal to A's columns (eq. 8)
    rng = np.random.default_rng(4)
    t = np.arange(100) * 0.1
    target = rng.uniform(-1, 1, size=(100, 6)) * limits.velocity_limits
    _, qd, _ = guess.sample(t)
    A = fourier_basis(t, 5, 10.0)[1][:, :10]
    np.testing.assert_allclose(A.T @ (qd - target), 0.0, atol=1e-9)
    np.testing.assert_allclose(guess.q0, 0.0)  # centres of the symmetric ranges
    scaled = scale_to_limits(guess, limits, margin=0.9)
    per = check_limits(scaled, limits, np.linspace(0, 10, FINE))['per_joint']
    tightest = np.max([per['position'], per['velocity'], per['acceleration']], axis=0)
    np.testing.assert_allclose(tightest, 0.9, rtol=1e-4)  # found on a coarser grid


def test_table1_in_our_joint_zeros(crs):
    robot, base = crs
    limits = ExcitationLimits.from_robot(robot)
    paper = FourierTrajectory.crs_table1()
    ours = table1_trajectory(robot)
    np.testing.assert_allclose(ours.q0 - paper.q0, [0, -np.pi / 2, np.pi / 2, 0, 0, 0])
    np.testing.assert_array_equal(ours.a, paper.a)
    raw = check_limits(paper, limits)['per_joint']['position']
    assert raw[1] > 1 and raw[2] > 1  # the paper's zeros leave our joint 2 and 3 ranges
    assert_within_limits(ours, robot, limits)
    # its default accelerations (2 /s x velocity limit) hold Table I's peaks
    assert limit_ratios(ours, robot, limits)['acceleration'] < 1
    with pytest.raises(IdentificationError, match='6 joints'):
        table1_trajectory(load_robot('mit_dd_arm'))


def test_limits_file_and_overrides(crs, tmp_path):
    robot, _ = crs
    path = tmp_path / 'limits.yaml'
    path.write_text('joint2: {position: [-0.5, 0.8], velocity: 1.5}\n'
                    'joint3: {acceleration: 3.0, effort: .inf}\n')
    lim = load_limits(path, robot)
    np.testing.assert_allclose(lim.position_limits[1], [-0.5, 0.8])
    assert lim.velocity_limits[1] == 1.5 and lim.acceleration_limits[2] == 3.0
    assert lim.acceleration_limits[1] == pytest.approx(3.0)  # default: 2 /s x velocity
    assert lim.acceleration_limits[0] == pytest.approx(2 * np.pi)
    assert lim.effort_limits[2] == np.inf and lim.effort_limits[1] == 120.0
    assert np.all(np.isinf(ExcitationLimits.from_robot(robot, effort=False).effort_limits))
    for text, match in [('jointX: {velocity: 1}', 'unknown joint'),
                        ('joint1: {speed: 1}', 'unknown keys'),
                        ('joint1: {velocity: -1}', 'finite number > 0'),
                        ('joint1: {velocity: .inf}', 'finite number > 0'),
                        ('joint1: {position: [1, -1]}', 'lo < hi'),
                        ('joint1: {position: [-.inf, 1]}', 'both infinite'),
                        ('joint1: {position: [a, b]}', 'numeric'),
                        ('joint1: 3', 'mapping'), ('[1, 2]', 'mapping'),
                        ('joint1: {velocity: [1', 'limits file .* is not valid YAML')]:
        path.write_text(text)
        with pytest.raises(IdentificationError, match=match):
            load_limits(path, robot)


# -- optimisation --------------------------------------------------------------------------------
def test_mit_arm_optimisation(mit):
    robot, base = mit
    tight = {'joint1': {'effort': 120.0}, 'joint2': {'position': [-1.0, 1.5]}}
    limits = ExcitationLimits.from_robot(robot).updated(tight)
    for criterion in CRITERIA:
        res = ex.optimize_excitation(robot, 3, 2.0, criterion, limits, base=base, maxiter=30,
                                     num_samples=60)
        assert res.improved and res.value < res.initial_value
        assert res.trajectory.harmonics == 3 and res.trajectory.period == 2.0
        assert res.trajectory.joint_names == robot.joint_names
        assert_within_limits(res.trajectory, robot, limits)
        assert_within_limits(res.initial, robot, limits)
        assert res.value == pytest.approx(
            criterion_value(robot, res.trajectory, criterion, base, 60))
        assert max(res.ratios[k] for k in LIMIT_KINDS) <= VERIFY_RATIO


@pytest.mark.parametrize('criterion', CRITERIA)
def test_crs_beats_initial_and_table1(crs, crs_results, criterion):
    robot, base = crs
    res = crs_results[criterion]
    limits = ExcitationLimits.from_robot(robot)
    assert_within_limits(res.trajectory, robot, limits)
    table1 = criterion_value(robot, table1_trajectory(robot), criterion, base)
    assert res.value < res.initial_value
    assert res.value < table1
    # the same with many more samples than the optimiser saw
    more = criterion_value(robot, res.trajectory, criterion, base, 400)
    assert more < criterion_value(robot, table1_trajectory(robot), criterion, base, 400)


def test_crs_from_table1(crs):
    robot, base = crs
    res = ex.optimize_excitation(robot, criterion='cond', base=base, maxiter=10,
                                 initial='table1', margin=0.0)  # Table I fits, not with 10 %
    np.testing.assert_allclose(res.initial.a, FourierTrajectory.crs_table1().a)
    assert res.initial_value == pytest.approx(
        criterion_value(robot, table1_trajectory(robot), 'cond', base))
    assert res.value < res.initial_value
    assert_within_limits(res.trajectory, robot, ExcitationLimits.from_robot(robot))


@pytest.mark.slow
def test_shrink_into_tight_effort_limits(crs):
    robot, _ = crs
    limits = ExcitationLimits.from_robot(robot).updated({'joint2': {'effort': 25.0}})
    traj, scale, ratios = shrink_into_limits(table1_trajectory(robot), robot, limits)
    assert 0 < scale < 1 and ratios['effort'] <= VERIFY_RATIO
    assert_within_limits(traj, robot, limits)
    with pytest.raises(IdentificationError, match='effort') as info:
        shrink_into_limits(table1_trajectory(robot), robot,
                           limits.updated({'joint2': {'effort': 1e-3}}))
    # the joint whose static torque exceeds its limit is named, the others are not
    assert re.search(r'\(joint2 [0-9.e+]+ x the limit\); --no-effort', str(info.value))
    assert 'joint1' not in str(info.value) and 'joint3' not in str(info.value)


@pytest.mark.parametrize('criterion', CRITERIA)
def test_optimised_trajectory_identifies_better_than_random(crs, crs_results, criterion):
    """Simulated identification, same noise and sample count: the optimised excitation gives
    smaller standard deviations than a random Fourier trajectory inside the same limits."""
    robot, base = crs
    limits = ExcitationLimits.from_robot(robot)
    beta = base.to_base(robot.phi_model)
    big = np.abs(beta) > 1e-3 * np.abs(beta).max()
    random = shrink_into_limits(FourierTrajectory.random(limits, 5, 10.0, seed=1), robot,
                                limits)[0]
    t = np.arange(1000) * 0.01

    def identify(traj):
        sim = simulate_kinematic(robot, None, traj, t, SensorNoise(torque_std=0.5), seed=7)
        Y = base.base_regressor(robot.regressor(sim.q, sim.qd, sim.qdd))
        est = LeastSquares(base.num_base, robot.dof)
        est.add(Y, sim.tau_meas)
        e = est.solve()
        assert np.all(np.abs(e.theta - beta) < 6 * e.stddev)
        rel = e.stddev[big] / np.abs(beta[big])
        return np.exp(np.log(e.stddev).mean()), rel.max()

    opt_geo, opt_max = identify(crs_results[criterion].trajectory)
    rnd_geo, rnd_max = identify(random)
    assert opt_geo < 0.7 * rnd_geo
    assert opt_max < 0.5 * rnd_max


def test_joint_trajectory_message(mit):
    robot, _ = mit
    traj = FourierTrajectory.random(ExcitationLimits.from_robot(robot), 2, 1.0, seed=0)
    msg = trajectory_to_joint_trajectory(traj, rate=50.0, periods=2)
    assert list(msg.joint_names) == robot.joint_names and len(msg.points) == 101
    t = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points])
    np.testing.assert_allclose(t, np.arange(101) / 50.0, atol=1e-9)
    for p, q, qd, qdd in zip(msg.points, *traj.sample(t)):
        np.testing.assert_allclose(p.positions, q)
        np.testing.assert_allclose(p.velocities, qd)
        np.testing.assert_allclose(p.accelerations, qdd)


def test_bad_arguments(mit):
    robot, base = mit
    for kwargs, match in [({'harmonics': 0}, 'harmonics'), ({'period': -1.0}, 'period'),
                          ({'criterion': 'aopt'}, 'criterion'), ({'maxiter': -1}, 'maxiter'),
                          ({'initial': 'table1'}, '6 joints'), ({'initial': 'x'}, 'initial'),
                          ({'noise_std': [1.0]}, 'noise_std')]:
        with pytest.raises(IdentificationError, match=match):
            ex.optimize_excitation(robot, **{'base': base, 'maxiter': 1, **kwargs})


# -- command line ------------------------------------------------------------------------------
@pytest.mark.slow
def test_cli_writes_yaml_csv_and_bag(crs, tmp_path, capsys):
    robot, base = crs
    out, bag = tmp_path / 'exc' / 'crs.yaml', tmp_path / 'bag'
    limits = tmp_path / 'limits.yaml'
    limits.write_text('joint1: {position: [-0.6, 0.4], velocity: 1.0}\n')
    argv = ['excite', '--robot', 'crs_a465', '--maxiter', '10', '--criterion', 'dopt',
            '--limits', str(limits), '--out', str(out), '--bag', str(bag), '--rate', '20']
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert 'criterion dopt' in text and '->' in text and 'Table I' in text
    assert 'worst limit ratios' in text
    doc = yaml.safe_load(out.read_text())
    assert doc['robot'] == 'crs_a465' and doc['joints'] == robot.joint_names
    assert doc['criterion']['value'] < doc['criterion']['initial']
    assert doc['criterion']['value'] < doc['criterion']['table1']
    assert doc['limits']['joint1']['velocity'] == 1.0
    assert all(doc['limit_ratios'][k]['worst'] <= 1 for k in LIMIT_KINDS)
    framed = load_trajectory(str(out), robot)
    assert isinstance(framed, FramedTrajectory) and framed.periods == DEFAULT_PERIODS
    traj = framed.periodic
    assert isinstance(traj, FourierTrajectory) and traj.period == 10.0
    lim = load_limits(limits, robot)
    assert_within_limits(traj, robot, lim)
    assert doc['criterion']['value'] == pytest.approx(
        criterion_value(robot, traj, 'dopt', base))
    assert doc['durations'] == pytest.approx(framed.parts())
    # samples beside the YAML, ramps included (positions read back by SampledTrajectory)
    sampled = SampledTrajectory.from_csv(out.with_suffix('.csv'))
    assert sampled.joint_names == robot.joint_names
    assert sampled.duration == pytest.approx(framed.duration)
    np.testing.assert_allclose(sampled.q, framed.sample(sampled.t)[0], atol=1e-12)
    # the bag: the framed trajectory at 20 Hz
    with BagReader(bag) as reader:
        assert reader.topics == {'/excitation_trajectory': JOINT_TRAJECTORY}
        msgs = [m for *_, m in iter_messages(reader)]
    assert len(msgs) == 1 and len(msgs[0].points) == math.ceil(framed.duration * 20 - 1e-9) + 1
    traj = framed
    p = msgs[0].points[37]
    t = p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
    np.testing.assert_allclose(p.positions, traj.sample([t])[0][0], atol=1e-12)
    np.testing.assert_allclose(p.accelerations, traj.sample([t])[2][0], atol=1e-12)
    # existing outputs need --overwrite
    assert main(argv) == 2
    assert 'error:' in capsys.readouterr().err
    assert main(argv + ['--overwrite', '--maxiter', '1']) == 0


@pytest.mark.slow
def test_cli_initial_file_and_table1(tmp_path, capsys):
    first = tmp_path / 'a.yaml'
    assert main(['excite', '--robot', 'crs_a465', '--initial', 'table1', '--maxiter', '3',
                 '--out', str(first)]) == 0
    assert 'initial table1' in capsys.readouterr().out
    second = tmp_path / 'b.yml'
    assert main(['excite', '--robot', 'crs_a465', '--initial', str(first), '--maxiter', '3',
                 '--criterion', 'cond', '--out', str(second)]) == 0
    doc = yaml.safe_load(second.read_text())
    assert doc['harmonics'] == 5 and doc['period'] == 10.0
    assert doc['criterion']['initial'] == pytest.approx(
        criterion_value(load_robot('crs_a465'),
                        load_trajectory(str(first), load_robot('crs_a465')), 'cond'))


@pytest.mark.parametrize('extra, match', [
    (['--robot', 'no_such_robot'], 'unknown robot'),
    (['--robot', 'mit_dd_arm', '--harmonics', '0'], 'harmonics'),
    (['--robot', 'mit_dd_arm', '--period', '0'], 'period'),
    (['--robot', 'mit_dd_arm', '--limits', 'MISSING'], 'limits file'),
    (['--robot', 'mit_dd_arm', '--limits', 'BAD'], 'unknown joint'),
    (['--robot', 'mit_dd_arm', '--initial', 'table1'], '6 joints'),
    (['--robot', 'mit_dd_arm', '--initial', 'nope'], 'initial'),
    (['--robot', 'mit_dd_arm', '--noise-std', 'a,b'], 'noise-std'),
    (['--robot', 'mit_dd_arm', '--rate', '0'], 'rate'),
    (['--robot', 'mit_dd_arm', '--out-suffix'], 'yaml'),
])
def test_cli_bad_input(tmp_path, capsys, extra, match):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('elbow: {velocity: 1}\n')
    extra = [str(bad) if a == 'BAD' else str(tmp_path / 'missing.yaml') if a == 'MISSING'
             else a for a in extra]
    out = str(tmp_path / 'o.yaml')
    if '--out-suffix' in extra:
        extra.remove('--out-suffix')
        out = str(tmp_path / 'o.txt')
    assert main(['excite', *extra, '--maxiter', '1', '--out', out]) == 2
    err = capsys.readouterr().err
    assert err.startswith('error:') and match in err
    assert not (tmp_path / 'o.yaml').exists() and not (tmp_path / 'o.csv').exists()
