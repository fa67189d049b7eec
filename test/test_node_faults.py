"""The node under middleware faults and abuse (issue 16), over real DDS on localhost: bursts of
20,000 messages, signals in every state, a stalled executor, failing callbacks, sim time
without /clock. Timeouts here detect hangs; they measure nothing."""
import json
import signal
import subprocess
import textwrap
import threading

import numpy as np
import pytest
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from identification_node.ros.node import IdentificationNode
from identification_node.ros.spin import STALLED_EXIT
from identification_node.wire.cdr import encode_joint_states
from ros_helpers import PYTHON, ROOT, wait_for

pytestmark = pytest.mark.ros

BEST_EFFORT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                         reliability=ReliabilityPolicy.BEST_EFFORT)
BURST = 20_000
HANG = 30.0       # s: no sign of life for this long is a hang (these tests measure nothing)


def node_process(ros, tmp_path, name, **params):
    # the smoother pinned: these test the input path (bursts, signals), not its choice
    params = {'robot': 'mit_dd_arm', 'torque_source': ['measured'],
              'smoother.half_window': 10, **params}
    proc = ros.start('node', params, tmp_path, name, extra=('-r', f'__node:={name}',
                                                            '-r', f'joint_states:=/{name}/js'))
    client = ros.client.create_client(Trigger, f'/{name}/get_estimate')
    up = client.wait_for_service(timeout_sec=120)   # start-up: imports, seconds when busy
    ros.client.destroy_client(client)
    assert up, proc.stderr.read() if proc.poll() is not None else f'{name} did not start'
    return proc


def ended(proc):
    """The exit status of ``proc`` once it ended; HANG s without: a hang (AssertionError)."""
    try:
        return proc.wait(HANG)
    except subprocess.TimeoutExpired:
        raise AssertionError(f'still running {HANG} s after the signal') from None


def bursts(count, size=BURST, seed=0):
    """``count`` bursts of ``size`` CDR joint states, stamps increasing throughout."""
    rng = np.random.default_rng(seed)
    names = ['joint1', 'joint2', 'joint3']
    for b in range(count):
        stamps = 10**9 + (b * size + np.arange(size)) * 10**5
        yield encode_joint_states(stamps, names, *rng.normal(size=(3, size, 3)))


def answers(ros, name, timeout):
    """Whether ~/get_estimate answers within ``timeout`` s (its JSON)."""
    res = ros.call(Trigger, f'/{name}/get_estimate', Trigger.Request(), timeout=timeout)
    return json.loads(res.message) if res.success else None


def test_bursts_do_not_hang_the_node_and_sigint_still_works(ros, tmp_path):
    """20 bursts of 20,000 messages, each within about 0.5 s: after each the node answers a
    service (the message-lost event, which deadlocked rmw_fastrtps under such
    bursts, is not registered); then SIGINT ends it cleanly."""
    proc = node_process(ros, tmp_path, 'burst')
    # the first answer comes with the first estimate, after the solver's start-up (seconds)
    assert answers(ros, 'burst', 60.0) is not None
    pub = ros.client.create_publisher(JointState, '/burst/js', BEST_EFFORT)
    assert wait_for(lambda: pub.get_subscription_count(), 10)
    for k, messages in enumerate(bursts(20)):
        for raw in messages:
            pub.publish(raw)
        assert answers(ros, 'burst', HANG) is not None, f'no answer after burst {k}'
        assert proc.poll() is None, proc.stderr.read()
    # it did take them in (the answers come from the newest published estimate; on a
    # starved machine most of these best-effort bursts are dropped, and counted, by design)
    assert wait_for(lambda: (answers(ros, 'burst', HANG) or {}).get('num_samples', 0) > 0,
                    HANG)
    proc.send_signal(signal.SIGINT)
    assert ended(proc) == 0, proc.stderr.read()
    ros.client.destroy_publisher(pub)


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_a_burst_ends_the_node(ros, tmp_path, sig):
    """Cleanly (0), or by the watchdog's forced exit (1, said in the log) if the shutdown
    outlasts its grace: a busy machine may stretch it (the grace itself is tested below)."""
    name = f'mid_{sig.name.lower()}'
    proc = node_process(ros, tmp_path, name)
    pub = ros.client.create_publisher(JointState, f'/{name}/js', BEST_EFFORT)
    assert wait_for(lambda: pub.get_subscription_count(), 10)
    messages = next(bursts(1))
    for k, raw in enumerate(messages):
        pub.publish(raw)
        if k == len(messages) // 2:
            proc.send_signal(sig)
    code = ended(proc)
    log = proc.stderr.read()
    assert code == 0 or (code == 1 and 'shutdown did not finish within' in log), (code, log)
    ros.client.destroy_publisher(pub)


def test_sim_time_without_clock_is_warned(ros, tmp_path):
    proc = node_process(ros, tmp_path, 'simtime', use_sim_time=True)
    lines: list[str] = []     # the log, read as it comes (a busy machine delays the warning)

    def read():
        for line in proc.stderr:
            lines.append(line)
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    warned = wait_for(lambda: any('use_sim_time is true but ROS time has not advanced' in line
                                  for line in lines), 120)
    proc.send_signal(signal.SIGINT)
    assert ended(proc) == 0
    reader.join(HANG)
    assert warned, ''.join(lines)


def test_failing_callbacks_are_counted_and_services_answer(ros):
    node = ros.add(IdentificationNode('failing', context=ros.context, parameter_overrides=[
        Parameter('robot', value='mit_dd_arm'), Parameter('torque_source', value=['measured'])]))
    assert ros.call(Trigger, '/failing/get_estimate', Trigger.Request()).success

    def broken():
        raise np.linalg.LinAlgError('Eigenvalues did not converge')
    node.pipeline.estimate = broken
    # the reset is applied, the estimate after it fails: both answer with the reason
    res = ros.call(Trigger, '/failing/reset', Trigger.Request())
    assert not res.success and 'LinAlgError: Eigenvalues did not converge' in res.message
    res = ros.call(Trigger, '/failing/get_estimate', Trigger.Request())
    assert not res.success and 'LinAlgError: Eigenvalues did not converge' in res.message
    assert node.callback_errors['estimate'] >= 1
    # a failing timer callback is counted too
    assert node.errors.guarded(node._publish_diagnostics)() is None
    assert node.callback_errors['publish_diagnostics'] == 1
    ros.remove(node)


# -- the watchdog itself, in a process of its own ------------------------------------------------
def run_python(code, timeout=20):
    return subprocess.run([PYTHON, '-c', textwrap.dedent(code)], cwd=ROOT, timeout=timeout,
                          capture_output=True, text=True,
                          env={'PYTHONPATH': str(ROOT), 'PATH': '/usr/bin:/bin'})


def test_watchdog_exits_a_stalled_process_with_status_3():
    out = run_python("""
        import time
        from identification_node.ros.spin import Watchdog
        beat = time.monotonic()
        Watchdog(0.5, {'the executor': lambda: beat}, print)
        time.sleep(15)
    """)
    assert out.returncode == STALLED_EXIT, out
    assert 'the executor made no progress' in out.stdout + out.stderr


def test_watchdog_ends_a_process_whose_main_thread_is_stuck_after_a_signal():
    """The main thread blocks where no Python signal handler can stop it; SIGTERM still ends
    the process (within the grace of 1.5 s)."""
    proc = subprocess.Popen([PYTHON, '-c', textwrap.dedent("""
        import threading, time
        from identification_node.ros.spin import Watchdog, stop_signals
        with stop_signals():
            Watchdog(0.0, {}, print)
            print('ready', flush=True)
            lock = threading.Lock(); lock.acquire(); lock.acquire()
    """)], cwd=ROOT, env={'PYTHONPATH': str(ROOT), 'PATH': '/usr/bin:/bin'},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == 'ready'
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(2.5) == 1
    assert 'shutdown did not finish' in proc.stderr.read()


def test_node_rejects_messages_with_too_many_names(ros):
    node = ros.add(IdentificationNode('names', context=ros.context, parameter_overrides=[
        Parameter('robot', value='mit_dd_arm'), Parameter('torque_source', value=['measured']),
        Parameter('max_names', value=10)], cli_args=['--ros-args', '-r', 'joint_states:=/n/js']))
    pub = ros.client.create_publisher(JointState, '/n/js', BEST_EFFORT)
    assert wait_for(lambda: pub.get_subscription_count(), 10)
    names = ['joint1', 'joint2', 'joint3'] + [f'x{i}' for i in range(20)]
    for raw in encode_joint_states(10**9 + np.arange(5) * 10**6, names,
                                   np.zeros((5, len(names)))):
        pub.publish(raw)
    assert wait_for(lambda: node.pipeline.rejected['too_many_names'] == 5, 10)
    ros.client.destroy_publisher(pub)
    ros.remove(node)
