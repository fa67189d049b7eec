"""Accuracy study (not a speed benchmark): Coulomb friction near velocity reversals.

A simulated arm (perfect tracking of seeded 5-harmonic Fourier excitations, 1 kHz, encoder
quantisation, velocity and torque noise) whose true joint friction is

- ``sign``: fv qd + fc sign(qd) + fo, the model's own form with a true discontinuity, or
- ``stribeck``: fv qd + (fc + (fs - fc) exp(-(qd / vs)^2)) sign(qd) + fo, fs = 1.5 fc,
  vs = 0.05 rad/s, a form the model does not have,

is identified from a training bag with the default extras (fv, fc, fo) by the streaming
pipeline (``identify``'s default) and by ``--method batch``, once per Coulomb treatment:

- ``exclusion``: sign(qd) in the regressor, a joint's equations left out while
  |qd| < 0.1 rad/s + |qdd| T_half (batch: |qd| < 0.1 rad/s within the filter's reach),
- ``sign``: sign(qd), no equation left out (coulomb_exclusion_speed 0),
- ``tanh V``: tanh(qd / V) in the regressor, no equation left out.

Figures: the held-out stacked torque error 100 ||tau - tau_hat||_2 / ||tau||_2 over all joints
and every sample of another trajectory (reversals included), against the true noise-free
torque (``true``) and against the raw noisy measured torque (``raw``); the largest
|error| / stddev of the inertial base parameters (``z``); and the share of the training
equations left out (``out``). Mean over the seeds.

    .venv/bin/python bench/coulomb_models.py [--robot crs_a465] [--seeds 3] [--duration 20]
"""
from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # before numpy loads OpenBLAS

import numpy as np  # noqa: E402


from identification_node.bags.writer import BagWriter  # noqa: E402
from identification_node.excitation.trajectories import FourierTrajectory  # noqa: E402
from identification_node.model.robot import load_robot  # noqa: E402
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic  # noqa: E402
from identification_node.batch.solve import offline_identify  # noqa: E402
from identification_node.replay.stream import replay_identify  # noqa: E402
from identification_node.settings import Settings  # noqa: E402

FRICTION = {   # per joint fv (N m s/rad), fc (N m), fo (N m): a geared arm's sizes
    'crs_a465': ([0.6, 0.8, 0.45, 0.08, 0.06, 0.04], [0.5, 0.7, 0.4, 0.1, 0.08, 0.05],
                 [0.1, -0.2, 0.05, 0.02, -0.01, 0.01]),
    'mit_dd_arm': ([0.5, 0.3, 0.1], [1.0, 0.5, 0.2], [0.2, -0.1, 0.05]),
}
TORQUE_STD = {'crs_a465': 0.2, 'mit_dd_arm': 0.2}
VARIANTS = [('exclusion', 0.0, 0.1), ('sign', 0.0, 0.0), ('tanh 0.005', 0.005, 0.0),
            ('tanh 0.01', 0.01, 0.0), ('tanh 0.02', 0.02, 0.0), ('tanh 0.05', 0.05, 0.0)]


def friction(kind: str, qd: np.ndarray, fv, fc, fo) -> np.ndarray:
    fv, fc, fo = (np.asarray(x, dtype=float) for x in (fv, fc, fo))
    if kind == 'sign':
        return fv * qd + fc * np.sign(qd) + fo
    fs, vs = 1.5 * fc, 0.05
    return fv * qd + (fc + (fs - fc) * np.exp(-(qd / vs) ** 2)) * np.sign(qd) + fo


def simulate(robot, kind: str, seed: int, duration: float, rate: float = 1000.0):
    """True (q, qd, qdd, tau) and the measured (q, qd, tau) of one seeded excitation."""
    traj = FourierTrajectory.random(robot, period=duration / 2, seed=seed)
    t = np.arange(int(round(duration * rate))) / rate
    sim = simulate_kinematic(robot, None, traj, t,
                             SensorNoise(encoder_counts=262144, velocity_std=0.001), seed=seed)
    tau = sim.tau + friction(kind, sim.qd, *FRICTION[robot.name])
    rng = np.random.default_rng(seed + 1000)
    meas = tau + TORQUE_STD[robot.name] * rng.standard_normal(tau.shape)
    return t, sim, tau, meas


def write_bag(path: Path, robot, t, q, qd, tau) -> Path:
    with BagWriter(path) as bag:
        bag.write_string('/robot_description', 0, robot.description)
        for k in range(len(t)):
            ns = int(round(t[k] * 1e9))
            bag.write_joint_state('/joint_states', ns, ns * 1e-9, robot.joint_names,
                                  q[k], qd[k], tau[k])
    return path


def stacked(a: np.ndarray, b: np.ndarray) -> float:
    return float(100 * np.linalg.norm(a - b) / np.linalg.norm(a))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--robot', default='crs_a465', choices=sorted(FRICTION))
    parser.add_argument('--seeds', type=int, default=3)
    parser.add_argument('--duration', type=float, default=20.0)
    args = parser.parse_args()
    inertial = load_robot(args.robot, extras=[])
    tmp = Path(tempfile.mkdtemp(prefix='coulomb_models_'))
    rows = []
    for kind in ('sign', 'stribeck'):
        for method in ('rls', 'batch'):
            for name, velocity, speed in VARIANTS:
                figures = []
                for seed in range(args.seeds):
                    train = tmp / f'{kind}_{seed}_train'
                    t, sim, _, meas = simulate(inertial, kind, 10 + seed, args.duration)
                    if not train.exists():
                        write_bag(train, inertial, t, sim.q_meas, sim.qd_meas, meas)
                    t2, sim2, tau2, meas2 = simulate(inertial, kind, 100 + seed,
                                                     args.duration / 2)
                    settings = Settings.from_dict({
                        'robot': args.robot, 'torque_source': ['measured'],
                        'extras': ['fv', 'fc', 'fo'], 'coulomb_velocity': velocity,
                        'coulomb_exclusion_speed': speed})
                    robot = settings.load_robot()
                    ident = (replay_identify(train, settings, robot) if method == 'rls'
                             else offline_identify(train, settings, robot))
                    base = ident.base
                    pred = base.base_regressor(robot.regressor(sim2.q, sim2.qd, sim2.qdd)) \
                        @ ident.theta
                    inertial_names = [i for i, n in enumerate(base.names)
                                      if not n.split('.')[-1] in ('fv', 'fc', 'fo')]
                    phi = np.concatenate([inertial.phi_model, np.ravel(np.column_stack(
                        FRICTION[args.robot]))])
                    z = np.abs(ident.theta - base.to_base(phi)) / ident.stddev
                    if method == 'rls':
                        total = ident.pipeline.used * robot.dof
                        out = ident.pipeline.excluded_rows / max(total, 1)
                    else:
                        out = ident.details['excluded_equations'] / (
                            ident.details['rows'] * robot.dof)
                    figures.append((stacked(tau2, pred), stacked(meas2, pred),
                                    float(z[inertial_names].max()), 100 * out))
                f = np.mean(figures, axis=0)
                rows.append((kind, method, name, *f))
                print(f'{kind:9s} {method:5s} {name:10s} held-out true {f[0]:6.3f} %  '
                      f'raw {f[1]:6.3f} %  max|z| inertial {f[2]:5.2f}  out {f[3]:5.1f} %',
                      flush=True)


if __name__ == '__main__':
    main()
