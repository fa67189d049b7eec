"""Accuracy study (not a speed benchmark): what the default friction columns cost on an arm
without friction, at the low rates of industrial controllers (issue 27).

example-robot-data's UR5 (a test dependency), perfect tracking of seeded 5-harmonic Fourier
excitations inside 80 % of its limits, 18-bit encoder, 0.01 rad/s velocity and 0.1 N m torque
noise, no friction in the torque (``--friction none``) or Stribeck friction per joint
(``stribeck``: fv qd + (fc + (fs - fc) exp(-(qd / vs)^2)) sign(qd) + fo, fs = 1.5 fc,
vs = 0.05 rad/s). Identified by the node's pipeline with the default settings (smoother chosen
from the data) without friction columns (extras: []), and with the default ones (fv, fc, fo):
the smoothed sign in the Coulomb column and the equations of |qd| < coulomb_exclusion_speed
left out (``default``), and, as the baseline in the same run, the former treatment: sign(qd)
(tanh(qd / 1e-9), which keeps it) with the equations whose smoothing window may hold a
reversal left out, |qd| < speed + |qdd| half window (``reach``).
Figures: held-out stacked torque error 100 ||tau - Yb theta|| / ||tau|| on another motion
against the simulated noise-free torque, its ratio to the fit without friction columns, and
the share of the joint equations left out (mean over joints, and the largest joint's).

    .venv/bin/python bench/coulomb_rate.py [--rates 100 250 1000] [--seeds 2] [--duration 60]
"""
from __future__ import annotations

import argparse
import os
import sys

from checkout import ROOT  # noqa: E402  (this checkout's package, here and in subprocesses)

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # before numpy loads OpenBLAS

import numpy as np  # noqa: E402

sys.path.insert(0, str(ROOT / 'test'))

from arms import arm_urdf  # noqa: E402
from identification_node.excitation.trajectories import FourierTrajectory  # noqa: E402
from identification_node.model.robot import load_robot  # noqa: E402
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic  # noqa: E402
from identification_node.settings import Settings  # noqa: E402
from identification_node.wire.records import JointStateRecord  # noqa: E402

NOISE = SensorNoise(encoder_counts=2 ** 18, velocity_std=0.01, torque_std=0.1)
FV = np.array([0.6, 0.8, 0.45, 0.08, 0.06, 0.04])   # N m s/rad
FC = np.array([0.5, 0.7, 0.4, 0.1, 0.08, 0.05])     # N m
FO = np.array([0.1, -0.2, 0.05, 0.02, -0.01, 0.01])  # N m


def friction(kind: str, qd: np.ndarray) -> np.ndarray:
    if kind == 'none':
        return np.zeros_like(qd)
    fs, vs = 1.5 * FC, 0.05
    return FV * qd + (FC + (fs - FC) * np.exp(-(qd / vs) ** 2)) * np.sign(qd) + FO


def simulate(robot, kind: str, rate: float, duration: float, seed: int):
    traj = FourierTrajectory.random(robot, seed=seed)
    t = np.arange(int(duration * rate)) / rate
    sim = simulate_kinematic(robot, None, traj, t, NOISE, seed=seed)
    f = friction(kind, sim.qd)
    sim.tau, sim.tau_meas = sim.tau + f, sim.tau_meas + f
    return sim


def identify(urdf: str, extras: list[str], sim, **settings):
    robot = load_robot(urdf, extras=extras, coulomb_velocity=settings.get('coulomb_velocity', 0))
    p = Settings.from_dict({'robot': urdf, 'extras': extras, **settings}).build(robot)
    ns = 1_700_000_000_000_000_000 + np.round(sim.t * 1e9).astype(np.int64)
    p.add_joint_states(JointStateRecord(ns, tuple(robot.joint_names), sim.q_meas, sim.qd_meas,
                                        sim.tau_meas))
    p.process(flush=True)
    return p


def heldout(p, sim) -> float:
    Yb = p.base.base_regressor(p.robot.regressor(sim.q, sim.qd, sim.qdd))
    return float(100 * np.linalg.norm(sim.tau - Yb @ p.rls.theta) / np.linalg.norm(sim.tau))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--rates', type=float, nargs='+', default=[100.0])
    parser.add_argument('--seeds', type=int, default=2)
    parser.add_argument('--duration', type=float, default=60.0)
    parser.add_argument('--friction', choices=('none', 'stribeck'), default='none')
    args = parser.parse_args()
    urdf = str(arm_urdf('ur5'))
    inertial = load_robot(urdf, extras=[])
    print(f'UR5, friction in the data: {args.friction}; held-out error % against the true '
          'torque, mean over seeds')
    print('rate Hz | no columns % | reach % (ratio, left out %: mean, largest) | '
          'default % (ratio, left out %)')
    for rate in args.rates:
        err: dict[str, list[float]] = {'none': [], 'reach': [], 'default': []}
        out: dict[str, list[tuple[float, float]]] = {'reach': [], 'default': []}
        for seed in range(args.seeds):
            train = simulate(inertial, args.friction, rate, args.duration, 1 + seed)
            held = simulate(inertial, args.friction, rate, args.duration / 2, 100 + seed)
            err['none'].append(heldout(identify(urdf, [], train), held))
            for name, velocity in (('reach', 1e-9), ('default', 0.0)):
                p = identify(urdf, ['fv', 'fc', 'fo'], train, coulomb_velocity=velocity)
                err[name].append(heldout(p, held))
                share = p.estimator.excluded / max(p.used, 1)
                out[name].append((100 * share.mean(), 100 * share.max()))
        base = np.mean(err['none'])
        cells = [f'{np.mean(err[k]):.4f} ({np.mean(err[k]) / base:.2f}, '
                 f'{np.mean([o[0] for o in out[k]]):.1f}, {np.mean([o[1] for o in out[k]]):.1f})'
                 for k in ('reach', 'default')]
        print(f'{rate:7.0f} | {base:.4f} | ' + ' | '.join(cells))


if __name__ == '__main__':
    main()
