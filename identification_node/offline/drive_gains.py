"""Drive gains from bags (estimation/drive_gains.py): the back-EMF method from a bag's joint
states, motor currents and motor voltages; the known-payload method from a bag without and one
with a known payload. And the settings whose kt carry the identified gains.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import yaml

from identification_node.bags.reader import iter_joint_state_blocks, open_bag
from identification_node.errors import IdentificationError
from identification_node.estimation.drive_gains import (DriveGain, back_emf_equations,
                                                        back_emf_gains, check_voltages,
                                                        known_payload_gains, payload_equations)
from identification_node.model.drive import emf_shape, motor_speed
from identification_node.model.robot import RobotModel
from identification_node.model.torque import TorqueConverter
from identification_node.offline.identification import (BatchOptions, auto_cutoff, batch_rows,
                                                        read_samples)
from identification_node.offline.replay import JOINT_STATES, MOTOR_CURRENTS
from identification_node.payload.fit import (PayloadChange, attachment, read_payload_changes,
                                             with_payload)
from identification_node.pipeline.samples import stack_records
from identification_node.pipeline.signals import central_derivatives
from identification_node.settings import Settings

MOTOR_VOLTAGES = '/motor_voltages'


def configured_gains(converter: TorqueConverter) -> np.ndarray:
    """kt * gear_ratio per joint (N m/A at the joint)."""
    return np.array([c.kt * c.gear_ratio for c in converter.configs])


def converter_of(settings: Settings, robot: RobotModel) -> TorqueConverter:
    return TorqueConverter(robot.joint_names, settings.torque_configs(robot.joint_names))


# -- back-EMF ---------------------------------------------------------------------------------
@dataclass
class _Channels:
    """A channel topic's values by stamp: stamps (M,) int64 ns, values (M, n, 3) (effort) and
    electrical angles (M, n) (position; NaN where not given)."""
    stamps: np.ndarray
    values: np.ndarray
    theta: np.ndarray


def _read_channels(reader, topic: str, converter: TorqueConverter, what: str) -> _Channels:
    """A motor_currents-shaped topic: channels <joint>/ia ... or <joint>/i in any order."""
    slots = converter.current_channel_slots()
    index = {name: k for k, (name, _, _) in enumerate(slots)}
    blocks = [r for _, r in iter_joint_state_blocks(reader, topic)]
    stamps, values, theta = [], [], []
    for r in stack_records(blocks):
        names = list(r.names)
        if sorted(names) != sorted(index):
            raise IdentificationError(
                f'{what} ({topic}) has channels {names}; expected {sorted(index)} (the same '
                'shape as motor_currents: the torque sources of the configuration)')
        order = [names.index(s[0]) for s in slots]
        eff = np.atleast_2d(r.effort)
        if eff.shape[1] != len(names):
            raise IdentificationError(f'{what} ({topic}): effort must hold one value per '
                                      f'channel, got {eff.shape[1]} for {len(names)}')
        stamps.append(np.atleast_1d(r.stamp_ns).astype(np.int64))
        values.append(converter.pack_currents(eff[:, order]))
        pos = np.atleast_2d(r.position)
        th = np.full((len(eff), converter.dof), np.nan)
        if pos.shape[1] == len(names):
            for k, (_, j, _) in enumerate(slots):
                th[:, j] = pos[:, order[k]]
        theta.append(th)
    if not stamps:
        raise IdentificationError(f'{what}: topic {topic} has no messages')
    s = np.concatenate(stamps)
    keep = np.argsort(s, kind='stable')
    return _Channels(s[keep], np.concatenate(values)[keep], np.concatenate(theta)[keep])


def _match(ref: np.ndarray, t: np.ndarray, tolerance_ns: float) -> np.ndarray:
    """Index of the nearest ``ref`` stamp within tolerance for each ``t`` (-1: none)."""
    hi = np.clip(np.searchsorted(ref, t), 1, max(len(ref) - 1, 1))
    lo = hi - 1
    pick = np.where(np.abs(ref[lo] - t) <= np.abs(ref[hi] - t), lo, hi)
    return np.where(np.abs(ref[pick] - t) <= tolerance_ns, pick, -1)


def back_emf_from_bag(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                      joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS,
                      motor_voltages: str = MOTOR_VOLTAGES) -> list[DriveGain]:
    """Back-EMF drive gains of the current-driven joints from one bag: joint states (measured
    velocity, else central differences of the positions), currents and voltages matched by
    header stamp within align_tolerance; di/dt by central differences of the currents."""
    converter = converter_of(settings, robot)
    if not converter.needs_currents:
        raise IdentificationError('the back-EMF method needs current-driven joints '
                                  '(torque_source current or three_phase)')
    samples = read_samples(bag, settings, robot, joint_states, motor_currents)
    with open_bag(bag) as reader:
        if motor_voltages not in reader.topics:
            raise IdentificationError(f'bag {bag} has no {motor_voltages} topic: the back-EMF '
                                      'method needs the motor voltages')
        cur = _read_channels(reader, motor_currents, converter, 'motor currents')
        volt = _read_channels(reader, motor_voltages, converter, 'motor voltages')
    check_voltages(volt.values)
    tol = settings['align_tolerance'] * 1e9
    n = robot.dof
    equations, speed_sq, count = None, np.zeros(n), 0
    for s in samples.streams:
        ic, iv = _match(cur.stamps, s.stamps_ns, tol), _match(volt.stamps, s.stamps_ns, tol)
        ok = (ic >= 0) & (iv >= 0)
        if ok.sum() < 3:
            continue
        t = (s.stamps_ns[ok] - s.stamps_ns[ok][0]) * 1e-9
        q = s.q[ok]
        qd = s.qd[ok] if samples.velocity_measured else central_derivatives(t, q)[0]
        i, v = cur.values[ic[ok]], volt.values[iv[ok]]
        used = np.isfinite(i)
        di = central_derivatives(t, np.where(used, i, 0.0).reshape(len(t), -1))[0]
        di = np.where(used, di.reshape(i.shape), np.nan)
        w = motor_speed(converter, qd)
        eq = back_emf_equations(v, i, di, emf_shape(converter, q, cur.theta[ic[ok]]), w)
        equations = eq if equations is None else equations + eq
        speed_sq += (w ** 2).sum(axis=0)
        count += len(t)
    if equations is None:
        raise IdentificationError(f'bag {bag}: no joint state has currents and voltages within '
                                  f'align_tolerance ({settings["align_tolerance"]} s)')
    gear = np.array([c.gear_ratio for c in converter.configs])
    return back_emf_gains(robot.joint_names, equations, gear, configured_gains(converter),
                          np.sqrt(speed_sq / count))


# -- known payload ----------------------------------------------------------------------------
def read_known_payload(path: str) -> PayloadChange:
    """PAYLOAD.yaml: one mapping {mass, com, inertia, link}, the fields of --payload-events
    entries (no time)."""
    try:
        with open(path) as f:
            data = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as exc:
        raise IdentificationError(f'cannot read known payload {path}: {exc}') from None
    if not isinstance(data, dict) or 'time' in data:
        raise IdentificationError(f'known payload {path}: expected one mapping of mass, com, '
                                  'inertia and link')
    change = read_payload_changes(yaml.safe_dump([dict(data, time=0.0)]))[0]
    if not change.mass > 0:
        raise IdentificationError(f'known payload {path}: mass must be > 0 kg')
    return change


def known_payload_from_bags(bag: str | os.PathLike, loaded_bag: str | os.PathLike,
                            payload: PayloadChange, settings: Settings, robot: RobotModel,
                            joint_states: str = JOINT_STATES,
                            motor_currents: str = MOTOR_CURRENTS) -> list[DriveGain]:
    """Known-payload drive gains of every joint from ``bag`` (no payload) and ``loaded_bag``
    (the arm carrying ``payload`` throughout), each processed as batch identification's
    filtered rows (shipped defaults); the payload's torque is its base-parameter increment
    through the same rows; both bags filtered at the cut-off chosen for ``bag``."""
    converter = converter_of(settings, robot)
    base = settings.build(robot).base
    attach = attachment(robot, payload.link)
    d_beta = base.to_base(with_payload(robot, attach, np.zeros(robot.num_params),
                                       payload.parameters()))
    equations, options = None, None
    for path, loaded in ((bag, False), (loaded_bag, True)):
        samples = read_samples(path, settings, robot, joint_states, motor_currents, base)
        if options is None:   # both motions filtered alike
            options = BatchOptions(cutoff=auto_cutoff(samples, settings, robot, base)[0])
        _, rows = batch_rows(samples, settings, robot, base, options)
        for r in rows:
            eq = payload_equations(r.regressor, r.tau, r.regressor @ d_beta if loaded else None,
                                   r.mask)
            equations = eq if equations is None else equations + eq
    return known_payload_gains(robot.joint_names, equations, configured_gains(converter),
                               payload.mass)


def settings_with_gains(settings: Settings, robot: RobotModel,
                        gains: list[DriveGain]) -> Settings:
    """``settings`` with kt = identified gain / gear_ratio for every current-driven joint whose
    gain is determined."""
    converter = converter_of(settings, robot)
    kt = [c.kt for c in converter.configs]
    by_joint = {g.joint: g for g in gains if g.value is not None}   # the last one wins
    for j, (name, c) in enumerate(zip(robot.joint_names, converter.configs)):
        if name in by_joint and c.source != 'measured':
            kt[j] = by_joint[name].value / c.gear_ratio
    values = dict(settings.values, kt=kt)
    return Settings(values, settings.given | {'kt'})


def identify_drive_gains(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                         joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS,
                         motor_voltages: str | None = None, loaded_bag: str | None = None,
                         payload: str | None = None) -> list[DriveGain]:
    """The drive gains of the methods asked for: back-EMF when ``motor_voltages`` is given,
    known payload when ``loaded_bag`` and ``payload`` (PAYLOAD.yaml) are; per joint the
    determined gain of least stddev is marked ``used`` (details)."""
    if (loaded_bag is None) != (payload is None):
        raise IdentificationError('--known-payload-bag and --known-payload go together')
    gains = []
    if motor_voltages:
        gains += back_emf_from_bag(bag, settings, robot, joint_states, motor_currents,
                                   motor_voltages)
    if loaded_bag:
        gains += known_payload_from_bags(bag, loaded_bag, read_known_payload(payload),
                                         settings, robot, joint_states, motor_currents)
    for joint in robot.joint_names:
        mine = [g for g in gains if g.joint == joint and g.value is not None]
        if mine:
            min(mine, key=lambda g: g.stddev / g.value).used = True
    return gains


def used_gains(gains: list[DriveGain]) -> list[DriveGain]:
    """The gains identify_drive_gains marked used (one per joint at most)."""
    return [g for g in gains if g.used]
