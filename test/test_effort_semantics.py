"""Effort without gravity (issue 27): a UR driver's "gravity-compensated" effort, identified as
if it were the joint torque, is named in a warning.

A UR5 (example-robot-data) simulated at 500 Hz with encoder, velocity and torque noise; the
same bag with the gravity torque of the simulated parameters subtracted from the effort."""
import json

import numpy as np
import pytest

from arms import arm_urdf
from identification_node.bags.writer import BagWriter
from identification_node.cli import main
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.results.effort_semantics import gravity_check, gravity_warning
from identification_node.wire.cdr import JOINT_STATE

pytestmark = pytest.mark.slow
RATE = 500.0


def write_bag(path, robot, sim, effort) -> str:
    with BagWriter(path, 'mcap') as bag:
        bag.add_topic('/joint_states', JOINT_STATE)
        bag.write_string('/robot_description', 1, robot.description)
        for k, t in enumerate(sim.t):
            ns = int(round(t * 1e9)) + 1_000_000_000
            bag.write_joint_state('/joint_states', ns, ns * 1e-9, robot.joint_names,
                                  sim.q_meas[k], sim.qd_meas[k], effort[k])
    return str(path)


@pytest.fixture(scope='module')
def ur5_bags(tmp_path_factory):
    path = tmp_path_factory.mktemp('effort')
    robot = load_robot(arm_urdf('ur5'))
    t = np.arange(int(20 * RATE)) / RATE
    sim = simulate_kinematic(robot, None, FourierTrajectory.random(robot, seed=3), t,
                             SensorNoise(encoder_counts=2 ** 18, velocity_std=0.01,
                                         torque_std=0.1), seed=3)
    gravity = robot.inverse_dynamics(sim.q, 0 * sim.q, 0 * sim.q)
    assert np.sqrt(np.mean(gravity ** 2)) > 10    # N m: the test means something
    return robot, {'raw': write_bag(path / 'raw', robot, sim, sim.tau_meas),
                   'compensated': write_bag(path / 'compensated', robot, sim,
                                            sim.tau_meas - gravity)}


def identify(bag, capsys) -> dict:
    assert main(['identify', bag, '--urdf', str(arm_urdf('ur5')), '--json']) == 0
    return json.loads(capsys.readouterr().out)


def test_effort_without_gravity_is_named(ur5_bags, capsys):
    robot, bags = ur5_bags
    doc = identify(bags['raw'], capsys)
    assert not any('gravity' in w for w in doc['warnings']), doc['warnings']
    doc = identify(bags['compensated'], capsys)
    (line,) = [w for w in doc['warnings'] if 'effort without gravity?' in w]
    assert 'shoulder_lift_joint' in line and 'use_currents_as_efforts' in line, line


def test_gravity_check_closed_form():
    """The identified gravity's slope on the URDF's is the ratio of the parameters' scales,
    and a residual of -g correlates with g at -1."""
    from identification_node.model.identifiability import BaseParameters, sample_motion
    robot = load_robot(arm_urdf('ur5'))
    base = BaseParameters.from_robot(robot)
    q, _, _ = sample_motion(robot, 200, seed=1)
    g = robot.inverse_dynamics(q, 0 * q, 0 * q)
    theta = base.to_base(robot.phi_model)
    check = gravity_check(robot, base, 0.3 * theta, q, -g)
    assert set(check) == {'shoulder_lift_joint', 'elbow_joint'}
    for slope, corr, left in check.values():
        assert slope == pytest.approx(0.3) and corr == pytest.approx(-1.0)
        assert left == pytest.approx(-1.0)


def test_an_exact_fit_is_no_effort_without_gravity():
    """A noise-free recording fitted exactly leaves a residual of rounding size, which may
    correlate with anything (an exact 3-joint finger warned so): no warning unless the
    residual holds a share of the gravity torque (MIN_LEFT); with half of it left, the
    warning."""
    from identification_node.model.identifiability import BaseParameters, sample_motion
    robot = load_robot(arm_urdf('ur5'))
    base = BaseParameters.from_robot(robot)
    q, _, _ = sample_motion(robot, 200, seed=2)
    g = robot.inverse_dynamics(q, 0 * q, 0 * q)
    theta = base.to_base(robot.phi_model)
    noise = np.random.default_rng(0).normal(0.0, 1e-9, g.shape)
    assert abs(gravity_check(robot, base, theta, q, 1e-7 * g + noise)['elbow_joint'][1]) > 0.9
    assert gravity_warning(robot, base, theta, q, 1e-7 * g + noise) is None
    line = gravity_warning(robot, base, theta, q, -0.5 * g + noise)
    assert line is not None and 'elbow_joint 100 % (-1.00)' in line, line
