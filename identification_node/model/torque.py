"""Joint torques from measured efforts or motor currents.

Per joint, the torque comes from one of three sources:

- ``measured``: the joint effort as reported (e.g. JointState.effort), N m, used as is.
- ``current``: one motor current i (A), e.g. the q-axis current of a field-oriented drive:
  tau = gear_ratio * kt * i.
- ``three_phase``: the three winding currents of a brushless motor, An, Atkeson and Hollerbach
  (1986) eq. 10: tau_motor = kt (Ia sin th + Ib sin(th + 120 deg) + Ic sin(th + 240 deg)),
  tau = gear_ratio * tau_motor, with the electrical angle
  th = pole_pairs * gear_ratio * q + angle_offset (rotor angle = gear_ratio * joint angle).

kt is the motor-side torque constant in N m/A. For prismatic joints gear_ratio has units 1/m
(joint force = gear_ratio * motor torque). ``phase_order`` 'acb' means the wires of phases b and
c are swapped: the channel called ``ib`` carries the current of phase c and vice versa.
Current arrays have shape (N, n, 3) in channel (wire) order ``ia, ib, ic``; a single current
sits in channel 0.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields
from typing import Any, Mapping, Sequence

import numpy as np

from identification_node.config import default
from identification_node.errors import IdentificationError

SOURCES = ('measured', 'current', 'three_phase')
PHASE_ORDERS = ('abc', 'acb')
# Channel permutation: physical phase k is read from channel PERM[order][k] (an involution).
PERM = {'abc': (0, 1, 2), 'acb': (0, 2, 1)}
SHIFT = 2.0 * np.pi / 3.0


def _number(value: Any, field: str, joint: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise IdentificationError(
            f'torque config of joint {joint!r}: {field} must be a number, got {value!r}')
    value = float(value)
    if not math.isfinite(value):
        raise IdentificationError(
            f'torque config of joint {joint!r}: {field} must be finite, got {value}')
    return value


def _checked(values: dict, joint: str) -> dict:
    """Validated and normalised field values; errors name the joint and the field."""
    out = dict(values)
    source = out['source']
    if source not in SOURCES:
        raise IdentificationError(
            f'torque config of joint {joint!r}: source must be one of {SOURCES}, got {source!r}')
    for name in ('kt', 'gear_ratio'):
        out[name] = _number(out[name], name, joint)
        if out[name] <= 0:
            raise IdentificationError(
                f'torque config of joint {joint!r}: {name} must be > 0, got {out[name]}')
    pp = _number(out['pole_pairs'], 'pole_pairs', joint)
    if pp != round(pp) or pp < 1:
        raise IdentificationError(
            f'torque config of joint {joint!r}: pole_pairs must be an integer >= 1, '
            f'got {out["pole_pairs"]!r}')
    out['pole_pairs'] = int(pp)
    out['angle_offset'] = _number(out['angle_offset'], 'angle_offset', joint)
    if out['phase_order'] not in PHASE_ORDERS:
        raise IdentificationError(
            f'torque config of joint {joint!r}: phase_order must be one of {PHASE_ORDERS}, '
            f'got {out["phase_order"]!r}')
    return out


@dataclass(frozen=True)
class JointTorqueConfig:
    """How the torque of one joint is obtained (see the module docstring for the laws)."""

    source: str = default('torque_source')[0]
    kt: float = default('kt')[0]                # motor torque constant, N m/A (motor side)
    gear_ratio: float = default('gear_ratio')[0]   # joint torque = gear_ratio * motor torque
    pole_pairs: int = default('pole_pairs')[0]
    angle_offset: float = default('angle_offset')[0]   # electrical angle at q = 0, rad
    phase_order: str = default('phase_order')[0]

    def __post_init__(self) -> None:
        values = _checked({f.name: getattr(self, f.name) for f in fields(self)}, '(unnamed)')
        for k, v in values.items():
            object.__setattr__(self, k, v)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, joint: str = '(unnamed)'
                  ) -> 'JointTorqueConfig':
        """Config from a mapping (e.g. YAML); errors name the joint and the bad field.

        A current source needs an explicit ``kt``: a silent 1 N m/A would scale every
        identified parameter.
        """
        d = {} if d is None else d
        if not isinstance(d, Mapping):
            raise IdentificationError(
                f'torque config of joint {joint!r} must be a mapping, got {type(d).__name__}')
        allowed = [f.name for f in fields(cls)]
        unknown = sorted(set(d) - set(allowed))
        if unknown:
            raise IdentificationError(
                f'torque config of joint {joint!r}: unknown field(s) {unknown}; '
                f'allowed: {allowed}')
        values = {f.name: d.get(f.name, f.default) for f in fields(cls)}
        if values['source'] in ('current', 'three_phase') and 'kt' not in d:
            raise IdentificationError(
                f"torque config of joint {joint!r}: source {values['source']!r} needs kt "
                '(motor torque constant, N m/A)')
        return cls(**_checked(values, joint))


# -- the laws, vectorised (all arguments broadcast) ----------------------------------------------
def electrical_angle(q: np.ndarray, pole_pairs: Any, gear_ratio: Any,
                     angle_offset: Any) -> np.ndarray:
    """Electrical angle (rad) of the motor: pole_pairs * gear_ratio * q + angle_offset."""
    return (np.asarray(pole_pairs, dtype=float) * np.asarray(gear_ratio, dtype=float)
            * np.asarray(q, dtype=float) + np.asarray(angle_offset, dtype=float))


def three_phase_torque(ia: np.ndarray, ib: np.ndarray, ic: np.ndarray, theta_e: np.ndarray,
                       kt: Any) -> np.ndarray:
    """Motor torque (N m) from phase currents (A), paper 000 eq. 10."""
    th = np.asarray(theta_e, dtype=float)
    return np.asarray(kt, dtype=float) * (
        np.asarray(ia) * np.sin(th) + np.asarray(ib) * np.sin(th + SHIFT)
        + np.asarray(ic) * np.sin(th + 2.0 * SHIFT))


def phase_currents(tau_motor: np.ndarray, theta_e: np.ndarray, kt: Any
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phase currents (Ia, Ib, Ic) producing motor torque tau_motor: I sin(th + k 120 deg)
    with I = 2 tau / (3 kt), the inverse of :func:`three_phase_torque`."""
    th = np.asarray(theta_e, dtype=float)
    amp = 2.0 * np.asarray(tau_motor, dtype=float) / (3.0 * np.asarray(kt, dtype=float))
    return (amp * np.sin(th), amp * np.sin(th + SHIFT), amp * np.sin(th + 2.0 * SHIFT))


class TorqueConverter:
    """Joint torques (N, n) of the identified joints from efforts and/or motor currents.

    ``configs`` maps joint names to :class:`JointTorqueConfig` or dicts (joints not listed are
    'measured'), or is a sequence of them in joint order, or None (all measured).
    """

    def __init__(self, joint_names: Sequence[str],
                 configs: Mapping[str, Any] | Sequence[Any] | None = None):
        names = [str(j) for j in joint_names]
        if len(set(names)) != len(names):
            raise IdentificationError(f'joints listed more than once: {names}')
        if configs is None:
            configs = {}
        if isinstance(configs, Mapping):
            unknown = sorted(set(configs) - set(names))
            if unknown:
                raise IdentificationError(
                    f'torque config for unknown joint(s) {unknown}; joints: {names}')
            items = [configs.get(j) for j in names]
        else:
            items = list(configs)
            if len(items) != len(names):
                raise IdentificationError(
                    f'{len(items)} torque configs for {len(names)} joints {names}')
        self.joint_names = names
        self.configs = [c if isinstance(c, JointTorqueConfig)
                        else JointTorqueConfig.from_dict(c, j) for j, c in zip(names, items)]
        src = np.array([c.source for c in self.configs])
        self._measured = src == 'measured'
        self._single = src == 'current'
        self._three = src == 'three_phase'
        self._kt = np.array([c.kt for c in self.configs])
        self._gear = np.array([c.gear_ratio for c in self.configs])
        self._poles = np.array([c.pole_pairs for c in self.configs], dtype=float)
        self._offset = np.array([c.angle_offset for c in self.configs])
        self._perm = np.array([PERM[c.phase_order] for c in self.configs])  # (n, 3)
        # for torque(): the channels it reads, the three-phase joints and their phase columns
        self._used = np.zeros((len(names), 3), dtype=bool)   # current channels read
        self._used[self._single, 0] = True
        self._used[self._three, :] = True
        self._three_joints = np.flatnonzero(self._three)
        self._three_perm = self._perm[self._three]

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    @functools.cached_property
    def needs_currents(self) -> bool:
        return bool((~self._measured).any())

    @functools.cached_property
    def needs_measured(self) -> bool:
        return bool(self._measured.any())

    @property
    def current_joints(self) -> list[str]:
        return [j for j, m in zip(self.joint_names, self._measured) if not m]

    @property
    def measured_joints(self) -> list[str]:
        return [j for j, m in zip(self.joint_names, self._measured) if m]

    # -- channel naming -------------------------------------------------------------------------
    def current_channel_slots(self) -> list[tuple[str, int, int]]:
        """(name, joint index, channel index) of every current channel, in joint order:
        ``<joint>/ia``, ``<joint>/ib``, ``<joint>/ic`` for three-phase joints (channels 0-2),
        ``<joint>/i`` (channel 0) for single-current joints."""
        out = []
        for i, (j, c) in enumerate(zip(self.joint_names, self.configs)):
            if c.source == 'three_phase':
                out += [(f'{j}/{w}', i, k) for k, w in enumerate(('ia', 'ib', 'ic'))]
            elif c.source == 'current':
                out.append((f'{j}/i', i, 0))
        return out

    def current_channel_names(self) -> list[str]:
        """Names of the current channels the converter expects, in order."""
        return [s[0] for s in self.current_channel_slots()]

    def pack_currents(self, values: np.ndarray) -> np.ndarray:
        """(N, m) values in :meth:`current_channel_names` order -> (N, n, 3) currents, NaN in
        unused channels."""
        slots = self.current_channel_slots()
        v = np.asarray(values, dtype=float)
        if v.ndim == 1:
            v = v[None, :]
        if v.ndim != 2 or v.shape[1] != len(slots):
            raise IdentificationError(
                f'current values have shape {v.shape}; expected (N, {len(slots)}) for channels '
                f'{[s[0] for s in slots]}')
        out = np.full((v.shape[0], self.dof, 3), np.nan)
        if slots:
            out[:, [s[1] for s in slots], [s[2] for s in slots]] = v
        return out

    # -- conversions ------------------------------------------------------------------------------
    def _array(self, a: Any, name: str, shape: tuple) -> np.ndarray:
        a = np.asarray(a, dtype=float)
        if a.ndim == len(shape) - 1:
            a = a[None]
        if a.shape[1:] != shape[1:] or (shape[0] is not None and a.shape[0] != shape[0]):
            want = ('N',) + shape[1:] if shape[0] is None else shape
            raise IdentificationError(
                f'{name} has shape {a.shape}; expected {want} for joints {self.joint_names}')
        return a

    def _need_finite(self, a: np.ndarray, name: str) -> None:
        bad = ~np.isfinite(a)
        if bad.any():
            k, j = (int(v) for v in np.argwhere(bad)[0][:2])
            raise IdentificationError(
                f'{name} of joint {self.joint_names[j]!r} is NaN or inf (first at sample {k})')

    def theta_e(self, q: np.ndarray) -> np.ndarray:
        """Electrical angles (N, n) computed from joint positions (N, n)."""
        return electrical_angle(q, self._poles, self._gear, self._offset)

    def torque(self, q: np.ndarray, measured: np.ndarray | None = None,
               currents: np.ndarray | None = None, theta_e: np.ndarray | None = None
               ) -> np.ndarray:
        """Joint torques (N, n), N m.

        q (N, n) joint positions; measured (N, n) efforts (read for 'measured' joints only);
        currents (N, n, 3) in wire order (read for current joints only); theta_e (N, n)
        measured electrical angles, NaN where not given (then computed from q).
        """
        q = self._array(q, 'q', (None, self.dof))
        shape = (q.shape[0], self.dof)
        tau = np.zeros(shape)
        m = self._measured
        if m.any():
            if measured is None:
                raise IdentificationError(
                    f'measured efforts needed for joints {self.measured_joints}')
            meas = self._array(measured, 'measured effort', shape)
            self._need_finite(np.where(m, meas, 0.0), 'measured effort')
            tau[:, m] = meas[:, m]
        if self.needs_currents:
            if currents is None:
                raise IdentificationError(
                    f'motor currents needed for joints {self.current_joints} '
                    f'(channels {self.current_channel_names()})')
            cur = self._array(currents, 'currents', shape + (3,))
            self._need_finite(np.where(self._used, cur, 0.0), 'current')
            s = self._single
            tau[:, s] = self._gear[s] * self._kt[s] * cur[:, s, 0]
            t = self._three
            if len(self._three_joints):
                th = np.zeros(shape)
                th[:, t] = electrical_angle(q[:, t], self._poles[t], self._gear[t],
                                            self._offset[t])
                if theta_e is not None:
                    given = self._array(theta_e, 'theta_e', shape)
                    th = np.where(np.isnan(given), th, given)
                self._need_finite(np.where(t, th, 0.0), 'electrical angle (theta_e or q)')
                phys = cur[:, self._three_joints[:, None], self._three_perm]   # physical order
                tau[:, t] = self._gear[t] * three_phase_torque(
                    phys[..., 0], phys[..., 1], phys[..., 2], th[:, t], self._kt[t])
        return tau

    def currents_from_torque(self, tau: np.ndarray, q: np.ndarray,
                             theta_e: np.ndarray | None = None) -> np.ndarray:
        """Currents (N, n, 3) in wire order that :meth:`torque` turns back into tau (N, n).
        NaN for 'measured' joints and unused channels (for simulation)."""
        tau = self._array(tau, 'tau', (None, self.dof))
        q = self._array(q, 'q', tau.shape)
        out = np.full(tau.shape + (3,), np.nan)
        s = self._single
        out[:, s, 0] = tau[:, s] / (self._gear[s] * self._kt[s])
        t = self._three
        if t.any():
            th = self.theta_e(q)
            if theta_e is not None:
                given = self._array(theta_e, 'theta_e', tau.shape)
                th = np.where(np.isnan(given), th, given)
            phys = np.stack(phase_currents(tau[:, t] / self._gear[t], th[:, t], self._kt[t]),
                            axis=-1)
            # PERM is an involution: channel k carries physical phase perm[k].
            out[:, t] = np.take_along_axis(phys, self._perm[t][None], axis=2)
        return out
