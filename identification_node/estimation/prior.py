"""The model's own parameters as a prior, checked: a degenerate URDF inertial (mass <= 0 or
not finite, inertia about the centre of mass not positive definite) is replaced by a safe one
for the regularised parts of the solution (the full parameter set closest to the model's
that reproduces the estimate). A triangle-inequality violation alone (CAD tables have them)
is kept.

The safe inertial of a bad link keeps what the URDF gives of it: its mass when positive and
finite (else the mean mass of the good links, 1 kg if none), its centre of mass when finite
(else the joint origin), with an inertia about the centre of mass of m r^2 (identity), r =
0.05 m. A link the URDF leaves without any inertial whose child joints all sit at its origin
is the frame between concurrent axes (a ball joint written as three revolute joints), no
body: it gets VIRTUAL_MASS of that mean mass, so that the consistent solve (each body's mass
within consistency.mass_ratio of its prior) leaves it nearly massless. Standard parameter
order and frames as in robot.py (link frame, about the joint origin).
"""
from __future__ import annotations

import numpy as np

from identification_node.model.urdf_export import consistency_problems

FALLBACK_RADIUS = 0.05   # m, radius of gyration of the safe inertial
VIRTUAL_MASS = 1e-3      # of the mean mass: the prior of a link between concurrent axes


def between_concurrent_axes(robot) -> list[bool]:
    """Per identified link: whether it has child joints and all of them sit at its origin
    (the frame between the axes of a ball or universal joint written as revolute joints)."""
    model = robot.model
    out = []
    for j in robot.joint_ids:
        children = [k for k in range(1, model.njoints) if model.parents[k] == j]
        out.append(bool(children) and all(
            np.linalg.norm(model.jointPlacements[k].translation) <= 1e-9 for k in children))
    return out


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
    fallback = float(np.mean(masses)) if masses else 1.0
    virtual = between_concurrent_axes(robot)
    replaced = {}
    for i in bad:
        given = phi[10 * i:10 * i + 10]
        m = float(given[0]) if np.isfinite(given[0]) and given[0] > 0 else fallback
        massless = virtual[i] and not np.any(given)
        if massless:
            m = VIRTUAL_MASS * fallback
        c = given[1:4] / given[0] if m == given[0] else np.zeros(3)
        if not np.isfinite(c).all():
            c = np.zeros(3)
        inertia = m * FALLBACK_RADIUS ** 2 * np.eye(3) + m * (c @ c * np.eye(3) - np.outer(c, c))
        phi[10 * i:10 * i + 10] = np.r_[m, m * c, inertia[np.triu_indices(3)]]
        replaced[robot.link_names[i]] = (
            f"{m:.3g} kg at {'its centre of mass' if np.any(c) else 'the joint origin'}, "
            f'radius of gyration {FALLBACK_RADIUS:g} m'
            + ('; a link between concurrent joint axes, kept nearly massless'
               if massless else ''))
    extras = phi[robot.n_inertial:]
    extras[~np.isfinite(extras)] = 0.0
    notes = [f'degenerate model inertial, replaced in the prior by a safe one '
             f"({replaced[p.split(':')[0]]}): {p}" for p in problems
             if p.split(':')[0] in replaced]
    notes += [p for p in problems if p.split(':')[0] not in set(robot.link_names)]
    return phi, notes
