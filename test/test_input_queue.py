"""The node's input queues are bounded in bytes (issue 31): large messages sent faster than
the node processes them are dropped oldest first beyond ``input_queue_bytes``, counted, and
nothing is lost without a count. Over real DDS, in this process."""
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from identification_node.ros.conversions import PolledSubscription, wait_for_all_acked
from identification_node.ros.node import IdentificationNode
from identification_node.wire.cdr import encode_joint_states
from ros_helpers import (RELIABLE, Collector, diagnostic_values, wait_for)

pytestmark = pytest.mark.ros

WIDE = 12_500          # doubles per message: ~100 kB each


def wide_messages(n, first=0):
    """``n`` JointStates of ~100 kB (one name, WIDE positions: malformed for any arm)."""
    return encode_joint_states((first + np.arange(n)) * 10**6, ['a'] * WIDE,
                               np.random.default_rng(first).random((n, WIDE)))


def test_polled_input_keeps_the_newest_within_its_byte_bound(ros):
    node = Node('bytes', context=ros.context)
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                     reliability=ReliabilityPolicy.RELIABLE)
    sent = wide_messages(50)
    size = len(sent[0])
    got = []
    source = PolledSubscription(node, JointState, '/bytes/js', got.extend, qos,
                                max_bytes=10.5 * size)
    pub = ros.client.create_publisher(JointState, '/bytes/js', RELIABLE)
    assert wait_for(lambda: pub.get_subscription_count(), 10)
    for raw in sent:
        pub.publish(raw)
    assert wait_for_all_acked([pub], 10)
    assert source.poll() == 10
    assert got == sent[-10:]                     # the newest, in order, byte-exact
    assert source.dropped == 40 and source.lost == 0
    assert source.peak_bytes <= 10.5 * size
    ros.client.destroy_publisher(pub)
    source.destroy()
    node.destroy_node()


def test_node_drops_beyond_input_queue_bytes_while_processing_stalls(ros):
    """The processing thread held up (its lock taken here) while 60 messages of ~100 kB
    arrive: the node holds at most input_queue_bytes of them; every message sent is either
    received by the pipeline or counted dropped in diagnostics."""
    size = len(wide_messages(1)[0])
    node = ros.add(IdentificationNode('bounded', context=ros.context, parameter_overrides=[
        Parameter('robot', value='mit_dd_arm'), Parameter('torque_source', value=['measured']),
        Parameter('input_queue_bytes', value=int(5.5 * size)),
        Parameter('publish.diagnostics_rate', value=5.0),
        Parameter('qos_overrides./bounded/js.subscription.reliability', value='reliable')],
        cli_args=['--ros-args', '-r', 'joint_states:=/bounded/js']))
    diag = Collector(ros, DiagnosticArray, '/diagnostics')
    pub = ros.client.create_publisher(JointState, '/bounded/js', RELIABLE)
    assert wait_for(lambda: pub.get_subscription_count(), 10)
    source = node.inputs[0]
    with node.lock:
        for raw in wide_messages(60):
            pub.publish(raw)
        assert wait_for_all_acked([pub], 30)     # the receiving thread took them all
        assert wait_for(lambda: source.dropped >= 55, 10), source.dropped
    assert source.peak_bytes <= 5.5 * size

    def counts():
        found = [diagnostic_values(s) for m in diag.snapshot() for s in m.status
                 if s.name.startswith('bounded:')]
        return found and (int(found[-1]['samples_received']),
                          int(found[-1]['dropped_messages.joint_states']))
    assert wait_for(lambda: (c := counts()) and sum(c) == 60, 10), counts()
    assert counts() == (5, 55)
    diag.close()
    ros.client.destroy_publisher(pub)
    ros.remove(node)
