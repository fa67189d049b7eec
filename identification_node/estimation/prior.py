"""The model's own parameters as a prior, checked: a degenerate URDF inertial (mass <= 0 or
not finite, inertia about the centre of mass not positive definite) is replaced by a safe one
for the regularised parts of the solution (the full parameter set closest to the model's
that reproduces the estimate). A triangle-inequality violation alone (CAD tables have them)
is kept.

The safe inertial of a bad link: the mean mass of the good links (1 kg if none), centre of
mass at the joint origin, inertia about it m r^2 (identity) with r = 0.05 m. Standard
parameter order and frames as in robot.py (link frame, about the joint origin).
"""
from __future__ import annotations

import numpy as np

from identification_node.model.urdf_export import consistency_problems

FALLBACK_RADIUS = 0.05   # m, radius of gyration of the safe inertial


def safe_prior(robot) -> tuple[np.ndarray, list[str]]:
    """(prior phi (p,), problems): the model's own standard parameters with each degenerate
    link's 10 values replaced by the safe inertial, and what was wrong (empty when nothing).
    Non-finite friction/rotor values become 0."""
    phi = np.array(robot.phi_model, dtype=float)
    problems = [p for p in consistency_problems(robot, phi) if 'triangle' not in p]
    bad = [i for i, link in enumerate(robot.link_names)
           if any(p.startswith(f'{link}:') for p in problems)]
    good = [i for i in range(robot.dof) if i not in bad]
    masses = [phi[10 * i] for i in good]
    mass = float(np.mean(masses)) if masses else 1.0
    for i in bad:
        block = np.zeros(10)
        block[0] = mass
        block[[4, 7, 9]] = mass * FALLBACK_RADIUS ** 2     # Ixx, Iyy, Izz
        phi[10 * i:10 * i + 10] = block
    extras = phi[robot.n_inertial:]
    extras[~np.isfinite(extras)] = 0.0
    notes = [f'degenerate model inertial, replaced in the prior by a safe one ({mass:.3g} kg '
             f'at the joint origin): {p}' for p in problems if p.split(':')[0] in
             {robot.link_names[i] for i in bad}]
    notes += [p for p in problems if p.split(':')[0] not in set(robot.link_names)]
    return phi, notes
