"""``simulate``: the simulated arm, as fast as the machine allows, into a rosbag2 bag with
its ``true_parameters.yaml`` (what is written: simulation/bag.py)."""
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


def run(args: argparse.Namespace) -> int:
    from identification_node.simulation.bag import SimulationOptions, simulate_bag

    given = {k: v for k, v in sorted(vars(args).items()) if k != 'verb'}
    opts = SimulationOptions(**{f: given[f] for f in SimulationOptions.__dataclass_fields__
                                if f != 'arguments'}, arguments=given)
    done = simulate_bag(settings_from_args(args), opts)
    print(f'wrote {done.samples} samples ({done.duration:.2f} s) of {done.robot} to {args.out} '
          f'({args.storage}); true parameters in {done.truth}')
    return 0
