"""Drive gains from bags (estimation/drive_gains.py): the back-EMF method from a bag's joint
states, motor currents and motor voltages; the known-payload method from a bag without and one
with a known payload. And the settings whose kt carry the identified gains.
"""
from __future__ import annotations

import os

import numpy as np
import yaml

from identification_node.bags.feed import JOINT_STATES, MOTOR_CURRENTS
from identification_node.bags.reader import iter_joint_state_blocks, open_bag
from identification_node.batch.rows import BatchOptions, auto_cutoff, batch_rows
from identification_node.batch.samples import read_samples
from identification_node.errors import IdentificationError
from identification_node.estimation.drive_gains import (DriveGain, known_payload_gains,
                                                        mark_used, payload_equations)
from identification_node.model.robot import RobotModel
from identification_node.model.torque import TorqueConverter
from identification_node.payload.fit import (PayloadChange, attachment, read_payload_changes,
                                             with_payload)
from identification_node.pipeline.back_emf import BackEmfStream
from identification_node.settings import Settings

__all__ = ['MOTOR_VOLTAGES', 'configured_gains', 'converter_of', 'back_emf_from_bag',
           'read_known_payload', 'known_payload_from_bags', 'settings_with_gains',
           'identify_drive_gains', 'used_gains']

MOTOR_VOLTAGES = '/motor_voltages'


def configured_gains(converter: TorqueConverter) -> np.ndarray:
    """kt * gear_ratio per joint (N m/A at the joint)."""
    return np.array([c.kt * c.gear_ratio for c in converter.configs])


def converter_of(settings: Settings, robot: RobotModel) -> TorqueConverter:
    return TorqueConverter(robot.joint_names, settings.torque_configs(robot.joint_names))


# -- back-EMF ---------------------------------------------------------------------------------
def back_emf_from_bag(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                      joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS,
                      motor_voltages: str = MOTOR_VOLTAGES) -> list[DriveGain]:
    """Back-EMF drive gains of the current-driven joints from one bag's joint states, currents
    and voltages, through the node's BackEmfStream."""
    stream = BackEmfStream(converter_of(settings, robot), settings['align_tolerance'])
    with open_bag(bag) as reader:
        for topic, intake in ((joint_states, stream.joint_states),
                              (motor_currents, stream.currents),
                              (motor_voltages, stream.voltages)):
            if topic not in reader.topics:
                raise IdentificationError(f'bag {bag} has no {topic} topic: the back-EMF '
                                          'method needs joint states, motor currents and '
                                          'voltages')
            for _, record in iter_joint_state_blocks(reader, topic):
                intake.add(record)
    stream.process(flush=True)
    return stream.gains()


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
    """Known-payload drive gains of the current-driven joints from ``bag`` (no payload) and
    ``loaded_bag`` (the arm carrying ``payload`` throughout), each processed as batch
    identification's filtered rows (shipped defaults); the payload's torque is its
    base-parameter increment through the same rows; both bags filtered at the cut-off chosen
    for ``bag``."""
    converter = converter_of(settings, robot)
    if not converter.needs_currents:
        raise IdentificationError('drive gains need current-driven joints (torque_source '
                                  'current or three_phase)')
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
    assert equations is not None   # batch_rows yields rows or raises
    gains = known_payload_gains(robot.joint_names, equations, configured_gains(converter),
                                payload.mass)
    return [g for g in gains if g.joint in converter.current_joints]


def settings_with_gains(settings: Settings, robot: RobotModel,
                        gains: list[DriveGain]) -> Settings:
    """``settings`` with kt = identified gain / gear_ratio for every current-driven joint whose
    gain is determined."""
    converter = converter_of(settings, robot)
    kt = [c.kt for c in converter.configs]
    by_joint = {g.joint: g.value for g in gains if g.value is not None}   # the last one wins
    for j, (name, c) in enumerate(zip(robot.joint_names, converter.configs)):
        if name in by_joint and c.source != 'measured':
            kt[j] = by_joint[name] / c.gear_ratio
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
    if loaded_bag and payload is not None:   # both or neither
        gains += known_payload_from_bags(bag, loaded_bag, read_known_payload(payload),
                                         settings, robot, joint_states, motor_currents)
    return mark_used(gains)


def used_gains(gains: list[DriveGain]) -> list[DriveGain]:
    """The gains identify_drive_gains marked used (one per joint at most)."""
    return [g for g in gains if g.used]
