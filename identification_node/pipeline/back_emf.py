"""The back-EMF drive-gain stream: joint states, motor currents and motor voltages (records, CDR
bytes or blocks, as the pipeline's intake takes them) matched by header stamp and summed into
per-joint normal equations of V = R i + L di/dt + K_E omega s (estimation/drive_gains.py).

Used by the node (live topics) and by ``identify --back-emf`` (a bag's messages) alike. A
joint state is decided once currents and voltages stamped at or after it are in (or at
``flush``); it is used when both lie within ``align_tolerance``. Motor speed: the measured joint
velocity, else central differences of the positions; di/dt: central differences of the
currents, within runs of samples without a gap over GAP_STEPS sample periods.
"""
from __future__ import annotations

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.drive_gains import (DriveGain, back_emf_equations,
                                                        back_emf_gains, check_voltages)
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.model.drive import emf_shape, motor_speed
from identification_node.model.torque import TorqueConverter
from identification_node.pipeline.intake import Intake
from identification_node.pipeline.samples import stack_records
from identification_node.pipeline.signals import central_derivatives
from identification_node.pipeline.validate import Counters

GAP_STEPS = 5.0


def _empty(n: int, channels: bool) -> tuple:
    shape = (0, n, 3) if channels else (0, n)
    return np.zeros(0, dtype=np.int64), np.zeros(shape), np.zeros((0, n))


class BackEmfStream:
    """Queued inputs (``joint_states``, ``currents``, ``voltages``: Intakes), ``process``
    sums what is decided; ``gains`` solves. Joints follow ``converter.joint_names``."""

    def __init__(self, converter: TorqueConverter, align_tolerance: float):
        if not converter.needs_currents:
            raise IdentificationError('the back-EMF method needs current-driven joints '
                                      '(torque_source current or three_phase)')
        self.converter, self.tolerance = converter, int(round(align_tolerance * 1e9))
        self.counters = Counters()
        self.joint_states = Intake(self.counters)
        self.currents = Intake(self.counters)
        self.voltages = Intake(self.counters)
        n = converter.dof
        self._js: tuple[np.ndarray, ...] = (np.zeros(0, dtype=np.int64), np.zeros((0, n)),
                                            np.zeros((0, n)))
        self._cur, self._volt = _empty(n, True), _empty(n, True)
        self.equations = NormalEquations.zeros(3, n)
        self._speed_sq, self.samples = np.zeros(n), 0
        self._velocity = True

    # -- records to arrays --------------------------------------------------------------------
    def _joint_arrays(self, records: list) -> list:
        names = self.converter.joint_names
        parts = []
        for r in stack_records(records):
            have = list(r.names)
            if not set(names) <= set(have):
                continue   # the pipeline counts messages without every joint
            idx = [have.index(j) for j in names]
            pos, vel = np.atleast_2d(r.position), np.atleast_2d(r.velocity)
            qd = (vel[:, idx] if vel.shape[1] == len(have)
                  else np.full((len(pos), len(idx)), np.nan))
            parts.append((np.atleast_1d(r.stamp_ns).astype(np.int64), pos[:, idx], qd))
        return parts

    def _channel_arrays(self, records: list, what: str) -> list:
        slots = self.converter.current_channel_slots()
        wanted = sorted(s[0] for s in slots)
        parts = []
        for r in stack_records(records):
            have = list(r.names)
            if sorted(have) != wanted:
                raise IdentificationError(
                    f'{what} have channels {have}; expected {wanted} (the shape of '
                    'motor_currents: the torque sources of the configuration)')
            order = [have.index(s[0]) for s in slots]
            eff = np.atleast_2d(r.effort)
            if eff.shape[1] != len(have):
                raise IdentificationError(f'{what}: effort must hold one value per channel, '
                                          f'got {eff.shape[1]} for {len(have)}')
            pos = np.atleast_2d(r.position)
            th = np.full((len(eff), self.converter.dof), np.nan)
            if pos.shape[1] == len(have):
                th[:, [s[1] for s in slots]] = pos[:, order]
            parts.append((np.atleast_1d(r.stamp_ns).astype(np.int64),
                          self.converter.pack_currents(eff[:, order]), th))
        return parts

    @staticmethod
    def _append(buffer: tuple, parts: list) -> tuple:
        if not parts:
            return buffer
        out = tuple(np.concatenate([b] + [p[k] for p in parts]) for k, b in enumerate(buffer))
        order = np.argsort(out[0], kind='stable')
        return tuple(a[order] for a in out)

    # -- processing ---------------------------------------------------------------------------
    def process(self, flush: bool = False) -> int:
        """Sum the joint states decided so far (all at ``flush``); returns how many were used.
        Raises IdentificationError on voltages or currents of the wrong shape or units."""
        self._js = self._append(self._js, self._joint_arrays(self.joint_states.take()))
        self._cur = self._append(self._cur, self._channel_arrays(self.currents.take(),
                                                                 'motor currents'))
        volts = self._channel_arrays(self.voltages.take(), 'motor voltages')
        for p in volts:
            check_voltages(p[1])
        self._volt = self._append(self._volt, volts)
        t = self._js[0]
        if len(t) == 0 or len(self._cur[0]) == 0 or len(self._volt[0]) == 0:
            return 0
        horizon = np.inf if flush else min(self._cur[0][-1], self._volt[0][-1])
        k = int(np.searchsorted(t, horizon, side='right'))
        if k < 3:
            return 0
        ic, iv = self._match(self._cur[0], t[:k]), self._match(self._volt[0], t[:k])
        ok = np.flatnonzero((ic >= 0) & (iv >= 0))
        used = self._add(ok, ic, iv) if len(ok) >= 3 else 0
        keep = t[k - 1] - self.tolerance
        self._js = tuple(a[k:] for a in self._js)
        self._cur = tuple(a[self._cur[0] >= keep] for a in self._cur)
        self._volt = tuple(a[self._volt[0] >= keep] for a in self._volt)
        return used

    def _match(self, ref: np.ndarray, t: np.ndarray) -> np.ndarray:
        hi = np.minimum(np.searchsorted(ref, t), len(ref) - 1)
        lo = np.maximum(hi - 1, 0)
        pick = np.where(np.abs(ref[lo] - t) <= np.abs(ref[hi] - t), lo, hi)
        return np.where(np.abs(ref[pick] - t) <= self.tolerance, pick, -1)

    def _add(self, rows: np.ndarray, ic: np.ndarray, iv: np.ndarray) -> int:
        """Equations of the matched joint states ``rows``, run by run between gaps."""
        stamps = self._js[0][rows]
        step = np.diff(stamps)
        if len(step) == 0:
            return 0
        cut = np.flatnonzero(step > GAP_STEPS * max(np.median(step), 1)) + 1
        used = 0
        for run in np.split(np.arange(len(rows)), cut):
            if len(run) < 3:
                continue
            r = rows[run]
            t = (self._js[0][r] - self._js[0][r[0]]) * 1e-9
            q, qd = self._js[1][r], self._js[2][r]
            if np.isnan(qd).any():
                self._velocity = False
                qd = central_derivatives(t, q)[0]
            i, v, th = self._cur[1][ic[r]], self._volt[1][iv[r]], self._cur[2][ic[r]]
            present = np.isfinite(i)
            di = central_derivatives(t, np.where(present, i, 0.0).reshape(len(t), -1))[0]
            di = np.where(present, di.reshape(i.shape), np.nan)
            w = motor_speed(self.converter, qd)
            self.equations = self.equations + back_emf_equations(
                v, i, di, emf_shape(self.converter, q, th), w)
            self._speed_sq += (w ** 2).sum(axis=0)
            self.samples += len(t)
            used += len(t)
        return used

    def gains(self) -> list[DriveGain]:
        """The drive gains of the current-driven joints from everything summed."""
        if self.samples == 0:
            raise IdentificationError('no joint state had motor currents and voltages within '
                                      f'align_tolerance ({self.tolerance * 1e-9:g} s)')
        conv = self.converter
        gear = np.array([c.gear_ratio for c in conv.configs])
        configured = np.array([c.kt * c.gear_ratio for c in conv.configs])
        return back_emf_gains(conv.joint_names, self.equations, gear, configured,
                              np.sqrt(self._speed_sq / self.samples))
