"""The sign of the Coulomb friction model, tau_fc = fc sign(qd), shared by the regressor, the
smoothed Coulomb column and the residual checks.

A joint at rest has a smoothed or differentiated velocity of rounding size (1e-19 to 1e-12
rad/s), whose sign is arbitrary: taken as it is, a resting joint's Coulomb column flips between
-1 and 1 with the arithmetic's order. Speeds below REST_SPEED are rest: sign 0.
"""
from __future__ import annotations

import numpy as np

__all__ = ['REST_SPEED', 'coulomb_column', 'coulomb_sign']

REST_SPEED = 1e-9   # rad/s (m/s for prisms): far below any encoder's resolution of a motion


def coulomb_sign(qd: np.ndarray) -> np.ndarray:
    """sign(qd), 0 where |qd| <= REST_SPEED (same shape)."""
    qd = np.asarray(qd, dtype=float)
    return np.where(np.abs(qd) > REST_SPEED, np.sign(qd), 0.0)


def coulomb_column(qd: np.ndarray, coulomb_velocity: float | np.ndarray) -> np.ndarray:
    """The Coulomb term per unit fc: tanh(qd / coulomb_velocity) (one value, or one per joint
    of qd's last axis, all > 0), or coulomb_sign(qd) when coulomb_velocity is 0."""
    v = np.asarray(coulomb_velocity, dtype=float)
    return np.tanh(qd / v) if np.all(v > 0) else coulomb_sign(qd)
