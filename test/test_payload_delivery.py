"""Delivering the payload to controllers: the request mapping (the UR and Franka request
layouts, reproduced with their field names and types) and the forwarder node against a
stand-in service (sensor_msgs/SetCameraInfo: its 3x3 array and sequence fields)."""
import time

import pytest
from geometry_msgs.msg import Inertia, InertiaStamped, Vector3
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.srv import SetCameraInfo

from identification_node.errors import IdentificationError
from identification_node.payload.delivery import PRESETS, fill_request, parse_fields
from identification_node.ros.payload_forwarder import PayloadForwarder
from ros_helpers import LATCHED, wait_for


def inertia():
    return Inertia(m=1.25, com=Vector3(x=0.01, y=-0.02, z=0.08), ixx=0.004, ixy=0.0001,
                   ixz=-0.0002, iyy=0.005, iyz=0.0003, izz=0.003)


class URSetPayloadRequest:
    """ur_msgs/srv/SetPayload's request: float32 mass, geometry_msgs/Vector3
    center_of_gravity."""
    def __init__(self):
        self.mass, self.center_of_gravity = 0.0, Vector3()


class Duration:
    def __init__(self):
        self.sec, self.nanosec = 0, 0


class URSetPayloadInertiaRequest(URSetPayloadRequest):
    """ur_msgs/srv/SetPayload's request with the inertia (ur_msgs #42/#43): float32 mass,
    Vector3 center_of_gravity, float64 ixx iyy izz ixy ixz iyz, Duration transition_time."""
    def __init__(self):
        super().__init__()
        self.ixx = self.iyy = self.izz = self.ixy = self.ixz = self.iyz = 0.0
        self.transition_time = Duration()


class URSetPayloadWholeRequest:
    """A SetPayload request carrying geometry_msgs/Inertia payload and float64
    transition_time."""
    def __init__(self):
        self.payload, self.transition_time = Inertia(), 0.0


class FrankaSetLoadRequest:
    """franka_msgs/srv/SetLoad's request: float64 mass, float64[3] center_of_mass,
    float64[9] load_inertia (column-major)."""
    def __init__(self):
        self.mass, self.center_of_mass, self.load_inertia = 0.0, [0.0] * 3, [0.0] * 9


def test_ur_and_franka_requests_filled_by_their_presets():
    ur = fill_request(URSetPayloadRequest(), PRESETS['ur']['fields'], inertia(),
                      PRESETS['ur']['optional'])
    assert ur.mass == 1.25
    assert (ur.center_of_gravity.x, ur.center_of_gravity.y, ur.center_of_gravity.z) == (
        0.01, -0.02, 0.08)
    fr = fill_request(FrankaSetLoadRequest(), PRESETS['franka']['fields'], inertia())
    assert fr.mass == 1.25 and fr.center_of_mass == [0.01, -0.02, 0.08]
    assert fr.load_inertia == [0.004, 0.0001, -0.0002, 0.0001, 0.005, 0.0003,
                               -0.0002, 0.0003, 0.003]


def test_ur_newer_layouts_get_the_inertia_and_transition_time():
    """Each SetPayload layout filled from the one preset: the inertia where the request has
    it, the transition time as a Duration or a number; the older layout as before."""
    fields, optional = PRESETS['ur']['fields'], PRESETS['ur']['optional']
    new = fill_request(URSetPayloadInertiaRequest(), fields, inertia(), optional, 1.25)
    assert new.mass == 1.25 and new.center_of_gravity.z == 0.08
    assert (new.ixx, new.iyy, new.izz, new.ixy, new.ixz, new.iyz) == (
        0.004, 0.005, 0.003, 0.0001, -0.0002, 0.0003)
    assert (new.transition_time.sec, new.transition_time.nanosec) == (1, 250_000_000)
    whole = fill_request(URSetPayloadWholeRequest(), fields, inertia(), optional, 0.5)
    assert whole.payload == inertia() and whole.transition_time == 0.5
    old = fill_request(URSetPayloadRequest(), fields, inertia(), optional, 0.5)
    assert old.mass == 1.25 and not hasattr(old, 'transition_time')
    with pytest.raises(IdentificationError, match='none of the preset'):
        fill_request(Duration(), fields, inertia(), optional)
    with pytest.raises(IdentificationError, match='transition_time'):
        fill_request(URSetPayloadInertiaRequest(), fields, inertia(), optional, -1.0)


def test_bad_mappings_refused():
    with pytest.raises(IdentificationError, match='quantity must be one of'):
        parse_fields(['mass=weight'])
    with pytest.raises(IdentificationError, match='field.path=quantity'):
        parse_fields(['mass'])
    with pytest.raises(IdentificationError, match='no field'):
        fill_request(URSetPayloadRequest(), {'payload_mass': 'mass'}, inertia())
    with pytest.raises(IdentificationError, match='has 9 elements, not 3'):
        fill_request(FrankaSetLoadRequest(), {'load_inertia': 'com'}, inertia())


@pytest.mark.ros
def test_forwarder_calls_a_stand_in_service(ros):
    received = []

    def serve(req, res):
        received.append(req)
        res.success, res.status_message = True, 'ok'
        return res
    server = ros.add(Node('stand_in', context=ros.context))
    server.create_service(SetCameraInfo, '/stand_in/set_load', serve)
    fwd = ros.add(PayloadForwarder('forwarder', context=ros.context, parameter_overrides=[
        Parameter('service', value='/stand_in/set_load'),
        Parameter('service_type', value='sensor_msgs/srv/SetCameraInfo'),
        Parameter('fields', value=['camera_info.k=inertia_matrix', 'camera_info.d=com']),
        Parameter('frame', value='link7')],
        cli_args=['--ros-args', '-r', 'payload:=/arm/payload']))
    pub = ros.client.create_publisher(InertiaStamped, '/arm/payload', LATCHED)
    wrong = InertiaStamped(inertia=inertia())
    wrong.header.frame_id = 'link6'
    pub.publish(wrong)
    assert wait_for(lambda: fwd.refused == 1, 10)
    msg = InertiaStamped(inertia=inertia())
    msg.header.frame_id = 'link7'
    pub.publish(msg)
    assert wait_for(lambda: received and fwd.sent == 1, 10)
    req = received[-1]
    assert list(req.camera_info.k) == [0.004, 0.0001, -0.0002, 0.0001, 0.005, 0.0003,
                                       -0.0002, 0.0003, 0.003]
    assert list(req.camera_info.d) == [0.01, -0.02, 0.08]
    time.sleep(0.2)
    assert len(received) == 1     # the wrong frame never reached the controller
    for node in (fwd, server):
        ros.remove(node)
        node.destroy_node()


@pytest.mark.ros
def test_forwarder_refuses_unknown_service_type(ros):
    with pytest.raises(IdentificationError, match='service_type: ur_msgs/srv/SetPayload is '
                       'not installed'):
        PayloadForwarder('fwd_ur', context=ros.context,
                         parameter_overrides=[Parameter('preset', value='ur')])
