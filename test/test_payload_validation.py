"""A payload given by a user is checked as a URDF <inertial> would have to be (issue 31):
physically valid bodies (pinocchio's solid primitives) pass, with the parameters pinocchio
gives them; every defect is refused naming it."""
import math

import numpy as np
import pinocchio as pin
import pytest

from identification_node.errors import IdentificationError
from identification_node.model.robot import PIN_ORDER, load_robot
from identification_node.payload.validation import (checked_payload, max_payload_mass,
                                                    payload_problems)

SYM = ([0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2])


def six(I3):
    return np.asarray(I3)[SYM].tolist()


@pytest.mark.parametrize('body', [pin.Inertia.FromBox(2.0, 0.1, 0.2, 0.3),
                                  pin.Inertia.FromCylinder(0.5, 0.04, 0.2),
                                  pin.Inertia.FromSphere(1.5, 0.05),
                                  pin.Inertia.FromEllipsoid(0.3, 0.02, 0.05, 0.1)])
def test_solid_bodies_pass_with_pinocchios_parameters(body):
    rng = np.random.default_rng(3)
    R = pin.exp3(rng.normal(size=3))
    c = rng.uniform(-0.1, 0.1, 3)
    Ic = R @ body.inertia @ R.T            # rotated: products of inertia too
    phi = checked_payload(body.mass, c.tolist(), six(Ic), max_mass=10.0)
    expected = pin.Inertia(body.mass, c, Ic).toDynamicParameters()[PIN_ORDER]
    np.testing.assert_allclose(phi, expected, rtol=1e-12, atol=1e-15)


def test_a_point_mass_passes():
    assert payload_problems(0.7, [0.0, 0.0, 0.1], [0.0] * 6) == []


@pytest.mark.parametrize('mass, com, inertia, reason', [
    (1e300, [0, 0, 0], [0] * 6, 'exceeds'),
    (-1.0, [0, 0, 0], [0] * 6, 'not positive'),
    (0.0, [0, 0, 0], [0] * 6, 'not positive'),
    (math.nan, [0, 0, 0], [0] * 6, 'not positive'),
    (math.inf, [0, 0, 0], [0] * 6, 'not positive'),
    (1.0, [0, math.nan, 0], [0] * 6, 'com'),
    (1.0, [0, 0], [0] * 6, 'com'),
    (1.0, [0, 0, 0], [-1, 0, 0, 0.01, 0, 0.01], 'not positive definite'),
    (1.0, [0, 0, 0], [0.01, 0.02, 0, 0.01, 0, 0.01], 'not positive definite'),
    (1.0, [0, 0, 0], [0.05, 0, 0, 0.01, 0, 0.01], 'triangle inequality'),
    (1.0, [0, 0, 0], [0.01, 0, 0, 0.01, 0, math.inf], 'inertia'),
    (1.0, [0, 0, 0], [0.01] * 5, 'inertia'),
    ('heavy', [0, 0, 0], [0] * 6, 'numbers'),
])
def test_defects_are_refused_naming_them(mass, com, inertia, reason):
    problems = payload_problems(mass, com, inertia, max_mass=100.0)
    assert len(problems) == 1 and reason in problems[0], problems
    with pytest.raises(IdentificationError, match=reason):
        checked_payload(mass, com, inertia, max_mass=100.0)


def test_the_mass_bound_is_the_arms_own_mass_times_the_margin():
    robot = load_robot('test/fixtures/panda_like.urdf')
    total = sum(robot.model.inertias[j].mass for j in range(1, robot.model.njoints))
    assert math.isclose(max_payload_mass(robot, 2.0), 2.0 * total, rel_tol=1e-12)
    assert payload_problems(2.0 * total * 1.01, [0, 0, 0], [0] * 6,
                            max_payload_mass(robot, 2.0))
