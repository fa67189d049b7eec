"""Back-EMF drive gains in the node over DDS: the simulated arm (another process) publishes
joint states, motor currents and motor voltages of drives whose true kt is 10-20 % off the
configured one; the node (another process) identifies the gains. Truth: the sim's kt_error."""
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.srv import GetParameters

from arms import arm_urdf
from ros_helpers import Collector, RosHarness, diagnostic_values, domain_id, wait_for

KT_ERROR = [0.15, -0.12, 0.18, -0.10, 0.20, 0.11]
NS = '/dg'


@pytest.fixture(scope='module')
def ros():
    harness = RosHarness(domain_id(__name__))
    yield harness
    harness.shutdown()


@pytest.mark.ros
@pytest.mark.slow
def test_node_identifies_the_drive_gains_from_live_voltages(ros, tmp_path):
    torque = {'robot': str(arm_urdf('ur5')), 'torque_source': ['current'], 'kt': [0.12],
              'gear_ratio': [100.0]}
    name = 'drive_node'
    reliable = {f'qos_overrides.{NS}/{t}.subscription.reliability': 'reliable'
                for t in ('joint_states', 'motor_currents', 'motor_voltages')}
    diag = Collector(ros, DiagnosticArray, '/diagnostics')
    node = ros.start('node', dict(torque, **{'drive_gains.back_emf': True,
                                             'publish.diagnostics_rate': 5.0}, **reliable),
                     tmp_path, name, extra=('-r', f'__node:={name}', '-r', f'__ns:={NS}'))
    joints = ['shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint', 'wrist_1_joint',
              'wrist_2_joint', 'wrist_3_joint']
    try:
        client = ros.client.create_client(GetParameters, f'{NS}/{name}/get_parameters')
        assert client.wait_for_service(timeout_sec=60), node.stderr.read() if node.poll() else ''
        ros.client.destroy_client(client)
        sim = ros.start('sim', dict(torque, **{
            'trajectory': 'fourier', 'duration': 6.0, 'publish_currents': True,
            'publish_voltages': True, 'drive.kt_error': KT_ERROR, 'noise.current_std': 0.01,
            'noise.voltage_std': 0.05, 'noise.velocity_std': 0.002, 'wait_for_subscribers': 1}),
            tmp_path, 'simulated_arm', extra=('-r', f'__ns:={NS}'))
        assert sim.wait(90) == 0, sim.stderr.read()
        truth = {j: 12.0 * (1 + e) for j, e in zip(joints, KT_ERROR)}
        names = [f'drive_gain.{j}' for j in joints]

        def close():
            got = ros.get_parameters(f'{NS}/{name}', names)
            return got if all(abs(got[f'drive_gain.{j}'] / truth[j] - 1) < 0.01
                              for j in joints) else None
        assert wait_for(close, 20), (ros.get_parameters(f'{NS}/{name}', names),
                                     node.stderr.read()[-2000:] if node.poll() else '')
        values = wait_for(lambda: [diagnostic_values(s) for m in diag.snapshot()
                                   for s in m.status if s.name.endswith('identification')
                                   and 'drive_gain.elbow_joint.ratio' in diagnostic_values(s)],
                          10)[-1]
        assert abs(float(values['drive_gain.elbow_joint.ratio']) - 1.18) < 0.01
        assert 'differs from the configured' in values['drive_gain.elbow_joint.warning']
        assert int(values['drive_gains.samples']) > 3000
    finally:
        diag.close()
        node.terminate()
        node.wait(10)
