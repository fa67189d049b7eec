"""The simulated arm into a rosbag2 bag (the ``simulate`` verb's use case), and the true
parameters a simulation runs with.

The bag holds /joint_states (position, velocity, effort), /motor_currents when the torque
sources use currents (channels ``<joint>/ia`` ..., amperes in effort, electrical angle in
position) and /motor_voltages alike (volts in effort; model/drive.py: the drives' true kt may
differ from the configured one, true values under ``drives``), /robot_description (latched)
and /clock, stamped at the simulated sample times plus ``stamp_offset``; and
``true_parameters.yaml`` beside it with the parameters the arm was simulated with (payload
events under ``payload_events``, with their stamps).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from identification_node.config import flatten
from identification_node.errors import IdentificationError
from identification_node.model.robot import RobotModel
from identification_node.safe_yaml import read_yaml

__all__ = ['SimulationOptions', 'SimulatedBag', 'read_true_parameters', 'simulate_bag']


def read_true_parameters(path: str, robot: RobotModel, what: str) -> np.ndarray:
    """The robot's own phi with the values of a YAML mapping (standard parameter name -> value,
    nested mappings joined with dots) put in; the links it changes must stay physically
    consistent. ``what`` names the option or parameter in errors."""
    from identification_node.model.urdf_export import consistency_problems

    data = read_yaml(path, f'{what}: {path}')
    if not isinstance(data, Mapping):
        raise IdentificationError(f'{what}: {path} does not hold a mapping')
    phi = robot.phi_model.copy()
    for key, value in flatten(data).items():
        if key not in robot.param_names:
            raise IdentificationError(f'{what}: {path} names {key!r}, not a standard '
                                      f'parameter of {robot.name} ({robot.param_names[0]}, ...)')
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise IdentificationError(f'{what}: {key} = {value!r} is not a number')
        phi[robot.param_names.index(key)] = float(value)
    own = set(consistency_problems(robot, robot.phi_model))   # the description's own faults
    problems = [p for p in consistency_problems(robot, phi) if p not in own]
    if problems:
        raise IdentificationError(f'{what}: the parameters of {path} are not '
                                  f'physically consistent: {"; ".join(problems)}')
    return phi


@dataclass(frozen=True)
class SimulationOptions:
    """What to simulate and how to record it (SI units; the ``simulate`` verb's options)."""
    out: str
    trajectory: str = 'fourier'
    duration: float | None = None
    rate: float = 1000.0
    storage: str = 'mcap'
    overwrite: bool = False
    seed: int = 0
    trajectory_seed: int | None = None
    stamp_offset: float = 0.0
    position_std: float = 0.0
    encoder_counts: int = 0
    velocity_std: float = 0.0
    torque_std: float = 0.0
    current_std: float = 0.0
    voltage_std: float = 0.0
    kt_error: Sequence[float] = (0.0,)
    motor_resistance: Sequence[float] = (0.5,)
    motor_inductance: Sequence[float] = (1e-3,)
    no_velocity: bool = False
    no_effort: bool = False
    clock: bool = False
    true_parameters: str | None = None
    payload_events: str | None = None
    arguments: Mapping[str, Any] = field(default_factory=dict)   # recorded in the truth file


@dataclass(frozen=True)
class SimulatedBag:
    """The bag written: its robot, sample count, duration (s) and truth file."""
    robot: str
    samples: int
    duration: float
    truth: Path


def simulate_bag(settings: Any, opts: SimulationOptions) -> SimulatedBag:
    """Simulate the arm of ``settings`` (a settings.Settings) as fast as the machine allows and
    write the bag and its truth file (module docstring)."""
    from identification_node.bags.writer import BagWriter, check_replaceable
    from identification_node.excitation.trajectories import load_trajectory
    from identification_node.fileio import atomic_write_yaml
    from identification_node.model.drive import DriveModel
    from identification_node.model.identifiability import BaseParameters
    from identification_node.model.torque import TorqueConverter
    from identification_node.payload.fit import (attachment, read_payload_changes,
                                                 true_parameter_changes)
    from identification_node.simulation.simulator import ArmSimulator, SensorNoise
    from identification_node.wire.cdr import JOINT_STATE

    if opts.overwrite:   # before simulating: only a bag is replaced
        check_replaceable(opts.out, '--out')
    robot = settings.load_robot()
    configured = TorqueConverter(robot.joint_names, settings.torque_configs(robot.joint_names))
    drives = DriveModel.per_joint(robot.dof, list(opts.motor_resistance),
                                  list(opts.motor_inductance), list(opts.kt_error))
    converter = drives.true_converter(configured)
    noise = SensorNoise(opts.position_std, opts.encoder_counts, opts.velocity_std,
                        opts.torque_std, opts.current_std)
    trajectory = load_trajectory(opts.trajectory, robot, opts.seed if (
        opts.trajectory_seed is None) else opts.trajectory_seed)
    phi = (read_true_parameters(opts.true_parameters, robot, '--true-parameters')
           if opts.true_parameters else robot.phi_model.copy())
    payloads = read_payload_changes(opts.payload_events) if opts.payload_events else []
    substeps = max(1, math.ceil(1000.0 / opts.rate - 1e-9)) if opts.rate > 0 else 1
    sim = ArmSimulator(robot, phi, rate=opts.rate, substeps=substeps).run(
        trajectory, opts.duration, noise, opts.seed, converter,
        changes=true_parameter_changes(robot, phi, payloads))
    names = list(robot.joint_names)
    slots = converter.current_channel_slots()
    volts = drives.voltages(converter, sim.t, sim.q, sim.qd, sim.tau, opts.voltage_std,
                            np.random.default_rng([opts.seed, 1])) if slots else None
    stamps = np.round((sim.t + opts.stamp_offset) * 1e9).astype(np.int64)
    with BagWriter(opts.out, opts.storage, overwrite=opts.overwrite) as bag:
        bag.add_topic('/joint_states', JOINT_STATE)
        if robot.kind == 'urdf':
            bag.write_string('/robot_description', int(stamps[0]), robot.description)
        for k, ns in enumerate(stamps.tolist()):
            t = ns * 1e-9
            bag.write_joint_state('/joint_states', ns, t, names, sim.q_meas[k],
                                  () if opts.no_velocity else sim.qd_meas[k],
                                  () if opts.no_effort else sim.tau_meas[k])
            if volts is not None:   # current channels (slots)
                bag.write_joint_state(
                    '/motor_currents', ns, t, [s[0] for s in slots],
                    [sim.theta_e[k, i] for _, i, _ in slots],
                    (), [sim.currents[k, i, c] for _, i, c in slots])
                bag.write_joint_state(
                    '/motor_voltages', ns, t, [s[0] for s in slots],
                    [sim.theta_e[k, i] for _, i, _ in slots],
                    (), [volts[k, i, c] for _, i, c in slots])
            if opts.clock:
                bag.write_clock(ns)
    base = BaseParameters.from_robot(robot)
    truth: dict[str, Any] = {
        'robot': robot.name, 'joints': names, 'arguments': dict(opts.arguments),
        'trajectory': opts.trajectory, 'rate': opts.rate, 'samples': len(sim),
        'noise': vars(noise), 'seed': opts.seed,
        'standard_parameters': dict(zip(robot.param_names, map(float, phi))),
        'base_parameters': {n: float(v) for n, v in zip(base.names, base.to_base(phi))},
    }
    if slots:
        truth['drives'] = {j: {'kt': c.kt, 'gain': c.kt * c.gear_ratio, 'resistance': float(r),
                               'inductance': float(ind), 'configured_kt': k.kt}
                           for j, c, k, r, ind in zip(names, converter.configs, configured.configs,
                                                      drives.resistance, drives.inductance)
                           if c.source != 'measured'}
    if payloads:
        truth['payload_events'] = [dict(
            c.document(), link=attachment(robot, c.link).link, stamp=c.time + opts.stamp_offset,
            parameters=c.parameters().tolist()) for c in payloads]
    path = atomic_write_yaml(f'{opts.out}/true_parameters.yaml', truth)
    return SimulatedBag(robot.name, len(sim), float(sim.t[-1]), Path(path))
