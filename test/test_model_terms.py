"""Friction on by default, missing model terms flagged, joints taken from the bag.

The simulated arms: perfectly tracked seeded Fourier excitations (simulate_kinematic) whose
torque carries a known joint friction (or none, or a spring the model lacks), with encoder
quantisation, velocity and torque noise; identified with the package's defaults."""
import json
import re

import numpy as np
import pytest

from identification_node.config import PARAMETERS
from identification_node.bags.writer import BagWriter
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.estimation.model_terms import (MIN_CORRELATION, ModelTermStatistics,
                                                        features, missing_term_warnings)
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.batch.solve import offline_identify
from identification_node.replay.stream import replay_identify
from identification_node.results.identification import exclusion_warnings
from identification_node.settings import Settings

FV = np.array([0.5, 0.3, 0.1])      # N m s/rad, per joint of the MIT arm
FC = np.array([1.0, 0.5, 0.2])      # N m
FO = np.array([0.2, -0.1, 0.05])    # N m
NOISE = np.array([0.4, 0.2, 0.1])   # N m, torque noise per joint
SPRING = 3.0                        # N m/rad on joint 1, a term the model lacks


@pytest.fixture(scope='module')
def arm():
    """The MIT arm's rigid bodies only (the truth adds its own joint torques)."""
    return load_robot('mit_dd_arm', extras=[])


def simulate(robot, seed, duration=8.0, friction=True, spring=0.0, rate=1000.0):
    """(t, q, qd, tau measured) and the truth (q, qd, qdd, tau) of one excitation."""
    traj = FourierTrajectory.random(robot, period=duration / 2, seed=seed)
    t = np.arange(int(round(duration * rate))) / rate
    sim = simulate_kinematic(robot, None, traj, t,
                             SensorNoise(encoder_counts=262144, velocity_std=0.001), seed=seed)
    tau = sim.tau.copy()
    if friction:
        tau += FV * sim.qd + FC * np.sign(sim.qd) + FO
    tau[:, 0] += spring * sim.q[:, 0]
    meas = tau + NOISE * np.random.default_rng(seed + 1000).standard_normal(tau.shape)
    return (t, sim.q_meas, sim.qd_meas, meas), (sim.q, sim.qd, sim.qdd, tau)


def write_bag(path, robot, t, q, qd, tau, names=None, description=None):
    with BagWriter(path) as bag:
        bag.write_string('/robot_description', 0, description or robot.description)
        for k in range(len(t)):
            ns = int(round(t[k] * 1e9))
            bag.write_joint_state('/joint_states', ns, ns * 1e-9, names or robot.joint_names,
                                  q[k], qd[k], tau[k])
    return path


def true_base(ident, arm, friction=True):
    """The base parameters of the simulated truth, in ident's parameter set."""
    per_joint = {'fv': FV, 'fc': FC, 'fo': FO} if friction else {}
    extra = [per_joint.get(e, np.zeros(3))[i] for i in range(3) for e in ident.robot.extras]
    return ident.base.to_base(np.concatenate([arm.phi_model, extra]))


def defaults(**given):
    return Settings.from_dict({'robot': 'mit_dd_arm', 'torque_source': ['measured'], **given})


@pytest.fixture(scope='module')
def bags(tmp_path_factory, arm):
    path = tmp_path_factory.mktemp('terms')
    out = {}
    for name, seed, kwargs in (('friction', 1, {}), ('none', 2, {'friction': False}),
                               ('spring', 3, {'spring': SPRING}), ('heldout', 4, {})):
        measured, truth = simulate(arm, seed, **kwargs)
        out[name] = write_bag(path / name, arm, *measured), truth
    return out


# -- the statistics against a direct computation ----------------------------------------------
def test_partial_correlations_are_those_of_the_residual_regression():
    # Reference: residualise r and each feature on the other features (and 1) by lstsq, then
    # np.corrcoef; the weighted variant by sqrt(w) on every row.
    rng = np.random.default_rng(0)
    N, n, b = 3000, 2, 4
    Yb = rng.standard_normal((N, n, b))
    q = rng.standard_normal((N, n)).cumsum(axis=0) * 0.05
    qd = np.gradient(q, axis=0) * 50 + 0.3 * rng.standard_normal((N, n))
    theta = rng.standard_normal(b)
    tau = Yb @ theta + 0.7 * np.sign(qd) + 0.2 * q + rng.standard_normal((N, n))
    stats = ModelTermStatistics(n, b + 1)
    rows = np.concatenate([Yb, tau[..., None]], axis=2)
    F = features(q, qd)
    for k in range(0, N, 700):   # in batches: the sums add
        stats.add(F[k:k + 700], rows[k:k + 700])
    est = theta + 0.1
    r = tau - Yb @ est
    partial, offset = stats.correlations(est, (r ** 2).sum(axis=0))
    for j in range(n):
        X = np.column_stack([np.sign(qd[:, j]), qd[:, j], q[:, j]])
        for k in range(3):
            others = np.column_stack([np.ones(N), np.delete(X, k, axis=1)])
            res = [y - others @ np.linalg.lstsq(others, y, rcond=None)[0]
                   for y in (X[:, k], r[:, j])]
            assert partial[j, k] == pytest.approx(np.corrcoef(*res)[0, 1], abs=1e-9)
        assert offset[j] == pytest.approx(r[:, j].mean() / np.sqrt((r[:, j] ** 2).mean()))
    assert np.all(stats.count == N)


def test_a_feature_that_does_not_vary_gives_no_correlation():
    stats = ModelTermStatistics(1, 2)
    qd = np.ones((500, 1))   # never reverses: sign(qd) is constant
    q = np.linspace(0, 1, 500)[:, None]
    rows = np.concatenate([np.ones((500, 1, 1)), (q + 0.1 * np.sin(50 * q))[..., None]], axis=2)
    stats.add(features(q, qd), rows)
    r, _ = stats.correlations(np.zeros(1), (rows[:, :, 1] ** 2).sum(axis=0))
    assert r[0, 0] == 0.0 and np.isfinite(r).all()
    assert missing_term_warnings(None, np.zeros(1), np.ones(1), ['j'], ()) == []


# -- friction on by default -------------------------------------------------------------------
def test_friction_is_on_by_default():
    assert PARAMETERS['extras'][0] == ['fv', 'fc', 'fo']
    assert Settings.from_dict({}).load_robot().extras == ('fv', 'fc', 'fo')


@pytest.mark.parametrize('method', ['rls', 'batch'])
def test_a_bag_with_friction_identified_with_the_defaults_is_accurate_and_flags_nothing(
        bags, arm, method):
    s = defaults()
    robot = s.load_robot()
    bag = bags['friction'][0]
    ident = (replay_identify(bag, s, robot) if method == 'rls'
             else offline_identify(bag, s, robot))
    assert ident.warnings == []
    # 24 base parameters, 4 sigma each: family-wise false alarms below 0.2 %
    z = (ident.theta - true_base(ident, arm)) / ident.stddev
    assert np.all(np.abs(z) < 4), dict(zip(ident.base.names, z.round(1)))
    # held out: another motion's true torque, reversals included, to 1 % (stacked)
    q, qd, qdd, tau = bags['heldout'][1]
    predicted = ident.base.base_regressor(robot.regressor(q, qd, qdd)) @ ident.theta
    assert 100 * np.linalg.norm(tau - predicted) / np.linalg.norm(tau) < 1.0
    # the equations left out near velocity reversals are counted per joint
    excluded = ident.details['excluded_per_joint']
    assert list(excluded) == robot.joint_names and all(v > 0 for v in excluded.values())
    assert sum(excluded.values()) == ident.details['excluded_equations']


@pytest.mark.parametrize('method', ['rls', 'batch'])
def test_a_bag_without_friction_gives_consistent_inertials_and_friction_near_zero(
        bags, arm, method):
    s = defaults()
    robot, bag = s.load_robot(), bags['none'][0]
    ident = (replay_identify(bag, s, robot) if method == 'rls'
             else offline_identify(bag, s, robot))
    z = (ident.theta - true_base(ident, arm, friction=False)) / ident.stddev
    names = ident.base.names
    friction = np.array([n.rsplit('.', 1)[1] in ('fv', 'fc', 'fo') for n in names])
    assert friction.sum() == 9
    # 4 sigma each (family-wise false alarms below 0.5 %); the friction estimates are zero
    # within 4 of their standard deviations
    assert np.all(np.abs(z) < 4), dict(zip(names, z.round(2)))
    assert np.sqrt(np.mean(z[~friction] ** 2)) < 2.0
    assert np.all(np.abs(ident.theta[friction]) < 4 * ident.stddev[friction])
    assert ident.warnings == []


RAIL = """<robot name="rail">
  <link name="base"/>
  <joint name="slide" type="prismatic"><parent link="base"/><child link="carriage"/>
    <axis xyz="1 0 0"/><limit lower="-0.3" upper="0.3" effort="500" velocity="0.07"/></joint>
  <link name="carriage"><inertial><origin xyz="0 0 0.05"/><mass value="5"/>
    <inertia ixx="0.05" ixy="0" ixz="0" iyy="0.05" iyz="0" izz="0.05"/></inertial></link>
  <joint name="arm" type="revolute"><parent link="carriage"/><child link="link"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="2"/></joint>
  <link name="link"><inertial><origin xyz="0.2 0 0.01"/><mass value="2"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
</robot>"""


@pytest.mark.parametrize('method', ['rls', 'batch'])
def test_a_slow_linear_axis_keeps_its_equations_above_a_tenth_of_the_exclusion_speed(
        tmp_path, method):
    """A prismatic joint at most 0.06 m/s (TIAGo's torso lift: 0.07) with 20 N of Coulomb
    friction: coulomb_exclusion_speed (0.1 rad/s) leaves out its equations below 0.01 m/s
    only, as many as the true motion has there, and its fc is identified (0.1 m/s left out
    every one)."""
    fv, fc, fo, noise = [50.0, 0.3], np.array([20.0, 1.0]), [2.0, 0.1], [2.0, 0.2]
    urdf = tmp_path / 'rail.urdf'
    urdf.write_text(RAIL)
    s = Settings.from_dict({'robot': str(urdf), 'torque_source': ['measured']})
    robot = s.load_robot()
    traj = FourierTrajectory.random(robot, period=10.0, seed=3)
    t = np.arange(30000) / 1000.0
    scale = 0.06 / np.abs(traj.sample(t)[1][:, 0]).max()
    traj.a[0] *= scale
    traj.b[0] *= scale
    sim = simulate_kinematic(robot, None, traj, t,
                             SensorNoise(encoder_counts=262144, velocity_std=0.001), seed=1)
    tau = sim.tau + fv * sim.qd + fc * np.sign(sim.qd) + fo
    tau += noise * np.random.default_rng(2).standard_normal(tau.shape)
    bag = write_bag(tmp_path / 'bag', robot, t, sim.q_meas, sim.qd_meas, tau, description=RAIL)
    ident = (replay_identify(bag, s, robot) if method == 'rls'
             else offline_identify(bag, s, robot))
    assert ident.warnings == []
    k = [ident.base.names.index(f'{j}.fc') for j in robot.joint_names]
    assert np.all(np.abs(ident.theta[k] - fc) < 4 * ident.stddev[k])
    assert ident.stddev[k[0]] < 0.01 * fc[0]
    if method == 'rls':   # the streaming rows: one equation per sample and joint
        slow = np.mean(np.abs(sim.qd[:, 0]) < 0.01)
        left_out = ident.details['excluded_per_joint']['slide'] / ident.num_samples
        assert 0.1 < slow < 0.2 and left_out == pytest.approx(slow, abs=0.02)
    assert exclusion_warnings(robot, np.array([95, 0]), 100, 0.1) == [
        'slide: 95 % of its equations left out near velocity reversals (|qd| < 0.01 m/s, '
        'coulomb_exclusion_speed 0.1 / 10 for a prismatic joint): a slow joint; lower '
        'coulomb_exclusion_speed or set it to 0']


def test_a_joint_without_equations_reads_n_a_in_the_errors_and_its_parameters_not_excited(
        tmp_path, capsys):
    """A rail that never exceeds 0.008 m/s: coulomb_exclusion_speed leaves out every one of
    its equations. identify says so in a warning, its parameters are not excited, and the
    relative errors of the rows fitted read n/a for it (no torque to relate to), not inf."""
    urdf = tmp_path / 'rail.urdf'
    urdf.write_text(RAIL)
    robot = load_robot(str(urdf))
    traj = FourierTrajectory.random(robot, period=10.0, seed=3)
    t = np.arange(12000) / 1000.0
    scale = 0.008 / np.abs(traj.sample(t)[1][:, 0]).max()
    traj.a[0] *= scale
    traj.b[0] *= scale
    sim = simulate_kinematic(robot, None, traj, t, SensorNoise(torque_std=0.2), seed=1)
    bag = write_bag(tmp_path / 'bag', robot, t, sim.q_meas, sim.qd_meas, sim.tau_meas,
                    description=RAIL)
    assert main(['identify', str(bag)]) == 0
    out = capsys.readouterr().out
    fitted = next(x for x in out.splitlines() if 'rows fitted, percent:' in x)
    assert 'slide n/a' in fitted and 'inf' not in fitted, fitted
    assert re.search(r'warning: slide: 100 % of its equations left out', out), out
    assert re.search(r'slide\.\w+ +not excited', out), out


def test_a_prismatic_joint_smooths_its_coulomb_sign_over_a_tenth_of_coulomb_velocity(tmp_path):
    """coulomb_velocity is rad/s as coulomb_exclusion_speed: tanh(qd / 0.1) on the revolute
    joint, tanh(qd / 0.01) (m/s) on the prismatic one, in the regressor and in rnea."""
    urdf = tmp_path / 'rail.urdf'
    urdf.write_text(RAIL)
    robot = load_robot(str(urdf), extras=['fc'], coulomb_velocity=0.1)
    qd = np.array([[0.005, 0.05], [-0.02, -0.3]])
    Y = robot.regressor(np.zeros((2, 2)), qd, np.zeros((2, 2)))
    k = [robot.param_index(f'{j}.fc') for j in robot.joint_names]
    np.testing.assert_allclose(Y[:, [0, 1], k], np.tanh(qd / [0.01, 0.1]), rtol=1e-12)
    phi = robot.phi_model.copy()
    phi[k] = [20.0, 1.0]
    np.testing.assert_allclose(robot.rnea(np.zeros((2, 2)), qd, np.zeros((2, 2)), phi),
                               Y @ phi, rtol=1e-9, atol=1e-9)


# -- a missing term is flagged ----------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize('method', ['rls', 'batch'])
def test_missing_coulomb_friction_is_flagged(bags, method, capsys):
    args = ['identify', str(bags['friction'][0]), '--robot', 'mit_dd_arm', '--extras', 'fv,fo',
            '--method', method]
    assert main(args + ['--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    flagged = [w for w in doc['warnings'] if 'Coulomb friction (fc) missing?' in w]
    # joints 1 and 2 carry 1.0 and 0.5 N m of Coulomb friction over 0.4 and 0.2 N m of noise
    assert {w.split(':')[0] for w in flagged} >= {'joint1', 'joint2'}, doc['warnings']
    for w in flagged:
        assert 'residual correlates with sign(qd) (r=' in w
        assert float(w.split('(r=')[1].split(')')[0]) > MIN_CORRELATION
    assert not any('viscous' in w for w in doc['warnings'])   # fv is in the model
    assert main(args) == 0
    text = capsys.readouterr().out
    assert 'warning: joint1: residual correlates with sign(qd)' in text


def test_a_missing_position_dependent_torque_is_flagged(bags):
    s = defaults()
    ident = offline_identify(bags['spring'][0], s, s.load_robot())
    assert len(ident.warnings) == 1 and ident.warnings[0].startswith(
        'joint1: residual correlates with q (r='), ident.warnings
    assert 'position-dependent torque' in ident.warnings[0]


def test_no_offset_column_and_an_offset_in_the_torque_is_flagged(bags):
    s = defaults(extras=['fv', 'fc'])
    ident = offline_identify(bags['friction'][0], s, s.load_robot())
    # joints 1 and 2: 0.2 and -0.1 N m of offset; the residual's mean is no friction term's
    assert any(w.startswith('joint1: residual mean') and 'torque offset (fo) missing?' in w
               for w in ident.warnings), ident.warnings
    assert not any('sign(qd)' in w or 'viscous' in w for w in ident.warnings)


# -- joints and names -------------------------------------------------------------------------
@pytest.fixture(scope='module')
def partial_bag(tmp_path_factory):
    """A CRS A465 whose joint states carry joints 1..3 only (4..6 at rest at 0)."""
    arm3 = load_robot('crs_a465', ['joint1', 'joint2', 'joint3'], extras=[])
    measured, _ = simulate(arm3, 5, friction=False)
    full = load_robot('crs_a465')
    return write_bag(tmp_path_factory.mktemp('partial') / 'bag', arm3, *measured,
                     description=full.description), arm3


def test_the_joints_the_bag_carries_are_identified_and_the_others_locked(
        partial_bag, capsys, tmp_path):
    bag, arm3 = partial_bag
    # per-joint lists of one value per movable joint follow the joints kept (else: 'kt has
    # 6 values; give 1 or one per joint')
    config = tmp_path / 'config.yaml'
    config.write_text('kt: [1, 2, 3, 4, 5, 6]\n')
    assert main(['identify', str(bag), '--extras', 'none', '--json', '--config',
                 str(config)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['robot'] == 'crs_a465'     # the URDF's <robot name>, from /robot_description
    assert doc['joints'] == ['joint1', 'joint2', 'joint3']
    assert doc['warnings'][0].startswith('joint(s) joint4, joint5, joint6 of crs_a465 are '
                                         "not in the bag's /joint_states: locked")
    base3 = BaseParameters.from_robot(arm3)   # the simulated arm: joints 4..6 locked at 0
    true = dict(zip(base3.names, base3.to_base(arm3.phi_model)))
    got = {b['name']: b for b in doc['base_parameters']}
    assert set(got) == set(true)
    z = {n: (b['unconstrained_estimate'] - true[n]) / b['stddev'] for n, b in got.items()}
    assert all(abs(v) < 4 for v in z.values()), z
    # given joints are kept as given: the bag then lacks joint4, named in the error
    assert main(['identify', str(bag), '--extras', 'none', '--joints',
                 'joint1,joint2,joint3,joint4']) == 2
    err = capsys.readouterr().err
    assert 'no usable samples' in err and 'lacks joint(s) joint4' in err
    assert 'identified joints: joint1, joint2, joint3, joint4' in err


def test_the_robot_name_is_the_urdfs(tmp_path):
    urdf = load_robot('mit_dd_arm').description.replace('<robot name="mit_dd_arm"',
                                                        '<robot name="my_arm"')
    path = tmp_path / 'renamed.urdf'
    path.write_text(urdf)
    assert load_robot(urdf).name == load_robot(str(path)).name == 'my_arm'
    with pytest.raises(IdentificationError, match="robot my_arm"):
        load_robot(urdf, ['nope'])
