"""parameter_forwarder over DDS: a stand-in admittance_controller declaring exactly the
parameters of ros2_controllers' admittance_controller_parameters.yaml (names, types,
read-only flags, the fixed size of CoG.pos) gets the payload's CoG position and weight; small
changes (below the threshold in stddev), physically inconsistent values, unexcited ones and
payloads in another frame never reach it. A joint's friction goes to any node's parameter."""
import math

import numpy as np
import pytest
from geometry_msgs.msg import InertiaStamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from identification_node.errors import IdentificationError
from identification_node.parameter_mapping import (GRAVITY, ChangeGate, check_estimate_quantity,
                                                   estimate_quantity, parse_mapping,
                                                   payload_quantity)
from ros_helpers import LATCHED, wait_for

# ros2_controllers admittance_controller/src/admittance_controller_parameters.yaml:
# name -> (type, read_only, default (None: none))
ADMITTANCE_PARAMETERS = {
    'joints': (Parameter.Type.STRING_ARRAY, True, None),
    'command_joints': (Parameter.Type.STRING_ARRAY, True, []),
    'command_interfaces': (Parameter.Type.STRING_ARRAY, True, None),
    'state_interfaces': (Parameter.Type.STRING_ARRAY, True, None),
    'chainable_command_interfaces': (Parameter.Type.STRING_ARRAY, True, None),
    'kinematics.plugin_name': (Parameter.Type.STRING, False, None),
    'kinematics.plugin_package': (Parameter.Type.STRING, False, None),
    'kinematics.base': (Parameter.Type.STRING, False, None),
    'kinematics.tip': (Parameter.Type.STRING, False, None),
    'kinematics.alpha': (Parameter.Type.DOUBLE, False, 0.01),
    'ft_sensor.name': (Parameter.Type.STRING, False, None),
    'ft_sensor.frame.id': (Parameter.Type.STRING, False, None),
    'ft_sensor.filter_coefficient': (Parameter.Type.DOUBLE, False, 0.05),
    'control.frame.id': (Parameter.Type.STRING, False, None),
    'fixed_world_frame.frame.id': (Parameter.Type.STRING, False, None),
    'gravity_compensation.frame.id': (Parameter.Type.STRING, False, None),
    'gravity_compensation.CoG.pos': (Parameter.Type.DOUBLE_ARRAY, False, None),
    'gravity_compensation.CoG.force': (Parameter.Type.DOUBLE, False, 0.0),
    'admittance.selected_axes': (Parameter.Type.BOOL_ARRAY, False, None),
    'admittance.mass': (Parameter.Type.DOUBLE_ARRAY, False, None),
    'admittance.damping_ratio': (Parameter.Type.DOUBLE_ARRAY, False, None),
    'admittance.stiffness': (Parameter.Type.DOUBLE_ARRAY, False, None),
    'admittance.joint_damping': (Parameter.Type.DOUBLE, False, 5.0),
    'robot_description': (Parameter.Type.STRING, True, None),
    'enable_parameter_update_without_reactivation': (Parameter.Type.BOOL, False, True),
}
# values a configuration gives those without a default
CONFIGURED = {
    'joints': [f'joint{i}' for i in range(1, 7)], 'command_interfaces': ['position'],
    'state_interfaces': ['position', 'velocity'],
    'chainable_command_interfaces': ['position', 'velocity'],
    'kinematics.plugin_name': 'kinematics_interface_kdl/KinematicsInterfaceKDL',
    'kinematics.plugin_package': 'kinematics_interface', 'kinematics.base': 'base_link',
    'kinematics.tip': 'tool0', 'ft_sensor.name': 'ft_sensor', 'ft_sensor.frame.id': 'tool0',
    'control.frame.id': 'tool0', 'fixed_world_frame.frame.id': 'base_link',
    'gravity_compensation.frame.id': 'tool0', 'gravity_compensation.CoG.pos': [0.0, 0.0, 0.0],
    'admittance.selected_axes': [True] * 6, 'admittance.mass': [3.0] * 6,
    'admittance.damping_ratio': [2.8] * 6, 'admittance.stiffness': [50.0] * 6,
    'robot_description': '<robot name="arm"/>',
}


class StandInAdmittance(Node):
    """The admittance_controller's parameter interface, recording every accepted set."""

    def __init__(self, context):
        super().__init__('admittance_controller', context=context)
        for name, (kind, read_only, default) in ADMITTANCE_PARAMETERS.items():
            self.declare_parameter(name, CONFIGURED.get(name, default), ParameterDescriptor(
                type=kind.value, read_only=read_only))
        self.history: list[dict] = []
        self.add_on_set_parameters_callback(self._validate)

    def _validate(self, params):
        for p in params:
            if p.name == 'gravity_compensation.CoG.pos' and len(p.value) != 3:
                return SetParametersResult(successful=False, reason='fixed_size<>: 3')
        self.history.append({p.name: p.value for p in params})
        return SetParametersResult(successful=True)

    def value(self, name):
        v = self.get_parameter(name).value
        return list(v) if isinstance(v, (list, tuple)) or hasattr(v, 'tolist') else v


class FakeSource(Node):
    """The identification node's interface the forwarder reads: ~/payload and
    ~/payload/stddev (a pair per fit), estimate.* / estimate_stddev.* parameters."""

    def __init__(self, context, base_names):
        super().__init__('identification_node', context=context)
        self.declare_parameter('base_parameter_names', base_names)
        for name in base_names:
            self.declare_parameter('estimate.' + name, 0.0)
            self.declare_parameter('estimate_stddev.' + name, -1.0)
        self.pub = self.create_publisher(InertiaStamped, '~/payload', LATCHED)
        self.pub_sd = self.create_publisher(InertiaStamped, '~/payload/stddev', LATCHED)
        self.sec = 0

    def payload(self, m, com, m_sd, com_sd, frame='tool0'):
        self.sec += 1
        msgs = []
        for mass, c in ((m_sd, com_sd), (m, com)):
            msg = InertiaStamped()
            msg.header.frame_id = frame
            msg.header.stamp.sec = self.sec
            msg.inertia.m = float(mass)
            msg.inertia.com.x, msg.inertia.com.y, msg.inertia.com.z = map(float, c)
            msgs.append(msg)
        self.pub_sd.publish(msgs[0])
        self.pub.publish(msgs[1])

    def estimate(self, values: dict, stddev: dict):
        self.set_parameters_atomically(
            [Parameter('estimate.' + k, value=float(v)) for k, v in values.items()]
            + [Parameter('estimate_stddev.' + k, value=float(v)) for k, v in stddev.items()])


# -- the mapping's core --------------------------------------------------------------------------
def test_mapping_and_quantities():
    assert parse_mapping(['a.b=payload.com', 'c = joint1.fv']) == {
        'a.b': 'payload.com', 'c': 'joint1.fv'}
    for bad in (['nothing'], ['a=payload.inertia'], []):
        with pytest.raises(IdentificationError):
            parse_mapping(bad)
    q = payload_quantity('payload.weight', 2.0, [0, 0, 0.1], 0.01, [0.001] * 3)
    assert q.value[0] == pytest.approx(2.0 * GRAVITY) and q.stddev[0] == pytest.approx(
        0.01 * GRAVITY) and not q.problem
    assert payload_quantity('payload.com', -1.0, [0, 0, 0.1], 0.01, [0.001] * 3).problem
    assert payload_quantity('payload.com.y', 1.0, [0, 0, 0.1], 0.01,
                            [0.001, math.inf, 0.001]).problem
    assert estimate_quantity('joint1.fv', -0.1, 0.01).problem
    assert estimate_quantity('link3.m', 0.0, 0.01).problem
    assert estimate_quantity('joint1.fo', -0.1, 0.01).problem == ''
    assert check_estimate_quantity('link2.my', ['link2.myR']).startswith('link2.my is identified')
    gate = ChangeGate(3.0)
    first = payload_quantity('payload.com', 1.0, [0, 0, 0.1], 0.01, [0.001] * 3)
    assert gate.due('pos', first)
    gate.mark_sent('pos', first)
    near = payload_quantity('payload.com', 1.0, [0, 0.0029, 0.1], 0.01, [0.001] * 3)
    far = payload_quantity('payload.com', 1.0, [0, 0.0031, 0.1], 0.01, [0.001] * 3)
    assert not gate.due('pos', near) and gate.due('pos', far)


# -- over DDS ------------------------------------------------------------------------------------
@pytest.fixture
def nodes(ros):
    from identification_node.ros.parameter_forwarder import ParameterForwarder
    made = []

    def make(base_names, **params):
        source = ros.add(FakeSource(ros.context, base_names))
        made.append(source)
        forwarder = ros.add(ParameterForwarder(context=ros.context, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()]))
        made.append(forwarder)
        return source, forwarder
    yield make
    for node in made:
        ros.remove(node)


@pytest.mark.ros
def test_admittance_gravity_compensation(ros, nodes):
    controller = ros.add(StandInAdmittance(ros.context))
    try:
        source, forwarder = nodes([], preset='admittance')
        pos, force = 'gravity_compensation.CoG.pos', 'gravity_compensation.CoG.force'

        def now(m, com):
            return wait_for(lambda: np.allclose(controller.value(pos), com, atol=1e-12)
                            and controller.value(force) == pytest.approx(m * GRAVITY), 10)

        def send(*args, **kwargs):   # and wait until the forwarder has it
            source.payload(*args, **kwargs)
            assert wait_for(lambda: forwarder.payload is not None
                            and forwarder.payload[0].header.stamp.sec == source.sec, 10)

        send(1.5, [0.01, 0.02, 0.1], 0.01, [0.002] * 3)
        assert now(1.5, [0.01, 0.02, 0.1])
        # mass moved 2 stddev (not sent), CoG 10 stddev (sent): force stays
        send(1.52, [0.01, 0.02, 0.12], 0.01, [0.002] * 3)
        assert now(1.5, [0.01, 0.02, 0.12])
        # inconsistent (negative mass), then an unexcited CoG: neither is sent
        send(-0.5, [0.3, 0.3, 0.3], 0.01, [0.002] * 3)
        assert wait_for(lambda: any('not physically consistent' in p
                                    for p in forwarder.problems), 10)
        send(1.5, [0.5, 0.5, 0.5], 0.01, [0.002, math.inf, 0.002])
        assert wait_for(lambda: any('not excited' in p for p in forwarder.problems), 10)
        # another frame: refused
        send(2.5, [0.7, 0.7, 0.7], 0.01, [0.002] * 3, frame='flange')
        assert wait_for(lambda: forwarder.refused == 1, 10)
        send(2.0, [0.0, 0.0, 0.2], 0.01, [0.002] * 3)
        assert now(2.0, [0.0, 0.0, 0.2])
        sent = [v for h in controller.history for v in [h.get(force)] if v is not None]
        assert sent == pytest.approx([1.5 * GRAVITY, 2.0 * GRAVITY])
        positions = [list(h[pos]) for h in controller.history if pos in h]
        np.testing.assert_allclose(positions, [[0.01, 0.02, 0.1], [0.01, 0.02, 0.12],
                                               [0.0, 0.0, 0.2]])
        assert controller.value('gravity_compensation.frame.id') == 'tool0'
    finally:
        ros.remove(controller)


class Friction(Node):
    def __init__(self, context):
        super().__init__('friction_observer', context=context)
        self.declare_parameter('viscous', 0.0)
        self.declare_parameter('mass', 0.0)


@pytest.mark.ros
def test_joint_friction_to_any_node(ros, nodes):
    target = ros.add(Friction(ros.context))
    try:
        source, forwarder = nodes(['link2.myR', 'joint1.fv', 'joint1.fc'],
                                  target='friction_observer',
                                  mapping=['viscous=joint1.fv', 'mass=link2.my'])
        source.estimate({'joint1.fv': 0.8}, {'joint1.fv': 0.01})
        assert wait_for(lambda: target.get_parameter('viscous').value == 0.8, 10)
        assert 'mass' not in forwarder.mapping   # regrouped: refused at start
        source.estimate({'joint1.fv': -0.2}, {'joint1.fv': 0.01})      # inconsistent
        source.estimate({'joint1.fv': 0.81}, {'joint1.fv': 0.01})      # within 3 stddev
        source.estimate({'joint1.fv': 0.9}, {'joint1.fv': 0.01})
        assert wait_for(lambda: target.get_parameter('viscous').value == 0.9, 10)
        assert forwarder.sent == 2
        assert target.get_parameter('mass').value == 0.0
    finally:
        ros.remove(target)
