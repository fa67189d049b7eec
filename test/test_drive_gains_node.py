"""Back-EMF drive gains in the node over DDS: the simulated arm (another process) publishes
joint states, motor currents and motor voltages of drives whose true kt is 10-20 % off the
configured one; the node (another process) identifies the gains. Truth: the sim's kt_error."""
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.srv import GetParameters

from arms import arm_urdf
from ros_helpers import Collector, diagnostic_values, wait_for

KT_ERROR = [0.15, -0.12, 0.18, -0.10, 0.20, 0.11]
NS = '/dg'


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
        key = 'drive_gain.elbow_joint.back_emf'
        values = wait_for(lambda: [diagnostic_values(s) for m in diag.snapshot()
                                   for s in m.status if s.name.endswith('identification')
                                   and key + '.ratio' in diagnostic_values(s)], 10)[-1]
        assert abs(float(values[key + '.ratio']) - 1.18) < 0.01
        assert 'differs from the configured' in values[key + '.warning']
        assert int(values['drive_gains.back_emf_samples']) > 3000
    finally:
        diag.close()
        node.terminate()
        node.wait(10)


def _arm_runs():
    """A UR5 driven by currents whose true kt is KT_ERROR off the configured 0.12 N m/A: one
    motion without and one (another) with PAYLOAD; the pipeline's torque configuration."""
    import numpy as np

    from identification_node.excitation.trajectories import FourierTrajectory
    from identification_node.model.drive import DriveModel
    from identification_node.model.robot import load_robot
    from identification_node.simulation.simulator import ArmSimulator, SensorNoise
    from identification_node.model.torque import JointTorqueConfig, TorqueConverter
    from identification_node.payload.fit import PayloadChange, true_parameter_changes
    robot = load_robot(str(arm_urdf('ur5')))
    cfg = JointTorqueConfig('current', 0.12, 100.0)
    conf = TorqueConverter(robot.joint_names, [cfg] * robot.dof)
    true = DriveModel.per_joint(robot.dof, kt_error=KT_ERROR).true_converter(conf)
    loaded = true_parameter_changes(robot, robot.phi_model, [PayloadChange(0.0, None, *PAYLOAD)])
    noise = SensorNoise(velocity_std=0.002, current_std=0.01, encoder_counts=2 ** 20)
    runs = [ArmSimulator(robot, phi).run(FourierTrajectory.random(robot, seed=seed), 20.0,
                                         noise, seed, true)
            for seed, phi in ((0, robot.phi_model), (1, loaded[0][1]))]
    return robot, cfg, runs, np


PAYLOAD = (3.0, (0.04, 0.03, 0.06), (0.01, 0, 0, 0.012, 0, 0.008))


def _records(robot, sim, offset, np):
    from identification_node.wire.records import JointStateRecord
    ns = np.round((sim.t + offset) * 1e9).astype(np.int64)
    empty = np.zeros((len(ns), 0))
    return (JointStateRecord(ns, tuple(robot.joint_names), sim.q_meas, sim.qd_meas, empty),
            JointStateRecord(ns, tuple(f'{j}/i' for j in robot.joint_names), empty, empty,
                             sim.currents[:, :, 0]))


@pytest.mark.slow
def test_known_payload_segments_of_the_pipeline_output_recover_the_gains():
    """The node's known-payload core on the streaming pipeline's output: every gain within 1 %
    and 3 stddev."""
    from identification_node.pipeline import IdentificationPipeline, PipelineConfig
    from identification_node.payload.known_payload import KnownPayloadSegments
    from identification_node.payload.fit import payload_parameters
    robot, cfg, runs, np = _arm_runs()
    pipe = IdentificationPipeline(robot, PipelineConfig(torque={j: cfg
                                                                for j in robot.joint_names}))
    seg = KnownPayloadSegments(robot, pipe.base, pipe.converter)
    for k, sim in enumerate(runs):
        if k == 1:
            seg.start(payload_parameters(PAYLOAD[0], np.array(PAYLOAD[1]),
                                         np.array(PAYLOAD[2])))
        js, cur = _records(robot, sim, 30.0 * k, np)
        pipe.add_joint_states(js)
        pipe.add_currents(cur)
        out = pipe.process(flush=True)
        seg.add(out.q, out.qd, out.qdd, out.measured, pipe.row_builder.half_window or 1)
    for g in seg.gains():
        truth = 12.0 * (1 + KT_ERROR[robot.joint_names.index(g.joint)])
        assert g.value is not None, g.reason
        assert abs(g.value / truth - 1) < 0.01 and abs(g.value - truth) < 3 * g.stddev, (
            g, truth)


def taken(node) -> bool:
    """Whether the node's processing thread has taken every sample put into its pipeline
    (the smoother's choice made, nothing queued nor waiting for its currents)."""
    with node.lock:
        p = node.pipeline
        return not (p.pending or p.choosing or len(p.samples.alignment.pending))


@pytest.mark.ros
@pytest.mark.slow
def test_known_payload_service_marks_the_segment_in_the_node(ros):
    """~/drive_gains/known_payload starts (mass > 0) and ends (mass 0) the segment; the node's
    drive_gain.<joint> parameters then carry the known-payload gains; bad requests are
    refused with the reason."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter as P

    from identification_node.ros.node import IdentificationNode
    robot, cfg, runs, np = _arm_runs()
    name = 'known_payload_node'
    node = ros.add(IdentificationNode(name, context=ros.context, parameter_overrides=[
        P('robot', value=str(arm_urdf('ur5'))), P('torque_source', value=['current']),
        P('kt', value=[0.12]), P('gear_ratio', value=[100.0]),
        P('drive_gains.known_payload', value=True)]))
    service = f'/{name}/drive_gains/known_payload'

    def call(**params):
        return ros.call(SetParameters, service, SetParameters.Request(parameters=[
            P(k, value=v).to_parameter_msg() for k, v in params.items()])).results[0]
    try:
        bad = call(mass=1.0, colour=[1.0])
        assert not bad.successful and 'give mass' in bad.reason
        assert not call(mass=1.0, link='nowhere').successful
        segments = node.drive_gains.segments
        for k, sim in enumerate(runs[::-1]):     # the loaded motion first
            res = call(mass=PAYLOAD[0], com=[float(v) for v in PAYLOAD[1]],
                       inertia=[float(v) for v in PAYLOAD[2]]) \
                if k == 0 else call(mass=0.0)
            assert res.successful, res.reason
            before = dict(segments.samples)
            js, cur = _records(robot, sim, 30.0 * k, np)
            with node.lock:
                node.pipeline.add_joint_states(js)
                node.pipeline.add_currents(cur)
            kind = 'loaded' if k == 0 else 'free'
            # The segment ends once the node has taken the whole motion (every half smoother
            # window of it: ~180 samples of 20 s with the automatic smoother).
            assert wait_for(lambda: taken(node), 120), segments.samples
            assert segments.samples[kind] - before[kind] > 150, (before, segments.samples)
        names = [f'drive_gain.{j}' for j in robot.joint_names]

        def close():
            got = ros.get_parameters(f'/{name}', names)
            return got if all(abs(got[f'drive_gain.{j}'] / (12.0 * (1 + e)) - 1) < 0.01
                              for j, e in zip(robot.joint_names, KT_ERROR)) else None
        assert wait_for(close, 30), ros.get_parameters(f'/{name}', names)
    finally:
        ros.remove(node)
