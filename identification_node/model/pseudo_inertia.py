"""The pseudo-inertia of a rigid body, and how a link's identified block is shared with the
locked bodies merged into it.

A link block phi = [m, mx, my, mz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz] (robot.py's order: inertia
about the frame origin, kg, kg m, kg m^2) has the 4x4 pseudo-inertia (Wensing, Kim and Slotine
2017)

    J = [[Sigma, h], [h', m]],  Sigma = tr(I)/2 1 - I,  h = (mx, my, mz),

positive definite exactly when the block is a physical body, and linear in phi.

The links of locked joints (a gripper's fingers, a hand) are merged into the identified link
they hang from: the torques see the link's own body and theirs only as one sum. Their share is
their description's block F scaled by s > 0 (every locked body scaled alike, so each stays
physical), s the minimiser of the log-det (Bregman) divergences of the own body to its
description's and of the scaled share to F (Lee, Wensing and Park 2020):

    d(J - s J_F || J0) + d(s J_F || J_F),  d(J || J0) = -log det(J0^-1 J) + tr(J0^-1 J) - 4,

the split the consistent solve's prior makes (estimation/consistency.py). Any physical block
J > 0 has one, with the own body J - s J_F > 0.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import eigh
from scipy.optimize import brentq

__all__ = ['FROM_J', 'from_pseudo_inertia', 'inertia_about_origin', 'link_inertia',
           'locked_scale', 'pseudo_inertia', 'regularised', 'repaired']

# phi block (10,) = FROM_J @ vec(J) (J symmetric 4x4, row-major flattening)
FROM_J = np.zeros((10, 16))
for _row, _terms in enumerate([
        [(3, 3, 1)], [(0, 3, 1)], [(1, 3, 1)], [(2, 3, 1)],
        [(1, 1, 1), (2, 2, 1)], [(0, 1, -1)], [(0, 2, -1)],
        [(0, 0, 1), (2, 2, 1)], [(1, 2, -1)], [(0, 0, 1), (1, 1, 1)]]):
    for _a, _b, _c in _terms:
        FROM_J[_row, 4 * _a + _b] = _c


def inertia_about_origin(phi10: np.ndarray) -> np.ndarray:
    """The 3x3 inertia (kg m^2, about the frame origin) of a link block."""
    Ixx, Ixy, Ixz, Iyy, Iyz, Izz = phi10[4:]
    return np.array([[Ixx, Ixy, Ixz], [Ixy, Iyy, Iyz], [Ixz, Iyz, Izz]])


def link_inertia(phi10: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, centre of mass (3,), inertia about the centre of mass (3, 3)) of one link block;
    a massless one: centre at the origin, its inertia about the origin."""
    m = float(phi10[0])
    Io = inertia_about_origin(phi10)
    c = phi10[1:4] / m if m != 0 else np.zeros(3)
    return m, c, Io - m * (c @ c * np.eye(3) - np.outer(c, c))


def pseudo_inertia(phi10: np.ndarray) -> np.ndarray:
    """The 4x4 pseudo-inertia of a link block (about the frame origin; kg m^2, kg m, kg)."""
    m, h = phi10[0], np.asarray(phi10[1:4])
    inertia = inertia_about_origin(phi10)
    J = np.empty((4, 4))
    J[:3, :3] = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    J[:3, 3] = J[3, :3] = h
    J[3, 3] = m
    return J


def from_pseudo_inertia(J: np.ndarray) -> np.ndarray:
    """The link block [m, mx, ..., Izz] of a pseudo-inertia (inverse of pseudo_inertia)."""
    return FROM_J @ np.asarray(J, dtype=float).reshape(16)


def repaired(J: np.ndarray, floor: float) -> np.ndarray:
    """The nearest pseudo-inertia with eigenvalues >= floor (eigenvalues raised)."""
    ev, V = np.linalg.eigh(0.5 * (J + J.T))
    return (V * np.maximum(ev, floor)) @ V.T


def regularised(J: np.ndarray, floor: float = 0.0) -> tuple[np.ndarray, bool]:
    """A prior's pseudo-inertia made positive definite, and whether it had to be: unchanged
    when its smallest eigenvalue exceeds 1e-9 of its largest, else (singular to rounding: no
    physical body) its eigenvalues raised to max(1e-3 x the largest, ``floor``)."""
    ev = np.linalg.eigvalsh(J)
    if ev[0] > 1e-9 * max(ev[-1], 0.0):
        return J, False
    return repaired(J, max(1e-3 * ev[-1], floor)), True


def locked_scale(total: np.ndarray, locked: np.ndarray, prior: np.ndarray) -> float:
    """The scale s of the locked bodies' block ``locked`` (10,) within a link's identified
    block ``total`` (10,), given the description's own body ``prior`` (4x4 pseudo-inertia;
    raised to positive definite when it is not): the minimiser of the divergences above, so
    that the own body total - s locked is physical. 1 when nothing is locked or ``total`` is
    not a physical body (no split has a physical own body)."""
    B = pseudo_inertia(np.asarray(locked, dtype=float))
    if not B[3, 3] > 0:
        return 1.0
    A = pseudo_inertia(np.asarray(total, dtype=float))
    if not np.isfinite(A).all() or np.linalg.eigvalsh(A)[0] <= 0:
        return 1.0
    J0 = regularised(prior, 1e-15)[0]
    lam = eigh(B, A, eigvals_only=True)          # det(A - s B) = det A prod(1 - s lam)
    if not lam[-1] > 0:
        return 1.0
    c = float(np.trace(np.linalg.solve(J0, B)))
    s_max = 1.0 / lam[-1]

    def slope(s: float) -> float:                # d/ds of the divergences, increasing in s
        return float(np.sum(lam / (1.0 - s * lam))) - c + 4.0 - 4.0 / s

    return float(brentq(slope, 1e-12 * s_max, (1.0 - 1e-12) * s_max, xtol=1e-14, rtol=1e-12))
