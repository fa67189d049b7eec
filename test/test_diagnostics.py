"""Diagnostics values a program parses: plain numbers, true/false, words, or the literals
``not determined`` / ``not excited``; never Python syntax. Checked on the formatter and on a
running node's /diagnostics before and after samples, with payload identification on."""
import math
import re

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.ros.diagnostics import NOT_DETERMINED, NOT_EXCITED, plain, vector
from ros_helpers import RELIABLE, Collector, diagnostic_values, joint_state_msgs, wait_for

NUMBER = re.compile(r'-?\d+(\.\d+)?(e[+-]\d+)?')
# keys whose value is text by nature (words, a sentence, names)
TEXT = {'smoother', 'robust_gate', 'consistency_status', 'consistency_notes', 'missing_joints',
        'model_term_warnings', 'consistency_problems', 'consistency_method', 'payload.link',
        'payload.state', 'payload.excited', 'payload.not_excited', 'payload.last_change',
        'payload.last_change_detected'}
PYTHON_SYNTAX = re.compile(r"None|True|False|\[|\]|\{|'|\bnan\b|\binf\b")


def test_plain_values():
    assert plain(3) == '3' and plain(np.int64(7)) == '7'
    assert plain(0.1 + 0.2) == '0.3' and plain(np.float64(1.5e-9)) == '1.5e-09'
    assert plain(True) == 'true' and plain(np.bool_(False)) == 'false'
    assert plain(None) == plain(math.nan) == plain(-math.inf) == NOT_DETERMINED
    assert plain('gating') == 'gating'
    with pytest.raises(TypeError):
        plain([1.0, None])
    assert vector('com', 'xyz', [0.1, None, 0.2], [True, False, True]) == {
        'com.x': 0.1, 'com.y': NOT_EXCITED, 'com.z': 0.2}


def check(values: dict) -> None:
    for key, value in values.items():
        assert not PYTHON_SYNTAX.search(value), f'{key} = {value!r}'
        if key not in TEXT:
            assert (NUMBER.fullmatch(value) or value in ('true', 'false', NOT_DETERMINED,
                                                         NOT_EXCITED)), f'{key} = {value!r}'


@pytest.mark.ros
def test_node_diagnostics_are_plain(ros):
    from identification_node.ros.node import IdentificationNode
    params = {'robot': 'mit_dd_arm', 'extras': ['fv', 'fc'], 'payload.enabled': True,
              'publish.diagnostics_rate': 5.0}
    diag = Collector(ros, DiagnosticArray, '/diagnostics')
    node = ros.add(IdentificationNode('plain', context=ros.context, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()]))

    def last():
        found = [diagnostic_values(s) for m in diag.snapshot() for s in m.status
                 if s.name.startswith('plain:')]
        return found[-1] if found else None

    first = wait_for(last, 30)
    check(first)
    assert first['smoother_delay_samples'] == NOT_DETERMINED
    assert first['residual_rms.joint1'] == NOT_DETERMINED
    assert first['converged'] == 'false'

    sender = ros.client.create_publisher(JointState, '/joint_states', RELIABLE)
    assert wait_for(lambda: sender.get_subscription_count(), 10)
    traj = FourierTrajectory.random(node.robot, harmonics=3, period=10.0, seed=4)
    n = 8000
    sim = simulate_kinematic(node.robot, None, traj, np.arange(n) / 1000.0,
                             SensorNoise(torque_std=0.2), seed=4)
    msgs = joint_state_msgs(10**9 + np.arange(n) * 10**6, node.robot.joint_names, sim.q_meas,
                            sim.qd_meas, sim.tau_meas)
    for k in range(0, n, 250):
        for msg in msgs[k:k + 250]:
            sender.publish(msg)
        assert wait_for(lambda: node.pipeline.received >= min(n, k + 250), 10)
    values = wait_for(lambda: (v := last()) and 'payload.mass' in v
                      and v['smoother'] == 'automatic' and v, 30)
    assert values, last()
    check(values)
    assert NUMBER.fullmatch(values['residual_rms.joint1'])
    assert int(values['smoother_delay_samples']) == node.pipeline.smoother.half_window
    for axis in 'xyz':
        assert NUMBER.fullmatch(values[f'payload.com.{axis}']) or \
            values[f'payload.com.{axis}'] == NOT_EXCITED
    # ~/get_estimate: the keys and types the README writes down
    import json
    from std_srvs.srv import Trigger
    from ros_helpers import ROOT
    res = ros.call(Trigger, '/plain/get_estimate', Trigger.Request(), timeout=120)
    got = json.loads(res.message)
    readme = (ROOT / 'README.md').read_text()
    block = readme[readme.index('`~/get_estimate` answers'):]
    block = block[:block.index('"condition_number"') + 60]
    documented = dict(re.findall(r'"(\w+)": (\[?\w+\]?(?: \| null)?)', block))
    assert set(got) == set(documented)
    kinds = {'str': str, 'int': int, 'float': float, 'bool': bool}
    for key, kind in documented.items():
        value = got[key]
        if kind.endswith('| null') and value is None:
            continue
        kind = kind.replace(' | null', '')
        if kind.startswith('['):
            assert isinstance(value, list), (key, value)
        else:
            assert isinstance(value, kinds[kind]), (key, value)
    assert len(got['names']) == len(got['values']) == len(got['stddev'])
    diag.close()
    ros.client.destroy_publisher(sender)
    ros.remove(node)
