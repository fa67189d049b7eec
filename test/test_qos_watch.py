"""Incompatible QoS is logged with both profiles and counted in diagnostics (issue 31): a
best-effort publisher to the node's reliable input receives nothing, and a subscriber asking
a durability the node's output does not offer neither; a compatible one is no finding. Over
real DDS, the node a process of its own (its log read back)."""
import signal

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from ros_helpers import RELIABLE, Collector, diagnostic_values, wait_for

pytestmark = pytest.mark.ros

BEST_EFFORT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                         reliability=ReliabilityPolicy.BEST_EFFORT)
TRANSIENT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)


def test_incompatible_qos_is_logged_with_both_profiles_and_counted(ros, tmp_path):
    name = 'qos'
    params = {'robot': 'mit_dd_arm', 'torque_source': ['measured'],
              'publish.diagnostics_rate': 5.0,
              f'qos_overrides./{name}/js.subscription.reliability': 'reliable'}
    proc = ros.start('node', params, tmp_path, name, extra=(
        '-r', f'__node:={name}', '-r', f'joint_states:=/{name}/js'))
    client = ros.client.create_client(Trigger, f'/{name}/get_estimate')
    assert client.wait_for_service(timeout_sec=60), proc.stderr.read() if proc.poll() else ''
    ros.client.destroy_client(client)
    diag = Collector(ros, DiagnosticArray, '/diagnostics')
    lossy = ros.client.create_publisher(JointState, f'/{name}/js', BEST_EFFORT)
    fine = ros.client.create_publisher(JointState, f'/{name}/js', RELIABLE)
    late = Collector(ros, Float64MultiArray, f'/{name}/base_parameters', TRANSIENT)
    plain = Collector(ros, Float64MultiArray, f'/{name}/base_parameters')   # compatible

    def count():
        found = [diagnostic_values(s) for m in diag.snapshot() for s in m.status
                 if s.name.startswith(f'{name}:')]
        return int(found[-1]['qos_incompatible']) if found else None
    try:
        assert wait_for(lambda: count() == 2, 30), count()
        assert wait_for(lambda: fine.get_subscription_count() == 1, 10)
        assert count() == 2          # the compatible publisher and subscription are none
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(10)
        for c in (diag, late, plain):
            c.close()
        ros.client.destroy_publisher(lossy)
        ros.client.destroy_publisher(fine)
    log = [line for line in proc.stderr.read().splitlines()
           if "incompatible QoS between this node's" in line]
    assert len(log) == 2, log
    sub = next(line for line in log if f'/{name}/js' in line)
    assert "this node's subscription and the publisher of /test_client" in sub
    assert 'offered best_effort' in sub and 'requested reliable' in sub
    pub = next(line for line in log if f'/{name}/base_parameters' in line)
    assert "this node's publisher and the subscription of /test_client" in pub
    assert 'offered reliable, volatile' in pub and 'requested reliable, transient_local' in pub
