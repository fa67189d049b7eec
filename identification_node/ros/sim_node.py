"""The simulated arm: ``python -m identification_node sim --ros-args -p robot:=crs_a465 ...``.

A real-time stand-in for a robot: the forward dynamics of a bundled or URDF robot following a
reference trajectory under computed-torque control (:class:`ArmSimulator`, true parameters from
the description or from ``true_parameters_file``), with sensor noise. It publishes

- ``joint_states`` (sensor_msgs/JointState: position, velocity unless ``publish_velocity`` is
  false, effort (joint torque, N m) when ``publish_effort``),
- ``motor_currents`` when ``publish_currents`` (channels ``<joint>/ia|ib|ic`` or ``<joint>/i``
  of the joints whose ``torque_source`` is three_phase or current, amperes in effort, the
  electrical angle (rad) in position when ``publish_electrical_angle``),
- ``motor_voltages`` when ``publish_voltages`` (the same channels, volts in effort: the
  drives' law of model/drive.py with ``drive.resistance``, ``drive.inductance`` and the true
  kt = kt x (1 + ``drive.kt_error``), which the currents also obey),
- ``/clock`` with the sample time when ``publish_clock``,
- ``robot_description`` (std_msgs/String, transient local).

The torque parameters (torque_source, kt, gear_ratio, pole_pairs, angle_offset, phase_order)
are parsed as the identification node parses them, so one parameter file serves both.

Timing: the dynamics run at ``rate`` (>= 1000 Hz); every ``publish_decimation``-th sample is
published. A dedicated thread schedules sample k at start + k / rate on time.monotonic and
publishes what is due, catching up in batches of at most ``MAX_BATCH`` samples. Header stamps
are the simulated sample times plus ``stamp_offset``, never wall time. With
``wait_for_subscribers`` the first sample waits for that many subscriptions; as the noise is
drawn sample by sample from ``seed``, such a run is reproducible (:class:`SampleSource`). After
the last sample of a run with a ``duration`` the node waits (at most ``ACK_TIMEOUT``) until
its reliable subscribers have acknowledged every sample, then exits.

The reported torque (and the currents) at sample k is the actuator torque at t_k, consistent
with the motion at t_k (the simulator's torque is continuous over the sample period).
"""
from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass, field, fields
from typing import Any, Mapping

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from identification_node.config import PARAMETERS, PER_JOINT, coerce
from identification_node.errors import IdentificationError
from identification_node.excitation.trajectory_base import Trajectory
from identification_node.excitation.trajectories import load_trajectory
from identification_node.model.drive import DriveModel
from identification_node.model.robot import RobotModel
from identification_node.simulation.bag import read_true_parameters
from identification_node.simulation.simulator import ArmSimulator, SensorNoise, SimResult
from identification_node.model.torque import TorqueConverter
from identification_node.payload.fit import read_payload_changes, true_parameter_changes
from identification_node.ros.conversions import publish_joint_states, time_msg, wait_for_all_acked
from identification_node.ros.parameters import declare_settings
from identification_node.ros.spin import run_node
from identification_node.settings import Settings

MAX_BATCH = 20      # samples per catch-up batch
LINGER = 0.5        # s the process stays up after the acks, for best-effort samples in flight
ACK_TIMEOUT = 10.0  # s the last samples wait for reliable subscribers' acknowledgements
ROBOT_KEYS = ('robot', 'robot_description', 'joints', 'extras', 'coulomb_velocity')

SIM_PARAMETERS: dict[str, tuple[Any, str]] = {k: PARAMETERS[k] for k in ROBOT_KEYS + PER_JOINT}
SIM_PARAMETERS.update({
    'trajectory': ('fourier', 'paper_moves, table1, fourier, or a .yaml (Fourier) or .csv file'),
    'rate': (1000.0, 'Hz of the dynamics and of the samples, >= 1000'),
    'publish_decimation': (1, 'publish every k-th sample'),
    'duration': (0.0, 's of motion, then stop; 0 = run until stopped'),
    'noise.position_std': (0.0, 'rad (m) of Gaussian noise on positions'),
    'noise.encoder_counts': (0, 'encoder counts per revolution (0: no quantisation)'),
    'noise.velocity_std': (0.0, 'rad/s (m/s) of Gaussian noise on velocities'),
    'noise.torque_std': (0.0, 'N m (N) of Gaussian noise on efforts'),
    'noise.current_std': (0.0, 'A of Gaussian noise on every current channel'),
    'publish_velocity': (True, 'fill JointState.velocity'),
    'publish_effort': (True, 'fill JointState.effort with the joint torques'),
    'publish_currents': (False, 'publish motor_currents (needs current or three_phase joints)'),
    'publish_electrical_angle': (False, 'electrical angles in motor_currents.position'),
    'publish_voltages': (False, 'publish motor_voltages (volts in effort, the channels of '
                         'motor_currents; model/drive.py)'),
    'noise.voltage_std': (0.0, 'V of Gaussian noise on every voltage channel'),
    'drive.kt_error': ([0.0], 'per joint: true kt = configured kt x (1 + value)'),
    'drive.resistance': ([0.5], 'per joint motor resistance per phase, ohm'),
    'drive.inductance': ([1e-3], 'per joint motor inductance per phase, H'),
    'true_parameters_file': ('', 'YAML of standard parameter name -> true value (default: '
                             'the robot description)'),
    'payload_events': ('', 'payloads attached at given sample times: YAML file or inline list '
                       'of {time: s, mass: kg, com: [x, y, z], inertia: [ixx, ixy, ixz, iyy, '
                       'iyz, izz], link: L} (mass 0 detaches)'),
    'seed': (0, 'seed of the sensor noise'),
    'publish_clock': (False, 'publish /clock with the sample time'),
    'stamp_offset': (0.0, 's; header stamps are stamp_offset + sample time'),
    'wait_for_subscribers': (0, 'start once joint_states and motor_currents together have '
                             'this many subscriptions (0: at once)'),
})

SENSOR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                        reliability=ReliabilityPolicy.RELIABLE)
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _bad(name: str, value: Any, expected: str) -> IdentificationError:
    return IdentificationError(f'parameter {name} = {value!r} must be {expected}')


@dataclass
class SimSetup:
    """Everything the simulated arm needs, validated from its parameters (ROS-free)."""
    values: dict[str, Any]
    robot: RobotModel
    trajectory: Trajectory
    converter: TorqueConverter
    noise: SensorNoise
    phi_true: np.ndarray
    changes: list = field(default_factory=list)   # (sample time s, true phi) payload events
    drives: DriveModel | None = None               # converter: the drives' true kt

    @classmethod
    def from_parameters(cls, given: Mapping[str, Any]) -> SimSetup:
        """Validate ``given`` (SIM_PARAMETERS names, defaults for the rest); an error names the
        parameter."""
        unknown = sorted(set(given) - set(SIM_PARAMETERS))
        if unknown:
            raise IdentificationError(f'unknown parameter(s) {unknown}')
        v = {k: d for k, (d, _) in SIM_PARAMETERS.items()}
        v.update(given)
        for name in SIM_PARAMETERS:
            if name not in ROBOT_KEYS + PER_JOINT:
                v[name] = coerce(name, v[name], SIM_PARAMETERS[name][0])
        if not 1000.0 <= v['rate'] <= 1e6:
            raise _bad('rate', v['rate'], 'in [1000, 1e6] Hz (lower the published rate with '
                       'publish_decimation)')
        if v['publish_decimation'] < 1:
            raise _bad('publish_decimation', v['publish_decimation'], '>= 1')
        if v['duration'] < 0:
            raise _bad('duration', v['duration'], '>= 0 s (0: run until stopped)')
        if v['stamp_offset'] < 0:
            raise _bad('stamp_offset', v['stamp_offset'], '>= 0 s')
        for name in ('seed', 'wait_for_subscribers'):
            if v[name] < 0:
                raise _bad(name, v[name], '>= 0')
        for key in ('position_std', 'velocity_std', 'torque_std', 'current_std',
                    'encoder_counts'):
            if v[f'noise.{key}'] < 0:
                raise _bad(f'noise.{key}', v[f'noise.{key}'], '>= 0')
        settings = Settings.from_dict({k: v[k] for k in ROBOT_KEYS + PER_JOINT if k in given})
        robot = settings.load_robot()
        configured = TorqueConverter(robot.joint_names,
                                     settings.torque_configs(robot.joint_names))
        try:
            drives = DriveModel.per_joint(robot.dof, v['drive.resistance'],
                                          v['drive.inductance'], v['drive.kt_error'])
        except IdentificationError as exc:
            raise IdentificationError(f'parameters drive.*: {exc}') from None
        converter = drives.true_converter(configured)   # the currents the true drives need
        if v['noise.voltage_std'] < 0:
            raise _bad('noise.voltage_std', v['noise.voltage_std'], '>= 0')
        if v['publish_voltages'] and not converter.needs_currents:
            raise _bad('publish_voltages', True, 'false unless some joint has torque_source '
                       'current or three_phase')
        if v['publish_currents'] and not converter.needs_currents:
            raise _bad('publish_currents', True, 'false unless some joint has torque_source '
                       'current or three_phase')
        try:
            trajectory = load_trajectory(v['trajectory'], robot)
        except IdentificationError as exc:
            raise IdentificationError(f'parameter trajectory: {exc}') from None
        what = 'parameter true_parameters_file'
        phi = (read_true_parameters(v['true_parameters_file'], robot, what)
               if v['true_parameters_file'].strip() else robot.phi_model)
        noise = SensorNoise(v['noise.position_std'], v['noise.encoder_counts'],
                            v['noise.velocity_std'], v['noise.torque_std'],
                            v['noise.current_std'])
        try:
            changes = true_parameter_changes(robot, phi, read_payload_changes(
                v['payload_events'])) if v['payload_events'].strip() else []
        except IdentificationError as exc:
            raise IdentificationError(f'parameter payload_events: {exc}') from None
        return cls(v, robot, trajectory, converter, noise, phi, changes, drives)

    @property
    def num_samples(self) -> int | None:
        """Samples t = 0, 1/rate, ... <= duration, or None to run forever."""
        d = self.values['duration']
        return int(math.floor(d * self.values['rate'] + 1e-9)) + 1 if d > 0 else None

    def stamps_ns(self, index: np.ndarray) -> np.ndarray:
        """Header stamps (int ns) of sample indices: stamp_offset + index / rate."""
        offset = round(self.values['stamp_offset'] * 1e9)
        return offset + np.round(np.asarray(index) * (1e9 / self.values['rate'])).astype(
            np.int64)


class SampleSource:
    """The arm's samples as its sensors report them, in batches. The simulator measures sample
    by sample, so the noise does not depend on how samples are batched: a run is reproducible
    from its parameters."""

    def __init__(self, setup: SimSetup):
        self.setup = setup
        self.sim = ArmSimulator(setup.robot, setup.phi_true, rate=setup.values['rate'])
        self.sim.reset(setup.trajectory, noise=setup.noise, seed=setup.values['seed'],
                       converter=setup.converter)
        self.index = 0   # of the next sample
        self._changes = list(setup.changes)

    def take(self, count: int) -> SimResult:
        """The next ``count`` samples: true values and measurements."""
        rows = []
        for _ in range(count):
            while self._changes and self._changes[0][0] <= self.sim.t + 1e-9:
                self.sim.set_true_parameters(self._changes.pop(0)[1])
            rows.append(self.sim.step())
        self.index += count
        return SimResult(**{f.name: np.concatenate([getattr(r, f.name) for r in rows])
                            for f in fields(SimResult) if f.name != 'joint_names'},
                         joint_names=rows[0].joint_names)


@dataclass
class RealTimeStats:
    """How the sample thread kept up: busy is the time spent simulating and publishing."""
    samples: int = 0
    elapsed: float = 0.0
    busy: float = 0.0
    max_lag: float = 0.0

    @property
    def load(self) -> float:
        """Busy fraction of real time (the real-time margin is 1 / load)."""
        return self.busy / self.elapsed if self.elapsed > 0 else math.nan


class SimulatedArmNode(Node):
    """The simulated arm (see the module doc); the sample thread starts with the node."""

    def __init__(self, node_name: str = 'simulated_arm', **kwargs: Any):
        super().__init__(node_name, **kwargs)
        self.setup = SimSetup.from_parameters(declare_settings(self, SIM_PARAMETERS))
        v = self.setup.values
        self.source = SampleSource(self.setup)
        self._slots = self.setup.converter.current_channel_slots()
        self._pub_js = self.create_publisher(JointState, 'joint_states', SENSOR_QOS)
        self._pub_cur = (self.create_publisher(JointState, 'motor_currents', SENSOR_QOS)
                         if v['publish_currents'] else None)
        self._pub_volt = (self.create_publisher(JointState, 'motor_voltages', SENSOR_QOS)
                          if v['publish_voltages'] else None)
        self._volt_rng = np.random.default_rng([v['seed'], 1])
        # (t, q, qd, tau) of the last sample: di/dt across batches
        self._last: tuple[np.ndarray, ...] | None = None
        self._pub_clock = (self.create_publisher(Clock, '/clock', SENSOR_QOS)
                           if v['publish_clock'] else None)
        self._sample_pubs = [p for p in (self._pub_js, self._pub_cur, self._pub_volt)
                             if p is not None]
        self._pub_urdf = self.create_publisher(String, 'robot_description', LATCHED_QOS)
        self._pub_urdf.publish(String(data=self.setup.robot.description))
        self.stats = RealTimeStats()
        self.finished = threading.Event()
        self.error: BaseException | None = None
        self._stop = threading.Event()
        robot = self.setup.robot
        total = self.setup.num_samples
        self.get_logger().info(
            f'simulating {robot.name} (joints {", ".join(robot.joint_names)}) on trajectory '
            f'{v["trajectory"]} at {v["rate"]:g} Hz, publishing every '
            f'{v["publish_decimation"]} sample(s), '
            + (f'{total} samples' if total else 'until stopped'))
        self._thread = threading.Thread(target=self._run, name='simulated_arm', daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the sample thread (idempotent)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def destroy_node(self) -> None:
        self.stop()
        super().destroy_node()

    # -- the sample thread ------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._loop()
            if not self._stop.is_set() and not wait_for_all_acked(self._sample_pubs,
                                                                  ACK_TIMEOUT):
                self.get_logger().warning(
                    f'reliable subscribers did not acknowledge every sample in {ACK_TIMEOUT} s')
            st = self.stats
            if self.context.ok():
                self.get_logger().info(
                    f'{st.samples} samples in {st.elapsed:.2f} s; simulating and publishing '
                    f'took {100 * st.load:.0f} % of real time (margin {1 / st.load:.1f}x), '
                    f'largest lag {1e3 * st.max_lag:.1f} ms')
        except Exception as exc:   # a diverging simulation, a context shut down under us
            self.error = exc
            if self.context.ok():
                self.get_logger().error(f'simulation stopped: {exc}')
        finally:
            self.finished.set()

    def _loop(self) -> None:
        rate = self.setup.values['rate']
        total = self.setup.num_samples
        st, src = self.stats, self.source
        if not self._wait_for_subscribers():
            return
        start = time.monotonic()
        warned = False
        while not self._stop.is_set() and (total is None or src.index < total):
            now = time.monotonic()
            due = int((now - start) * rate) + 1        # samples with t_k <= now
            if total is not None:
                due = min(due, total)
            if due <= src.index:
                self._stop.wait(start + src.index / rate - now)
                continue
            lag = now - start - src.index / rate
            st.max_lag = max(st.max_lag, lag)
            if lag > 0.1 and not warned:
                warned = True
                self.get_logger().warning(f'{1e3 * lag:.0f} ms behind real time')
            first = src.index
            batch = src.take(min(due - first, MAX_BATCH))
            self._publish(first, batch)
            st.samples = src.index
            done = time.monotonic()
            st.busy += done - now
            st.elapsed = done - start

    def _wait_for_subscribers(self) -> bool:
        """Wait for ``wait_for_subscribers`` subscriptions; False when stopped first."""
        want = self.setup.values['wait_for_subscribers']
        pubs = self._sample_pubs
        if want and sum(p.get_subscription_count() for p in pubs) < want:
            self.get_logger().info(f'waiting for {want} subscriptions')
            while sum(p.get_subscription_count() for p in pubs) < want:
                if self._stop.wait(0.01):
                    return False
            self._stop.wait(0.1)   # the subscribers' side of the match may lag a little
        return not self._stop.is_set()

    def _publish(self, first: int, b: SimResult) -> None:
        v = self.setup.values
        index = first + np.arange(len(b))
        keep = index % v['publish_decimation'] == 0
        if not keep.any():
            return
        stamps = self.setup.stamps_ns(index[keep])
        names = self.setup.robot.joint_names
        publish_joint_states(self._pub_js, stamps, names, position=b.q_meas[keep],
                             velocity=b.qd_meas[keep] if v['publish_velocity'] else None,
                             effort=b.tau_meas[keep] if v['publish_effort'] else None)
        if self._pub_cur is not None:
            joint = [i for _, i, _ in self._slots]
            channel = [k for _, _, k in self._slots]
            cur = b.currents[keep][:, joint, channel]
            angle = b.theta_e[keep][:, joint] if v['publish_electrical_angle'] else None
            publish_joint_states(self._pub_cur, stamps, [s[0] for s in self._slots],
                                 position=angle, effort=cur)
        if self._pub_volt is not None:
            self._publish_voltages(b, keep, stamps)
        if self._pub_clock is not None:
            self._pub_clock.publish(Clock(clock=time_msg(int(stamps[-1]))))

    def _publish_voltages(self, b: SimResult, keep: np.ndarray, stamps: np.ndarray) -> None:
        """The drives' terminal voltages of batch ``b`` (its previous sample prepended, so
        di/dt is continuous across batches)."""
        arrays = (b.t, b.q, b.qd, b.tau)
        if self._last is not None:
            t, q, qd, tau = (np.concatenate([p, a]) for p, a in zip(self._last, arrays))
            arrays = (t, q, qd, tau)
        self._last = tuple(a[-1:] for a in (b.t, b.q, b.qd, b.tau))
        assert self.setup.drives is not None   # the node's setup always has its drives
        volts = self.setup.drives.voltages(self.setup.converter, *arrays,
                                           self.setup.values['noise.voltage_std'],
                                           self._volt_rng)[-len(b):]
        joint = [i for _, i, _ in self._slots]
        channel = [k for _, _, k in self._slots]
        publish_joint_states(self._pub_volt, stamps, [s[0] for s in self._slots],
                             effort=volts[keep][:, joint, channel])


def main(args: list[str] | None = None) -> int:
    """Run the simulated arm until ``duration`` is over (exit 0, or 1 if the simulation
    failed) or interrupted; invalid parameters exit 2."""
    nodes = []

    def make() -> SimulatedArmNode:
        nodes.append(SimulatedArmNode())
        return nodes[-1]

    code = run_node(make, 'simulated_arm', args, done=lambda n: n.finished.is_set(),
                    linger=LINGER)
    if nodes:
        nodes[0].stop()
        if nodes[0].error is not None:
            return 1
    return code


if __name__ == '__main__':
    sys.exit(main())
