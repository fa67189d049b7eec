"""``~/links/<link>/inertia``: each identified link's mass, centre of mass and inertia about it
(geometry_msgs/InertiaStamped), checked against the node's estimate converted by pinocchio
(pin.Inertia, a second formulation of the parallel-axis theorem), on a UR5 over DDS."""
import numpy as np
import pinocchio as pin
import pytest
from geometry_msgs.msg import InertiaStamped
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from arms import arm_urdf
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import PIN_ORDER, load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.ros.link_outputs import inertia_stamped, topic_token
from ros_helpers import LATCHED, RELIABLE, Collector, joint_state_msgs, stamp_ns, wait_for


def expected(block):
    """(m, com, inertia about the com) of a block [m, mx, my, mz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz]
    by pinocchio."""
    inertia = pin.Inertia.FromDynamicParameters(np.asarray(block)[PIN_ORDER])
    return inertia.mass, inertia.lever, inertia.inertia


def as_arrays(msg):
    i = msg.inertia
    return (i.m, np.array([i.com.x, i.com.y, i.com.z]),
            np.array([[i.ixx, i.ixy, i.ixz], [i.ixy, i.iyy, i.iyz], [i.ixz, i.iyz, i.izz]]))


def test_message_is_the_inertia_about_the_centre_of_mass():
    robot = load_robot(str(arm_urdf('ur5')))
    rng = np.random.default_rng(3)
    for i, link in enumerate(robot.link_names):
        block = robot.phi_model[10 * i:10 * i + 10] * rng.uniform(0.5, 2.0)
        msg = inertia_stamped(link, block, 1_700_000_000_123_456_789)
        assert msg.header.frame_id == link and stamp_ns(msg) == 1_700_000_000_123_456_789
        m, c, Ic = as_arrays(msg)
        em, ec, eIc = expected(block)
        assert m == pytest.approx(em)
        np.testing.assert_allclose(c, ec, atol=1e-12)
        np.testing.assert_allclose(Ic, eIc, atol=1e-12)


def test_topic_tokens():
    assert topic_token('panda_link1') == 'panda_link1'
    assert topic_token('link-2.a') == 'link_2_a' and topic_token('3rd') == '_3rd'


@pytest.mark.ros
def test_every_link_published_after_each_refresh(ros):
    """With the shipped defaults (physically consistent estimate): every message equals the
    pinocchio conversion of a standard parameter vector the node published from (recorded on
    the way in), the newest one reaches late subscribers (transient local), and each refresh
    after new samples publishes again."""
    urdf = str(arm_urdf('ur5'))
    robot = load_robot(urdf)
    params = {'robot': urdf, 'publish.estimate_rate': 5.0}
    from identification_node.ros.node import IdentificationNode
    node = ros.add(IdentificationNode(
        'links', context=ros.context, parameter_overrides=[Parameter(k, value=v) for k, v in
                                                           params.items()]))
    published = []   # the phi each refresh published from
    publish = node.links.publish
    node.links.publish = lambda phi, ns: (published.append(np.array(phi)), publish(phi, ns))
    sender = ros.client.create_publisher(JointState, '/joint_states', RELIABLE)
    traj = FourierTrajectory.random(robot, harmonics=4, period=10.0, seed=5)
    n = 8000
    sim = simulate_kinematic(robot, None, traj, np.arange(n) / 1000.0,
                             SensorNoise(torque_std=0.1), seed=5)
    stamps = 2 * 10**9 + np.arange(n) * 10**6
    msgs = joint_state_msgs(stamps, robot.joint_names, sim.q_meas, sim.qd_meas, sim.tau_meas)
    assert wait_for(lambda: sender.get_subscription_count(), 10)
    topics = {link: f'/links/links/{topic_token(link)}/inertia' for link in robot.link_names}
    early = Collector(ros, InertiaStamped, topics[robot.link_names[-1]], LATCHED)

    def send(a, b):
        for k in range(a, b, 250):
            for msg in msgs[k:min(b, k + 250)]:
                sender.publish(msg)
            assert wait_for(lambda: node.pipeline.received >= min(b, k + 250), 10)

    send(0, 6000)
    assert wait_for(lambda: len(early), 60), node.links.withheld
    before = node.estimate().stamp
    send(6000, n)
    assert wait_for(lambda: node.estimate().stamp > before + 1.5, 10)
    last = int(round(node.estimate().stamp * 1e9))
    # late subscribers (transient local) get each link's newest message
    got = {link: Collector(ros, InertiaStamped, topic, LATCHED) for link, topic in topics.items()}
    assert wait_for(lambda: all(len(c) and stamp_ns(c.snapshot()[-1]) == last
                                for c in got.values()), 60), node.links.withheld
    assert node.links.withheld == []
    for i, link in enumerate(robot.link_names):
        for msg in got[link].snapshot():
            assert msg.header.frame_id == link
            m, c, Ic = as_arrays(msg)
            assert any(np.isclose(m, e[0], rtol=1e-12) and np.allclose(c, e[1], atol=1e-12)
                       and np.allclose(Ic, e[2], rtol=1e-9, atol=1e-12)
                       for e in (expected(phi[10 * i:10 * i + 10]) for phi in published)), link
    # published again at a refresh after new samples: the first subscriber saw both stamps
    assert len({stamp_ns(m) for m in early.snapshot()}) >= 2
    for c in [early, *got.values()]:
        c.close()
    ros.client.destroy_publisher(sender)
    ros.remove(node)
