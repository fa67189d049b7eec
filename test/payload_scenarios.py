"""Payload scenarios as a user runs them, with the shipped defaults: an arm (example-robot-data
or the project's 7-DOF fixture, with or without joint friction) is identified first on a
motion without payload by the node's pipeline (default settings: the automatic smoother),
then the payload monitor of the default ``payload.*`` settings, given that identified arm
(``--arm``), watches a different motion with a sequence of payload changes.

The motion follows a seeded Fourier trajectory exactly (simulate_kinematic); the torque is
the true arm's, with the payload of each span, plus the sensor noise. Used by
test_payload_matrix.py (pass/fail) and bench/bench_payload.py (the figures).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.simulation.simulator import SensorNoise, SimResult, measure
from identification_node.payload.fit import ArmPrior, PayloadChange, true_parameter_changes
from identification_node.payload.monitor import PayloadMonitor, monitor_from_settings
from identification_node.settings import Settings
from identification_node.wire.records import JointStateRecord

from arms import ARMS, arm_urdf

FIXTURE = str(Path(__file__).parent / 'fixtures' / 'panda_like.urdf')
T0_NS = 1_700_000_000_000_000_000
# joint friction of the arms 'with friction': viscous (N m s/rad), Coulomb (N m), offset (N m),
# from the base joint to the wrist
FRICTION = {'fv': (0.5, 0.6, 0.4, 0.3, 0.1, 0.1, 0.05),
            'fc': (0.6, 0.8, 0.5, 0.4, 0.2, 0.15, 0.1),
            'fo': (0.1, -0.2, 0.05, 0.1, -0.05, 0.02, 0.0)}


def noise(torque_std: float) -> SensorNoise:
    """An 18-bit encoder, measured velocities (0.01 rad/s) and the torque noise (N m)."""
    return SensorNoise(encoder_counts=2 ** 18, velocity_std=0.01, torque_std=torque_std)


@dataclass
class Arm:
    """A robot of the default settings (friction columns identified), its true parameters
    (``friction``: with joint friction) and the settings."""
    name: str
    settings: Settings
    robot: object
    phi: np.ndarray


def make_arm(name: str, friction: bool = True) -> Arm:
    """'ur5', 'panda', 'kinova' (example-robot-data) or 'fixture' (the 7-DOF Panda-like)."""
    urdf = FIXTURE if name == 'fixture' else str(arm_urdf(name))
    joints = None if name == 'fixture' else ARMS[name][1]
    settings = Settings.from_dict({'robot': urdf, **({'joints': joints} if joints else {})})
    robot = settings.load_robot()
    phi = robot.phi_model.copy()
    for kind, values in FRICTION.items() if friction else ():
        for joint, value in zip(robot.joint_names, values):
            phi[robot.param_index(f'{joint}.{kind}')] = value
    return Arm(name, settings, robot, phi)


def simulate(arm: Arm, rate: float, duration: float, torque_std: float, seed: int,
             changes: list[PayloadChange] = (), motion_seed: int | None = None) -> SimResult:
    """``duration`` s at ``rate`` Hz of a seeded Fourier motion (10 s period; its own seed
    ``motion_seed``, default ``seed``: the noise's), the payload changing at ``changes``."""
    robot = arm.robot
    traj = FourierTrajectory.random(robot, harmonics=5, period=10.0,
                                    seed=seed if motion_seed is None else motion_seed)
    t = np.arange(int(duration * rate)) / rate
    q, qd, qdd = traj.sample(t)
    tau = np.empty_like(q)
    spans = [(0.0, arm.phi)] + true_parameter_changes(robot, arm.phi, list(changes))
    for k, (start, phi) in enumerate(spans):
        end = spans[k + 1][0] if k + 1 < len(spans) else np.inf
        for a in range(int(np.searchsorted(t, start)), int(np.searchsorted(t, end)), 4096):
            s = slice(a, min(a + 4096, int(np.searchsorted(t, end))))
            tau[s] = robot.inverse_dynamics(q[s], qd[s], qdd[s], phi)
    return measure(robot, t, q, qd, qdd, tau, noise(torque_std), np.random.default_rng(seed),
                   None)


@dataclass
class IdentifiedArm:
    """An arm identified without payload: its standard parameters and the prior of their
    error, from the estimate's covariance (what ~/save writes and --arm reads)."""
    phi: np.ndarray
    prior: ArmPrior | None


def identify_arm(arm: Arm, rate: float, torque_std: float, seed: int = 1000,
                 duration: float = 30.0) -> IdentifiedArm:
    """The arm identified by the default pipeline on ``duration`` s without payload."""
    sim = simulate(arm, rate, duration, torque_std, seed)
    pipe = arm.settings.build(arm.robot)
    stream(pipe, sim)
    pipe.process(flush=True)
    return IdentifiedArm(pipe.standard_parameters(),
                         ArmPrior.from_covariance(pipe.base, pipe.covariance))


def stream(pipe, sim: SimResult, on_output=None, block: float = 0.05) -> None:
    """The samples into the pipeline in blocks of ``block`` s (as the node takes them)."""
    ns = T0_NS + np.round(sim.t * 1e9).astype(np.int64)
    names = tuple(pipe.robot.joint_names)
    step = max(1, int(round(block / float(sim.t[1] - sim.t[0]))))
    for a in range(0, len(ns), step):
        s = slice(a, a + step)
        pipe.add_joint_states(JointStateRecord(ns[s], names, sim.q_meas[s], sim.qd_meas[s],
                                               sim.tau_meas[s]))
        out = pipe.process()
        if on_output is not None:
            on_output(out)


def monitor(arm: Arm, model: IdentifiedArm | np.ndarray) -> PayloadMonitor:
    """The default settings' payload monitor against an identified arm, or against standard
    parameters taken as exact."""
    mon = monitor_from_settings(arm.settings, arm.robot)
    if isinstance(model, IdentifiedArm):
        return PayloadMonitor(arm.robot, mon.attach, model.phi, mon.config,
                              arm_prior=model.prior)
    mon.set_arm(model)
    return mon


def watch(mon: PayloadMonitor, sim: SimResult, block: float = 0.05) -> list:
    """The simulated samples into the monitor as the pipeline hands them on (its validated
    input samples, PipelineOutput.inputs) in blocks of ``block`` s: the events."""
    ns = T0_NS + np.round(sim.t * 1e9).astype(np.int64)
    step = max(1, int(round(block / float(sim.t[1] - sim.t[0]))))
    events = []
    for a in range(0, len(ns), step):
        s = slice(a, a + step)
        events += mon.add(ns[s], sim.q_meas[s], sim.tau_meas[s])
    return events


def run(arm: Arm, model: IdentifiedArm | np.ndarray, rate: float, torque_std: float,
        seed: int, changes: list[PayloadChange]) -> tuple[PayloadMonitor, list, list]:
    """The monitor against ``model`` (``monitor``) watching a simulation of ``changes`` and
    5 s after the last: (the monitor, its events, its segments)."""
    mon = monitor(arm, model)
    events = watch(mon, simulate(arm, rate, changes[-1].time + 5.0, torque_std, seed, changes))
    return mon, events, mon.finish()


def seconds(stamp: float) -> float:
    """A monitor stamp (header seconds) as seconds since the simulation's start."""
    return stamp - T0_NS * 1e-9
