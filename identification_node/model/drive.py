"""The electrical law of a joint's motor drive: terminal voltage from current and motor speed.

Per channel of ``motor_currents`` (the same channels on ``motor_voltages``):

    V = R i + L di/dt + e,   e = K_E omega_motor s,   omega_motor = gear_ratio * qd,

with s = 1 for a ``current`` joint (one current, e.g. the q axis of a field-oriented drive) and
s = sin(th + k 120 deg) for phase k of a ``three_phase`` joint (th the electrical angle, as in
model/torque.py). Convention (README, Conventions): phase quantities are per phase, phase to
neutral (star point), instantaneous values (so amplitudes are peak, not RMS). With this
convention the electrical power of the back-EMF, sum_k e_k i_k, equals tau_motor omega_motor
for eq. 10's torque, tau_motor = K_T sum_k i_k sin(th + k 120 deg), exactly when K_E = K_T
(V s/rad = N m/A). Line-to-line voltages are phase differences: divide a line-to-line peak
back-EMF constant by sqrt(3) for this one. The drive gain of a joint is K_T * gear_ratio
(N m/A at the joint). Arrays: (N, n, 3) in wire order, NaN in unused channels, SI units.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.model.torque import PERM, SHIFT, JointTorqueConfig, TorqueConverter


def emf_shape(converter: TorqueConverter, q: np.ndarray, theta_e: np.ndarray | None = None
              ) -> np.ndarray:
    """s (N, n, 3) in wire order: 1 in channel 0 of current joints, sin(th + k 120 deg) of the
    physical phase a three-phase channel carries; NaN elsewhere."""
    q = np.asarray(q, dtype=float)
    out = np.full(q.shape + (3,), np.nan)
    src = np.array([c.source for c in converter.configs])
    out[:, src == 'current', 0] = 1.0
    t = src == 'three_phase'
    if t.any():
        th = converter.theta_e(q)
        if theta_e is not None:
            th = np.where(np.isnan(theta_e), th, theta_e)
        phys = np.sin(th[:, t, None] + SHIFT * np.arange(3))
        perm = np.array([PERM[c.phase_order] for c in converter.configs])[t]
        out[:, t] = np.take_along_axis(phys, perm[None], axis=2)
    return out


def motor_speed(converter: TorqueConverter, qd: np.ndarray) -> np.ndarray:
    """omega_motor (N, n) = gear_ratio * qd (rad/s)."""
    return np.asarray(qd, dtype=float) * np.array([c.gear_ratio for c in converter.configs])


@dataclass(frozen=True)
class DriveModel:
    """The electrical parameters of a simulated arm's drives, per joint: resistance R (ohm),
    inductance L (H), and ``kt_error``, the relative error of the configured torque constant:
    true K_T = configured K_T * (1 + kt_error) (the true one is also K_E)."""

    resistance: np.ndarray
    inductance: np.ndarray
    kt_error: np.ndarray

    @classmethod
    def per_joint(cls, n: int, resistance=0.5, inductance=1e-3, kt_error=0.0) -> DriveModel:
        values = []
        for name, v in (('motor resistance', resistance), ('motor inductance', inductance),
                        ('kt error', kt_error)):
            a = np.atleast_1d(np.asarray(v, dtype=float))
            if a.shape not in ((1,), (n,)) or not np.all(np.isfinite(a)):
                raise IdentificationError(f'{name}: give 1 or {n} finite values, got {v!r}')
            values.append(np.broadcast_to(a, (n,)).copy())
        if np.any(values[0] < 0) or np.any(values[1] < 0) or np.any(values[2] <= -1):
            raise IdentificationError('motor resistance and inductance must be >= 0 and the kt '
                                      'error > -1')
        return cls(*values)

    def true_converter(self, configured: TorqueConverter) -> TorqueConverter:
        """The converter of the true torque constants (what the simulated drives obey)."""
        configs = [JointTorqueConfig(c.source, c.kt * (1.0 + e), c.gear_ratio, c.pole_pairs,
                                     c.angle_offset, c.phase_order)
                   for c, e in zip(configured.configs, self.kt_error)]
        return TorqueConverter(configured.joint_names, configs)

    def voltages(self, true: TorqueConverter, t: np.ndarray, q: np.ndarray, qd: np.ndarray,
                 tau: np.ndarray, voltage_std: float = 0.0,
                 rng: np.random.Generator | None = None) -> np.ndarray:
        """Terminal voltages (N, n, 3) of the drives producing joint torques tau (N, n) at
        (q, qd) (N, n) and times t (N,), plus Gaussian noise of ``voltage_std`` V. di/dt:
        the torque's derivative by central differences, the phase rotation analytically."""
        if not (math.isfinite(voltage_std) and voltage_std >= 0):
            raise IdentificationError(f'voltage std must be >= 0, got {voltage_std!r}')
        t = np.asarray(t, dtype=float)
        i = true.currents_from_torque(tau, q)
        step = max(float(np.median(np.diff(t))), 1e-9) if len(t) > 1 else 1.0
        tau_dot = np.gradient(tau, axis=0) / step if len(t) > 1 else np.zeros_like(tau)
        di = true.currents_from_torque(tau_dot, q)   # the amplitude's change, rotation frozen
        s = emf_shape(true, q)
        w = motor_speed(true, qd)
        three = np.array([c.source == 'three_phase' for c in true.configs])
        if three.any():   # d/dt of A sin(th + k 120) adds A cos(th + k 120) omega_e
            pp = np.array([c.pole_pairs for c in true.configs], dtype=float)
            amp = 2.0 * tau / (3.0 * np.array([c.kt * c.gear_ratio for c in true.configs]))
            cos = _phase_cos(true, q)
            di[:, three] += (amp * pp * w)[:, three, None] * cos[:, three]
        kt = np.array([c.kt for c in true.configs])
        v = (self.resistance[:, None] * i + self.inductance[:, None] * di
             + (kt * w)[..., None] * s)
        if voltage_std > 0:
            rng = np.random.default_rng(0) if rng is None else rng
            v = v + voltage_std * rng.standard_normal(v.shape)
        return v


def _phase_cos(converter: TorqueConverter, q: np.ndarray) -> np.ndarray:
    """cos(th + k 120 deg) (N, n, 3) in wire order (three-phase joints; else NaN)."""
    th = converter.theta_e(q)
    out = np.full(th.shape + (3,), np.nan)
    perm = np.array([PERM[c.phase_order] for c in converter.configs])
    phys = np.cos(th[..., None] + SHIFT * np.arange(3))
    out[:] = np.take_along_axis(phys, perm[None], axis=2)
    return out
