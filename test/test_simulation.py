"""Simulated arm: dynamics consistent with the regressor, closed forms, energy, sensor models."""
import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from identification_node.errors import IdentificationError
from identification_node.excitation.quintic_moves import QuinticMoves
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import (ArmSimulator, SensorNoise, default_converter,
                                                      simulate_kinematic)

CRS_URDF = Path(__file__).resolve().parents[1] / 'identification_node' / 'robots' / \
    'crs_a465.urdf'
G = 9.81
M, L, IC = 2.0, 0.5, 0.01   # pendulum mass, centre-of-mass distance, inertia about the COM

PENDULUM = f"""<robot name="pendulum">
  <link name="base"/>
  <joint name="swing" type="revolute">
    <parent link="base"/><child link="bob"/>
    <origin xyz="0 0 1" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="10"/>
  </joint>
  <link name="bob">
    <inertial>
      <origin xyz="0 0 {-L}" rpy="0 0 0"/><mass value="{M}"/>
      <inertia ixx="{IC}" ixy="0" ixz="0" iyy="{IC}" iyz="0" izz="{IC}"/>
    </inertial>
  </link>
</robot>"""
I_O = IC + M * L ** 2   # inertia about the joint axis


def perturbed(robot, rel=0.1, seed=1, extras=(0.5, 2.0, 0.3, 0.2)):
    """The robot's phi with friction/offset/rotor values and a relative perturbation."""
    phi = robot.phi_model.copy()
    ne = len(robot.extras)
    if ne:
        phi[robot.n_inertial:] = np.tile(extras[:ne], robot.dof)
    rng = np.random.default_rng(seed)
    return phi, phi * (1 + rel * rng.standard_normal(phi.size))


@pytest.fixture(scope='module')
def mit_full():
    return load_robot('mit_dd_arm', extras=('fv', 'fc', 'fo', 'Ia'))


@pytest.mark.parametrize('coulomb_velocity', [0.0, 0.05])
def test_applied_torque_is_inverse_dynamics_of_the_simulated_state(coulomb_velocity):
    robot = load_robot('mit_dd_arm', extras=('fv', 'fc', 'fo', 'Ia'),
                       coulomb_velocity=coulomb_velocity)
    nominal, true = perturbed(robot)
    res = ArmSimulator(robot, phi_true=true, model_phi=nominal).run(
        QuinticMoves.mit_paper(), duration=1.5)
    scale = np.abs(res.tau).max()
    np.testing.assert_allclose(robot.inverse_dynamics(res.q, res.qd, res.qdd, true), res.tau,
                               rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(robot.rnea(res.q, res.qd, res.qdd, true), res.tau,
                               rtol=0, atol=1e-6 * scale)
    # The nominal model would not explain the data: the check above can fail.
    assert np.abs(robot.inverse_dynamics(res.q, res.qd, res.qdd, nominal) - res.tau).max() \
        > 1e-3 * scale


@pytest.mark.skipif(not CRS_URDF.is_file(), reason='crs_a465.urdf not there')
def test_six_dof_consistency_and_tracking():
    robot = load_robot(str(CRS_URDF), extras=('fv', 'fc'))
    nominal = robot.phi_model.copy()
    nominal[robot.n_inertial:] = np.repeat(0.01 * robot.effort_limits, 2)  # fv, fc per joint
    true = nominal * (1 + 0.1 * np.random.default_rng(1).standard_normal(nominal.size))
    traj = FourierTrajectory.crs_table1()
    res = ArmSimulator(robot, phi_true=true, model_phi=nominal).run(traj, duration=1.0)
    scale = np.abs(res.tau).max()
    np.testing.assert_allclose(robot.inverse_dynamics(res.q, res.qd, res.qdd, true), res.tau,
                               rtol=0, atol=1e-6 * scale)
    # The light wrist joints (1e-4 kg m^2) feel a 10 % model error most.
    assert np.abs(traj.sample(res.t)[0] - res.q).max() < 0.05
    res = ArmSimulator(robot, phi_true=nominal, model_phi=nominal).run(traj, duration=1.0)
    assert np.abs(traj.sample(res.t)[0] - res.q).max() < 1e-3


def test_stiff_viscous_friction_on_light_links_takes_more_steps(monkeypatch):
    """example-robot-data's iCub damps every joint by 1 N m s/rad (URDF <dynamics>) while
    its arm's links weigh down to 1e-5 kg m^2: one RK4 step per 1 kHz sample diverges. The
    simulator takes the steps the damping needs and follows the motion, each sample's
    torque the inverse dynamics of its state."""
    from arms import robots_dir
    from identification_node.simulation import simulator
    robot = load_robot(str(robots_dir() / 'icub_description' / 'robots' / 'icub_reduced.urdf'),
                       ['l_shoulder_pitch', 'l_shoulder_roll', 'l_shoulder_yaw', 'l_elbow',
                        'l_wrist_prosup', 'l_wrist_pitch', 'l_wrist_yaw'], extras=('fv',))
    assert np.all(robot.phi_model[robot.n_inertial:] == 1.0)
    traj = FourierTrajectory.random(robot, harmonics=5, period=10.0, seed=1)
    sim = ArmSimulator(robot)
    assert sim.substeps > 1
    res = sim.run(traj, duration=1.0)
    scale = np.abs(res.tau).max()
    np.testing.assert_allclose(robot.inverse_dynamics(res.q, res.qd, res.qdd), res.tau,
                               rtol=0, atol=1e-6 * scale)
    assert np.abs(traj.sample(res.t)[0] - res.q).max() < 1e-3
    monkeypatch.setattr(simulator, 'RK4_STEP', math.inf)   # one step per sample, as before
    with pytest.raises(IdentificationError, match='diverged'):
        ArmSimulator(robot).run(traj, duration=1.0)


def test_a_singular_configuration_is_named_when_the_simulation_diverges():
    """example-robot-data's human arm writes its shoulder as three revolute joints with
    massless links between them: its mass matrix is singular where two of their axes align.
    The arm simulates (massless links kept: robot.pinocchio_model) until the motion nears such
    a configuration, and the error says what the mass matrix did there."""
    from arms import robots_dir
    robot = load_robot(str(robots_dir() / 'human_description' / 'robots' / 'human.urdf'),
                       ['right_shoulder_Z', 'right_shoulder_X', 'right_shoulder_Y',
                        'right_elbow_Z', 'right_elbow_Y', 'right_wrist_Z', 'right_wrist_X'])
    traj = FourierTrajectory.random(robot, harmonics=5, period=10.0, seed=1)
    res = ArmSimulator(robot).run(traj, duration=1.5)
    assert np.abs(traj.sample(res.t)[0] - res.q).max() < 1e-3
    with pytest.raises(IdentificationError, match=r'diverged at t = 2\.0\d* s \(smallest '
                       r'eigenvalue of the mass matrix at the reference there [0-9.e-]+, '
                       r'0\.00247 at the start: a tiny one marks a singular configuration'):
        ArmSimulator(robot).run(traj, duration=3.0)


def test_tracking_error_small(mit_full):
    traj = QuinticMoves.mit_paper()
    nominal, true = perturbed(mit_full)
    exact = ArmSimulator(mit_full, phi_true=nominal, model_phi=nominal).run(traj)
    assert exact.t[-1] == pytest.approx(traj.duration)
    err = np.abs(traj.sample(exact.t)[0] - exact.q).max()
    assert err < 1e-3
    # 10 % model error: the PD loop keeps it within a fraction of a degree.
    mism = ArmSimulator(mit_full, phi_true=true, model_phi=nominal).run(traj)
    err_mism = np.abs(traj.sample(mism.t)[0] - mism.q).max()
    assert err < err_mism < np.radians(0.5)
    # Starts on the trajectory at rest, ends near its last waypoint.
    np.testing.assert_allclose(exact.q[0], traj.waypoints[0])
    np.testing.assert_allclose(exact.q[-1], traj.waypoints[-1], atol=1e-3)


def test_pendulum_closed_form_torques():
    robot = load_robot(PENDULUM)
    traj = FourierTrajectory([[1.5, -0.7]], [[0.4, 0.3]], [0.2], period=3.0)
    res = ArmSimulator(robot).run(traj, duration=3.0)
    # tau = I_o qdd + m g l sin q for a pendulum hanging at q = 0, turning about +y.
    closed = I_O * res.qdd + M * G * L * np.sin(res.q)
    np.testing.assert_allclose(res.tau, closed, atol=1e-9 * np.abs(closed).max())
    # Holding still at q = 0.7 rad takes m g l sin 0.7.
    hold = QuinticMoves([[0.7], [0.7]], 0.5)
    res = ArmSimulator(robot).run(hold)
    np.testing.assert_allclose(res.tau, M * G * L * np.sin(0.7), rtol=1e-9)
    np.testing.assert_allclose(res.q, 0.7, atol=1e-12)


def test_work_equals_energy_change():
    robot = load_robot('mit_dd_arm')  # no friction: the applied work all goes into energy
    res = ArmSimulator(robot).run(QuinticMoves.mit_paper(), duration=2.0)
    # The actuator torque ramps linearly over each period: its work there is the trapezoid
    # 0.5 (tau_k + tau_k+1) . dq up to O(h^3).
    mid = 0.5 * (res.tau[:-1] + res.tau[1:])
    work = np.cumsum(np.einsum('kj,kj->k', mid, np.diff(res.q, axis=0)))
    model = robot.pinocchio_model(robot.phi_model)
    data = model.createData()
    Q = robot.configuration(res.q)
    energy = np.array([pin.computeKineticEnergy(model, data, Q[k], res.qd[k])
                       + pin.computePotentialEnergy(model, data, Q[k]) for k in range(len(res))])
    flow = np.cumsum(np.abs(np.einsum('kj,kj->k', mid, np.diff(res.q, axis=0))))
    np.testing.assert_allclose(energy[1:] - energy[0], work, atol=1e-6 * flow[-1])
    # A held torque would not balance: the check can fail.
    held = np.cumsum(np.einsum('kj,kj->k', res.tau[:-1], np.diff(res.q, axis=0)))
    assert np.max(np.abs(energy[1:] - energy[0] - held)) > 1e-4 * flow[-1]


def test_step_reproduces_run(mit_full):
    nominal, true = perturbed(mit_full)
    sim = ArmSimulator(mit_full, phi_true=true, model_phi=nominal, substeps=2)
    traj = QuinticMoves.mit_paper()
    res = sim.run(traj, duration=0.05)
    sim.reset(traj)
    rows = [sim.step() for _ in range(len(res))]
    for name in ('t', 'q', 'qd', 'qdd', 'tau'):
        np.testing.assert_array_equal(np.concatenate([getattr(r, name) for r in rows]),
                                      getattr(res, name))
    assert sim.t == pytest.approx(0.051)


def test_noise_statistics(mit_full):
    noise = SensorNoise(position_std=1e-3, velocity_std=0.02, torque_std=0.5, current_std=0.1)
    traj = FourierTrajectory.random(mit_full, seed=2)
    t = np.arange(20000) * 1e-3
    clean = simulate_kinematic(mit_full, None, traj, t)
    res = simulate_kinematic(mit_full, None, traj, t, noise=noise, seed=4)
    np.testing.assert_array_equal(res.tau, clean.tau)
    for meas, true, std in ((res.q_meas, res.q, 1e-3), (res.qd_meas, res.qd, 0.02),
                            (res.tau_meas, res.tau, 0.5), (res.currents, clean.currents, 0.1)):
        e = (meas - true).ravel()
        assert np.std(e) == pytest.approx(std, rel=0.03)
        assert abs(np.mean(e)) < 5 * std / np.sqrt(e.size)
    # Same seed, same noise.
    again = simulate_kinematic(mit_full, None, traj, t[:100], noise=noise, seed=4)
    np.testing.assert_array_equal(again.q_meas, res.q_meas[:100])


def test_encoder_quantisation_step():
    robot = load_robot('mit_dd_arm')
    counts = 4096
    step = 2 * np.pi / counts
    traj = QuinticMoves([[0.0, 0.0, 0.0], [0.05, -0.02, 0.01]], 1.0)
    res = simulate_kinematic(robot, None, traj, np.linspace(0, 1, 2001),
                             noise=SensorNoise(encoder_counts=counts))
    ticks = res.q_meas / step
    np.testing.assert_allclose(ticks, np.round(ticks), atol=1e-9)
    assert np.abs(res.q_meas - res.q).max() <= step / 2 + 1e-15
    levels = np.diff(np.unique(res.q_meas[:, 0]))
    np.testing.assert_allclose(levels, step, rtol=1e-9)
    assert levels.size == round(0.05 / step)


def test_currents_convert_back_to_the_applied_torque(mit_full):
    torque = pytest.importorskip('identification_node.model.torque')
    kt, gear, pp, off = 0.5, 3.0, 4, 0.3
    conv = torque.TorqueConverter(mit_full.joint_names, [
        torque.JointTorqueConfig('three_phase', kt=kt, gear_ratio=gear, pole_pairs=pp,
                                 angle_offset=off, phase_order='acb'),
        torque.JointTorqueConfig('current', kt=2.0),
        torque.JointTorqueConfig('measured')])
    res = ArmSimulator(mit_full).run(QuinticMoves.mit_paper(), duration=0.5, converter=conv)
    # Eq. 10 of An, Atkeson, Hollerbach written out; 'acb' swaps the b and c wires.
    th = pp * gear * res.q[:, 0] + off
    ia, ic, ib = res.currents[:, 0].T
    tau0 = gear * kt * (ia * np.sin(th) + ib * np.sin(th + 2 * np.pi / 3)
                        + ic * np.sin(th + 4 * np.pi / 3))
    np.testing.assert_allclose(tau0, res.tau[:, 0], atol=1e-9 * np.abs(res.tau).max())
    np.testing.assert_allclose(2.0 * res.currents[:, 1, 0], res.tau[:, 1], atol=1e-9)
    np.testing.assert_allclose(res.theta_e[:, 0], th)
    back = conv.torque(res.q, measured=res.tau_meas, currents=res.currents,
                       theta_e=res.theta_e)
    np.testing.assert_allclose(back, res.tau, atol=1e-9 * np.abs(res.tau).max())
    # Default converter: three-phase currents with kt = 1 for every joint.
    res = ArmSimulator(mit_full).run(QuinticMoves.mit_paper(), duration=0.1)
    back = default_converter(mit_full.joint_names).torque(res.q, currents=res.currents)
    np.testing.assert_allclose(back, res.tau, atol=1e-9 * np.abs(res.tau).max())


def test_bad_input_raises(mit_full):
    with pytest.raises(IdentificationError, match='1 ms'):
        ArmSimulator(mit_full, rate=200.0)
    ArmSimulator(mit_full, rate=200.0, substeps=5)  # a 1 ms step is fine
    with pytest.raises(IdentificationError, match='parameter vector'):
        ArmSimulator(mit_full, phi_true=np.ones(3))
    with pytest.raises(IdentificationError, match='kp'):
        ArmSimulator(mit_full, kp=-1.0)
    sim = ArmSimulator(mit_full)
    with pytest.raises(IdentificationError, match='reset'):
        sim.step()
    with pytest.raises(IdentificationError, match='6 joints'):
        sim.run(FourierTrajectory.crs_table1(), duration=0.1)
    with pytest.raises(IdentificationError, match='duration'):
        sim.run(FourierTrajectory.random(mit_full), duration=math.inf)
    with pytest.raises(IdentificationError, match='position_std'):
        SensorNoise(position_std=-1.0)
    with pytest.raises(IdentificationError, match='encoder_counts'):
        SensorNoise(encoder_counts=1.5)


@pytest.mark.slow
def test_simulate_verb_seeds_the_motion_and_shows_its_defaults(tmp_path, capsys):
    """Another --seed is another motion (held-out bags), unless --trajectory-seed fixes it; 100
    Hz is integrated at 1 kHz; --help states rate, noise and friction defaults."""
    import yaml

    from identification_node.cli import main
    from identification_node.batch.samples import read_samples
    from identification_node.settings import Settings

    def positions(seed: int, *more: str):
        out = tmp_path / f'{seed}{"".join(more)}'
        assert main(['simulate', '--robot', 'mit_dd_arm', '--extras', 'none', '--rate', '100',
                     '--duration', '2', '--seed', str(seed), *more, '--out', str(out)]) == 0
        settings = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': []})
        samples = read_samples(out, settings, load_robot('mit_dd_arm'))
        assert yaml.safe_load((out / 'true_parameters.yaml').read_text())['rate'] == 100
        return samples.streams[0].q

    one, two = positions(1), positions(2)
    assert one.shape == two.shape == (201, 3)
    assert np.abs(one - two).max() > 0.1
    np.testing.assert_array_equal(positions(1, '--trajectory-seed', '2'), two)
    np.testing.assert_array_equal(positions(0), positions(5, '--trajectory-seed', '0'))
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(['simulate', '--help'])
    text = ' '.join(capsys.readouterr().out.split())
    for words in ('Hz (default: 1000', 'sensor noise (default: none)',
                  "friction is the URDF's <dynamics damping friction> (none without)"):
        assert words in text, words
