"""The model corpus of issue 27: simulated third-party arms, identified with the defaults.

A case is an arm of example-robot-data (test/arms.py), a sampling rate and a seed. Its truth
is the URDF's bodies each scaled by 1 +- 30 % (a scaled rigid body stays physical; the URDF is
then a prior 30 % off), with joint friction: viscous fv, Coulomb fc and a Stribeck bump
(fs - fc) exp(-(qd / vs)^2) sign(qd) that the model has no column for, fc a few percent of the
joint's rigid-body RMS torque. The arm follows a random Fourier excitation (training) and one
of another seed (held out), measured with an 18-bit encoder, 0.01 rad/s velocity noise and
torque noise of 1 % of the mean RMS torque; both are written as rosbag2 bags
(recordings.joint_state_bag) with /robot_description. ``identify_case`` runs
``identify BAG --validate HELDOUT --json`` in this process, exactly as a user would with the
defaults, and scores it. ``clean``: the URDF's own parameters, no friction, no noise.
"""
from __future__ import annotations

import contextlib
import io
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from checkout import ROOT  # noqa: E402  (this checkout's package, here and in subprocesses)

import numpy as np

sys.path.insert(0, str(ROOT / 'test'))
sys.path.insert(0, str(ROOT / 'bench'))
from arms import ARMS, arm_urdf  # noqa: E402

from identification_node.errors import IdentificationError  # noqa: E402
from identification_node.excitation.trajectories import FourierTrajectory  # noqa: E402
from identification_node.model.identifiability import BaseParameters  # noqa: E402
from identification_node.model.robot import load_robot  # noqa: E402
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic  # noqa: E402
from recordings import joint_state_bag  # noqa: E402

RATES = (100.0, 250.0, 500.0, 1000.0, 2000.0)
EXTRAS = ['fv', 'fc', 'fo']           # the defaults' columns
PERTURBATION = 0.3                   # truth = URDF body x (1 +- 0.3)
STRIBECK_VELOCITY = 0.05             # rad/s
MASS_SLACK = 0.01                    # relative: 'between the URDF and the truth' to 1 %


@dataclass(frozen=True)
class Case:
    arm: str
    rate: float
    duration: float = 60.0
    seed: int = 0
    clean: bool = False    # the URDF's own parameters, no friction, no noise (issue 27's UR5)

    @property
    def name(self) -> str:
        return f"{self.arm}_{int(self.rate)}hz_s{self.seed}{'_clean' if self.clean else ''}"


def case_robot(arm: str):
    """The arm's RobotModel with the default friction columns (its identified joints)."""
    return load_robot(str(arm_urdf(arm)), ARMS[arm][1], extras=EXTRAS)


def truth(robot, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(phi_true, per-link body factor): every link body scaled by 1 +- PERTURBATION."""
    rng = np.random.default_rng(1000 + seed)
    factors = 1.0 + PERTURBATION * rng.choice([-1.0, 1.0], robot.dof)
    phi = robot.phi_model.copy()
    for i, f in enumerate(factors):
        phi[10 * i:10 * i + 10] *= f
    return phi, factors


def make_case(case: Case, directory: Path) -> dict:
    """Simulate ``case`` into directory/<name>/{train,heldout}; return its truth: phi,
    base parameters, link masses and the URDF's."""
    robot = case_robot(case.arm)
    base = BaseParameters.from_robot(robot)
    phi, factors = truth(robot, case.seed)
    if case.clean:
        phi, factors = robot.phi_model.copy(), np.ones(robot.dof)
    t = np.arange(int(round(case.duration * case.rate))) / case.rate
    motions = [FourierTrajectory.random(robot, seed=case.seed + k) for k in (0, 1)]
    rigid = simulate_kinematic(robot, phi, motions[0], t[::max(1, len(t) // 2000)])
    rms = np.sqrt(np.mean(rigid.tau ** 2, axis=0))
    fc, fv, fs = 0.03 * rms, 0.03 * rms, 0.045 * rms     # N m, N m s/rad, N m
    if case.clean:
        fc = fv = fs = np.zeros(robot.dof)
    for j, joint in enumerate(robot.joint_names):
        phi[robot.param_index(f'{joint}.fc')] = fc[j]
        phi[robot.param_index(f'{joint}.fv')] = fv[j]
    noise = SensorNoise() if case.clean else SensorNoise(
        encoder_counts=2 ** 18, velocity_std=0.01, torque_std=0.01 * float(np.mean(rms)))
    out = Path(directory) / case.name
    for k, (label, motion) in enumerate(zip(('train', 'heldout'), motions)):
        sim = simulate_kinematic(robot, phi, motion, t, noise, seed=case.seed + 10 * k)
        bump = (fs - fc) * np.exp(-(sim.qd / STRIBECK_VELOCITY) ** 2) * np.sign(sim.qd)
        sim.tau = sim.tau + bump
        sim.tau_meas = sim.tau_meas + bump
        joint_state_bag(out / label, sim.t, robot.joint_names, sim.q_meas, sim.qd_meas,
                        sim.tau_meas, robot.description)
    return {'phi': phi, 'beta': base.to_base(phi), 'masses': phi[0:robot.n_inertial:10],
            'urdf_masses': robot.phi_model[0:robot.n_inertial:10], 'factors': factors,
            'dir': out}


def masses_in_data(robot) -> list[str]:
    """The links whose mass alone is a combination of base parameters (the joint torques
    determine it, whatever the other parameters); every other mass is determined only together
    with other links' masses and first moments, and the prior and physical consistency split
    that combination."""
    base = BaseParameters.from_robot(robot)
    out = []
    for k, link in enumerate(robot.link_names):
        try:
            base.combination({base.param_names[10 * k]: 1.0})
        except IdentificationError:   # not identifiable alone
            continue
        out.append(link)
    return out


def plausible_masses(masses: np.ndarray, true: np.ndarray, urdf: np.ndarray) -> np.ndarray:
    """Per link: the mass within PERTURBATION of the truth, or between the URDF's and the
    truth (both to MASS_SLACK)."""
    lo, hi = np.minimum(true, urdf), np.maximum(true, urdf)
    return ((np.abs(masses / true - 1) <= PERTURBATION + MASS_SLACK)
            | ((masses >= lo * (1 - MASS_SLACK)) & (masses <= hi * (1 + MASS_SLACK))))


def run_identify(args: list[str]) -> tuple[int, dict]:
    """``identify ARGS --json`` in this process: (exit status, its JSON document)."""
    from identification_node.cli import main

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = main(['identify', *args, '--json'])
    text = buffer.getvalue()
    return code, (json.loads(text) if text.strip() else {})


def score(doc: dict, truth_: dict | None = None) -> dict:
    """The figures of one identification: consistency and solver path, held-out error of the
    estimate and of the unconstrained fit (percent, stacked), link masses (and against the
    truth: ratios, whether each is within +-30 % or between prior and truth, RMS of the
    normalised base-parameter errors)."""
    solver = doc['consistency_solver']
    held = doc['validation'][0]
    masses = np.array([v['mass'] for v in doc['links'].values()])
    urdf = np.array([v['urdf_mass'] for v in doc['links'].values()])
    row = {'consistent': doc['physically_consistent'], 'errors': doc['errors'],
           'path': solver['method'] + (f" after {len(solver['attempts'])} failure(s)"
                                       if solver['attempts'] else ''),
           'status': solver['status'], 'excess': solver['excess'],
           'heldout': held['estimate']['stacked'],
           'heldout_unconstrained': held['unconstrained']['stacked'],
           'links': list(doc['links']), 'masses': masses, 'urdf_masses': urdf,
           'notes': solver['notes']}
    row['heldout_ratio'] = row['heldout'] / row['heldout_unconstrained']
    row['urdf_ratio'] = masses / urdf
    if truth_ is not None:
        true = truth_['masses']
        row['truth_ratio'] = masses / true
        row['masses_ok'] = bool(np.all(plausible_masses(masses, true, urdf)))
        est = np.array([np.nan if b['estimate'] is None else b['estimate']
                        for b in doc['base_parameters']])
        sd = np.array([np.nan if b['stddev'] is None else b['stddev']
                       for b in doc['base_parameters']])
        z = (est - truth_['beta']) / sd
        row['z_rms'] = float(np.sqrt(np.nanmean(z ** 2)))
    return row


def identify_case(case: Case, directory: Path, extra: list[str] = ()) -> dict:
    """Simulate and identify ``case`` with the defaults; its score (``score``)."""
    truth_ = make_case(case, directory)
    args = [str(truth_['dir'] / 'train'), '--validate', str(truth_['dir'] / 'heldout')]
    if ARMS[case.arm][1]:
        args += ['--joints', ','.join(ARMS[case.arm][1])]
    code, doc = run_identify(args + list(extra))
    if code != 0 or not doc:
        raise RuntimeError(f'identify failed on {case.name} (exit {code})')
    return score(doc, truth_)
