"""Effort semantics: does the recorded effort carry the gravity torque?

Some drivers publish an effort with the gravity torque taken out (UR's ROS 2 driver by default
since its "gravity-compensated" effort; Franka's external-torque estimate). Identified from it,
the estimate's gravity torque collapses toward zero and what is left of gravity shows in the
residual. On a subsample of the training bag's rows (q and the raw torque of every sample the
smoother gives motion for, validation.evaluate), per joint whose gravity torque under the
URDF's own parameters matters: the slope of the estimate's gravity torque on the URDF's
(about 1 for a right effort and a roughly right URDF, near 0 without gravity) and the
correlation of the residual (raw torque - Yb theta) with the URDF's gravity torque, and the
share of the URDF's gravity torque the residual holds (its slope on it). SI units.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from identification_node.estimation.model_terms import MIN_CORRELATION
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel

__all__ = ['GravityFit', 'MIN_LEFT', 'MIN_ROWS', 'MIN_SHARE', 'MIN_SLOPE', 'gravity_check',
           'gravity_warning', 'training_gravity_warning']

MIN_SLOPE = 0.5         # identified gravity below half the URDF's: effort without gravity?
MIN_SHARE = 0.25        # joints whose gravity RMS is at least this share of the largest one
MIN_ROWS = 100          # fewer rows: no judgement
MIN_LEFT = 0.05         # a correlated residual warns when it holds this share of the gravity


class GravityFit(NamedTuple):
    """One joint's gravity_check: the estimate's gravity torque's slope on the URDF's, the
    residual's correlation with the URDF's, and the residual's slope on it (the share of the
    URDF's gravity torque left in the residual)."""
    slope: float
    correlation: float
    left: float


def gravity_check(robot: RobotModel, base: BaseParameters, theta: np.ndarray,
                  q: np.ndarray, residual: np.ndarray) -> dict[str, GravityFit]:
    """Per joint carrying gravity (its RMS gravity torque under the URDF's parameters at least
    MIN_SHARE of the largest): the GravityFit of the estimate ``theta`` (b,) and ``residual``
    (N, n: raw torque - Yb theta) against the URDF's gravity torque, over rows at positions q
    (N, n); empty with fewer than MIN_ROWS rows or without gravity."""
    q, residual = np.asarray(q, dtype=float), np.asarray(residual, dtype=float)
    if len(q) < MIN_ROWS:
        return {}
    zero = np.zeros_like(q)
    Yg = base.base_regressor(robot.regressor(q, zero, zero))
    g_model = Yg @ base.to_base(robot.phi_model)
    g_est = Yg @ np.asarray(theta, dtype=float)
    rms = np.sqrt(np.mean(g_model ** 2, axis=0))
    if not rms.max() > 0:
        return {}
    out = {}
    for j in np.flatnonzero(rms >= MIN_SHARE * rms.max()):
        gm = g_model[:, j]
        gg = gm @ gm
        r, c = residual[:, j] - residual[:, j].mean(), gm - gm.mean()
        scale = np.sqrt((r @ r) * (c @ c))
        out[robot.joint_names[j]] = GravityFit(float(g_est[:, j] @ gm / gg),
                                               float(r @ c / scale) if scale > 0 else 0.0,
                                               float(residual[:, j] @ gm / gg))
    return out


def gravity_warning(robot: RobotModel, base: BaseParameters, theta: np.ndarray,
                    q: np.ndarray, residual: np.ndarray) -> str | None:
    """The warning when, on a joint carrying gravity (gravity_check), the estimate's gravity
    torque is below MIN_SLOPE of the URDF's, or the residual correlates with the URDF's gravity
    torque beyond MIN_CORRELATION and holds at least MIN_LEFT of it (a residual near nothing,
    an exact fit, correlates with anything); None otherwise."""
    found = {j: v for j, v in gravity_check(robot, base, theta, q, residual).items()
             if v.slope < MIN_SLOPE or (abs(v.correlation) > MIN_CORRELATION
                                        and abs(v.left) >= MIN_LEFT)}
    if not found:
        return None
    return ('effort without gravity? identified gravity torque in % of the URDF\'s (residual '
            'correlation with it): ' + ', '.join(
                f'{j} {100 * v.slope:.0f} % ({v.correlation:.2f})' for j, v in found.items())
            + '; the effort may have the gravity torque taken out (UR driver: record with '
            'use_currents_as_efforts, or the motor currents; Franka: the measured joint torque, '
            'not the external-torque estimate), or the URDF\'s masses are far off')


def training_gravity_warning(ident, training) -> str | None:
    """gravity_warning of an Identification's estimate on its training bag's evaluated rows
    (validation.BagError ``training``, whose series keeps q); None without them."""
    series = None if training is None else training.series
    if series is None or series.q is None or not len(series.q):
        return None
    residual = series.measured - series.predicted(ident.estimate)
    return gravity_warning(ident.robot, ident.base, ident.estimate, series.q, residual)
