"""Live bag replay and recording over real rclpy/FastDDS (identification_node.ros.player,
identification_node.ros.recorder, the play and record verbs).

Independent truths: the bytes and log times written with BagWriter (play), the bytes and
send times of the messages this test publishes (record), the `mcap` library's reader, and
the QoS the ROS graph reports for the other process' endpoints. The player and the recorder
run in another process (`python -m identification_node ...`) except where the in-process API
is the subject. One ROS domain per test module (derived from the pid), localhost discovery.
"""
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import (DurabilityPolicy, QoSProfile, ReliabilityPolicy)  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from rosbags.interfaces import QosDurability  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from identification_node.bags.reader import iter_messages, open_bag  # noqa: E402
from identification_node.bags.writer import BagWriter  # noqa: E402
from identification_node.errors import IdentificationError  # noqa: E402
from identification_node.ros.conversions import wait_for_all_acked  # noqa: E402
from identification_node.ros.player import BagPlayer, offered_qos  # noqa: E402
from identification_node.ros.recorder import BagRecorder  # noqa: E402
from identification_node.wire.cdr import JOINT_STATE, STRING, encode_joint_state  # noqa: E402
from ros_helpers import domain_id  # noqa: E402

pytestmark = pytest.mark.ros

DOMAIN = domain_id('test_play_record')   # claimed for the whole run
ROOT = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000  # bag log time origin [ns]
PERIOD_NS = 5_000_000  # 200 Hz
N_JS = 301  # 1.5 s of joint states
URDF = '<robot name="arm"><link name="base"/></robot>'
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
BEST_EFFORT = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)


@pytest.fixture(scope='module')
def ros():
    """(context, node, executor) on this module's domain; localhost-only discovery."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv('ROS_DOMAIN_ID', str(DOMAIN))
        mp.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        ctx = Context()
        rclpy.init(context=ctx, domain_id=DOMAIN,
                   signal_handler_options=SignalHandlerOptions.NO)
        node = Node('play_record_test', context=ctx)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        try:
            yield ctx, node, executor
        finally:
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)


def spin_until(executor, predicate, timeout):
    """Spin until predicate() is true or timeout [s]; return predicate()."""
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
    return predicate()


def cli(*args):
    """Start `python -m identification_node ARGS` on this module's domain."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1')
    return subprocess.Popen([sys.executable, '-m', 'identification_node', *map(str, args)],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    """A 1.5 s bag: latched /robot_description at the start, JointState at 200 Hz.
    Returns (path, [(log_ns, cdr bytes)] of /joint_states, cdr bytes of the URDF)."""
    path = tmp_path_factory.mktemp('play') / 'bag'
    with BagWriter(path) as w:
        w.write_string('/robot_description', T0, URDF)
        for k in range(N_JS):
            t = T0 + k * PERIOD_NS
            w.write_joint_state('/joint_states', t, t * 1e-9, ['shoulder', 'elbow'],
                                [0.01 * k, -0.02 * k], [0.5, -0.5 + 1e-3 * k], [k, 2.0])
    with open_bag(path) as r:
        js = [(t, raw) for _, _, t, raw in r.raw_messages(['/joint_states'])]
        (_, _, _, urdf), = r.raw_messages(['/robot_description'])
    assert len(js) == N_JS
    return path, js, urdf


def same_cdr(wire, stored):
    """Equal CDR messages: the wire may carry up to 3 trailing zero bytes that pad the
    serialized payload to a multiple of 4 (FastDDS), the bag stores none."""
    pad = wire[len(stored):]
    return wire.startswith(stored) and len(pad) < 4 and not pad.strip(b'\0')


def _raw_sink(node, msg_type, topic, qos):
    """Raw subscription collecting (monotonic arrival time, bytes)."""
    got = []
    sub = node.create_subscription(msg_type, topic, lambda raw: got.append(
        (time.monotonic(), raw)), qos, raw=True)
    return sub, got


# ---------------------------------------------------------------------------------------
# play
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize('rate, topic, args, report', [
    (1.0, '/joint_states', [], f'published {N_JS + 1} messages on 2 topics'),
    (2.0, '/arm/js', ['--topics', 'joint_states', '--ros-args', '-r', '/joint_states:=/arm/js'],
     f'published {N_JS} messages on 1 topic '),
], ids=['rate1', 'rate2-remapped'])
def test_play_in_other_process_raw_bytes_timing_and_latched(ros, bag, rate, topic, args,
                                                            report):
    _, node, executor = ros
    path, js, urdf = bag
    sub, got = _raw_sink(node, JointState, topic, RELIABLE)
    late, late_sub = [], None
    proc = cli('play', path, '--rate', rate, '--wait-for-subscribers', 30,
               '--wait-for-all-acked', 10, *args)
    try:
        assert spin_until(executor, lambda: got or proc.poll() is not None, 30), 'no message'
        assert proc.poll() is None, proc.communicate()
        if rate == 1.0:
            # the player's endpoints as the graph reports them (QoS from the bag metadata)
            js_pub, = node.get_publishers_info_by_topic('/joint_states')
            rd_pub, = node.get_publishers_info_by_topic('/robot_description')
            assert js_pub.qos_profile.reliability == ReliabilityPolicy.RELIABLE
            assert js_pub.qos_profile.durability == DurabilityPolicy.VOLATILE
            assert rd_pub.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
            # subscribed after /robot_description was published at the bag start
            late_sub, late = _raw_sink(node, String, '/robot_description', LATCHED)
        spin_until(executor, lambda: len(got) >= N_JS and (rate != 1.0 or late), 30)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        node.destroy_subscription(sub)
        if late_sub is not None:
            node.destroy_subscription(late_sub)
    assert proc.returncode == 0, err
    assert report in out
    assert [raw for _, raw in got] == [raw for _, raw in js]  # all, in order, same bytes
    span = got[-1][0] - got[0][0]
    expected = (js[-1][0] - js[0][0]) * 1e-9 / rate
    assert 0.7 * expected < span < 1.3 * expected, (span, expected)
    if rate == 1.0:
        assert len(late) == 1 and same_cdr(late[0][1], urdf)
        assert deserialize_message(late[0][1], String).data == URDF


def test_play_loop_in_other_process_stops_cleanly_on_sigint(ros, bag):
    _, node, executor = ros
    path, js, _ = bag
    sub, got = _raw_sink(node, JointState, '/loop/js', RELIABLE)
    proc = cli('play', path, '--loop', '--rate', 8, '--topics', '/joint_states',
               '--wait-for-subscribers', 30, '--ros-args', '-r', '/joint_states:=/loop/js')
    try:
        assert spin_until(executor, lambda: len(got) > N_JS or proc.poll() is not None, 30)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    spin_until(executor, lambda: False, 0.2)
    node.destroy_subscription(sub)
    assert proc.returncode == 0, err
    assert out.rstrip().endswith('[interrupted]') and 'loops' in out
    # FastDDS may print its own (timestamped) warnings on stdout: find the summary.
    published = int(re.search(r'published (\d+)', out).group(1))
    assert N_JS < len(got) <= published  # no ack wait on interrupt: the tail may be in flight
    raws = [raw for _, raw in js]
    assert [raw for _, raw in got] == (raws * (published // N_JS + 1))[:len(got)]


def test_play_bag_without_the_topics_exits_2(bag):
    path, _, _ = bag
    proc = cli('play', path, '--topics', '/not_there', '/neither')
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: ') and '/not_there' in lines[0]
    assert out == ''


def test_player_in_process_clock_filter_and_late_latched(ros, bag):
    ctx, node, executor = ros
    path, js, urdf = bag
    sim = Node('sim_time_follower', context=ctx,
               parameter_overrides=[Parameter('use_sim_time', value=True)])
    executor.add_node(sim)
    pnode = Node('inprocess_player', context=ctx)
    sub, got = _raw_sink(node, JointState, '/joint_states', RELIABLE)
    clocks = []
    clock_sub = node.create_subscription(
        Clock, '/clock', lambda m: clocks.append(m.clock.sec * 10**9 + m.clock.nanosec), 10)
    with BagPlayer(pnode, path, rate=4.0, topics=['joint_states', '/robot_description'],
                   clock=200.0) as player:
        assert player.topics == ['/joint_states', '/robot_description']
        assert player.latched_topics == ['/robot_description']
        assert player.wait_for_subscribers(20) == []
        assert spin_until(executor, lambda: clock_sub.get_publisher_count() == 1, 20)
        stats = []
        thread = threading.Thread(target=lambda: stats.append(player.play()))
        thread.start()
        try:
            spin_until(executor, lambda: not thread.is_alive() and len(got) >= N_JS, 30)
        finally:
            player.stop()
            thread.join()
        # publishers live until close(): the latched URDF reaches a subscriber made now
        late_sub, late = _raw_sink(node, String, '/robot_description', LATCHED)
        assert spin_until(executor, lambda: late, 20)
    assert [raw for _, raw in got] == [raw for _, raw in js]
    assert len(late) == 1 and same_cdr(late[0][1], urdf)
    st, = stats
    assert (st.published, st.per_topic, st.loops) == (N_JS + 1, {
        '/joint_states': N_JS, '/robot_description': 1}, 1)
    assert st.bag_time == pytest.approx((js[-1][0] - T0) * 1e-9)
    # /clock carries the bag time: from its start to its end, never back
    end = js[-1][0]
    assert spin_until(executor, lambda: sim.get_clock().now().nanoseconds == end, 10)
    assert spin_until(executor, lambda: clocks and clocks[-1] == end, 10)
    assert clocks[0] == T0 and clocks == sorted(clocks) and len(clocks) > 2
    assert st.clock_published >= len(clocks)
    for s in (sub, clock_sub, late_sub):
        node.destroy_subscription(s)
    executor.remove_node(sim)
    sim.destroy_node()
    pnode.destroy_node()


def test_player_loops_until_stopped(ros, bag):
    ctx, node, executor = ros
    path, js, _ = bag
    pnode = Node('looping_player', context=ctx)
    sub, got = _raw_sink(node, JointState, '/joint_states', RELIABLE)
    with BagPlayer(pnode, path, rate=8.0, topics=['/joint_states'], loop=True) as player:
        assert player.wait_for_subscribers(20) == []
        stats = []
        thread = threading.Thread(target=lambda: stats.append(player.play()))
        thread.start()
        try:
            assert spin_until(executor, lambda: len(got) > N_JS + 20, 30)
        finally:
            player.stop()
            thread.join()
        spin_until(executor, lambda: len(got) == stats[0].published, 5)
    node.destroy_subscription(sub)
    pnode.destroy_node()
    st, = stats
    assert st.interrupted and st.loops >= 2 and st.published == len(got)
    raws = [raw for _, raw in js]
    expected = (raws * (len(got) // N_JS + 1))[:len(got)]
    assert [raw for _, raw in got] == expected


# ---------------------------------------------------------------------------------------
# record
# ---------------------------------------------------------------------------------------

def _publish_mix(node, executor, pubs, n_js=200):
    """Publish JointState CDR bytes (reliable) interleaved with best-effort Strings;
    return [(send ns, bytes)] of the joint states and the best-effort texts."""
    js_pub, be_pub = pubs
    sent, texts = [], []
    for k in range(n_js):
        raw = encode_joint_state(k * 1e-3, ['j1', 'j2', 'j3'], [k, -k, 0.5],
                                 [0.25 * k], [])
        sent.append((time.time_ns(), raw))
        js_pub.publish(raw)
        if k % 10 == 0:
            texts.append(f'note {k}')
            be_pub.publish(String(data=texts[-1]))
        time.sleep(0.002)
    assert js_pub.wait_for_all_acked(rclpy.duration.Duration(seconds=10))
    return sent, texts


def _check_recorded(out, sent, texts, t_start, t_stop):
    assert out.is_dir()
    assert not [p for p in out.parent.iterdir() if p.name.startswith('.')]  # no temp dirs
    with open_bag(out) as r:
        assert r.topics == {'/rec/js': JOINT_STATE, '/rec/be': STRING,
                            '/rec/latched': STRING}
        durability = {t: q[0].durability for t, q in offered_qos(r).items()}
        rows = list(r.raw_messages())
        strings = {t: [m.data for _, _, _, m in iter_messages(r, [t])]
                   for t in ('/rec/be', '/rec/latched')}
    assert durability == {'/rec/js': QosDurability.VOLATILE,
                          '/rec/be': QosDurability.VOLATILE,
                          '/rec/latched': QosDurability.TRANSIENT_LOCAL}
    js = [(t, raw) for topic, _, t, raw in rows if topic == '/rec/js']
    assert [raw for _, raw in js] == [raw for _, raw in sent]  # reliable: all, same bytes
    # log time = receive time: after the send, before the recorder stopped
    assert all(ts <= t <= t_stop for (t, _), (ts, _) in zip(js, sent))
    assert all(t_start <= t for _, _, t, _ in rows)
    assert strings['/rec/latched'] == ['published before the recorder started']
    be = strings['/rec/be']  # best effort: an ordered subsequence (on loopback: all)
    assert be and [t for t in texts if t in be] == be
    return rows


def _record_subprocess(ros, tmp_path, storage, sig):
    _, node, executor = ros
    pubs = (node.create_publisher(JointState, '/rec/js', RELIABLE),
            node.create_publisher(String, '/rec/be', BEST_EFFORT))
    latched = node.create_publisher(String, '/rec/latched', LATCHED)
    latched.publish(String(data='published before the recorder started'))
    out = tmp_path / 'rec' / 'bag'
    t_start = time.time_ns()
    proc = cli('record', out, '--topics', '/rec/js', 'rec/be', '/rec/latched',
               '--storage', storage)
    try:
        assert spin_until(executor, lambda: proc.poll() is not None or all(
            p.get_subscription_count() for p in (*pubs, latched)), 30), 'recorder not seen'
        assert proc.poll() is None, proc.communicate()
        sent, texts = _publish_mix(node, executor, pubs)
        assert wait_for_all_acked(pubs[:1], 10), 'the recorder did not acknowledge'
        time.sleep(0.3)  # the best-effort tail
        assert not out.exists()  # the bag appears only when recording ends
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=30)
        t_stop = time.time_ns()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        for p in (*pubs, latched):
            node.destroy_publisher(p)
    assert proc.returncode == 0, stderr
    assert 'recorded' in stdout and '/rec/latched [std_msgs/msg/String]: 1 (latched)' in stdout
    return out, _check_recorded(out, sent, texts, t_start, t_stop)


def test_record_in_other_process_stopped_by_sigint(ros, tmp_path):
    from mcap.reader import make_reader
    out, rows = _record_subprocess(ros, tmp_path, 'mcap', signal.SIGINT)
    with open(out / 'bag.mcap', 'rb') as f:
        got = [(ch.topic, m.log_time, sc.name, m.data)
               for sc, ch, m in make_reader(f).iter_messages(log_time_order=True)]
    assert sorted(got) == sorted((t, ns, ty, bytes(raw)) for t, ty, ns, raw in rows)


def test_record_sqlite3_stopped_by_sigterm(ros, tmp_path):
    out, _ = _record_subprocess(ros, tmp_path, 'sqlite3', signal.SIGTERM)
    assert (out / 'bag.db3').is_file()


def test_recorder_in_process_duration_and_missing_topic(ros, tmp_path):
    ctx, node, _ = ros
    rnode = Node('inprocess_recorder', context=ctx)
    rex = SingleThreadedExecutor(context=ctx)
    rex.add_node(rnode)
    pub = node.create_publisher(String, '/rec/inproc', RELIABLE)
    out = tmp_path / 'inproc'
    texts = [f'm{k}' for k in range(50)]

    def publish():
        deadline = time.monotonic() + 20
        while not pub.get_subscription_count() and time.monotonic() < deadline:
            time.sleep(0.01)
        for text in texts:
            pub.publish(String(data=text))
        pub.wait_for_all_acked(rclpy.duration.Duration(seconds=10))

    thread = threading.Thread(target=publish)
    thread.start()
    try:
        with BagRecorder(rnode, out, ['/rec/inproc', '/rec/nobody'], 'sqlite3') as rec:
            rec.spin(rex, duration=2.5)
            assert not out.exists()
    finally:
        thread.join()
        node.destroy_publisher(pub)
        rex.shutdown()
        rnode.destroy_node()
    assert rec.missing == ['/rec/nobody'] and 'no publisher seen' in rec.summary()
    with open_bag(out) as r:
        assert r.topics == {'/rec/inproc': STRING}
        assert [m.data for _, _, _, m in iter_messages(r)] == texts


def test_recorder_without_any_publisher_leaves_no_bag(ros, tmp_path):
    ctx, _, _ = ros
    rnode = Node('lonely_recorder', context=ctx)
    rex = SingleThreadedExecutor(context=ctx)
    rex.add_node(rnode)
    out = tmp_path / 'none'
    try:
        with pytest.raises(IdentificationError, match='none of the topics'):
            with BagRecorder(rnode, out, ['/rec/ghost']) as rec:
                rec.spin(rex, discovery_timeout=0.3)
    finally:
        rex.shutdown()
        rnode.destroy_node()
    assert list(tmp_path.iterdir()) == []
