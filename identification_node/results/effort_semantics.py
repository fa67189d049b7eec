"""Effort semantics: does the recorded effort carry the gravity torque?

Some drivers publish an effort with the gravity torque taken out (UR's ROS 2 driver by default
since its "gravity-compensated" effort; Franka's external-torque estimate). Identified from it,
the estimate's gravity torque collapses toward zero and what is left of gravity shows in the
residual. On a subsample of the training bag's rows (q and the raw torque of every sample the
smoother gives motion for, validation.evaluate), per joint whose gravity torque under the
URDF's own parameters matters: the slope of the estimate's gravity torque on the URDF's
(about 1 for a right effort and a roughly right URDF, near 0 without gravity) and the
correlation of the residual (raw torque - Yb theta) with the URDF's gravity torque. SI units.
"""
from __future__ import annotations

import numpy as np

from identification_node.estimation.model_terms import MIN_CORRELATION
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel

__all__ = ['MIN_SLOPE', 'MIN_SHARE', 'MIN_ROWS', 'gravity_check', 'gravity_warning',
           'training_gravity_warning']

MIN_SLOPE = 0.5         # identified gravity below half the URDF's: effort without gravity?
MIN_SHARE = 0.25        # joints whose gravity RMS is at least this share of the largest one
MIN_ROWS = 100          # fewer rows: no judgement


def gravity_check(robot: RobotModel, base: BaseParameters, theta: np.ndarray,
                  q: np.ndarray, residual: np.ndarray) -> dict[str, tuple[float, float]]:
    """Per joint carrying gravity (its RMS gravity torque under the URDF's parameters at least
    MIN_SHARE of the largest): (slope of the estimate ``theta``'s (b,) gravity torque on the
    URDF's, correlation of ``residual`` (N, n: raw torque - Yb theta) with the URDF's gravity
    torque), over rows at positions q (N, n); empty with fewer than MIN_ROWS rows or without
    gravity."""
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
        slope = float(g_est[:, j] @ gm / (gm @ gm))
        r, c = residual[:, j] - residual[:, j].mean(), gm - gm.mean()
        scale = np.sqrt((r @ r) * (c @ c))
        out[robot.joint_names[j]] = (slope, float(r @ c / scale) if scale > 0 else 0.0)
    return out


def gravity_warning(robot: RobotModel, base: BaseParameters, theta: np.ndarray,
                    q: np.ndarray, residual: np.ndarray) -> str | None:
    """The warning when, on a joint carrying gravity (gravity_check), the estimate's gravity
    torque is below MIN_SLOPE of the URDF's or the residual correlates with the URDF's gravity
    torque beyond MIN_CORRELATION; None otherwise."""
    found = {j: v for j, v in gravity_check(robot, base, theta, q, residual).items()
             if v[0] < MIN_SLOPE or abs(v[1]) > MIN_CORRELATION}
    if not found:
        return None
    return ('effort without gravity? identified gravity torque in % of the URDF\'s (residual '
            'correlation with it): ' + ', '.join(
                f'{j} {100 * k:.0f} % ({r:.2f})' for j, (k, r) in found.items())
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
