"""A payload given by a user (``~/payload/set``), checked as a URDF <inertial> would have to be
before it is used: mass (kg) positive, finite and at most ``max_mass``; centre of mass (m,
3 values, the payload link's frame) finite; inertia about the centre of mass (kg m^2, ixx ixy
ixz iyy iyz izz) positive definite with principal moments obeying the triangle inequality,
or all zero (a point mass)."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.model.robot import RobotModel
from identification_node.model.urdf_export import inertia_problems
from identification_node.payload.fit import payload_parameters


def max_payload_mass(robot: RobotModel, margin: float) -> float:
    """The heaviest plausible payload (kg): ``margin`` times the arm's own mass in its
    description (no arm carries more than itself); unbounded when the description has no
    positive finite masses."""
    total = float(np.sum(robot.phi_model[0:robot.n_inertial:10]))
    return margin * total if math.isfinite(total) and total > 0 else math.inf


def payload_problems(mass: float, com: Sequence[float], inertia: Sequence[float],
                     max_mass: float = math.inf) -> list[str]:
    """Why the payload cannot be used (empty when it can); see the module doc."""
    problems = []
    try:
        m = float(mass)
        c = np.asarray(com, dtype=float)
        Ic = np.asarray(inertia, dtype=float)
    except (TypeError, ValueError):
        return ['mass, com and inertia must be numbers']
    if not (math.isfinite(m) and m > 0):
        problems.append(f'mass {m:g} kg is not positive and finite')
    elif m > max_mass:
        problems.append(f'mass {m:g} kg exceeds {max_mass:g} kg (plausibility.margin times '
                        "the arm's own mass)")
    if c.shape != (3,) or not np.isfinite(c).all():
        problems.append('com needs 3 finite values (m)')
    if Ic.shape != (6,) or not np.isfinite(Ic).all():
        problems.append('inertia needs 6 finite values ixx ixy ixz iyy iyz izz (kg m^2)')
    elif Ic.any():
        matrix = np.array([[Ic[0], Ic[1], Ic[2]], [Ic[1], Ic[3], Ic[4]],
                           [Ic[2], Ic[4], Ic[5]]])
        problems += inertia_problems(matrix)
    return problems


def checked_payload(mass: float, com: Sequence[float] = (0.0, 0.0, 0.0),
                    inertia: Sequence[float] = (0.0,) * 6,
                    max_mass: float = math.inf) -> np.ndarray:
    """The payload's 10 parameters about the link frame origin (fit.payload_parameters), or
    IdentificationError saying everything wrong with it."""
    problems = payload_problems(mass, com, inertia, max_mass)
    if problems:
        raise IdentificationError('payload refused: ' + '; '.join(problems))
    return payload_parameters(float(mass), com, inertia)
