"""Drive gains identified in situ: N m/A at the joint (K_T * gear ratio), two methods.

- ``back_emf`` (Corke; the second seed paper, section IV.A): per joint, least squares of the
  terminal voltage on (current, its derivative, back-EMF shape * motor speed), model/drive.py's
  law V = R i + L di/dt + K_E omega_motor s, all channels of the joint stacked; K_T = K_E.
- ``known_payload`` (Gautier and Briot's global identification): motion without and with a
  known payload. The measured quantity is the current, so it is the output: per joint j,
  tau_conf_j = Y_j psi_j + c_j tau_payload_j, with tau_conf the torque of the configured gain
  (a fixed multiple of the current, the noise where it is), Y_j the base regressor row, psi_j =
  theta * g_conf / g_true and c_j = g_conf_j / g_true_j; linear in (psi_j, c_j). The payload's
  known torque is the only term not scaled by the unknown gain, so it fixes the scale.

Both solve per-joint normal equations (estimation/normal_equations.py): the equations of joint
j are tau_j = X_j x_j. A gain whose relative standard deviation exceeds ``DETERMINED`` is
reported 'not determined' (with its stddev).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.normal_equations import NormalEquations

DETERMINED = 0.05     # relative stddev above which a gain is not determined
WARN_SIGMA = 3.0      # identified vs configured: warn beyond this many stddev ...
WARN_RELATIVE = 0.05  # ... and this relative difference
MIN_FIT = 0.9         # back-EMF: fraction of the voltage variance the law must explain
MAX_VOLTAGE = 1000.0  # V: larger terminal voltages are taken for wrong units
METHODS = ('back_emf', 'known_payload')


@dataclass
class DriveGain:
    """One joint's identified drive gain ``value`` (N m/A at the joint, None when not
    determined) with ``stddev``, by ``method``, beside the ``configured`` kt * gear_ratio;
    ``reason`` says why it is not determined; ``details`` holds the method's other values
    (back-EMF: resistance ohm, inductance H, the fraction of the voltage variance explained)."""

    joint: str
    value: float | None
    stddev: float
    method: str
    configured: float
    reason: str = ''
    details: dict = field(default_factory=dict)
    used: bool = False   # the gain the identification's torques were computed with

    @property
    def ratio(self) -> float | None:
        """identified / configured."""
        return None if self.value is None else self.value / self.configured

    @property
    def warning(self) -> str | None:
        """A warning when the identified gain differs from the configured one by more than
        WARN_SIGMA stddev and WARN_RELATIVE."""
        if self.value is None:
            return f'drive gain of {self.joint} not determined by {self.method}: {self.reason}'
        diff = abs(self.value - self.configured)
        if diff > WARN_SIGMA * self.stddev and diff > WARN_RELATIVE * self.configured:
            return (f'drive gain of {self.joint}: identified {self.value:.5g} +- '
                    f'{self.stddev:.2g} N m/A ({self.method}) differs from the configured '
                    f'kt * gear_ratio = {self.configured:.5g} '
                    f'by {100 * (self.value / self.configured - 1):+.1f} '
                    '%: the torques (and every parameter of this joint) scale with it')
        return None

    def document(self) -> dict:
        return {'joint': self.joint, 'value': self.value, 'stddev': self.stddev,
                'method': self.method, 'configured': self.configured, 'ratio': self.ratio,
                'determined': self.value is not None, 'reason': self.reason or None,
                'used': self.used,
                **{k: float(v) for k, v in self.details.items()}}


def _joint_solve(equations: NormalEquations, j: int, rcond: float = 1e-10
                 ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Least squares of joint j's equations: x, covariance, rss and the degrees of freedom.
    Columns that never enter the joint's rows are 0 with infinite variance; directions the
    joint's rows leave free are dropped (pseudo-inverse)."""
    G, b = equations.gram[j], equations.cross[j]
    d = np.sqrt(np.maximum(np.diag(G), 0.0))
    used = d > 1e-12 * max(d.max(), 1e-300)
    x = np.zeros(len(d))
    cov = np.diag(np.full(len(d), np.inf))
    if not used.any():
        return x, cov, float(equations.sq[j]), float(equations.count[j])
    s = d[used]
    Gs = G[np.ix_(used, used)] / np.outer(s, s)
    w, V = np.linalg.eigh(Gs)
    keep = w > rcond * w[-1]
    P = (V[:, keep] / w[keep]) @ V[:, keep].T / np.outer(s, s)
    x[used] = P @ b[used]
    rss = float(equations.rss(x)[j])
    dof = float(equations.count[j]) - int(keep.sum())
    if dof < 1:
        raise IdentificationError(f'not enough samples: {int(equations.count[j])} equations '
                                  f'for {int(keep.sum())} unknowns of joint {j}')
    cov[np.ix_(used, used)] = P * (rss / dof)
    return x, cov, rss, dof


def _gain(joint: str, value: float, stddev: float, method: str, configured: float,
          reason: str, details: dict | None = None) -> DriveGain:
    ok = (math.isfinite(value) and value > 0 and math.isfinite(stddev)
          and stddev <= DETERMINED * value)
    if ok:
        reason = ''
    elif math.isfinite(value) and value <= 0:
        reason = f'the fit gives a gain <= 0 ({value:.3g}): {reason}'
    return DriveGain(joint, float(value) if ok else None,
                     float(stddev) if math.isfinite(stddev) else math.inf, method,
                     float(configured), reason, details or {})


# -- back-EMF ---------------------------------------------------------------------------------
def back_emf_equations(voltage: np.ndarray, current: np.ndarray, current_rate: np.ndarray,
                       shape: np.ndarray, speed: np.ndarray) -> NormalEquations:
    """Per-joint normal equations of V = [i, di/dt, omega s] [R, L, K_E]' from (N, n, 3)
    arrays in channel order (NaN in unused channels: left out) and motor speed (N, n)."""
    X = np.stack([current, current_rate, shape * speed[..., None]], axis=-1)  # (N, n, 3, 3)
    ok = np.isfinite(X).all(axis=-1) & np.isfinite(voltage)
    X = np.where(ok[..., None], X, 0.0)
    v = np.where(ok, voltage, 0.0)
    rows = np.concatenate([X, v[..., None]], axis=-1)          # (N, n, 3, 4)
    aug = np.einsum('kjcp,kjcq->jpq', rows, rows)
    return NormalEquations(aug, ok.sum(axis=(0, 2)).astype(float))


def back_emf_gains(joints: list[str], equations: NormalEquations, gear: np.ndarray,
                   configured: np.ndarray, speed_rms: np.ndarray) -> list[DriveGain]:
    """Drive gains K_E * gear (N m/A at the joint) of the joints with current channels
    (count > 0), with R (ohm) and L (H) in the details."""
    out = []
    for j, name in enumerate(joints):
        if equations.count[j] == 0:
            continue
        x, cov, rss, dof = _joint_solve(equations, j)
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
        explained = 1.0 - rss / max(float(equations.sq[j]), 1e-300)
        reason = f'not excited: the motor barely turns (speed rms {speed_rms[j]:.3g} rad/s)'
        g = _gain(name, x[2] * gear[j], sd[2] * gear[j], 'back_emf', configured[j], reason,
                  {'resistance': x[0], 'inductance': x[1], 'explained': explained})
        if g.value is not None and explained < MIN_FIT:
            g.value, g.reason = None, (
                f'implausible voltages: the law V = R i + L di/dt + K_E omega explains '
                f'{100 * explained:.0f} % of their variance (units, channel order, sign?)')
        out.append(g)
    return out


def check_voltages(voltage: np.ndarray, what: str = 'motor voltages') -> None:
    """The plausibility gate of terminal voltages (N, n, 3) in volts: finite where used, and
    within MAX_VOLTAGE (larger ones are mV or counts, not V)."""
    v = voltage[np.isfinite(voltage)]
    if v.size == 0:
        raise IdentificationError(f'{what}: no values')
    peak = float(np.abs(v).max())
    if peak > MAX_VOLTAGE:
        raise IdentificationError(
            f'{what} reach {peak:.4g}, beyond {MAX_VOLTAGE:g} V: not volts (mV or counts?); '
            'the topic carries volts in effort')


# -- known payload ----------------------------------------------------------------------------
def payload_equations(regressor: np.ndarray, tau: np.ndarray, payload_tau: np.ndarray | None,
                      mask: np.ndarray | None = None) -> NormalEquations:
    """Per-joint normal equations of tau = [Y | tau_payload] [psi; c] for rows (N, n, b),
    torques (N, n) of the configured gains and the known payload's torque (N, n; None: no
    payload); ``mask`` (N, n) False leaves an equation out."""
    N, n, _ = regressor.shape
    p = np.zeros((N, n)) if payload_tau is None else payload_tau
    X = np.concatenate([regressor, p[..., None]], axis=2)
    m = np.ones((N, n)) if mask is None else mask.astype(float)
    eq = NormalEquations.from_rows(X * m[..., None], tau * m)
    return NormalEquations(eq.augmented, m.sum(axis=0))


def known_payload_gains(joints: list[str], equations: NormalEquations,
                        configured: np.ndarray, payload_mass: float) -> list[DriveGain]:
    """Drive gains g = configured / c per joint from payload_equations of both motions."""
    out = []
    for j, name in enumerate(joints):
        x, cov, _, _ = _joint_solve(equations, j)
        c, sc = x[-1], math.sqrt(max(cov[-1, -1], 0.0))
        value = configured[j] / c if c != 0 else math.inf
        sd = configured[j] * sc / c ** 2 if c != 0 else math.inf
        reason = (f'the payload ({payload_mass:g} kg) is too small, or too little excited, to '
                  f'fix the scale (relative stddev {100 * sd / abs(value):.2g} % > '
                  f'{100 * DETERMINED:g} %)' if math.isfinite(sd) and value != 0 else
                  'the payload changes no torque of this joint')
        out.append(_gain(name, value, sd, 'known_payload', configured[j], reason))
    return out


def mark_used(gains: list[DriveGain]) -> list[DriveGain]:
    """``gains`` with, per joint, the determined gain of least relative stddev marked
    ``used`` (the others not)."""
    best: dict[str, tuple[float, DriveGain]] = {}   # joint: (relative stddev, gain)
    for g in gains:
        g.used = False
        if g.value is not None:
            relative = g.stddev / g.value
            if g.joint not in best or relative < best[g.joint][0]:
                best[g.joint] = (relative, g)
    for _, g in best.values():
        g.used = True
    return gains


def gains_text(gains: list[DriveGain]) -> list[str]:
    """The drive gains as text lines."""
    lines = ['', 'drive gains (N m/A at the joint = K_T x gear ratio):']
    for g in gains:
        shown = (f'{g.value:.5g} +- {g.stddev:.2g}' if g.value is not None
                 else f'not determined (stddev {g.stddev:.2g})')
        ratio = '' if g.ratio is None else f', ratio {g.ratio:.4f}'
        used = ', used' if g.used else ''
        lines.append(f'  {g.joint}: {shown} ({g.method}{used}); configured '
                     f'{g.configured:.5g}{ratio}')
        if g.value is None:
            lines.append(f'    {g.reason}')
    return lines
