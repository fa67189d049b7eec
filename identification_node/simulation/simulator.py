"""A simulated arm: forward dynamics under a computed-torque controller, and sensor models.

The true dynamics are those of the regressor, tau = Y(q, qd, qdd) phi_true: pinocchio's rigid
bodies carrying phi_true's inertials, rotor inertia Ia as armature (0 when phi has no Ia column),
and the friction torque fv qd + fc sign(qd) + fo (tanh(qd / robot.coulomb_velocity) in place of
sign when that is > 0; terms whose column phi lacks are 0). Joint arrays follow the robot's
joint order; SI units (rad, rad/s, rad/s^2, N m, A).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import pinocchio as pin

from identification_node.errors import IdentificationError
from identification_node.excitation.trajectories import Trajectory, match_joints
from identification_node.model.identifiability import sample_motion

__all__ = ['DEFAULT_BANDWIDTH', 'DEFAULT_DAMPING', 'SensorNoise', 'SimResult',
           'default_converter', 'measure', 'ArmSimulator', 'simulate_kinematic']

DEFAULT_BANDWIDTH = 25.0   # rad/s, closed-loop natural frequency of the default gains
DEFAULT_DAMPING = 1.0      # damping ratio of the default gains
_CHUNK = 2048              # samples per regressor block in simulate_kinematic
RK4_STEP = 2.0             # h * (fastest viscous decay rate) per RK4 step at most (stable < 2.78)
_PROBES = 32               # configurations M(q) is sampled at for that rate


@dataclass
class SensorNoise:
    """Measurement noise: zero-mean Gaussian standard deviations and encoder resolution.

    position_std (rad), then quantisation to ``encoder_counts`` per revolution (0: none) on
    revolute joints; velocity_std (rad/s), torque_std (N m), current_std (A, every phase
    channel).
    """

    position_std: float = 0.0
    encoder_counts: int = 0
    velocity_std: float = 0.0
    torque_std: float = 0.0
    current_std: float = 0.0

    def __post_init__(self) -> None:
        for name in ('position_std', 'velocity_std', 'torque_std', 'current_std'):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and v >= 0):
                raise IdentificationError(f'sensor noise {name} must be a number >= 0, got {v!r}')
        c = self.encoder_counts
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or c < 0:
            raise IdentificationError(f'encoder_counts must be an integer >= 0, got {c!r}')

    @property
    def quantum(self) -> float:
        """Encoder step (rad), 0 without quantisation."""
        return 2.0 * math.pi / self.encoder_counts if self.encoder_counts else 0.0


@dataclass
class SimResult:
    """Simulated samples. True: t (N,), q, qd, qdd (from the dynamics), tau (applied joint
    torque), each (N, n). Measured: q_meas, qd_meas, tau_meas (N, n) and the phase currents
    (N, n, 3) in wire order (noisy; NaN in channels the converter leaves unused), with the true
    electrical angles theta_e (N, n)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau: np.ndarray
    q_meas: np.ndarray
    qd_meas: np.ndarray
    tau_meas: np.ndarray
    currents: np.ndarray
    theta_e: np.ndarray
    joint_names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return self.t.shape[0]


def default_converter(joint_names: list[str]):
    """Three-phase currents for every joint with kt = 1 N m/A, gear ratio 1, 1 pole pair."""
    from identification_node.model.torque import JointTorqueConfig, TorqueConverter
    cfg = JointTorqueConfig(source='three_phase', kt=1.0)
    return TorqueConverter(joint_names, [cfg] * len(joint_names))


def measure(robot, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
            tau: np.ndarray, noise: SensorNoise | None = None,
            rng: np.random.Generator | None = None, converter=None) -> SimResult:
    """Add sensor noise to true samples and derive the phase currents of ``tau`` (the inverse
    of eq. 10 of An, Atkeson and Hollerbach, by ``converter``, default
    :func:`default_converter`) at the true joint positions."""
    noise = SensorNoise() if noise is None else noise
    rng = np.random.default_rng(0) if rng is None else rng
    converter = default_converter(robot.joint_names) if converter is None else converter
    if list(converter.joint_names) != list(robot.joint_names):
        raise IdentificationError(f'torque converter joints {converter.joint_names} differ '
                                  f'from the robot joints {robot.joint_names}')

    def noisy(x: np.ndarray, std: float) -> np.ndarray:
        return x + std * rng.standard_normal(x.shape) if std > 0 else x.copy()

    q_meas = noisy(q, noise.position_std)
    if noise.quantum > 0:
        rev = ~np.asarray(robot.prismatic, dtype=bool)
        q_meas[:, rev] = noise.quantum * np.round(q_meas[:, rev] / noise.quantum)
    currents = noisy(converter.currents_from_torque(tau, q), noise.current_std)
    return SimResult(t=t, q=q, qd=qd, qdd=qdd, tau=tau, q_meas=q_meas,
                     qd_meas=noisy(qd, noise.velocity_std), tau_meas=noisy(tau, noise.torque_std),
                     currents=currents, theta_e=converter.theta_e(q),
                     joint_names=list(robot.joint_names))


class _Dynamics:
    """Forward and inverse dynamics of one parameter vector, per sample, in joint order."""

    def __init__(self, robot, phi: np.ndarray):
        phi = np.asarray(phi, dtype=float)
        if phi.shape != (robot.num_params,) or not np.all(np.isfinite(phi)):
            raise IdentificationError(f'parameter vector must be {robot.num_params} finite '
                                      f'values ({robot.param_names[:3]}...), got shape '
                                      f'{phi.shape}')
        if robot.model.nv != robot.dof:
            raise IdentificationError('simulation needs every movable joint identified or '
                                      'locked (model nv != number of joints)')
        self.model = robot.pinocchio_model(phi)
        n = robot.dof
        extra = dict(zip(robot.extras, np.reshape(phi[robot.n_inertial:], (n, -1)).T))
        zero = np.zeros(n)
        self.fv, self.fc, self.fo = (extra.get(k, zero) for k in ('fv', 'fc', 'fo'))
        # Friction enters as our own torque term, rotor inertia as armature (as the regressor).
        self.model.damping = np.zeros(self.model.nv)
        self.model.friction = np.zeros(self.model.nv)
        armature = np.zeros(self.model.nv)
        armature[robot.idx_v] = extra.get('Ia', zero)
        self.model.armature = armature
        self.data = self.model.createData()
        self.cv = robot.coulomb_velocity
        self.idx_v = robot.idx_v
        cont = np.asarray(robot.continuous, dtype=bool)
        self._plain, self._cont = np.flatnonzero(~cont), np.flatnonzero(cont)
        self._iq_plain, self._iq_cont = robot.idx_q[~cont], robot.idx_q[cont]
        self._Q = pin.neutral(self.model)
        self._V = np.zeros(self.model.nv)
        self._T = np.zeros(self.model.nv)

    def viscous_rate(self, robot) -> float:
        """1/s: the fastest decay fv / M of a joint motion under the viscous friction (the
        largest eigenvalue of M(q)^-1 diag(fv), M with the armature), over _PROBES seeded
        configurations within the joint limits (identifiability.sample_motion). An explicit
        step longer than RK4_STEP over it diverges (iCub's URDF: 1 N m s/rad on every joint,
        links down to 1e-5 kg m^2)."""
        if not np.any(self.fv > 0):
            return 0.0
        fastest = 0.0
        for qk in sample_motion(robot, _PROBES, 0)[0]:
            try:
                rates = np.linalg.eigvals(np.linalg.solve(self.mass_matrix(qk),
                                                          np.diag(self.fv)))
            except np.linalg.LinAlgError:
                continue
            fastest = max(fastest, float(np.max(rates.real)))
        return fastest

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """The joint-space mass matrix (n, n) at joint positions q (n,), armature included."""
        Q, _ = self._config(q, np.zeros(len(q)))
        M = pin.crba(self.model, self.data, Q)[np.ix_(self.idx_v, self.idx_v)]
        return np.triu(M) + np.triu(M, 1).T

    def smallest_inertia(self, q: np.ndarray) -> float:
        """The smallest eigenvalue of the mass matrix at q (n,): kg m^2 (kg: prismatic)."""
        return float(np.linalg.eigvalsh(self.mass_matrix(q))[0])

    def friction(self, qd: np.ndarray) -> np.ndarray:
        s = np.tanh(qd / self.cv) if self.cv > 0 else np.sign(qd)
        return self.fv * qd + self.fc * s + self.fo

    def _config(self, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Q, V = self._Q, self._V
        Q[self._iq_plain] = q[self._plain]
        qc = q[self._cont]
        Q[self._iq_cont], Q[self._iq_cont + 1] = np.cos(qc), np.sin(qc)
        V[self.idx_v] = qd
        return Q, V

    def forward(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """Joint accelerations (n,) under applied joint torques tau (n,)."""
        Q, V = self._config(q, qd)
        self._T[self.idx_v] = tau - self.friction(qd)
        return pin.aba(self.model, self.data, Q, V, self._T)[self.idx_v]

    def inverse(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """Joint torques (n,) for (q, qd, qdd), friction included."""
        Q, V = self._config(q, qd)
        A = np.zeros(self.model.nv)
        A[self.idx_v] = qdd
        return pin.rnea(self.model, self.data, Q, V, A)[self.idx_v] + self.friction(qd)


def _gain(value, default: float, n: int, name: str) -> np.ndarray:
    g = np.broadcast_to(np.asarray(default if value is None else value, dtype=float), (n,))
    if not np.all(np.isfinite(g)) or np.any(g < 0):
        raise IdentificationError(f'{name} must be finite and >= 0, got {value!r}')
    return g.copy()


class ArmSimulator:
    """The robot following a trajectory under computed-torque + PD control.

    tau = M^(q) (qdd_r + kd (qd_r - qd) + kp (q_r - q)) + h^(q, qd) + f^(qd_r), with the rigid
    body terms M^, h^ and the friction f^ from ``model_phi`` (default the robot's own phi),
    friction fed forward at the reference velocity qd_r, computed from the true state at every
    sample and held for the sample period 1/rate; the true arm (``phi_true``, default the
    robot's own phi) is integrated with RK4 at ``substeps`` steps per sample, or more where its
    viscous friction on a light link would make such a step diverge (_Dynamics.viscous_rate).
    Default gains give a critically damped 25 rad/s error bandwidth (kp = 625 1/s^2,
    kd = 50 1/s).
    """

    def __init__(self, robot, phi_true: np.ndarray | None = None, rate: float = 1000.0,
                 substeps: int = 1, kp: float | np.ndarray | None = None,
                 kd: float | np.ndarray | None = None, model_phi: np.ndarray | None = None):
        try:
            rate, substeps = float(rate), int(substeps)
        except (TypeError, ValueError):
            raise IdentificationError('rate and substeps must be numbers') from None
        if not (math.isfinite(rate) and rate > 0 and substeps >= 1):
            raise IdentificationError(f'need rate > 0 and substeps >= 1, got {rate}, {substeps}')
        if rate * substeps < 1000.0:
            raise IdentificationError(f'integration step 1/(rate*substeps) = '
                                      f'{1e3 / (rate * substeps):.3g} ms; must be <= 1 ms')
        self.robot = robot
        self.rate, self.substeps = rate, substeps
        self.phi_true = np.array(robot.phi_model if phi_true is None else phi_true, float)
        self.model_phi = np.array(robot.phi_model if model_phi is None else model_phi, float)
        self._true = _Dynamics(robot, self.phi_true)
        self._nominal = _Dynamics(robot, self.model_phi)
        self._stabilise()
        n = robot.dof
        w, z = DEFAULT_BANDWIDTH, DEFAULT_DAMPING
        self.kp = _gain(kp, w * w, n, 'kp')
        self.kd = _gain(kd, 2.0 * z * w, n, 'kd')
        self.trajectory: Trajectory | None = None
        self.t = 0.0
        self._k = 0
        self.q = np.zeros(n)
        self.qd = np.zeros(n)

    # -- real-time interface ----------------------------------------------------------------------
    def reset(self, trajectory: Trajectory, t0: float = 0.0, noise: SensorNoise | None = None,
              seed: int = 0, converter=None) -> None:
        """Follow ``trajectory`` from time t0 (s), starting on it: q = q_r(t0), qd = qd_r(t0).
        ``noise``, ``seed`` and ``converter`` are used by :meth:`step`."""
        self.trajectory = match_joints(trajectory, self.robot)
        q, qd, _ = self.trajectory.sample(np.array([float(t0)]))
        self.q, self.qd = q[0].copy(), qd[0].copy()
        self.t0, self._k = float(t0), 0
        self.t = self.t0
        self._tau = None   # actuator torque at the current time (None: not commanded yet)
        self._noise = SensorNoise() if noise is None else noise
        self._rng = np.random.default_rng(seed)
        self._converter = (default_converter(self.robot.joint_names) if converter is None
                           else converter)

    def step(self) -> SimResult:
        """The sample at the current time (one row: true state, applied torque, its
        acceleration, measurements), then advance the arm by 1/rate."""
        if self.trajectory is None:
            raise IdentificationError('call reset(trajectory) before step()')
        ref = self.trajectory.sample(np.array([self.t]))
        t, q, qd = self.t, self.q.copy(), self.qd.copy()
        tau, qdd = self._advance(ref[0][0], ref[1][0], ref[2][0])
        return measure(self.robot, np.array([t]), q[None], qd[None], qdd[None], tau[None],
                       self._noise, self._rng, self._converter)

    def _advance(self, q_r: np.ndarray, qd_r: np.ndarray, qdd_r: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Command a torque at the current state and integrate one sample period (RK4).

        The actuator torque is continuous, as a real drive's current loop makes it: over the
        period it ramps from its present value to the new command. Returns the instantaneous
        torque and acceleration at the start of the period, so every sample is consistent
        (tau = Y(q, qd, qdd) phi at the sample time) and smooth for differentiation; a
        zero-order hold would make qdd jump at every sample, half a sample off any symmetric
        derivative estimate."""
        q, qd = self.q, self.qd
        v = qdd_r + self.kd * (qd_r - qd) + self.kp * (q_r - q)
        # Friction is fed forward at the reference velocity: at the measured one, sign(qd)
        # chatters around zero speed on light joints (a wrist's 1e-4 kg m^2).
        nom = self._nominal
        command = nom.inverse(q, qd, v) - nom.friction(qd) + nom.friction(qd_r)
        start = command if self._tau is None else self._tau
        f = self._true.forward
        h = 1.0 / (self.rate * self.substeps)
        qdd0: np.ndarray | None = None
        for i in range(self.substeps):
            tau0 = start + (command - start) * (i / self.substeps)
            tau1 = start + (command - start) * ((i + 1) / self.substeps)
            tau_mid = 0.5 * (tau0 + tau1)
            a1 = f(q, qd, tau0)
            if qdd0 is None:
                qdd0 = a1
            v2 = qd + 0.5 * h * a1
            a2 = f(q + 0.5 * h * qd, v2, tau_mid)
            v3 = qd + 0.5 * h * a2
            a3 = f(q + 0.5 * h * v2, v3, tau_mid)
            v4 = qd + h * a3
            a4 = f(q + h * v3, v4, tau1)
            q = q + h / 6.0 * (qd + 2.0 * v2 + 2.0 * v3 + v4)
            qd = qd + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
            assert self.trajectory is not None   # reset() before any step
            start = self.trajectory.sample(np.array([self.t0]))[0][0]
            here, there = (self._true.smallest_inertia(x) for x in (q_r, start))
            raise IdentificationError(
                f'simulation diverged at t = {self.t:.4f} s (smallest eigenvalue of the mass '
                f'matrix at the reference there {here:.3g}, {there:.3g} at the start: '
                'a tiny one marks a singular configuration, such as aligned axes with massless '
                'links between them)')
        self.q, self.qd, self._tau = q, qd, command
        self._k += 1
        self.t = self.t0 + self._k / self.rate  # no drift from summing 1/rate
        assert qdd0 is not None   # substeps >= 1
        return start, qdd0

    # -- batch ------------------------------------------------------------------------------------
    def set_true_parameters(self, phi_true: np.ndarray) -> None:
        """Change the true arm from now on (a payload picked or placed); the controller's
        model stays."""
        self._true = _Dynamics(self.robot, phi_true)
        self.phi_true = np.array(phi_true, dtype=float)
        self._stabilise()

    def _stabilise(self) -> None:
        """More RK4 steps per sample where the true arm's viscous friction needs them."""
        fastest = self._true.viscous_rate(self.robot)
        if fastest > RK4_STEP * self.rate * self.substeps:
            self.substeps = math.ceil(fastest / (RK4_STEP * self.rate))

    def run(self, trajectory: Trajectory, duration: float | None = None,
            noise: SensorNoise | None = None, seed: int = 0, converter=None,
            changes: Sequence[tuple[float, np.ndarray]] = ()) -> SimResult:
        """Simulate ``duration`` s (default: the trajectory's duration, or one period) at
        ``rate``: samples t = 0, 1/rate, ... <= duration. ``changes``: (time s, true
        parameters) the arm switches to at that time (payload events)."""
        self.reset(trajectory)
        reference = self.trajectory
        assert reference is not None   # reset() sets it
        duration = reference.horizon() if duration is None else float(duration)
        if not (math.isfinite(duration) and duration >= 0):
            raise IdentificationError(f'duration must be finite and >= 0, got {duration}')
        N = int(math.floor(duration * self.rate + 1e-9)) + 1
        t = np.arange(N) / self.rate
        q_r, qd_r, qdd_r = reference.sample(t)
        n = self.robot.dof
        q, qd, qdd, tau = (np.empty((N, n)) for _ in range(4))
        switch = {int(math.ceil(time * self.rate - 1e-9)): phi
                  for time, phi in sorted(changes, key=lambda c: c[0])}
        for k in range(N):
            if k in switch:
                self.set_true_parameters(switch[k])
            q[k], qd[k] = self.q, self.qd
            tau[k], qdd[k] = self._advance(q_r[k], qd_r[k], qdd_r[k])
        return measure(self.robot, t, q, qd, qdd, tau, noise, np.random.default_rng(seed),
                       converter)


def simulate_kinematic(robot, phi: np.ndarray | None, trajectory: Trajectory, t: np.ndarray,
                       noise: SensorNoise | None = None, seed: int = 0,
                       converter=None) -> SimResult:
    """Perfect tracking: q, qd, qdd from ``trajectory`` at times ``t`` (s) and
    tau = Y(q, qd, qdd) phi (default the robot's own phi), with measurements as in run."""
    trajectory = match_joints(trajectory, robot)
    phi = robot.phi_model if phi is None else np.asarray(phi, dtype=float)
    t = np.atleast_1d(np.asarray(t, dtype=float))
    q, qd, qdd = trajectory.sample(t)
    tau = np.concatenate([robot.inverse_dynamics(q[s], qd[s], qdd[s], phi)
                          for s in (slice(k, k + _CHUNK) for k in range(0, len(t), _CHUNK))]
                         or [np.empty((0, robot.dof))])
    return measure(robot, t, q, qd, qdd, tau, noise, np.random.default_rng(seed), converter)
