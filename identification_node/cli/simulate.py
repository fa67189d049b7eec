"""``simulate``: the simulated arm, as fast as the machine allows, into a rosbag2 bag.

Writes /joint_states (position, velocity, effort), /motor_currents when the settings' torque
sources use currents (channels ``<joint>/ia`` ..., amperes in effort, electrical angle in
position) and /motor_voltages alike (volts in effort; model/drive.py: the drives' true kt may
differ from the configured one by --kt-error, true values under ``drives``),
/robot_description (latched) and /clock, with header stamps and log times at the simulated
sample times plus ``--stamp-offset``; and ``true_parameters.yaml`` in the bag
directory with the parameters the arm was simulated with (``--payload-events``: the payloads
attached at given times, under ``payload_events``, with their stamps).
"""
from __future__ import annotations

import argparse

from identification_node.cli import add_robot_arguments, add_settings_arguments, settings_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_robot_arguments(parser, required=False)
    add_settings_arguments(parser)
    parser.add_argument('--trajectory', default='fourier',
                        help="paper_moves, table1, fourier (random coefficients, see "
                        "--trajectory-seed), or a .yaml/.csv file (default: fourier)")
    parser.add_argument('--duration', type=float, default=None,
                        help='s (default: the trajectory duration or one period)')
    parser.add_argument('--rate', type=float, default=1000.0,
                        help='sample rate, Hz (default: 1000; integrated at 1 kHz or faster)')
    parser.add_argument('--out', required=True, help='bag directory to create')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='(default: mcap)')
    parser.add_argument('--overwrite', action='store_true')
    parser.add_argument('--seed', type=int, default=0,
                        help='seed of the sensor noise and of the fourier motion (default: 0)')
    parser.add_argument('--trajectory-seed', type=int, metavar='SEED',
                        help='seed of the fourier motion alone (default: --seed)')
    parser.add_argument('--stamp-offset', type=float, default=0.0,
                        help='s added to stamps (default: 0)')
    noise = parser.add_argument_group('sensor noise (default: none)')
    noise.add_argument('--position-std', type=float, default=0.0, help='rad (default: 0)')
    noise.add_argument('--encoder-counts', type=int, default=0,
                       help='per revolution (default: 0, no quantisation)')
    noise.add_argument('--velocity-std', type=float, default=0.0, help='rad/s (default: 0)')
    noise.add_argument('--torque-std', type=float, default=0.0, help='N m (default: 0)')
    noise.add_argument('--current-std', type=float, default=0.0, help='A (default: 0)')
    noise.add_argument('--voltage-std', type=float, default=0.0,
                       help='V, on motor_voltages (default: 0)')
    drive = parser.add_argument_group(
        'motor drives (current-driven joints; model/drive.py, README Conventions)')
    drive.add_argument('--kt-error', type=float, nargs='+', default=[0.0], metavar='E',
                       help='true kt = configured kt x (1 + E): one value or one per joint '
                       '(the manufacturer\'s specification off by E)')
    drive.add_argument('--motor-resistance', type=float, nargs='+', default=[0.5],
                       metavar='OHM', help='per phase (one value or one per joint)')
    drive.add_argument('--motor-inductance', type=float, nargs='+', default=[1e-3],
                       metavar='H', help='per phase (one value or one per joint)')
    parser.add_argument('--no-velocity', action='store_true', help='omit JointState.velocity')
    parser.add_argument('--no-effort', action='store_true', help='omit JointState.effort')
    parser.add_argument('--clock', action='store_true', help='also write /clock')
    parser.add_argument('--true-parameters', metavar='FILE',
                        help='YAML mapping of standard parameter names to the values to '
                        'simulate instead of the model\'s own (e.g. joint1.fv: 0.5); default: '
                        'the model\'s own, whose friction is the URDF\'s <dynamics damping '
                        'friction> (none without)')
    parser.add_argument('--payload-events', metavar='YAML',
                        help='payloads attached at given times: a YAML file or inline list '
                        'of {time: s, mass: kg, com: [x, y, z], inertia: [ixx, ixy, ixz, iyy, '
                        'iyz, izz], link: L} (com in the link frame, inertia about the com; '
                        'mass 0 detaches; default link the last identified one)')


def true_parameters(robot, path: str | None):
    """The robot's own standard parameters with the overrides of a YAML file."""
    from identification_node.errors import IdentificationError
    from identification_node.safe_yaml import read_yaml
    phi = robot.phi_model
    if not path:
        return phi
    given = read_yaml(path, f'true parameters {path}') or {}
    if not isinstance(given, dict):
        raise IdentificationError(f'{path} must map parameter names to values')
    for name, value in given.items():
        if not isinstance(value, (int, float)):
            raise IdentificationError(f'{path}: {name} = {value!r} is not a number')
        phi[robot.param_index(name)] = float(value)
    return phi


def run(args: argparse.Namespace) -> int:
    import math

    import numpy as np

    from identification_node.bags.writer import BagWriter, check_replaceable
    from identification_node.wire.cdr import JOINT_STATE
    from identification_node.fileio import atomic_write_yaml
    from identification_node.model.identifiability import BaseParameters
    from identification_node.payload.fit import (attachment, read_payload_changes,
                                                 true_parameter_changes)
    from identification_node.simulation.simulator import ArmSimulator, SensorNoise
    from identification_node.model.torque import TorqueConverter
    from identification_node.excitation.trajectories import load_trajectory

    settings = settings_from_args(args)
    if args.overwrite:   # before simulating: only a bag is replaced
        check_replaceable(args.out, '--out')
    robot = settings.load_robot()
    from identification_node.model.drive import DriveModel
    configured = TorqueConverter(robot.joint_names, settings.torque_configs(robot.joint_names))
    drives = DriveModel.per_joint(robot.dof, args.motor_resistance, args.motor_inductance,
                                  args.kt_error)
    converter = drives.true_converter(configured)
    noise = SensorNoise(args.position_std, args.encoder_counts, args.velocity_std,
                        args.torque_std, args.current_std)
    trajectory = load_trajectory(args.trajectory, robot, args.seed if (
        args.trajectory_seed is None) else args.trajectory_seed)
    phi = true_parameters(robot, args.true_parameters)
    payloads = read_payload_changes(args.payload_events) if args.payload_events else []
    substeps = max(1, math.ceil(1000.0 / args.rate - 1e-9)) if args.rate > 0 else 1
    sim = ArmSimulator(robot, phi, rate=args.rate, substeps=substeps).run(
        trajectory, args.duration, noise, args.seed, converter,
        changes=true_parameter_changes(robot, phi, payloads))
    names = list(robot.joint_names)
    slots = converter.current_channel_slots()
    volts = drives.voltages(converter, sim.t, sim.q, sim.qd, sim.tau, args.voltage_std,
                            np.random.default_rng([args.seed, 1])) if slots else None
    stamps = np.round((sim.t + args.stamp_offset) * 1e9).astype(np.int64)
    with BagWriter(args.out, args.storage, overwrite=args.overwrite) as bag:
        bag.add_topic('/joint_states', JOINT_STATE)
        if robot.kind == 'urdf':
            bag.write_string('/robot_description', int(stamps[0]), robot.description)
        for k, ns in enumerate(stamps.tolist()):
            t = ns * 1e-9
            bag.write_joint_state('/joint_states', ns, t, names, sim.q_meas[k],
                                  () if args.no_velocity else sim.qd_meas[k],
                                  () if args.no_effort else sim.tau_meas[k])
            if volts is not None:   # current channels (slots)
                bag.write_joint_state(
                    '/motor_currents', ns, t, [s[0] for s in slots],
                    [sim.theta_e[k, i] for _, i, _ in slots],
                    (), [sim.currents[k, i, c] for _, i, c in slots])
                bag.write_joint_state(
                    '/motor_voltages', ns, t, [s[0] for s in slots],
                    [sim.theta_e[k, i] for _, i, _ in slots],
                    (), [volts[k, i, c] for _, i, c in slots])
            if args.clock:
                bag.write_clock(ns)
    base = BaseParameters.from_robot(robot)
    truth = {
        'robot': robot.name, 'joints': names,
        'arguments': {k: v for k, v in sorted(vars(args).items()) if k != 'verb'},
        'trajectory': args.trajectory, 'rate': args.rate, 'samples': len(sim),
        'noise': vars(noise), 'seed': args.seed,
        'standard_parameters': dict(zip(robot.param_names, map(float, phi))),
        'base_parameters': {n: float(v) for n, v in zip(base.names,
                                                        base.to_base(phi))},
    }
    if slots:
        truth['drives'] = {j: {'kt': c.kt, 'gain': c.kt * c.gear_ratio, 'resistance': float(r),
                               'inductance': float(ind), 'configured_kt': k.kt}
                           for j, c, k, r, ind in zip(names, converter.configs, configured.configs,
                                                      drives.resistance, drives.inductance)
                           if c.source != 'measured'}
    if payloads:
        truth['payload_events'] = [dict(
            c.document(), link=attachment(robot, c.link).link, stamp=c.time + args.stamp_offset,
            parameters=c.parameters().tolist()) for c in payloads]
    path = atomic_write_yaml(f'{args.out}/true_parameters.yaml', truth)
    print(f'wrote {len(sim)} samples ({sim.t[-1]:.2f} s) of {robot.name} to {args.out} '
          f'({args.storage}); true parameters in {path}')
    return 0
