"""The identification node over real DDS (FastDDS): the simulated arm streams from another
process (``python -m identification_node sim``) at 1 kHz with known true parameters, the
identification nodes run in this process, spun by an executor in a thread.

Truth: the base parameters of the simulator's true parameter vector (a payload added to the
description's values), and the simulator's own samples, reproduced here from its seed."""
import json
import math
import os
import re
import signal
import subprocess
import time
import xml.etree.ElementTree as ET
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.event_handler import UnsupportedEventTypeError
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_event_handler import ParameterEventHandler
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool, Trigger

from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import (ConsistencyOptions, ConsistentSolver,
                                                        pipeline_equations)
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.model.torque import TorqueConverter
from identification_node.pipeline import REJECT_REASONS
from identification_node.ros import conversions
from identification_node.ros.conversions import PolledSubscription, wait_for_all_acked
from identification_node.ros.node import INPUT_QOS, IdentificationNode
from identification_node.ros.sim_node import SampleSource, SimSetup
from identification_node.settings import Settings
from identification_node.wire.cdr import encode_joint_states
from identification_node.wire.records import JointStateRecord
from ros_helpers import (LATCHED, RELIABLE, Collector, diagnostic_values,
                         joint_state_msgs, stamp_ns, wait_for)

pytestmark = pytest.mark.ros

DURATION = 15.0
INPUT_DEPTH = 20_000    # the reader caches of reliable() hold a whole run (15,001 samples)
OFFSET = 1000.0          # s: stamps = OFFSET + sample time
POSITION_NOISE = {'noise.position_std': 1e-5, 'noise.encoder_counts': 2 ** 20,
                  'noise.velocity_std': 1e-4}
MIT = dict(robot='mit_dd_arm', trajectory='fourier', torque_std=0.5, current_std=0.02,
           torque={'kt': [12.0, 6.0, 6.0], 'gear_ratio': [1.0], 'pole_pairs': [8],
                   'angle_offset': [0.3], 'phase_order': ['abc']},
           payload=('link3', 2.0, [0.0, 0.0, 0.3]), electrical_angle=False)
CRS = dict(robot='crs_a465', trajectory='table1', torque_std=0.2, current_std=0.01,
           torque={'kt': [0.1], 'gear_ratio': [100.0, 100.0, 100.0, 50.0, 50.0, 50.0],
                   'pole_pairs': [4], 'angle_offset': [0.0, 0.5, 1.0, 1.5, 2.0, 2.5],
                   'phase_order': ['abc', 'acb', 'abc', 'acb', 'abc', 'acb']},
           payload=('link6', 0.5, [0.0, 0.05, 0.1]), electrical_angle=True)
# The smoother pinned (its automatic choice holds 5 s back; tested on its own below)
FAST = {'process_period': 0.01, 'publish.effort_rate': 200.0, 'smoother.half_window': 10}


def remaps(prefix):
    """Each stream has its own topics /<prefix>/joint_states and /<prefix>/motor_currents."""
    return [f'{t}:=/{prefix}/{t}' for t in ('joint_states', 'motor_currents')]


def start_node(ros, name, params, prefix):
    """An IdentificationNode in this process (parameters as rclpy overrides)."""
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    args = ['--ros-args'] + [a for r in remaps(prefix) for a in ('-r', r)]
    return ros.add(IdentificationNode(name, context=ros.context, parameter_overrides=overrides,
                                      cli_args=args))


def reliable(prefix, depth=INPUT_DEPTH):
    """QoS overrides making the node's subscriptions reliable, their reader caches ``depth``
    deep (a whole run): under CPU contention (2 cores shared with other test processes) best
    effort loses messages, and a node not taking them for over a second (the default depth,
    1000, at 1 kHz) loses the oldest, reliable or not; these tests count every sample."""
    return {f'qos_overrides./{prefix}/{t}.subscription.{policy}': value
            for t in ('joint_states', 'motor_currents')
            for policy, value in (('reliability', 'reliable'), ('depth', depth))}


def start_node_process(ros, name, params, tmp, remaps=()):
    """``python -m identification_node node`` named ``name``; returns once its services are up."""
    extra = ['-r', f'__node:={name}']
    for remap in remaps:
        extra += ['-r', remap]
    proc = ros.start('node', params, tmp, name, extra=tuple(extra))
    client = ros.client.create_client(Trigger, f'/{name}/get_estimate')
    up = client.wait_for_service(timeout_sec=30)
    ros.client.destroy_client(client)
    assert up, proc.stderr.read() if proc.poll() is not None else f'{name} did not start'
    return proc


def exit_log(proc, timeout: float, what: str) -> str:
    """The node's log (stderr) once it exits, its pipes read while waiting (its output cannot
    fill them and block it); a node still up after ``timeout`` s (a hang, a bound no busy
    machine reaches) is killed and fails the test with its log, ``what`` it was waiting for."""
    try:
        return proc.communicate(timeout=timeout)[1]
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError(f'no exit within {timeout:g} s of {what}; its log:\n'
                             f'{proc.communicate()[1]}') from None


def stop_process(proc) -> str:
    """SIGINT, as Ctrl-C: the node shuts down cleanly with exit code 0, or by the watchdog's
    forced exit (1, said in the log) when a busy machine stretches the shutdown beyond its
    grace (the grace itself: test_node_faults). Returns the node's log (stderr)."""
    proc.send_signal(signal.SIGINT)
    log = exit_log(proc, 60, 'SIGINT')   # the watchdog exits first
    code = proc.returncode
    assert code == 0 or (code == 1 and 'shutdown did not finish within' in log), (code, log)
    return log


def current_noise(spec):
    """Per-joint std of the torque from noisy three-phase currents: the current noise times
    gear_ratio * kt * sqrt(3/2)."""
    n = load_robot(spec['robot']).dof
    kt, gear = (np.broadcast_to(spec['torque'][k], (n,)) for k in ('kt', 'gear_ratio'))
    return np.asarray(kt) * gear * spec['current_std'] * math.sqrt(1.5)


def payload_phi(robot, link, mass, point):
    """The robot's phi with a point mass at ``point`` (link frame) added to ``link``."""
    phi = robot.phi_model.copy()
    i = 10 * robot.link_names.index(link)
    p = np.asarray(point, dtype=float)
    inertia = mass * (p @ p * np.eye(3) - np.outer(p, p))
    phi[i:i + 4] += mass * np.concatenate([[1.0], p])
    phi[i + 4:i + 10] += inertia[[0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    return phi


def get_estimate(ros, target):
    res = ros.call(Trigger, f'{target}/get_estimate', Trigger.Request())
    assert res.success
    return json.loads(res.message)


def last_status(diag, name):
    """The newest /diagnostics status of node ``name`` (None before the first)."""
    found = [s for m in diag.snapshot() for s in m.status if s.name.startswith(f'{name}:')]
    return diagnostic_values(found[-1]) if found else None


def received_and_lost(diag, name):
    """(samples received, joint-state messages lost) in node ``name``'s newest diagnostics."""
    values = last_status(diag, name) or {}
    return (int(values.get('samples_received', 0)),
            int(values.get('lost_messages.joint_states', 0)))


class Stream:
    """One simulated-arm run and two identification node processes listening to it:
    ``<prefix>_measured`` (joint torque from JointState.effort) and ``<prefix>_currents``
    (three-phase currents)."""

    def __init__(self, ros, diag, spec, tmp, prefix):
        self.spec, self.ros, self.diag = spec, ros, diag
        self.robot = load_robot(spec['robot'])
        link, mass, point = spec['payload']
        self.phi = payload_phi(self.robot, link, mass, point)
        true_file = tmp / 'true_parameters.yaml'
        true_file.write_text(yaml.safe_dump({n: float(v) for n, v in
                                             zip(self.robot.param_names, self.phi)
                                             if n.startswith(link + '.')}))
        torque = dict(spec['torque'], torque_source=['three_phase'])
        self.sim_params = dict(
            torque, robot=spec['robot'], trajectory=spec['trajectory'], rate=1000.0,
            duration=DURATION, stamp_offset=OFFSET, seed=7, publish_currents=True,
            publish_electrical_angle=spec['electrical_angle'],
            true_parameters_file=str(true_file), **POSITION_NOISE,
            **{'noise.torque_std': spec['torque_std'], 'noise.current_std': spec['current_std']})
        # the simulated arms have no friction; not what these tests check: no columns. Nor
        # the solver's speed: a busy machine may stretch a solve past the default 5 s limit.
        common = dict(FAST, robot=spec['robot'], extras=[], output_directory=str(tmp / 'out'),
                      **{'consistency.time_limit': 60.0}, **reliable(prefix))
        self.names = (f'{prefix}_measured', f'{prefix}_currents')
        # The torque noise from the currents differs per joint (kt, gear ratio): the estimate
        # needs the ratios, or its covariance (one pooled noise variance) is wrong.
        self.node_params = dict(zip(self.names, (common, dict(
            common, joint_noise_std=current_noise(spec).tolist(), **torque))))
        self.prefix = prefix
        self.procs = {n: start_node_process(ros, n, self.node_params[n], tmp, remaps(prefix))
                      for n in self.names}
        self.predicted = {n: Collector(ros, JointState, f'/{n}/predicted_effort')
                          for n in self.names}

    def start(self, tmp, subscriptions):
        """Start the simulated arm once it has ``subscriptions`` on its sample topics: every
        node then sees every sample, and its estimate is reproducible."""
        self.sim_params['wait_for_subscribers'] = subscriptions
        self.proc = self.ros.start('sim', self.sim_params, tmp, 'simulated_arm',
                                   extra=('-r', f'__ns:=/{self.prefix}'))

    def wait_done(self):
        assert self.proc.wait(DURATION + 60) == 0, self.proc.stderr.read()
        self.sim_log = self.proc.stderr.read()
        # The arm left once the nodes had every sample; wait until they report them taken.
        total = SimSetup.from_parameters(self.sim_params).num_samples
        wait_for(lambda: all(received_and_lost(self.diag, n)[0] >= total
                             for n in self.names), 20)

    def stop(self):
        for proc in self.procs.values():
            stop_process(proc)
        for c in self.predicted.values():
            c.close()

    def index(self, stamps_ns):
        return np.round((np.asarray(stamps_ns) - int(OFFSET * 1e9)) * 1e-6).astype(int)


def simulated_samples(sim_params):
    """The simulated arm's samples (true and measured), recomputed from its parameters."""
    setup = SimSetup.from_parameters(sim_params)
    return SampleSource(setup).take(setup.num_samples)


def offline_estimate(sim_params, node_params, sim):
    """The estimate of a pipeline with the node's settings, fed every published sample
    offline (records as the node makes them from the messages)."""
    p = Settings.from_dict({k: v for k, v in node_params.items()
                            if not k.startswith('qos_overrides.')}).build()
    names = tuple(p.robot.joint_names)
    stamps = int(sim_params['stamp_offset'] * 1e9) + np.arange(len(sim.t)) * 1_000_000
    slots = p.converter.current_channel_slots()
    channels = tuple(name for name, _, _ in slots)
    joint, channel = [s[1] for s in slots], [s[2] for s in slots]
    currents = sim.currents[:, joint, channel]
    angle = (sim.theta_e[:, joint] if sim_params['publish_electrical_angle']
             else np.empty((len(sim.t), 0)))
    for start in range(0, len(sim.t), 10):
        for k in range(start, min(start + 10, len(sim.t))):
            p.add_joint_state(JointStateRecord(int(stamps[k]), names, sim.q_meas[k],
                                               sim.qd_meas[k], sim.tau_meas[k]))
            if slots:
                p.add_currents(JointStateRecord(int(stamps[k]), channels, angle[k],
                                                np.empty(0), currents[k]))
        p.process()
    return p


@pytest.fixture(scope='module')
def diag(ros):
    collector = Collector(ros, DiagnosticArray, '/diagnostics')
    yield collector
    collector.close()


@pytest.fixture(scope='module')
def mit(ros, diag, tmp_path_factory):
    tmp = tmp_path_factory.mktemp('mit')
    stream = Stream(ros, diag, MIT, tmp, 'mit')
    # One more node, in this process, for the services and parameters.
    stream.services = start_node(ros, 'services', {
        'robot': 'mit_dd_arm', 'extras': [], 'process_period': 0.01,
        'publish.estimate_rate': 5.0,
        'smoother.half_window': 10,
        'publish.diagnostics_rate': 5.0, 'publish.effort_rate': 10.0,
        'output_directory': str(tmp / 'saved')}, 'mit')
    stream.start(tmp, subscriptions=4)    # joint_states: 3 nodes, motor_currents: 1
    yield stream
    stream.stop()
    ros.remove(stream.services)


# -- while the stream runs ------------------------------------------------------------------------
def test_polled_input_takes_every_message_in_order_and_only_when_polled(ros):
    """The node's inputs are taken from the middleware queue when polled, never dispatched
    by the executor: a burst deeper than one poll arrives complete, in order, byte-exact."""
    node = Node('polled', context=ros.context)
    got, polling = [], [False]

    def handle(raws: list[bytes]) -> None:
        assert polling[0], 'dispatched by the executor'
        got.extend(raws)
    source = PolledSubscription(node, JointState, '/polled/joint_states', handle, RELIABLE)
    ros.add(node)               # spun by an executor, as the identification node is
    pub = ros.client.create_publisher(JointState, '/polled/joint_states', RELIABLE)
    assert wait_for(lambda: pub.get_subscription_count(), 10)
    sent = encode_joint_states(np.arange(300) * 10**6, ['a', 'b'], np.random.rand(300, 2))
    for raw in sent:
        pub.publish(raw)
    time.sleep(0.5)             # the executor spins meanwhile: it must not take them
    assert got == []

    def poll() -> int:
        polling[0] = True
        try:
            return source.poll()
        finally:
            polling[0] = False
    assert wait_for(lambda: poll() == 0 and len(got) == len(sent), 10)
    assert got == sent
    source.destroy()
    ros.client.destroy_publisher(pub)
    ros.remove(node)


def polled_burst(ros, topic, depth, bursts, publishers=1, publisher_of=lambda k: 0,
                 **options):
    """A PolledSubscription of ``topic`` keeping ``depth`` messages (reliable), fed by
    ``publishers`` publishers, message k by ``publisher_of(k)``; each burst of ``bursts`` is
    published whole, then polled. Returns the subscription and how many messages each poll
    took."""
    node = Node(topic.replace('/', '_').strip('_'), context=ros.context)
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                     reliability=ReliabilityPolicy.RELIABLE)
    got = []
    source = PolledSubscription(node, JointState, topic, got.extend, qos, **options)
    pubs = [ros.client.create_publisher(JointState, topic, RELIABLE) for _ in range(publishers)]
    assert wait_for(lambda: node.count_publishers(topic) == publishers and all(
        p.get_subscription_count() for p in pubs), 10)
    taken, k = [], 0
    for n in bursts:
        for raw in encode_joint_states(np.arange(k, k + n) * 10**6, ['a'], np.ones((n, 1))):
            pubs[publisher_of(k)].publish(raw)
            k += 1
        assert wait_for_all_acked(pubs, 10)
        taken.append(source.poll())
    for p in pubs:
        ros.client.destroy_publisher(p)
    source.destroy()
    node.destroy_node()
    return source, taken


def test_polled_input_counts_what_its_queue_dropped(ros):
    """After a first message, 300 into a queue of 10 between two polls: 290 lost (no
    middleware event reports a subscription's own queue overflowing; the sequence numbers
    tell); then a burst that fits loses nothing more. (What went before the first message
    taken is nobody's loss: the subscription may have joined late.)"""
    source, taken = polled_burst(ros, '/overflow/joint_states', 10, [1, 300, 5])
    assert taken == [1, 10, 5]
    assert source.lost == 290
    # without the middleware's message-lost event (it can deadlock rmw_fastrtps)
    assert source.sequence_numbers and not source.events


def test_polled_input_from_two_publishers_counts_no_loss(ros):
    """Two publishers' sequence numbers interleave (one sends every tenth message): their
    jumps are no gaps."""
    source, taken = polled_burst(ros, '/two/joint_states', 1000, [100, 100], publishers=2,
                                 publisher_of=lambda k: int(k % 10 == 9))
    assert taken == [100, 100]
    assert source.lost == 0


def test_polled_input_without_message_lost_events(ros, monkeypatch):
    """A middleware that cannot report lost messages (UnsupportedEventTypeError where rclpy
    raises it, after declaring the QoS override parameters): the subscription is made
    without the event, and the sequence numbers still count its queue's losses."""
    class Unsupported:
        def create_event_handlers(self, *args):
            raise UnsupportedEventTypeError('message lost')
    monkeypatch.setattr(conversions, 'SubscriptionEventCallbacks', lambda **_: Unsupported())
    source, taken = polled_burst(ros, '/no_events/joint_states', 10, [1, 50],
                                 message_lost_event=True)
    assert (taken, source.lost, source.events) == ([1, 10], 40, False)


def test_effort_topics_are_published_only_to_subscribers(ros):
    """Nobody listens to ~/measured_effort: it is not even serialized; ~/predicted_effort,
    subscribed, gets every sample through the smoother, stamped with the sample's stamp."""
    node = start_node(ros, 'lazy', {'robot': 'mit_dd_arm', 'torque_source': ['measured'],
                                    'process_period': 0.01, 'smoother.half_window': 10}, 'lazy')
    published = {'predicted': 0, 'measured': 0}
    for key, pub in (('predicted', node.efforts.predicted), ('measured', node.efforts.measured)):
        def counting(raw, key=key, publish=pub.publish):
            published[key] += 1
            publish(raw)
        pub.publish = counting
    got = Collector(ros, JointState, '/lazy/predicted_effort')
    sender = ros.client.create_publisher(JointState, '/lazy/joint_states', RELIABLE)
    assert wait_for(lambda: sender.get_subscription_count()
                    and node.efforts.predicted.get_subscription_count(), 10)
    n, names = 200, node.robot.joint_names
    stamps = 10**9 + np.arange(n) * 10**6
    rng = np.random.default_rng(3)
    for msg in joint_state_msgs(stamps, names, *rng.normal(size=(3, n, len(names)))):
        sender.publish(msg)
    lag = int(node.pipeline.delay)
    through = n - 2 * lag             # all but the smoother's first and last half windows
    assert wait_for(lambda: len(got) >= through, 10)
    assert [stamp_ns(m) for m in got.snapshot()] == list(stamps[lag:lag + through])
    assert published == {'predicted': through, 'measured': 0}
    got.close()
    ros.client.destroy_publisher(sender)
    ros.remove(node)


def test_processing_period_follows_whether_an_output_waits(ros, diag):
    """With nothing subscribed to the effort outputs the node processes every
    idle_process_period (no output's latency counts), and get_estimate still answers with
    every sample sent; once ~/predicted_effort is subscribed, every process_period (with
    latency_budget 0), and it gets the samples sent after that."""
    node = start_node(ros, 'idle', {'robot': 'mit_dd_arm', 'torque_source': ['measured'],
                                    'process_period': 0.01, 'idle_process_period': 1.0,
                                    'latency_budget': 0.0, 'smoother.half_window': 10}, 'idle')

    def period():
        return float((last_status(diag, 'idle') or {}).get('processing_period_s', 'nan'))
    assert wait_for(lambda: period() == 1.0, 20)
    sender = ros.client.create_publisher(JointState, '/idle/joint_states', RELIABLE)
    assert wait_for(lambda: sender.get_subscription_count(), 10)
    n, names, lag = 200, node.robot.joint_names, 10
    rng = np.random.default_rng(4)
    for msg in joint_state_msgs(10**9 + np.arange(n) * 10**6, names,
                                *rng.normal(size=(3, n, len(names)))):
        sender.publish(msg)
    # all but the smoother's first and last half windows used, and answered with
    assert wait_for(lambda: node.pipeline.used == n - 2 * lag, 10)
    used = node.estimate().num_samples
    assert used > 0 and wait_for(lambda: get_estimate(ros, '/idle')['num_samples'] == used, 10)
    got = Collector(ros, JointState, '/idle/predicted_effort')
    assert wait_for(lambda: period() == 0.01, 20)
    for msg in joint_state_msgs(10**9 + np.arange(n, 2 * n) * 10**6, names,
                                *rng.normal(size=(3, n, len(names)))):
        sender.publish(msg)
    assert wait_for(lambda: len(got) >= n, 10)   # the held half window, then all but the last
    assert [stamp_ns(m) for m in got.snapshot()] == list(
        10**9 + np.arange(n - lag, 2 * n - lag) * 10**6)
    got.close()
    ros.client.destroy_publisher(sender)
    ros.remove(node)


def test_processing_period_follows_the_latency_budget(ros, diag):
    """With an effort output subscribed the period is what the latency budget leaves of
    the recent runs (spin.BudgetPeriod), at least process_period and at most
    idle_process_period; every output is published."""
    node = start_node(ros, 'budget', {'robot': 'mit_dd_arm', 'torque_source': ['measured'],
                                      'process_period': 0.01, 'idle_process_period': 1.0,
                                      'latency_budget': 0.3, 'smoother.half_window': 10},
                      'budget')

    def period():
        return float((last_status(diag, 'budget') or {}).get('processing_period_s', 'nan'))
    got = Collector(ros, JointState, '/budget/predicted_effort')
    sender = ros.client.create_publisher(JointState, '/budget/joint_states', RELIABLE)
    assert wait_for(lambda: sender.get_subscription_count()
                    and node.efforts.predicted.get_subscription_count(), 10)
    n, names, lag = 400, node.robot.joint_names, 10
    rng = np.random.default_rng(6)
    for k, msg in enumerate(joint_state_msgs(10**9 + np.arange(n) * 10**6, names,
                                             *rng.normal(size=(3, n, len(names))))):
        sender.publish(msg)
        if k % 20 == 19:
            time.sleep(0.02)
    assert wait_for(lambda: len(got) >= n - 2 * lag, 20)
    assert [stamp_ns(m) for m in got.snapshot()] == list(
        10**9 + np.arange(lag, n - lag) * 10**6)
    # runs of a few ms (under 0.1 s even on a busy machine): a period well over
    # process_period, within the budget
    assert wait_for(lambda: 0.03 < period() < 0.3, 20), period()
    got.close()
    ros.client.destroy_publisher(sender)
    ros.remove(node)


def test_idle_receiving_keeps_up_with_the_input_rate(ros):
    """No output waits (idle_process_period 1 s), but the middleware's queue (1000 messages)
    is emptied before it would drop: 4000 joint states at about 2 kHz all arrive, none lost."""
    node = start_node(ros, 'burst', {'robot': 'mit_dd_arm', 'torque_source': ['measured'],
                                     'idle_process_period': 1.0,
                                     'smoother.half_window': 10}, 'burst')
    pub = ros.client.create_publisher(JointState, '/burst/joint_states', QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE))
    assert wait_for(lambda: pub.get_subscription_count(), 10)
    N, rng = 4000, np.random.default_rng(5)
    for k, raw in enumerate(encode_joint_states(10**9 + np.arange(N) * 10**6,
                                                node.robot.joint_names, *rng.random((3, N, 3)))):
        pub.publish(raw)
        if k % 10 == 9:
            time.sleep(0.005)
    assert wait_for(lambda: node.pipeline.received == N, 15), node.pipeline.received
    assert node.inputs[0].lost == 0
    ros.client.destroy_publisher(pub)
    ros.remove(node)


def test_automatic_smoother_is_chosen_after_5_s_of_motion_and_reported(ros, diag):
    """The default: no prediction until 5 s of motion are in, then every sample but the
    chosen window's edges, the choice in /diagnostics."""
    node = start_node(ros, 'auto', {'robot': 'mit_dd_arm', 'torque_source': ['measured'],
                                    'process_period': 0.01, 'publish.diagnostics_rate': 5.0},
                      'auto')
    got = Collector(ros, JointState, '/auto/predicted_effort')
    sender = ros.client.create_publisher(JointState, '/auto/joint_states', RELIABLE)
    assert wait_for(lambda: sender.get_subscription_count()
                    and node.efforts.predicted.get_subscription_count(), 10)
    traj = FourierTrajectory.random(node.robot, harmonics=4, period=10.0, seed=2)
    n = 7000
    sim = simulate_kinematic(node.robot, None, traj, np.arange(n) / 1000.0,
                             SensorNoise(torque_std=0.2), seed=2)
    stamps = 10**9 + np.arange(n) * 10**6
    msgs = joint_state_msgs(stamps, node.robot.joint_names, sim.q_meas, sim.qd_meas,
                            sim.tau_meas)

    def send(a, b):   # in bursts the node's input queue holds
        for k in range(a, b, 250):
            for msg in msgs[k:min(b, k + 250)]:
                sender.publish(msg)
            assert wait_for(lambda: node.pipeline.received >= min(b, k + 250), 10)
    send(0, 4000)
    time.sleep(0.3)
    assert len(got) == 0 and node.pipeline.smoother is None
    status = wait_for(lambda: (last_status(diag, 'auto') or {}).get('smoother'), 5)
    assert status and (last_status(diag, 'auto') or {})['smoother'].startswith('being chosen')
    send(4000, n)
    assert wait_for(lambda: node.pipeline.smoother is not None, 10)
    lag = node.pipeline.smoother.half_window
    assert node.pipeline.smoother.source == 'automatic'
    # every sample but the window's edges went through (the held ones in one burst of
    # predictions, which a subscriber's queue need not hold)
    assert wait_for(lambda: node.pipeline.used == n - 2 * lag, 10)
    assert wait_for(lambda: len(got) and stamp_ns(got.snapshot()[-1]) == stamps[n - lag - 1],
                    10)
    assert set(stamp_ns(m) for m in got.snapshot()) <= set(stamps[lag:n - lag].tolist())
    assert wait_for(lambda: (last_status(diag, 'auto') or {}).get('smoother') == 'automatic',
                    5)
    values = last_status(diag, 'auto')
    assert int(values['smoother_delay_samples']) == lag
    assert float(values['smoother_delay_ms']) == pytest.approx(lag, rel=1e-3)   # 1 kHz
    assert float(values['smoother_cutoff_hz']) == pytest.approx(
        node.pipeline.smoother.cutoff, rel=1e-5)
    got.close()
    ros.client.destroy_publisher(sender)
    ros.remove(node)


def test_estimate_parameters_while_streaming(ros, mit):
    target = '/services'
    node = mit.services
    names = node.pipeline.base.names
    got = ros.get_parameters(target, ['base_parameter_names'])
    assert got['base_parameter_names'] == names
    assert wait_for(lambda: node.estimate().num_samples > 1000, 20)
    # A ParameterEventHandler sees the estimate being refreshed.
    seen = []
    handler = ParameterEventHandler(ros.client)
    handle = handler.add_parameter_callback(f'estimate.{names[0]}', target, seen.append)
    assert wait_for(lambda: len(seen) >= 2, 60)   # 1 Hz refreshes; generous for a busy machine
    assert all(math.isfinite(parameter_value_to_python(m.value)) for m in seen)
    handler.remove_parameter_callback(handle)
    handler.destroy()
    est = ros.get_parameters(target, [f'estimate.{n}' for n in names]
                             + [f'estimate_stddev.{n}' for n in names])
    values = np.array([est[f'estimate.{n}'] for n in names])
    stddev = np.array([est[f'estimate_stddev.{n}'] for n in names])
    assert np.all(np.isfinite(values)) and np.any(values != 0)
    assert np.all(stddev > 0)
    # Outputs and settings cannot be set from outside.
    # (settings safe to change at run time are tested in test_runtime_parameters.py)
    before = ros.get_parameters(target, ['update_batch'])['update_batch']
    for name, value in ((f'estimate.{names[0]}', 1.0), (f'estimate_stddev.{names[1]}', 1.0),
                        ('base_parameter_names', ['x']), ('update_batch', before + 1)):
        results = ros.set_parameters(target, [Parameter(name, value=value)])
        assert not results[0].successful, name
        assert results[0].reason
    assert ros.get_parameters(target, ['update_batch'])['update_batch'] == before


def test_services_while_streaming(ros, mit):
    node = mit.services
    names = node.pipeline.base.names
    assert wait_for(lambda: node.estimate().num_samples > 1000, 20)
    # freeze: the estimate stops moving while the stream goes on; get_estimate (JSON) and the
    # parameters agree exactly.
    assert ros.call(SetBool, '/services/freeze', SetBool.Request(data=True)).success
    first = get_estimate(ros, '/services')
    received = node.pipeline.received
    assert wait_for(lambda: node.pipeline.received > received + 300, 5)
    second = get_estimate(ros, '/services')
    assert second['num_samples'] == first['num_samples'] and second['values'] == first['values']
    assert second['names'] == names and len(second['stddev']) == len(names)
    params = ros.get_parameters('/services', [f'estimate.{n}' for n in names])
    assert [params[f'estimate.{n}'] for n in names] == second['values']
    assert ros.call(SetBool, '/services/freeze', SetBool.Request(data=False)).success
    assert wait_for(lambda: get_estimate(ros, '/services')['num_samples']
                    > first['num_samples'], 5)

    # save: estimate.yaml and identified.urdf, atomically, in output_directory only. It writes
    # the physically consistent estimate, so it waits for the solver process's start-up (tens
    # of seconds on a busy machine; until then the estimate goes out 'starting').
    assert wait_for(lambda: get_estimate(ros, '/services')['consistency_status'] != 'starting',
                    120)
    out = Path(node.settings.output_directory)
    res = ros.call(Trigger, '/services/save', Trigger.Request())
    assert res.success, res.message
    paths = sorted(Path(p) for p in res.message.split())
    assert paths == [out / 'estimate.yaml', out / 'identified.urdf']
    assert sorted(os.listdir(out)) == ['estimate.yaml', 'identified.urdf']
    doc = yaml.safe_load(paths[0].read_text())
    assert [b['name'] for b in doc['base_parameters']] == names
    assert doc['num_samples'] > 0
    urdf = ET.fromstring(paths[1].read_text())
    assert len(urdf.findall('link/inertial')) >= 3

    # reset: the estimate starts again.
    before = get_estimate(ros, '/services')['num_samples']
    assert ros.call(Trigger, '/services/reset', Trigger.Request()).success
    assert get_estimate(ros, '/services')['num_samples'] < before


def test_published_outputs_while_streaming(ros, mit, diag):
    node = mit.services
    b = node.pipeline.base.num_base
    params = Collector(ros, Float64MultiArray, '/services/base_parameters')
    # (counters restarted with the reset above.) On a busy machine the stream may have ended
    # while the test above waited for the solver process: then half a second of samples goes
    # straight into the pipeline, stamped after the stream's, as its processing thread would.
    if not wait_for(lambda: node.pipeline.received, 2):
        robot = node.robot
        t = np.arange(0.0, 0.5, 1e-3)
        q, qd, qdd = FourierTrajectory.random(robot, period=4.0, seed=3).sample(t)
        stamps = round((OFFSET + DURATION + 5.0) * 1e9) + 1_000_000 * np.arange(len(t))
        with node.lock:
            node.pipeline.add_joint_states(JointStateRecord(
                stamps.astype(np.int64), tuple(robot.joint_names), q, qd,
                robot.inverse_dynamics(q, qd, qdd)))
    assert wait_for(lambda: len(params) and int((last_status(diag, 'services') or {}).get(
        'samples_received', 0)), 10)
    msg = params.snapshot()[-1]
    params.close()
    assert [(d.label, d.size) for d in msg.layout.dim] == [
        ('value_stddev_unconstrained', 3), ('base_parameter', b)]
    assert len(msg.data) == 3 * b and np.all(np.isfinite(msg.data))
    values = last_status(diag, 'services')
    assert {f'rejected.{r}' for r in REJECT_REASONS} <= set(values)
    assert int(values['samples_received']) > 0
    # The latched identified URDF reaches a subscriber that comes late.
    urdf = Collector(ros, String, '/services/robot_description', LATCHED)
    assert wait_for(lambda: len(urdf), 5)
    assert ET.fromstring(urdf.snapshot()[0].data).get('name') == 'mit_dd_arm'
    urdf.close()


# -- convergence ----------------------------------------------------------------------------------
def check_convergence(stream):
    """Both nodes got every sample and none was rejected; the unconstrained estimate is the one
    the pipeline computes offline from the same samples, within 3 standard deviations of the
    truth; the published one is the consistent solve of the same information and predicts the
    torque within 1.2 times the noise on the torque each node sees."""
    stream.wait_done()
    sim = simulated_samples(stream.sim_params)
    robot = stream.robot
    base = BaseParameters.from_robot(robot)
    truth = base.to_base(stream.phi)
    conv = TorqueConverter(robot.joint_names, SimSetup.from_parameters(
        stream.sim_params).converter.configs)
    angle = sim.theta_e if stream.spec['electrical_angle'] else None
    raw = {stream.names[0]: sim.tau_meas,
           stream.names[1]: conv.torque(sim.q_meas, currents=sim.currents, theta_e=angle)}
    noise = {stream.names[0]: np.full(robot.dof, stream.spec['torque_std']),
             stream.names[1]: current_noise(stream.spec)}
    report = {}
    for name in stream.names:
        pipeline = offline_estimate(stream.sim_params, stream.node_params[name], sim)
        offline = pipeline.estimate()
        # diagnostics and ~/get_estimate are snapshots published at their rates: wait for
        # those taken after the last sample (and solved: 'starting' while the solver process
        # builds its problem)
        est = wait_for(lambda: (e := get_estimate(stream.ros, f'/{name}'))['num_samples']
                       == offline.num_samples and e['consistency_status'] != 'starting'
                       and e, 120) or get_estimate(stream.ros, f'/{name}')
        assert est['names'] == base.names
        values, stddev = np.array(est['values']), np.array(est['stddev'])
        # stddev is the data's (unconstrained) estimate's; the consistent one may lie anywhere
        # in the data's confidence region (consistency.confidence), so it is checked against
        # its own solve below and by the torque it predicts
        z = (np.array(est['unconstrained_values']) - truth) / stddev
        report[name] = dict(max_z=round(float(np.abs(z).max()), 2),
                            num_samples=est['num_samples'], converged=est['converged'])
        status = wait_for(lambda: (v := last_status(stream.diag, name))
                          and int(v['samples_received']) == len(sim.t) and v, 30) \
            or last_status(stream.diag, name)
        rejected = {r: int(status[f'rejected.{r}']) for r in REJECT_REASONS}
        assert int(status['samples_received']) == len(sim.t), (name, status)
        assert sum(rejected.values()) == 0, rejected
        assert est['num_samples'] == offline.num_samples
        diff = np.abs(np.array(est['unconstrained_values']) - offline.values) / offline.stddev
        assert np.all(diff <= 1e-6), (name, diff.max())
        # the published estimate is the consistent solve on the same information, offline
        assert est['consistency_status'] == 'optimal'
        solver = ConsistentSolver.for_robot(robot, pipeline.base, ConsistencyOptions())
        consistent = solver.solve(*pipeline_equations(pipeline))
        # two solves to the solver's tolerance: a change of 1e-9 (relative) in the information,
        # as summing it in another order gives, moves the answer by 3e-3 standard deviations
        diff = np.abs(values - consistent.theta) / offline.stddev
        assert np.all(diff <= 2e-2), (name, diff.max())
        assert np.all(np.abs(z) <= 3.0), (name, z.round(2))
        # The final estimate predicts the raw measured torque to the noise level.
        Yb = base.base_regressor(robot.regressor(sim.q, sim.qd, sim.qdd))
        rms = np.sqrt(np.mean((Yb @ values - raw[name]) ** 2, axis=0))
        assert np.all(rms <= 1.2 * noise[name]), (name, rms, noise[name])
        # So does the running prediction the node published, over the second half.
        msgs = stream.predicted[name].snapshot()
        k = stream.index([stamp_ns(m) for m in msgs])
        late = k > len(sim.t) // 2
        assert late.sum() > 500
        predicted = np.array([m.effort for m in msgs])[late]
        run_rms = np.sqrt(np.mean((predicted - raw[name][k[late]]) ** 2, axis=0))
        assert np.all(run_rms <= 1.2 * noise[name]), (name, run_rms, noise[name])
        assert est['converged']
    return report


def test_mit_arm_converges_to_the_truth(mit):
    report = check_convergence(mit)
    print('\nMIT', report, re.findall(r'took .*', mit.sim_log))


def controller_client():
    """examples/controller_client.py, the example controller-side client (not in the
    package)."""
    import importlib.util
    path = Path(__file__).resolve().parents[1] / 'examples' / 'controller_client.py'
    spec = importlib.util.spec_from_file_location('controller_client', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_controller_client_feedforward(ros, mit):
    IdentifiedModel = controller_client().IdentifiedModel
    target = '/mit_measured'
    est = get_estimate(ros, target)     # also refreshes the estimate parameters
    model = IdentifiedModel.from_node(ros.client, target)
    np.testing.assert_array_equal(model.theta, est['values'])
    np.testing.assert_array_equal(model.stddev, est['stddev'])
    robot = load_robot('mit_dd_arm')
    assert model.joint_names == robot.joint_names
    # Independently: pinocchio's RNEA with standard parameters that reproduce the estimate.
    base = BaseParameters.from_robot(robot)
    phi = base.closest_standard(np.array(est['values']), robot.phi_model)
    rng = np.random.default_rng(5)
    q, qd, qdd = (rng.uniform(-2, 2, (50, 3)) for _ in range(3))
    expected = robot.rnea(q, qd, qdd, phi)
    tol = 1e-9 * np.abs(expected).max()
    np.testing.assert_allclose(model.feedforward(q, qd, qdd), expected, rtol=1e-9, atol=tol)
    np.testing.assert_allclose(model.feedforward(q[0], qd[0], qdd[0]), expected[0], rtol=1e-9,
                               atol=tol)
    # A model of other joints is refused (its base parameters differ).
    with pytest.raises(IdentificationError, match='do not match'):
        IdentifiedModel.from_node(ros.client, target, load_robot('mit_dd_arm',
                                                                 ['joint2', 'joint3']))


# -- bad input ------------------------------------------------------------------------------------
def test_bad_input_is_rejected_and_counted(ros, diag, tmp_path):
    """Published from this process to a node process, with three-phase currents."""
    torque = {'torque_source': ['three_phase'], 'kt': [12.0, 6.0, 6.0], 'pole_pairs': [8]}
    # Joint states 1 ms apart: a 0.5 ms tolerance keeps a neighbour's currents from matching.
    proc = start_node_process(ros, 'bad', dict(torque, hold_time=0.5, align_tolerance=5e-4, **{
        'publish.diagnostics_rate': 5.0, 'process_period': 0.01}, **reliable('bad')), tmp_path,
        remaps('bad'))
    robot = load_robot('mit_dd_arm')
    conv = TorqueConverter(robot.joint_names,
                           Settings.from_dict(torque).torque_configs(robot.joint_names))
    traj = FourierTrajectory.random(robot, harmonics=4, period=5.0, seed=2)
    N = 6000
    t = np.arange(N) / 1000.0
    sim = simulate_kinematic(robot, None, traj, t, SensorNoise(current_std=0.01), seed=2,
                             converter=conv)
    stamps = 50 * 10 ** 9 + np.round(t * 1e9).astype(np.int64)
    names = ['gripper'] + robot.joint_names      # an extra joint the model does not know
    zero = np.zeros((N, 1))
    js = joint_state_msgs(stamps, names, position=np.hstack([zero, sim.q_meas]),
                          velocity=np.hstack([zero, sim.qd_meas]))
    channels = conv.current_channel_names()
    cur = joint_state_msgs(stamps, channels, effort=np.stack(
        [sim.currents[:, i, k] for _, i, k in conv.current_channel_slots()], axis=1))

    def restamped(m, ns):
        out = JointState(name=m.name, position=m.position, velocity=m.velocity,
                         effort=m.effort)
        out.header.stamp.sec, out.header.stamp.nanosec = divmod(int(ns), 10 ** 9)
        return out

    def js_like(k, dt=0, **fields):
        return restamped(JointState(name=fields.get('name', names),
                                    position=fields.get('position', js[k].position),
                                    velocity=fields.get('velocity', js[k].velocity)),
                         stamps[k] + dt)

    bad_js = [js_like(3000, dt=1, position=[0.0, math.nan, 0.1, 0.2]),
              js_like(3000, dt=2, position=[0.0, 0.1, math.inf, 0.2]),
              js_like(3000, dt=3, name=['joint1', 'joint2', 'elbow'], position=[0.1] * 3,
                      velocity=[0.0] * 3),
              js_like(3000, dt=4, name=['joint1', 'joint2'], position=[0.1] * 2,
                      velocity=[0.0] * 2),
              js_like(3000, dt=5, position=[0.1, 0.2]),
              js_like(3000, dt=6, name=[], position=[], velocity=[]),
              js_like(3000), js_like(2990)]           # repeated and out-of-order stamps
    GARBAGE = b'\x00\x01\x00\x00' + b'\x07\x00\x00\x00' * 3   # truncated CDR
    bad_cur = [restamped(JointState(name=channels, effort=[math.nan] * len(channels)),
                         stamps[3500] + 100),
               restamped(JointState(name=['motor9/ia'], effort=[1.0]), stamps[3500] + 200)]
    # 20 joint states lose their currents, 30 currents their joint states; then the stream
    # stops and restarts 10 s earlier (as a restarted driver's clock would).
    keep_js = set(range(N)) - set(range(1200, 1230))
    keep_cur = set(range(N)) - set(range(2200, 2220))
    pub_js = ros.client.create_publisher(JointState, '/bad/joint_states', RELIABLE)
    pub_cur = ros.client.create_publisher(JointState, '/bad/motor_currents', RELIABLE)
    assert wait_for(lambda: pub_js.get_subscription_count() and pub_cur.get_subscription_count(),
                    10)

    # (publisher, samples kept, messages, sample after which the bad ones go, bad ones);
    # GARBAGE: raw bytes that are no JointState
    streams = ((pub_cur, keep_cur, cur, 3500, bad_cur),
               (pub_js, keep_js, js, 3000, bad_js + [GARBAGE]))

    def send(ks, shift=0):
        """Samples ks, currents first, in chunks of 20 every 20 ms (real time: faster, the
        node falls behind and its best-effort subscriptions drop messages)."""
        for start in range(0, len(ks), 20):
            chunk = ks[start:start + 20]
            for pub, keep, msgs, bad_at, bad in streams:
                for k in chunk:
                    if k in keep:
                        pub.publish(restamped(msgs[k], stamps[k] + shift))
                    if k == bad_at and not shift:
                        for m in bad:
                            pub.publish(m)
            time.sleep(0.02)

    send(list(range(4000)))
    time.sleep(0.3)
    send(list(range(4000, N)), shift=-10 * 10 ** 9)
    total = len(keep_js) + len(bad_js) + 1
    assert wait_for(lambda: int((last_status(diag, 'bad') or {}).get(
        'samples_received', 0)) >= total, 10), last_status(diag, 'bad')
    ros.client.destroy_publisher(pub_js)
    ros.client.destroy_publisher(pub_cur)
    values = last_status(diag, 'bad')
    key = 'qos_overrides./bad/joint_states.subscription.reliability'
    assert ros.get_parameters('/bad', [key])[key] == 'reliable'
    rejected = {r: int(values[f'rejected.{r}']) for r in REJECT_REASONS}
    expected = {'non_finite': 3, 'missing_joints': 2, 'length_mismatch': 1, 'empty': 1,
                'repeated_stamp': 1, 'out_of_order': 1, 'no_current': 20,
                'unmatched_current': 30, 'unknown_channels': 1, 'malformed': 1}
    assert {k: v for k, v in rejected.items() if k != 'stream_restart' and v} == expected
    assert values['missing_joints'] == 'joint3'   # the joint the two messages lacked
    # friction on by default: the equations left out near velocity reversals, per joint
    assert all(int(values[f'excluded_equations.{j}']) > 0 for j in robot.joint_names)
    assert int(values['stream_restarts']) == 1
    assert int(values['samples_received']) == total
    # Still running, with a finite estimate from the good samples of both streams: the
    # snapshot taken after the last of them (~/get_estimate answers from the newest one,
    # refreshed at publish.estimate_rate, and the last joint states wait hold_time for their
    # currents).
    est = wait_for(lambda: (e := get_estimate(ros, '/bad'))['num_samples'] > N - 200 and e,
                   30) or get_estimate(ros, '/bad')
    assert all(v is not None and math.isfinite(v) for v in est['values'] + est['stddev'])
    assert est['num_samples'] > N - 200
    stop_process(proc)


def test_messages_lost_before_the_node_takes_them_are_counted(ros, diag, tmp_path):
    """The node process is stopped (SIGSTOP) while 5000 of 7000 joint states go out through
    a publisher that keeps only 10: received plus lost is every message sent once the node
    took its first. A reset clears the count."""
    proc = start_node_process(ros, 'lossy', {
        'robot': 'mit_dd_arm', 'torque_source': ['measured'], 'process_period': 0.01,
        'publish.diagnostics_rate': 5.0}, tmp_path, remaps('lossy'))
    pub = ros.client.create_publisher(JointState, '/lossy/joint_states', QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE))
    assert wait_for(lambda: pub.get_subscription_count(), 10)
    N, rng = 7000, np.random.default_rng(4)
    sent = encode_joint_states(10**9 + np.arange(N) * 10**6, ['joint1', 'joint2', 'joint3'],
                               *rng.random((3, N, 3)))

    counts = partial(received_and_lost, diag, 'lossy')
    # The node's side of the match may lag ours: what it never subscribed to is not lost.
    first = 0
    while not wait_for(lambda: counts()[0], 0.5):
        assert first < 240, ('the node reported no message in 2 minutes; '
                             + ros.spinner_state(ros.client))
        pub.publish(sent[first])
        first += 1
    time.sleep(0.5)
    expected = counts()[0] + N - first
    for k in range(first, N):
        if k in (1000, 6000):
            os.kill(proc.pid, signal.SIGSTOP if k == 1000 else signal.SIGCONT)
        pub.publish(sent[k])
        if k % 10 == 0:
            time.sleep(0.005)
    assert wait_for(lambda: sum(counts()) == expected, 15), (counts(), expected)
    received, lost = counts()
    assert lost > 0 and received > 1000, (received, lost)
    assert ros.call(Trigger, '/lossy/reset', Trigger.Request()).success
    assert wait_for(lambda: counts() == (0, 0), 5), counts()
    ros.client.destroy_publisher(pub)
    assert re.search(r'messages on /lossy/joint_states lost before the node took them',
                     stop_process(proc))


def test_simulated_arm_waits_for_a_stalled_reliable_subscriber(ros, diag, tmp_path):
    """The node, a reliable subscriber, is stopped during the simulated arm's run: the arm
    stays up until the node has acknowledged (or been told it lost) every sample, then exits
    0; nothing goes missing uncounted."""
    proc = start_node_process(ros, 'stall', dict(
        robot='mit_dd_arm', torque_source=['measured'], process_period=0.01,
        **{'publish.diagnostics_rate': 5.0}, **reliable('stall')), tmp_path, remaps('stall'))
    duration = 1.5
    sim_params = {'robot': 'mit_dd_arm', 'trajectory': 'fourier', 'rate': 1000.0,
                  'duration': duration, 'wait_for_subscribers': 1}
    sim = ros.start('sim', sim_params, tmp_path, 'simulated_arm', extra=('-r', '__ns:=/stall'))

    counts = partial(received_and_lost, diag, 'stall')
    assert wait_for(lambda: counts()[0] > 0, 30), sim.stderr.read() if sim.poll() else ''
    os.kill(proc.pid, signal.SIGSTOP)
    time.sleep(duration + 1.0)
    alive = sim.poll() is None
    os.kill(proc.pid, signal.SIGCONT)
    assert alive, 'the simulated arm left while its reliable subscriber had not acknowledged'
    assert sim.wait(30) == 0
    N = SimSetup.from_parameters(sim_params).num_samples
    assert wait_for(lambda: sum(counts()) == N, 15), counts()
    assert 'did not acknowledge' not in sim.stderr.read()
    stop_process(proc)


def test_qos_overrides_apply_to_their_own_subscription_only(ros):
    """An override of one input's reliability changes neither the other input nor the
    default profile that later nodes of the process start from."""
    node = start_node(ros, 'qos_one', {
        'robot': 'mit_dd_arm', 'torque_source': ['three_phase'], 'kt': [1.0],
        'qos_overrides./qos_one/joint_states.subscription.reliability': 'reliable'}, 'qos_one')
    js, cur = (source.subscription.qos_profile.reliability for source in node.inputs)
    assert (js, cur) == (ReliabilityPolicy.RELIABLE, ReliabilityPolicy.BEST_EFFORT)
    assert INPUT_QOS.reliability == ReliabilityPolicy.BEST_EFFORT
    ros.remove(node)
    node.destroy_node()


def test_crs_a465_converges_to_the_truth(ros, diag, tmp_path):
    stream = Stream(ros, diag, CRS, tmp_path, 'crs')
    stream.start(tmp_path, subscriptions=3)
    try:
        report = check_convergence(stream)
        print('\nCRS', report, re.findall(r'took .*', stream.sim_log))
    finally:
        stream.stop()


# -- start-up -------------------------------------------------------------------------------------
@pytest.mark.parametrize('params, name', [
    ({'forgetting_factor': 2.0}, 'forgetting_factor'),
    ({'smoother.half_window': -1}, 'smoother.half_window'),
    ({'torque_source': ['warp']}, 'torque_source'),
    ({'kt': [1.0, 2.0]}, 'kt'),
    ({'process_period': -1.0}, 'process_period'),
    ({'output_directory': ' '}, 'output_directory'),
    ({'hold_time': 1}, 'hold_time'),                 # an integer for a double
])
def test_invalid_parameters_exit_2_naming_them(ros, tmp_path, params, name):
    proc = ros.start('node', params, tmp_path, 'identification_node')
    err = exit_log(proc, 120, 'a bad parameter')   # start-up stretches on a busy machine
    assert proc.returncode == 2, err
    assert f'parameter {name}' in err, err


def test_parameters_are_typed_and_ranged_by_the_settings_table(ros):
    """Each parameter's descriptor has the type of its default in config.PARAMETERS and the
    range of config.RANGES; the values given are the node's (its settings agree)."""
    from rcl_interfaces.msg import ParameterType
    from identification_node.config import EMPTY_LISTS, PARAMETERS, RANGES
    from identification_node.ros.parameters import RUNTIME
    node = start_node(ros, 'typed', {'robot': 'mit_dd_arm', 'forgetting_factor': 0.95,
                                     'joints': ['joint2', 'joint1'], 'extras': []}, 'typed')
    try:
        names = list(PARAMETERS)
        for name, d in zip(names, node.describe_parameters(names)):
            default = PARAMETERS[name][0]
            # an empty list cannot be typed in rclpy (see parameter_descriptor)
            # read-only but for the settings safe to change at run time
            assert d.read_only == (name not in RUNTIME), name
            assert d.dynamic_typing == (default == [] or name in EMPTY_LISTS)
            if isinstance(default, list):
                continue
            assert d.type == {bool: ParameterType.PARAMETER_BOOL,
                              int: ParameterType.PARAMETER_INTEGER,
                              float: ParameterType.PARAMETER_DOUBLE,
                              str: ParameterType.PARAMETER_STRING}[type(default)], name
            ranges = list(d.integer_range) + list(d.floating_point_range)
            assert [(r.from_value, r.to_value) for r in ranges] == (
                [RANGES[name]] if name in RANGES else []), name
        assert node.describe_parameter('kt').type == ParameterType.PARAMETER_DOUBLE_ARRAY
        assert node.settings['forgetting_factor'] == 0.95
        assert node.settings['joints'] == ['joint2', 'joint1']
        assert node.robot.joint_names == ['joint2', 'joint1']
        assert node.settings['extras'] == [] and node.robot.extras == ()   # given empty
    finally:
        ros.remove(node)


def test_unknown_parameters_are_named_in_a_warning(ros, tmp_path):
    """A misspelt parameter is not dropped silently: the node starts and names it."""
    proc = start_node_process(ros, 'typo', {'robot': 'mit_dd_arm', 'forgeting_factor': 0.9,
                                            'forgetting_factor': 0.999}, tmp_path)
    err = stop_process(proc)
    assert re.search(r'ignoring parameters this node does not have: forgeting_factor\s', err), err


# -- physical consistency ------------------------------------------------------------------------
def test_solver_time_out_publishes_the_projected_estimate(ros, diag):
    """Conic solves that cannot finish in consistency.time_limit are reported (service,
    diagnostics) and the unconstrained estimate projected onto physical bodies goes out
    instead, finite."""
    node = start_node(ros, 'timeout', {
        'robot': 'mit_dd_arm', 'torque_source': ['measured'], 'consistency.time_limit': 1e-5,
        'process_period': 0.01, 'publish.diagnostics_rate': 5.0}, 'timeout')
    robot = node.robot
    t = np.arange(0.0, 4.0, 1e-3)
    q, qd, qdd = FourierTrajectory.random(robot, period=4.0, seed=3).sample(t)
    tau = robot.inverse_dynamics(q, qd, qdd) + 0.01 * np.random.default_rng(4).standard_normal(
        q.shape)
    with node.lock:     # straight into the pipeline, as its processing thread would
        node.pipeline.add_joint_states(JointStateRecord(
            (1_000_000_000 + 1_000_000 * np.arange(len(t))).astype(np.int64),
            tuple(robot.joint_names), q, qd, tau))
        node.pipeline.process(flush=True)
    params = Collector(ros, Float64MultiArray, '/timeout/base_parameters')
    # answered from the newest snapshot: the one after the samples comes with the next refresh
    # ('starting': published unconstrained while the solver process builds its problem)
    est = wait_for(lambda: (e := get_estimate(ros, '/timeout'))['num_samples']
                   and e['consistency_status'] != 'starting' and e, 120)
    assert est['consistency_status'] == 'projected'
    assert est['num_samples'] > 3000
    assert np.all(np.isfinite(est['values'])) and np.all(np.isfinite(est['stddev']))
    assert wait_for(lambda: len(params), 5)
    params.close()
    assert wait_for(lambda: (last_status(diag, 'timeout') or {}).get('consistency_status')
                    == 'projected', 5)
    ros.remove(node)
