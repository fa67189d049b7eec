"""Payload identification in the node over DDS: the simulated arm (another process) picks up
a payload while the node (another process) runs; ~/payload, ~/payload_changed, diagnostics
and the payload services. Truth: the payload the simulated arm was given."""
import json
import math
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import InertiaStamped
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from std_msgs.msg import Header, String
from std_srvs.srv import Trigger

from ros_helpers import LATCHED, Collector, RosHarness, diagnostic_values, domain_id, wait_for

URDF = 'test/fixtures/panda_like.urdf'
PICK = 3.0                       # s (sample time) the arm picks the payload up
MASS, COM = 1.0, [0.0, 0.02, 0.06]


@pytest.fixture(scope='module')
def ros():
    harness = RosHarness(domain_id(__name__))
    yield harness
    harness.shutdown()


def reliable(prefix):
    return {f'qos_overrides./{prefix}/joint_states.subscription.reliability': 'reliable'}


def node_params(**extra):
    # the shipped defaults: the automatic smoother (the payload monitor filters on its own)
    return dict({'robot': URDF, 'torque_source': ['measured'], 'payload.enabled': True,
                 'publish.diagnostics_rate': 5.0, **reliable('pl')}, **extra)


# joint friction of the simulated arm: viscous (N m s/rad), Coulomb (N m), offset (N m)
FRICTION = {'fv': (0.5, 0.6, 0.4, 0.3, 0.1, 0.1, 0.05), 'fc': (0.6, 0.8, 0.5, 0.4, 0.2, 0.15, 0.1),
            'fo': (0.1, -0.2, 0.05, 0.1, -0.05, 0.02, 0.0)}
SEQUENCE = [(3.0, 1.0, [0.03, -0.02, 0.06]), (7.0, 0.0, [0.0, 0.0, 0.0]),
            (11.0, 0.6, [-0.05, 0.04, 0.03])]   # s, kg, m: pick, place, pick another


def log(node) -> str:
    """The node's log, once it is stopped (reading a running node's stderr would block)."""
    node.terminate()
    node.wait(10)
    return node.stderr.read()[-3000:]


def test_pick_place_pick_with_friction_and_defaults(ros, tmp_path):
    """The simulated arm with joint friction picks 1 kg, places it and picks 0.6 kg while the
    node runs with the shipped defaults, the arm (with its friction) given as payload.arm:
    ~/payload_changed marks each change near its time, and ~/payload follows each with its
    first fit (payload.fit_time after the detection) of the mass within 2 % (no payload:
    within payload.tolerance.mass) and its refined centre of mass within 5 mm."""
    import yaml
    from identification_node.model.robot import load_robot
    robot = load_robot(URDF, extras=['fv', 'fc', 'fo'])
    truth = {f'{j}.{kind}': float(v) for kind, values in FRICTION.items()
             for j, v in zip(robot.joint_names, values)}
    (tmp_path / 'truth.yaml').write_text(yaml.safe_dump(truth))
    phi = robot.phi_model.copy()
    for key, value in truth.items():
        phi[robot.param_index(key)] = value
    (tmp_path / 'arm.yaml').write_text(yaml.safe_dump({'standard_parameters': dict(zip(
        robot.param_names, map(float, phi)))}))
    name = 'payload_seq'
    params = node_params(**{'payload.arm': str(tmp_path / 'arm.yaml'),
                            **{k.replace('/pl/', '/ps/'): v for k, v in reliable('ps').items()}})
    payload = Collector(ros, InertiaStamped, f'/{name}/payload', LATCHED)
    changed = Collector(ros, Header, f'/{name}/payload_changed', LATCHED)
    node = ros.start('node', params, tmp_path, name,
                     extra=('-r', f'__node:={name}', '-r', 'joint_states:=/ps/joint_states'))
    client = ros.client.create_client(Trigger, f'/{name}/payload/reset')
    assert client.wait_for_service(timeout_sec=30), node.stderr.read() if node.poll() else ''
    ros.client.destroy_client(client)
    events = json.dumps([{'time': t, 'mass': m, 'com': c} for t, m, c in SEQUENCE])
    sim = ros.start('sim', {'robot': URDF, 'trajectory': 'fourier', 'rate': 1000.0,
                            'duration': 15.0, 'noise.torque_std': 0.1,
                            'noise.encoder_counts': 2 ** 18, 'noise.velocity_std': 0.01,
                            'true_parameters_file': str(tmp_path / 'truth.yaml'),
                            'payload_events': events, 'wait_for_subscribers': 1},
                    tmp_path, 'simulated_arm', extra=('-r', '__ns:=/ps'))
    try:
        assert sim.wait(120) == 0, sim.stderr.read()

        def stamp(h):
            return h.stamp.sec + h.stamp.nanosec * 1e-9
        assert wait_for(lambda: len(changed) == len(SEQUENCE) and stamp(
            payload.snapshot()[-1].header) > SEQUENCE[-1][0] - 0.2, 20), (
                [stamp(h) for h in changed.snapshot()], log(node))
        onsets = [stamp(h) for h in changed.snapshot()]
        for onset, (t, mass, com) in zip(onsets, SEQUENCE):
            assert t - 0.1 <= onset <= t + 0.5, (onsets, log(node))
            fits = [m for m in payload.snapshot() if abs(stamp(m.header) - onset) < 1e-6]
            assert fits, (onset, [stamp(m.header) for m in payload.snapshot()])
            m = fits[0].inertia    # the first fit (payload.fit_time after the detection)
            assert abs(m.m - mass) <= max(0.02 * mass, 0.02), (m.m, mass)
            m = fits[-1].inertia   # refined over the segment
            if mass:
                assert np.abs(np.subtract([m.com.x, m.com.y, m.com.z], com)).max() <= 0.005
    finally:
        for c in (payload, changed):
            c.close()
        node.terminate()
        node.wait(10)


def test_pick_up_payload_while_the_node_runs(ros, tmp_path):
    name = 'payload_node'
    payload = Collector(ros, InertiaStamped, f'/{name}/payload', LATCHED)
    changed = Collector(ros, Header, f'/{name}/payload_changed', LATCHED)
    diag = Collector(ros, DiagnosticArray, '/diagnostics')
    urdf = Collector(ros, String, f'/{name}/robot_description', LATCHED)
    node = ros.start('node', node_params(), tmp_path, name,
                     extra=('-r', f'__node:={name}', '-r', 'joint_states:=/pl/joint_states'))
    client = ros.client.create_client(Trigger, f'/{name}/payload/reset')
    assert client.wait_for_service(timeout_sec=30), node.stderr.read() if node.poll() else ''
    ros.client.destroy_client(client)
    events = json.dumps([{'time': PICK, 'mass': MASS, 'com': COM}])
    sim = ros.start('sim', {'robot': URDF, 'trajectory': 'fourier', 'rate': 1000.0,
                            'duration': 7.0, 'noise.torque_std': 0.05,
                            'noise.encoder_counts': 2 ** 20, 'publish_velocity': False,
                            'payload_events': events, 'wait_for_subscribers': 1},
                    tmp_path, 'simulated_arm', extra=('-r', '__ns:=/pl'))
    try:
        assert sim.wait(60) == 0, sim.stderr.read()
        after = lambda: [m for m in payload.snapshot()  # noqa: E731
                         if m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 > PICK - 0.2]
        assert wait_for(after, 10), (payload.snapshot(), node.stderr.read()[-2000:])
        msg = after()[-1]
        assert msg.header.frame_id == 'link7'
        assert abs(msg.inertia.m - MASS) <= 0.02 * MASS
        com = [msg.inertia.com.x, msg.inertia.com.y, msg.inertia.com.z]
        assert np.abs(np.subtract(com, COM)).max() <= 0.005
        first = payload.snapshot()[0]     # the start: no payload
        assert abs(first.inertia.m) < 0.05
        stamps = [h.stamp.sec + h.stamp.nanosec * 1e-9 for h in changed.snapshot()]
        assert len(stamps) == 1 and abs(stamps[0] - PICK) < 0.1, stamps
        status = wait_for(lambda: [diagnostic_values(s) for m in diag.snapshot()
                                   for s in m.status if s.name.endswith('identification')
                                   and 'payload.last_change_detected' in diagnostic_values(s)],
                          10)
        values = status[-1]
        detected = float(values['payload.last_change_detected'])
        assert PICK <= detected <= PICK + 0.5       # the event's delay in sample time
        assert values['payload.changes'] == '1'
        assert wait_for(lambda: any('name="payload"' in m.data for m in urdf.snapshot()), 10)
        # the services: a known payload is published at once; reset forgets it
        res = ros.call(SetParameters, f'/{name}/payload/set', SetParameters.Request(
            parameters=[Parameter('mass', value=0.7).to_parameter_msg(),
                        Parameter('com', value=[0.0, 0.0, 0.1]).to_parameter_msg()]))
        assert res.results[0].successful
        assert wait_for(lambda: math.isclose(payload.snapshot()[-1].inertia.m, 0.7), 5)
        bad = ros.call(SetParameters, f'/{name}/payload/set', SetParameters.Request(
            parameters=[Parameter('mass', value=-1.0).to_parameter_msg()]))
        assert not bad.results[0].successful and 'mass' in bad.results[0].reason
        assert ros.call(Trigger, f'/{name}/payload/reset', Trigger.Request()).success
    finally:
        for c in (payload, changed, diag, urdf):
            c.close()
        node.terminate()
        node.wait(10)


def test_unknown_payload_link_refused_at_start_up(ros, tmp_path):
    proc = ros.start('node', node_params(**{'payload.link': 'gripper'}), tmp_path,
                     'identification_node')
    assert proc.wait(30) == 2
    err = proc.stderr.read()
    assert 'payload.link' in err and 'gripper' in err and 'Traceback' not in err


def test_drop_in_the_stream_is_not_a_change(ros, tmp_path):
    """The simulated arm's stream stops for 1 s (the arm process is paused) and resumes with
    the same payload: no change event."""
    import os
    import signal
    name = 'payload_drop'
    changed = Collector(ros, Header, f'/{name}/payload_changed', LATCHED)
    payload = Collector(ros, InertiaStamped, f'/{name}/payload', LATCHED)
    params = node_params(**{k.replace('/pl/', '/pd/'): v for k, v in reliable('pd').items()})
    node = ros.start('node', params, tmp_path, name,
                     extra=('-r', f'__node:={name}', '-r', 'joint_states:=/pd/joint_states'))
    client = ros.client.create_client(Trigger, f'/{name}/payload/reset')
    assert client.wait_for_service(timeout_sec=30)
    ros.client.destroy_client(client)
    sim = ros.start('sim', {'robot': URDF, 'trajectory': 'fourier', 'rate': 1000.0,
                            'duration': 5.0, 'noise.torque_std': 0.05,
                            'payload_events': json.dumps([{'time': 0.0, 'mass': 0.8}]),
                            'wait_for_subscribers': 1},
                    tmp_path, 'simulated_arm', extra=('-r', '__ns:=/pd'))
    try:
        assert wait_for(lambda: len(payload), 30), node.stderr.read() if node.poll() else ''
        os.kill(sim.pid, signal.SIGSTOP)
        time.sleep(1.0)
        os.kill(sim.pid, signal.SIGCONT)
        assert sim.wait(60) == 0
        time.sleep(1.0)
        assert len(changed) == 0, changed.snapshot()
        assert abs(payload.snapshot()[-1].inertia.m - 0.8) < 0.03
    finally:
        changed.close()
        payload.close()
        node.terminate()
        node.wait(10)


def test_arm_from_the_running_estimate_taken_at_reset(ros):
    """payload.arm: estimate: each ~/payload/reset takes the node's running estimate of the
    arm (the full parameter set reproducing it) as the model the payload is fitted against."""
    from rclpy.parameter import Parameter as P

    from identification_node.payload.fit import PayloadChange, true_parameter_changes
    from identification_node.wire.records import JointStateRecord
    from identification_node.ros.node import IdentificationNode
    from identification_node.model.simulation import simulate_kinematic
    from identification_node.excitation.trajectories import load_trajectory
    node = ros.add(IdentificationNode('payload_arm', context=ros.context, parameter_overrides=[
        P('robot', value=URDF), P('payload.enabled', value=True),
        P('payload.arm', value='estimate')]))
    try:
        robot = node.robot
        truth = true_parameter_changes(robot, robot.phi_model, [PayloadChange(0, None, 2.0)])
        sim = simulate_kinematic(robot, truth[0][1], load_trajectory('fourier', robot),
                                 np.arange(2000) / 1000.0)
        with node._lock:   # an arm estimate that differs from the model's own
            node.pipeline.add_joint_states(JointStateRecord(
                np.round(sim.t * 1e9).astype(np.int64), tuple(robot.joint_names), sim.q,
                sim.qd, sim.tau))
            node.pipeline.process(flush=True)
            expected = node.pipeline.standard_parameters()
        assert not np.allclose(node.payload.monitor.phi_arm, expected)
        assert ros.call(Trigger, '/payload_arm/payload/reset', Trigger.Request()).success
        np.testing.assert_allclose(node.payload.monitor.phi_arm, expected)
    finally:
        ros.remove(node)
        node.destroy_node()
