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

from ros_helpers import LATCHED, Collector, diagnostic_values, wait_for

pytestmark = pytest.mark.ros

URDF = 'test/fixtures/panda_like.urdf'
PICK = 3.0                       # s (sample time) the arm picks the payload up
MASS, COM = 1.0, [0.0, 0.02, 0.06]


def reliable(prefix):
    return {f'qos_overrides./{prefix}/joint_states.subscription.reliability': 'reliable'}


def node_params(**extra):
    # the smoother pinned: the timing of the detections assumes its 10 ms delay
    return dict({'robot': URDF, 'torque_source': ['measured'], 'payload.enabled': True,
                 'publish.diagnostics_rate': 5.0, 'smoother.half_window': 10,
                 **reliable('pl')}, **extra)


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
    arm (the full parameter set reproducing it) as the model the payload is fitted against,
    with its covariance as the prior of the arm's correction (none before)."""
    from rclpy.parameter import Parameter as P

    from identification_node.payload.fit import PayloadChange, true_parameter_changes
    from identification_node.wire.records import JointStateRecord
    from identification_node.ros.node import IdentificationNode
    from identification_node.simulation.simulator import simulate_kinematic
    from identification_node.excitation.trajectories import load_trajectory
    node = ros.add(IdentificationNode('payload_arm', context=ros.context, parameter_overrides=[
        P('robot', value=URDF), P('payload.enabled', value=True),
        P('payload.arm', value='estimate')]))
    try:
        robot = node.robot
        truth = true_parameter_changes(robot, robot.phi_model, [PayloadChange(0, None, 2.0)])
        sim = simulate_kinematic(robot, truth[0][1], load_trajectory('fourier', robot),
                                 np.arange(2000) / 1000.0)
        with node.lock:   # an arm estimate that differs from the model's own
            node.pipeline.add_joint_states(JointStateRecord(
                np.round(sim.t * 1e9).astype(np.int64), tuple(robot.joint_names), sim.q,
                sim.qd, sim.tau))
            node.pipeline.process(flush=True)
            expected = node.pipeline.standard_parameters()
            covariance = node.pipeline.covariance
        monitor = node.payload.monitor
        assert not np.allclose(monitor.phi_arm, expected) and monitor.prior is None
        assert ros.call(Trigger, '/payload_arm/payload/reset', Trigger.Request()).success
        np.testing.assert_allclose(monitor.phi_arm, expected)
        known = np.isfinite(np.diag(covariance))
        assert known.any() and monitor.prior is not None
        np.testing.assert_allclose(
            monitor.prior.information[np.ix_(known, known)] @ covariance[np.ix_(known, known)],
            np.eye(int(known.sum())), atol=1e-6)
    finally:
        ros.remove(node)
        node.destroy_node()
