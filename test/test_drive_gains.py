"""Drive gains identified in situ (back-EMF and known payload) on simulated arms whose true kt
is 10-20 % off the configured one: recovery, the identification with the recovered gains, and
clear refusals of what cannot determine them."""
import json

import numpy as np
import pytest
import yaml

from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.estimation.drive_gains import (DriveGain, back_emf_equations,
                                                        back_emf_gains, check_voltages)
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.drive import DriveModel, emf_shape, motor_speed
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import simulate_kinematic
from identification_node.batch.drive_gains import back_emf_from_bag
from identification_node.model.torque import JointTorqueConfig, TorqueConverter
from identification_node.settings import Settings, read_parameter_file
from arms import ARMS, arm_urdf

KT_ERROR = [0.15, -0.12, 0.18, -0.10, 0.20, 0.11, -0.16]
NOISE = ['--current-std', '0.01', '--voltage-std', '0.05', '--velocity-std', '0.002',
         '--encoder-counts', '1048576']
PAYLOAD = {'mass': 3.0, 'com': [0.04, 0.03, 0.06], 'inertia': [0.01, 0, 0, 0.012, 0, 0.008]}


def _converter(source, n=3, kt=0.1, gear=50.0, pp=4):
    return TorqueConverter([f'j{k}' for k in range(n)],
                           [JointTorqueConfig(source, kt, gear, pp)] * n)


@pytest.mark.parametrize('order', ['abc', 'acb'])
def test_back_emf_power_is_the_mechanical_power_of_eq10(order):
    """With R = L = 0 the electrical power sum_k V_k i_k is tau_motor omega_motor (eq. 10's
    torque), whatever the wiring: the convention K_E = K_T."""
    cfg = JointTorqueConfig('three_phase', 0.08, 30.0, 4, 0.3, order)
    conv = TorqueConverter(['a', 'b'], [cfg, cfg])
    rng = np.random.default_rng(1)
    q, qd, tau = (rng.normal(size=(50, 2)) for _ in range(3))
    t = np.arange(50) * 1e-3
    v = DriveModel.per_joint(2, 0.0, 0.0).voltages(conv, t, q, qd, tau)
    i = conv.currents_from_torque(tau, q)
    assert np.allclose(np.sum(v * i, axis=2), tau / 30.0 * motor_speed(conv, qd), rtol=1e-12)


def test_back_emf_fit_recovers_r_l_ke_and_refuses_a_still_joint():
    """The per-joint fit on a kinematic UR5 with three-phase drives: K_E * gear within 0.1 %
    and 3 stddev, R within 5 % where the currents are large; a joint held still is 'not
    excited'."""
    robot = load_robot(str(arm_urdf('ur5')))
    traj = FourierTrajectory.random(robot, seed=3)
    keep = np.array([1, 1, 1, 1, 1, 0.0])[:, None]   # the last joint held still
    traj = FourierTrajectory(traj.a * keep, traj.b * keep, traj.q0, traj.period,
                             robot.joint_names)
    t = np.arange(0, 10, 1e-3)
    sim = simulate_kinematic(robot, None, traj, t)
    conf = TorqueConverter(robot.joint_names, [JointTorqueConfig('three_phase', 0.1, 100.0, 2)]
                           * robot.dof)
    drives = DriveModel.per_joint(robot.dof, 0.4, 2e-3, KT_ERROR[:6])
    true = drives.true_converter(conf)
    rng = np.random.default_rng(0)
    v = drives.voltages(true, t, sim.q, sim.qd, sim.tau, 0.05, rng)
    i = true.currents_from_torque(sim.tau, sim.q) + 0.01 * rng.standard_normal(v.shape)
    di = np.gradient(i, t, axis=0)
    w = motor_speed(conf, sim.qd + 0.002 * rng.standard_normal(sim.qd.shape))
    eq = back_emf_equations(v, i, di, emf_shape(conf, sim.q), w)
    gains = back_emf_gains(robot.joint_names, eq, np.full(6, 100.0), np.full(6, 10.0),
                           np.sqrt(np.mean(w ** 2, axis=0)))
    truth = 10.0 * (1 + np.array(KT_ERROR[:6]))
    for g, true_gain in zip(gains[:5], truth):
        assert abs(g.value / true_gain - 1) < 1e-3 and abs(g.value - true_gain) < 3 * g.stddev
    for g in gains[:3]:   # the wrists' currents are too small for R (a nuisance here)
        assert abs(g.details['resistance'] - 0.4) < 0.02
    assert gains[5].value is None and 'not excited' in gains[5].reason
    assert gains[5].warning.startswith('drive gain of wrist_3_joint not determined')


def test_voltage_plausibility_gate():
    check_voltages(np.array([[[48.0, np.nan, np.nan]]]))
    with pytest.raises(IdentificationError, match='not volts'):
        check_voltages(np.array([[[48000.0, np.nan, np.nan]]]))


def test_warning_needs_three_stddev_and_five_percent():
    assert DriveGain('j', 11.0, 0.1, 'back_emf', 10.0).warning.startswith('drive gain of j')
    assert DriveGain('j', 10.4, 0.01, 'back_emf', 10.0).warning is None      # 4 %
    assert DriveGain('j', 11.0, 0.5, 'back_emf', 10.0).warning is None       # 2 stddev
    assert DriveGain('j', 11.0, 0.1, 'back_emf', 10.0).ratio == pytest.approx(1.1)


# -- simulated bags, both methods, through the CLI ----------------------------------------------
def _config(tmp, arm, source):
    joints = ARMS[arm][1]
    doc = {'robot': str(arm_urdf(arm)), 'torque_source': [source], 'kt': [0.12],
           'gear_ratio': [100.0], 'pole_pairs': [2]}
    if joints:
        doc['joints'] = joints
    path = tmp / f'{arm}.yaml'
    path.write_text(yaml.safe_dump({'identification_node': {'ros__parameters': doc}}))
    return path


def _trajectory(tmp, robot, seed, still=None):
    traj = FourierTrajectory.random(robot, seed=seed)
    a, b = traj.a.copy(), traj.b.copy()
    if still is not None:
        a[still] = b[still] = 0.0
    path = tmp / f'traj{seed}{still}.yaml'
    path.write_text(yaml.safe_dump(FourierTrajectory(a, b, traj.q0, traj.period).to_dict()))
    return str(path)


def _simulate(tmp, name, config, traj, n, payload=None, seed=0, duration='20'):
    out = tmp / name
    args = ['simulate', '--config', str(config), '--trajectory', traj, '--duration', duration,
            '--seed', str(seed), '--kt-error', *map(str, KT_ERROR[:n]), '--out', str(out),
            *NOISE]
    if payload is not None:
        args += ['--payload-events', json.dumps([dict(payload, time=0.0)])]
    assert main(args) == 0
    return out


@pytest.fixture(scope='module', params=[('ur5', 'current'), ('panda', 'three_phase')])
def arm_bags(request, tmp_path_factory):
    arm, source = request.param
    tmp = tmp_path_factory.mktemp(arm)
    config = _config(tmp, arm, source)
    robot = Settings.from_dict(read_parameter_file(str(config))).load_robot()
    n = robot.dof
    payload = tmp / 'payload.yaml'
    payload.write_text(yaml.safe_dump(PAYLOAD))
    bags = {'free': _simulate(tmp, 'free', config, _trajectory(tmp, robot, 0), n),
            'loaded': _simulate(tmp, 'loaded', config, _trajectory(tmp, robot, 1), n,
                                PAYLOAD, seed=1)}
    truth = yaml.safe_load((bags['free'] / 'true_parameters.yaml').read_text())
    return tmp, config, robot, payload, bags, truth


def _identify(capsys, bag, config, *extra):
    capsys.readouterr()
    assert main(['identify', str(bag), '--config', str(config), '--method', 'batch', '--json',
                 *extra]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.slow
def test_both_methods_recover_every_gain(arm_bags, capsys):
    """Every joint's gain within 1 % and 3 stddev of the truth, by both methods; the warning
    names every joint (10-20 % off the configuration)."""
    tmp, config, robot, payload, bags, truth = arm_bags
    doc = _identify(capsys, bags['free'], config, '--back-emf', '--known-payload-bag',
                    str(bags['loaded']), '--known-payload', str(payload))
    gains = doc['drive_gains']
    assert sorted({g['method'] for g in gains}) == ['back_emf', 'known_payload']
    assert len(gains) == 2 * robot.dof
    for g in gains:
        true_gain = truth['drives'][g['joint']]['gain']
        assert g['determined'], g
        assert abs(g['value'] / true_gain - 1) < 0.01, g
        assert abs(g['value'] - true_gain) < 3 * g['stddev'], (g, true_gain)
        assert g['ratio'] == pytest.approx(g['value'] / g['configured'])
    assert sum(g['used'] for g in gains) == robot.dof
    warned = [w for w in doc['warnings'] if w.startswith('drive gain of')]
    assert len(warned) == 2 * robot.dof


def _held_out_error(robot, bag, estimate):
    """Relative error of the estimate's torque against the true arm's on a held-out motion."""
    from identification_node.model.identifiability import BaseParameters
    base = BaseParameters.from_robot(robot)
    truth = yaml.safe_load((bag / 'true_parameters.yaml').read_text())
    beta = np.array(list(truth['base_parameters'].values()))
    traj = FourierTrajectory.random(robot, seed=4)
    t = np.linspace(0, traj.period, 400)
    q, qd, qdd = traj.sample(t)
    Y = base.base_regressor(robot.regressor(q, qd, qdd))
    return np.linalg.norm(Y @ (np.array(estimate) - beta)) / np.linalg.norm(Y @ beta)


@pytest.mark.slow
def test_inertial_parameters_with_recovered_gains_are_as_good_as_with_true_ones(
        arm_bags, capsys):
    """Identified with the known-payload gains, the base parameters predict the true torque of
    a motion none of the bags ran within half a percentage point of those identified with the
    true kt, and several times better than with the configured (wrong) kt."""
    tmp, config, robot, payload, bags, truth = arm_bags
    recovered = _identify(capsys, bags['free'], config, '--known-payload-bag',
                          str(bags['loaded']), '--known-payload', str(payload))
    doc = yaml.safe_load(config.read_text())
    doc['identification_node']['ros__parameters']['kt'] = [
        truth['drives'][j]['kt'] for j in robot.joint_names]
    true_config = tmp / 'true_kt.yaml'
    true_config.write_text(yaml.safe_dump(doc))
    with_truth = _identify(capsys, bags['free'], true_config)
    configured = _identify(capsys, bags['free'], config)
    e_rec, e_true, e_conf = (_held_out_error(robot, bags['free'], d['unconstrained_estimate'])
                             for d in (recovered, with_truth, configured))
    assert e_rec < e_true + 0.005, (e_rec, e_true)
    assert e_conf > 5 * e_rec, (e_conf, e_rec)


@pytest.mark.slow
def test_too_small_a_payload_leaves_the_gains_not_determined(arm_bags, capsys):
    tmp, config, robot, _, bags, _ = arm_bags
    if robot.dof != 6:
        pytest.skip('one arm suffices')
    tiny = dict(PAYLOAD, mass=0.001, inertia=[1e-7, 0, 0, 1e-7, 0, 1e-7])
    loaded = _simulate(tmp, 'tiny', config, _trajectory(tmp, robot, 1), 6, tiny, seed=3,
                       duration='8')
    path = tmp / 'tiny.yaml'
    path.write_text(yaml.safe_dump(tiny))
    doc = _identify(capsys, bags['free'], config, '--known-payload-bag', str(loaded),
                    '--known-payload', str(path))
    for g in doc['drive_gains']:
        assert not g['determined'] and g['value'] is None and g['stddev'] > 0
        assert 'too small' in g['reason']
    assert main(['identify', str(bags['free']), '--config', str(config), '--method', 'batch',
                 '--known-payload-bag', str(loaded), '--known-payload', str(path)]) == 0
    assert 'not determined (stddev' in capsys.readouterr().out


@pytest.mark.slow
def test_back_emf_refuses_a_still_joint_and_bad_voltages(arm_bags, capsys, tmp_path):
    tmp, config, robot, _, bags, _ = arm_bags
    if robot.dof != 6:
        pytest.skip('one arm suffices')
    still = _simulate(tmp, 'still', config, _trajectory(tmp, robot, 0, still=5), 6,
                      duration='6')
    settings = Settings.from_dict(read_parameter_file(str(config)))
    gains = back_emf_from_bag(still, settings, robot)
    assert all(g.value is not None for g in gains[:5])
    assert gains[5].value is None and 'not excited' in gains[5].reason
    # voltages on the currents' topic under other channel names: refused, named
    assert main(['identify', str(bags['free']), '--config', str(config), '--back-emf',
                 '--voltages-topic', '/joint_states']) == 2
    assert 'motor voltages have channels' in capsys.readouterr().err
