"""Tests of bags.reader, bags.writer and wire.cdr: rosbag2 reading/writing and the fast JointState
CDR codec.

Independent truths: the rosbags serializer/deserializer and AnyReader, the `mcap` library's
own reader, rclpy's rmw serializer (if importable), and the values written.
"""
import math
import shutil
import tracemalloc

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader

from identification_node.bags.reader import (STORAGES, iter_joint_state_blocks, iter_joint_states,
                                             iter_messages, open_bag, read_string_topic)
from identification_node.bags.writer import (BagWriter, make_diagnostic_array,
                                             make_float64_multi_array, make_joint_state,
                                             make_joint_trajectory, make_string)
from identification_node.errors import IdentificationError
from identification_node.wire.cdr import (CLOCK, DIAGNOSTIC_ARRAY, FLOAT64_MULTI_ARRAY,
                                          JOINT_STATE, JOINT_TRAJECTORY, JointStateDecoder, STRING,
                                          decode_joint_state, decode_joint_state_reference,
                                          encode_joint_state, encode_joint_states, jazzy_typestore)
from identification_node.wire.records import JointStateRecord

TS = jazzy_typestore()
T0 = 1_700_000_000_000_000_000  # log time origin [ns]
ARM = ('shoulder', 'elbow', 'wrist')


def _random_joint_state(rng, k):
    """Random JointState fields covering empty arrays, unicode names, odd string lengths."""
    n = int(rng.integers(0, 8))
    alphabet = list('abcxyz_0123') + ['é', 'ß', '関', '節', '🦾']
    names = [''.join(rng.choice(alphabet, size=int(rng.integers(0, 12)))) + str(i)
             for i in range(n)]
    arrays = []
    for _ in range(3):
        size = n if rng.random() < 0.7 else int(rng.integers(0, 3))
        vals = rng.standard_normal(size) * 10.0 ** rng.integers(-3, 4)
        if size and rng.random() < 0.2:
            vals[rng.integers(size)] = rng.choice([np.nan, np.inf, -np.inf, -0.0])
        arrays.append(vals)
    stamp = float(rng.integers(-5, 2_000_000_000)) + int(rng.integers(0, 10**9)) * 1e-9
    frame = ''.join(rng.choice(list('base_link/é'), size=int(rng.integers(0, 9))))
    return stamp, names, arrays, frame


def _assert_msg(msg, stamp, names, arrays):
    assert msg.stamp_ns * 1e-9 == pytest.approx(stamp, abs=2e-9 * max(1.0, abs(stamp)))
    assert msg.names == tuple(names)
    for got, want in zip((msg.position, msg.velocity, msg.effort), arrays):
        assert got.dtype == np.float64 and got.ndim == 1
        np.testing.assert_array_equal(got, want)


# ---------------------------------------------------------------------------------------
# CDR codec
# ---------------------------------------------------------------------------------------

def test_encoder_byte_identical_to_rosbags_and_decoders_agree():
    rng = np.random.default_rng(1)
    dec = JointStateDecoder()  # one instance: exercises the names cache across msgs
    for k in range(600):
        stamp, names, arrays, frame = _random_joint_state(rng, k)
        ref_msg = make_joint_state(stamp, names, *arrays, frame_id=frame)
        ref = bytes(TS.serialize_cdr(ref_msg, JOINT_STATE, little_endian=True))
        assert encode_joint_state(stamp, names, *arrays, frame_id=frame) == ref
        fast = dec(ref)
        slow = decode_joint_state_reference(ref)
        rb = TS.deserialize_cdr(ref, JOINT_STATE)
        exact = rb.header.stamp.sec * 1_000_000_000 + rb.header.stamp.nanosec
        assert fast.stamp_ns == slow.stamp_ns == exact
        assert fast.names == slow.names == tuple(rb.name)
        for f, s, r in zip(fast[2:5], slow[2:5], (rb.position, rb.velocity, rb.effort)):
            np.testing.assert_array_equal(f, s)
            np.testing.assert_array_equal(f, r)
        _assert_msg(fast, stamp, names, arrays)


def test_batch_encoder_byte_identical_to_rosbags():
    rng = np.random.default_rng(7)
    Time, Header = TS.types['builtin_interfaces/msg/Time'], TS.types['std_msgs/msg/Header']
    for k in range(40):
        _, names, _, _ = _random_joint_state(rng, k)
        N, n = int(rng.integers(0, 6)), len(names)
        stamps = rng.integers(-3 * 10**9, 2 * 10**18, N)
        fields = [None if rng.random() < 0.3 else rng.standard_normal((N, n)) for _ in range(3)]
        if N and n and fields[0] is not None:
            fields[0] = np.asfortranarray(fields[0])   # any memory layout
            fields[0][0, 0] = np.nan
        got = encode_joint_states(stamps, names, *fields)
        assert len(got) == N
        for i, raw in enumerate(got):
            sec, nsec = divmod(int(stamps[i]), 10**9)
            msg = TS.types[JOINT_STATE](Header(Time(sec, nsec), ''), list(names), *(
                np.empty(0) if f is None else np.ascontiguousarray(f[i]) for f in fields))
            assert raw == bytes(TS.serialize_cdr(msg, JOINT_STATE, little_endian=True))


def test_fast_decoder_on_repeated_names_with_shifting_alignment():
    # same names, frame_id lengths shift the name block by 0..3 bytes: cache must stay right
    dec = JointStateDecoder()
    for k in range(40):
        frame = 'f' * (k % 7)
        names = ARM if k % 5 else ('a', 'bb', 'ccc')
        pos = np.arange(len(names)) + k
        raw = encode_joint_state(k * 0.01, names, pos, (), pos * 2, frame_id=frame)
        msg = dec(raw)
        assert msg.names == tuple(names)
        np.testing.assert_array_equal(msg.position, pos)
        assert msg.velocity.size == 0
        np.testing.assert_array_equal(msg.effort, pos * 2)


def test_big_endian_falls_back_to_rosbags():
    msg = make_joint_state(12.25, ARM, [1.0, -2.0, np.nan], [], [0.5, 0.25, 8.0])
    raw = bytes(TS.serialize_cdr(msg, JOINT_STATE, little_endian=False))
    assert raw[:2] == b'\x00\x00'
    out = JointStateDecoder()(raw)
    _assert_msg(out, 12.25, ARM, ([1.0, -2.0, np.nan], [], [0.5, 0.25, 8.0]))
    assert out.stamp_ns == 12_250_000_000


def test_trailing_padding_is_tolerated():
    raw = encode_joint_state(1.5, ARM, [1, 2, 3], [4, 5, 6], [])
    for extra in (b'\0' * 4, b'\0' * 8, b'\0' * 16):
        _assert_msg(decode_joint_state(raw + extra), 1.5, ARM, ([1, 2, 3], [4, 5, 6], []))
        ref = decode_joint_state_reference(raw + extra)
        _assert_msg(ref, 1.5, ARM, ([1, 2, 3], [4, 5, 6], []))


def test_rclpy_serialized_messages_decode():
    serialization = pytest.importorskip('rclpy.serialization')
    sensor_msgs = pytest.importorskip('sensor_msgs.msg')
    rng = np.random.default_rng(7)
    dec = JointStateDecoder()
    for k in range(200):
        stamp, names, arrays, frame = _random_joint_state(rng, k)
        stamp = abs(stamp)
        msg = sensor_msgs.JointState()
        sec, nsec = math.floor(stamp), round((stamp - math.floor(stamp)) * 1e9)
        sec, nsec = (sec + 1, 0) if nsec == 10**9 else (sec, nsec)
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(sec), int(nsec)
        msg.header.frame_id = frame
        msg.name = names
        msg.position, msg.velocity, msg.effort = (a.tolist() for a in arrays)
        raw = bytes(serialization.serialize_message(msg))
        _assert_msg(dec(raw), sec + nsec * 1e-9, names, arrays)
        _assert_msg(decode_joint_state_reference(raw), sec + nsec * 1e-9, names, arrays)


@pytest.mark.parametrize('cut', [1, 3, 9, 20, 30])
def test_truncated_or_garbage_cdr_raises(cut):
    raw = encode_joint_state(1.0, ARM, [1, 2, 3], [4, 5, 6], [7, 8, 9])
    with pytest.raises(IdentificationError, match='JointState'):
        decode_joint_state(raw[:-cut] if cut < 30 else raw[:cut])
    with pytest.raises(IdentificationError, match='not CDR'):
        decode_joint_state(b'\x07\x07' + raw[2:])


# ---------------------------------------------------------------------------------------
# Writing and reading bags
# ---------------------------------------------------------------------------------------

URDF = '<robot name="r\u00e9">\n  <link name="base"/>\n</robot>\n'


def _expected_stream():
    """(topic, log_ns, stamp, names, pos, vel, eff) with varying name order, NaN, empty vel."""
    rng = np.random.default_rng(3)
    rows = []
    for i in range(50):
        order = list(ARM) if i % 3 else list(ARM[::-1])
        pos = rng.standard_normal(3)
        vel = rng.standard_normal(3) if i % 4 else np.empty(0)
        eff = rng.standard_normal(3)
        if i == 7:
            pos[1] = np.nan
            eff[:] = np.nan
        # second topic interleaves in log time, written out of order with the first
        rows.append(('/joint_states', T0 + 2 * i * 1_000_000, 100.0 + 0.002 * i, order,
                     pos, vel, eff))
        if i % 2:
            rows.append(('/arm/joint_states', T0 + (2 * i + 1) * 1_000_000, 200.0 + 0.002 * i,
                         ['gripper'], pos[:1], [], []))
    return rows


def _write_bag(path, storage):
    rows = _expected_stream()
    with BagWriter(path, storage) as w:
        w.write_string('/robot_description', T0 - 1, 'old')
        w.write_string('/robot_description', T0, URDF)
        for topic, t_ns, stamp, names, pos, vel, eff in reversed(rows):
            w.write_joint_state(topic, t_ns, stamp, names, pos, vel, eff)
        for j in range(3):
            w.write_clock(T0 + j)
        w.write('/cmd', T0 + 5, make_float64_multi_array([[1.0, 2.0], [3.0, 4.5]],
                                                         ('row', 'col')))
        w.write('/diagnostics', T0 + 6, make_diagnostic_array(
            1.5, [(1, 'ident', 'warm-up', 'arm', {'cond': '1e3'})]))
        w.write('/trajectory', T0 + 7, make_joint_trajectory(
            2.0, ARM, [0.5, 1.0], np.ones((2, 3)), velocities=np.zeros((2, 3))))
    return rows


@pytest.fixture(params=STORAGES)
def written(request, tmp_path):
    path = tmp_path / f'bag_{request.param}'
    rows = _write_bag(path, request.param)
    return path, request.param, rows


def test_layout_and_metadata(written):
    path, storage, rows = written
    suffix = '.mcap' if storage == 'mcap' else '.db3'
    assert sorted(p.name for p in path.iterdir()) == sorted(['metadata.yaml', path.name + suffix])
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temp leftovers
    meta = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['storage_identifier'] == storage
    assert meta['message_count'] == len(rows) + 2 + 3 + 3
    with Reader(path) as r:
        qos = {c.topic: c.ext.offered_qos_profiles[0].durability for c in r.connections}
    assert qos['/robot_description'] == QosDurability.TRANSIENT_LOCAL
    assert qos['/joint_states'] == QosDurability.VOLATILE


def test_our_reader(written):
    path, _, rows = written
    with open_bag(path) as bag:
        assert bag.topics == {
            '/robot_description': STRING, '/joint_states': JOINT_STATE,
            '/arm/joint_states': JOINT_STATE, '/clock': CLOCK,
            '/cmd': FLOAT64_MULTI_ARRAY, '/diagnostics': DIAGNOSTIC_ARRAY,
            '/trajectory': JOINT_TRAJECTORY}
        assert bag.topic_counts['/joint_states'] == 50
        assert bag.topic_counts['/arm/joint_states'] == 25
        assert bag.message_count == len(rows) + 8
        assert bag.start_ns == T0 - 1
        assert bag.end_ns == rows[-1][1]
        assert bag.duration == pytest.approx((rows[-1][1] - T0 + 1) * 1e-9)
        got = list(iter_joint_states(bag, ['/joint_states', '/arm/joint_states']))
        assert len(got) == len(rows)
        for (topic, log_ns, msg), (etopic, t_ns, stamp, names, pos, vel, eff) in zip(got, rows):
            assert topic == etopic
            assert log_ns == t_ns
            _assert_msg(msg, stamp, names, (pos, vel, eff))
        only = [m for _, _, m in iter_joint_states(bag, '/arm/joint_states')]
        assert [m.names for m in only] == [('gripper',)] * 25
        assert read_string_topic(bag, '/robot_description') == URDF
        assert read_string_topic(bag, '/not_there') is None
        generic = {t: (ty, ns, m) for t, ty, ns, m in iter_messages(
            bag, ['/cmd', '/diagnostics', '/trajectory', '/clock'])}
    _check_generic(generic)


def _check_generic(generic):
    _, ns, cmd = generic['/cmd']
    assert ns == T0 + 5
    np.testing.assert_array_equal(cmd.data, [1.0, 2.0, 3.0, 4.5])
    dims = [(d.label, d.size, d.stride) for d in cmd.layout.dim]
    assert dims == [('row', 2, 4), ('col', 2, 2)]
    _, _, diag = generic['/diagnostics']
    st = diag.status[0]
    assert (st.level, st.name, st.message, st.hardware_id) == (1, 'ident', 'warm-up', 'arm')
    assert [(kv.key, kv.value) for kv in st.values] == [('cond', '1e3')]
    assert (diag.header.stamp.sec, diag.header.stamp.nanosec) == (1, 500_000_000)
    _, _, traj = generic['/trajectory']
    assert list(traj.joint_names) == list(ARM)
    assert [(p.time_from_start.sec, p.time_from_start.nanosec) for p in traj.points] == [
        (0, 500_000_000), (1, 0)]
    np.testing.assert_array_equal(traj.points[1].positions, np.ones(3))
    np.testing.assert_array_equal(traj.points[0].velocities, np.zeros(3))
    assert traj.points[0].accelerations.size == 0
    ty, ns, clock = generic['/clock']  # the last one
    assert ty == CLOCK and ns == T0 + 2
    assert (clock.clock.sec, clock.clock.nanosec) == divmod(T0 + 2, 10**9)


def test_rosbags_anyreader_reads_our_bag(written):
    path, _, rows = written
    with AnyReader([path]) as reader:  # uses the definitions embedded in the bag
        conns = [c for c in reader.connections if c.msgtype == JOINT_STATE]
        got = [(c.topic, t, reader.deserialize(raw, c.msgtype))
               for c, t, raw in reader.messages(connections=conns)]
        robot = [reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages(
            connections=[c for c in reader.connections if c.topic == '/robot_description'])]
    assert robot == ['old', URDF]
    assert len(got) == len(rows)
    for (topic, t_ns, msg), (etopic, et, stamp, names, pos, vel, eff) in zip(got, rows):
        assert (topic, t_ns) == (etopic, et)
        assert msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 == pytest.approx(stamp)
        assert list(msg.name) == list(names)
        np.testing.assert_array_equal(msg.position, pos)
        np.testing.assert_array_equal(msg.velocity, vel)
        np.testing.assert_array_equal(msg.effort, eff)


def test_mcap_library_reads_our_mcap(tmp_path):
    from mcap.reader import make_reader
    path = tmp_path / 'bag'
    rows = _write_bag(path, 'mcap')
    with open(path / 'bag.mcap', 'rb') as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary.statistics.message_count == len(rows) + 8
        got = [(ch.topic, m.log_time, sc.name, m.data) for sc, ch, m in reader.iter_messages(
            topics=['/joint_states', '/arm/joint_states'])]
        schemas = {s.name: s.encoding for s in summary.schemas.values()}
    assert schemas[JOINT_STATE] == 'ros2msg'
    assert len(got) == len(rows)
    for (topic, t_ns, schema, data), (etopic, et, stamp, names, pos, vel, eff) in zip(got, rows):
        assert (topic, t_ns, schema) == (etopic, et, JOINT_STATE)
        msg = TS.deserialize_cdr(data, schema)
        assert list(msg.name) == list(names)
        np.testing.assert_array_equal(msg.position, pos)
        np.testing.assert_array_equal(msg.velocity, vel)
        np.testing.assert_array_equal(msg.effort, eff)


def test_write_raw_rclpy_bytes_roundtrip(tmp_path):
    serialization = pytest.importorskip('rclpy.serialization')
    sensor_msgs = pytest.importorskip('sensor_msgs.msg')
    path = tmp_path / 'rec'
    with BagWriter(path) as w:
        w.add_topic('/joint_states', JOINT_STATE)
        for i in range(20):
            msg = sensor_msgs.JointState()
            msg.header.stamp.sec, msg.header.stamp.nanosec = i, 250_000_000
            msg.name = list(ARM)
            msg.position = [float(i), 0.0, -1.0]
            msg.effort = [] if i % 2 else [1.0, 2.0, 3.0]
            w.write_raw('/joint_states', T0 + i, serialization.serialize_message(msg))
    with open_bag(path) as bag:
        got = [m for _, _, m in iter_joint_states(bag, '/joint_states')]
    assert [m.stamp_ns for m in got] == [i * 1_000_000_000 + 250_000_000 for i in range(20)]
    assert [m.position[0] for m in got] == list(range(20))
    assert [m.effort.size for m in got] == [0 if i % 2 else 3 for i in range(20)]


def test_lone_mcap_without_metadata(tmp_path):
    path = tmp_path / 'bag'
    rows = _write_bag(path, 'mcap')
    (path / 'metadata.yaml').unlink()
    for target in (path, path / 'bag.mcap'):
        with open_bag(target) as bag:
            assert bag.topic_counts['/joint_states'] == 50
            n = sum(1 for _ in iter_joint_states(bag, '/joint_states'))
            assert n == 50
            assert bag.message_count == len(rows) + 8


# ---------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------

def _one_topic_bag(path, storage='mcap', n=200):
    with BagWriter(path, storage) as w:
        for i in range(n):
            w.write_joint_state('/joint_states', T0 + i * 1000, i * 1e-3, ARM, [i, 0, 0])
    return path


def test_missing_and_non_bag_paths(tmp_path):
    with pytest.raises(IdentificationError, match='does not exist'):
        open_bag(tmp_path / 'nope')
    (tmp_path / 'empty_dir').mkdir()
    with pytest.raises(IdentificationError, match='no metadata.yaml'):
        open_bag(tmp_path / 'empty_dir')
    (tmp_path / 'notes.txt').write_text('hi')
    with pytest.raises(IdentificationError, match='.mcap/.db3'):
        open_bag(tmp_path / 'notes.txt')
    two = tmp_path / 'two'
    two.mkdir()
    for name in ('a', 'b'):
        _one_topic_bag(tmp_path / name)
        shutil.copy(tmp_path / name / f'{name}.mcap', two)
    with pytest.raises(IdentificationError, match='several storage files.*a.mcap, b.mcap'):
        open_bag(two)


@pytest.mark.parametrize('keep', [0.0, 0.3, 0.7, 0.99])
def test_truncated_mcap(tmp_path, keep):
    path = _one_topic_bag(tmp_path / 'bag')
    f = path / 'bag.mcap'
    data = f.read_bytes()
    f.write_bytes(data[:int(len(data) * keep)])
    with pytest.raises(IdentificationError, match=r"bag '.*bag'.*(truncated|empty)"):
        open_bag(path)


def test_garbage_sqlite(tmp_path):
    path = _one_topic_bag(tmp_path / 'bag', 'sqlite3')
    (path / 'bag.db3').write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(IdentificationError, match='sqlite3 storage file is corrupt'):
        open_bag(path)


def test_unknown_storage_and_bad_metadata(tmp_path):
    path = _one_topic_bag(tmp_path / 'bag')
    meta = path / 'metadata.yaml'
    text = meta.read_text()
    meta.write_text(text.replace('storage_identifier: mcap', 'storage_identifier: foo'))
    with pytest.raises(IdentificationError, match="unsupported storage.*'foo'"):
        open_bag(path)
    meta.write_text('{{{ not yaml')
    with pytest.raises(IdentificationError, match='metadata'):
        open_bag(path)


@pytest.mark.parametrize('storage', STORAGES)
def test_empty_bag(tmp_path, storage):
    path = tmp_path / 'bag'
    with BagWriter(path, storage) as w:
        w.add_topic('/joint_states', JOINT_STATE)
    with pytest.raises(IdentificationError, match='contains no messages'):
        open_bag(path)
    with open_bag(path, allow_empty=True) as bag:
        assert bag.message_count == 0 and bag.topics == {'/joint_states': JOINT_STATE}
        assert list(iter_joint_states(bag, '/joint_states')) == []
    (tmp_path / 'zero.mcap').write_bytes(b'')
    with pytest.raises(IdentificationError, match='empty'):
        open_bag(tmp_path / 'zero.mcap')


def test_missing_topic_and_wrong_type(tmp_path):
    path = tmp_path / 'bag'
    with BagWriter(path) as w:
        w.write_joint_state('/joint_states', T0, 0.0, ARM, [0, 0, 0])
        w.write_string('/robot_description', T0, URDF)
    with open_bag(path) as bag:
        with pytest.raises(IdentificationError) as err:
            list(iter_joint_states(bag, ['/joint_states', '/arm/joint_states']))
        assert "'/arm/joint_states'" in str(err.value)
        assert '/joint_states [sensor_msgs/msg/JointState]' in str(err.value)
        assert '/robot_description [std_msgs/msg/String]' in str(err.value)
        with pytest.raises(IdentificationError,
                           match="'/robot_description'.*std_msgs/msg/String.*JointState"):
            list(iter_joint_states(bag, '/robot_description'))
        with pytest.raises(IdentificationError, match="'/joint_states'.*JointState.*String"):
            read_string_topic(bag, '/joint_states')


def test_corrupt_message_in_bag_names_topic(tmp_path):
    path = tmp_path / 'bag'
    good = encode_joint_state(0.0, ARM, [1, 2, 3])
    with BagWriter(path) as w:
        w.add_topic('/joint_states', JOINT_STATE)
        w.write_raw('/joint_states', T0, good)
        w.write_raw('/joint_states', T0 + 1, good[:-5])
    with open_bag(path) as bag:
        it = iter_joint_states(bag, '/joint_states')
        assert next(it)[2].names == ARM
        with pytest.raises(IdentificationError, match=f"'/joint_states' at log time {T0 + 1}"):
            next(it)


# ---------------------------------------------------------------------------------------
# Atomic writing
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize('storage', STORAGES)
def test_exception_leaves_no_output(tmp_path, storage):
    path = tmp_path / 'bag'
    with pytest.raises(RuntimeError, match='boom'):
        with BagWriter(path, storage) as w:
            w.write_joint_state('/joint_states', T0, 0.0, ARM, [0, 0, 0])
            raise RuntimeError('boom')
    assert list(tmp_path.iterdir()) == []


def test_overwrite_refused_and_replaced_only_on_success(tmp_path):
    path = _one_topic_bag(tmp_path / 'bag', n=10)
    with pytest.raises(IdentificationError, match='exists already.*overwrite=True'):
        BagWriter(path)
    with pytest.raises(RuntimeError):
        with BagWriter(path, 'sqlite3', overwrite=True) as w:
            w.write_joint_state('/joint_states', T0, 0.0, ARM, [0, 0, 0])
            raise RuntimeError('boom')
    with open_bag(path) as bag:  # the old bag is intact
        assert bag.message_count == 10
    with BagWriter(path, 'sqlite3', overwrite=True) as w:
        w.write_joint_state('/joint_states', T0, 0.0, ARM, [0, 0, 0])
    assert sorted(p.name for p in path.iterdir()) == ['bag.db3', 'metadata.yaml']
    with open_bag(path) as bag:
        assert bag.message_count == 1
    assert [p.name for p in tmp_path.iterdir()] == ['bag']
    assert not any(p.name.startswith('.') for p in tmp_path.iterdir())


def test_writer_input_errors(tmp_path):
    with pytest.raises(IdentificationError, match='unknown bag storage'):
        BagWriter(tmp_path / 'x', 'rosbag1')
    with BagWriter(tmp_path / 'bag') as w:
        with pytest.raises(IdentificationError, match='add_topic'):
            w.write_raw('/joint_states', T0, b'\x00\x01\x00\x00')
        with pytest.raises(IdentificationError, match='unknown message type'):
            w.add_topic('/x', 'my_msgs/msg/Nope')
        w.add_topic('/joint_states', JOINT_STATE)
        with pytest.raises(IdentificationError, match='already added'):
            w.add_topic('/joint_states', STRING)
        with pytest.raises(IdentificationError, match='not finite'):
            w.write_joint_state('/joint_states', T0, math.nan, ARM, [0, 0, 0])
    with pytest.raises(IdentificationError, match='closed'):
        w.write_joint_state('/joint_states', T0, 0.0, ARM, [0, 0, 0])


# ---------------------------------------------------------------------------------------
# Streaming memory
# ---------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize('storage', STORAGES)
def test_streaming_read_memory_is_flat(tmp_path, storage):
    n = 100_000
    path = tmp_path / 'big'
    raw = encode_joint_state(0.0, ARM, [0.1, 0.2, 0.3], [0.0] * 3, [1.0] * 3)
    with BagWriter(path, storage) as w:
        w.add_topic('/joint_states', JOINT_STATE)
        for i in range(n):
            w.write_raw('/joint_states', T0 + i * 1_000_000, raw)
    bag_bytes = sum(p.stat().st_size for p in path.iterdir())
    assert bag_bytes > n * len(raw)
    with open_bag(path) as bag:
        tracemalloc.start()
        try:
            count, last = 0, None
            for _, log_ns, msg in iter_joint_states(bag, '/joint_states'):
                count += 1
                last = log_ns
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    assert count == n and last == T0 + (n - 1) * 1_000_000
    assert peak < bag_bytes / 4, (peak, bag_bytes)
    with open_bag(path) as bag:  # blocks: one chunk (1 MiB) at a time
        tracemalloc.start()
        try:
            count = 0
            for log_ns, _ in iter_joint_state_blocks(bag, '/joint_states'):
                count += len(log_ns)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    assert count == n and peak < bag_bytes / 4, (peak, bag_bytes)


@pytest.mark.parametrize('storage', STORAGES)
def test_custom_type_read_from_embedded_definition(tmp_path, storage):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg('float64 x\nstring label\nint32[] ids\n',
                                      'my_msgs/msg/Foo'))
    path = tmp_path / 'bag'
    foo = store.types['my_msgs/msg/Foo']
    with BagWriter(path, storage, typestore=store) as w:
        w.write('/foo', T0 + 1, foo(x=1.5, label='b', ids=np.array([3, 4], np.int32)))
        w.write('/foo', T0, foo(x=-2.0, label='a', ids=np.array([], np.int32)))
    with open_bag(path) as bag:  # its typestore is Jazzy, without my_msgs
        assert 'my_msgs/msg/Foo' not in jazzy_typestore().types
        got = [(t, ns, m.x, m.label, list(m.ids)) for t, _, ns, m in iter_messages(bag)]
    assert got == [('/foo', T0, -2.0, 'a', []), ('/foo', T0 + 1, 1.5, 'b', [3, 4])]


# ---------------------------------------------------------------------------------------
# Block reading (iter_joint_state_blocks) against message-by-message reading
# ---------------------------------------------------------------------------------------

def _blocks_as_messages(bag, topic):
    """iter_joint_state_blocks flattened to (log ns, record), and how many items it yielded."""
    out, items = [], 0
    for log, rec in iter_joint_state_blocks(bag, topic):
        items += 1
        if np.ndim(rec.stamp_ns) == 0:
            assert len(log) == 1
            out.append((int(log[0]), rec))
            continue
        assert rec.position.ndim == rec.velocity.ndim == rec.effort.ndim == 2
        assert len(log) == len(rec.stamp_ns) == len(rec.position) > 1
        for i in range(len(log)):
            out.append((int(log[i]), JointStateRecord(
                int(rec.stamp_ns[i]), rec.names, rec.position[i], rec.velocity[i],
                rec.effort[i])))
    return out, items


def _assert_blocks_match(path, topic):
    """Same messages, order, log times, stamps, names and values (NaN included) as
    iter_joint_states; returns how many items the block reader yielded."""
    with open_bag(path) as bag:
        want = [(t, m) for _, t, m in iter_joint_states(bag, [topic])]
    with open_bag(path) as bag:
        got, items = _blocks_as_messages(bag, topic)
    assert len(got) == len(want)
    for (t, m), (et, em) in zip(got, want):
        assert t == et and m.stamp_ns == em.stamp_ns and m.names == em.names
        for a, b in zip(m[2:], em[2:]):
            assert a.dtype == np.float64 and a.shape == b.shape
            np.testing.assert_array_equal(a, b)
    return items


def test_blocks_equal_messages_with_changing_layouts(written):
    path, storage, rows = written
    # name order, velocity presence and frame change: runs of one layout are short here
    for topic in ('/joint_states', '/arm/joint_states'):
        items = _assert_blocks_match(path, topic)
        if storage == 'mcap' and topic == '/arm/joint_states':
            assert items == 1  # 25 messages of one layout: one block


def _long_bag(path, n, compression=None, order=None, frame=lambda i: 'base'):
    """n joint states (3 joints, 1 kHz) over several 1 MiB mcap chunks, interleaved with a
    String topic; ``order`` permutes the writing order, ``compression`` (rosbags
    CompressionMode) compresses."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat
    rng = np.random.default_rng(5)
    vals = rng.standard_normal((n, 3, 3))
    vals[17, 1, 2] = np.nan
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compression is not None:
        writer.set_compression(compression, CompressionFormat.ZSTD)
    with writer:
        js = writer.add_connection('/joint_states', JOINT_STATE, typestore=TS)
        text = writer.add_connection('/text', STRING, typestore=TS)
        for i in (range(n) if order is None else order):
            t = T0 + i * 1_000_000
            writer.write(js, t, encode_joint_state(
                i * 1e-3, ARM, *vals[i], frame_id=frame(i)))
            if i % 100 == 0:
                writer.write(text, t, TS.serialize_cdr(make_string('x' * (i % 7)),
                                                       STRING))
    return path


@pytest.mark.slow
def test_blocks_from_several_chunks_plain_and_compressed(tmp_path):
    from rosbags.rosbag2.enums import CompressionMode
    for name, compression in (('plain', None), ('zstd', CompressionMode.STORAGE)):
        path = _long_bag(tmp_path / name, 15000, compression)
        from mcap.reader import make_reader
        with open(next(path.glob('*.mcap')), 'rb') as f:
            kinds = [c.compression for c in make_reader(f).get_summary().chunk_indexes]
        assert len(kinds) >= 3 and set(kinds) == ({''} if compression is None else {'zstd'})
        items = _assert_blocks_match(path, '/joint_states')
        assert items <= 2 * len(kinds)  # ~5400 messages a chunk: blocks of <= 4096 rows


@pytest.mark.slow
def test_blocks_split_at_layout_changes_and_odd_messages(tmp_path):
    # the frame id changes (same message length) at 3 places, and one message is corrupt
    frames = {5000: 'bass', 5001: 'bass', 9000: 'b' * 9}
    path = _long_bag(tmp_path / 'bag', 12000, frame=lambda i: frames.get(i, 'base'))
    assert _assert_blocks_match(path, '/joint_states') < 12


@pytest.mark.slow
def test_blocks_fall_back_where_rosbags_merges_chunks(tmp_path):
    from rosbags.rosbag2.enums import CompressionMode
    # written backwards over several chunks: the chunks overlap in index order
    path = _long_bag(tmp_path / 'backwards', 13000, order=range(12999, -1, -1))
    assert _assert_blocks_match(path, '/joint_states') == 13000  # message by message
    # per-message compression: read message by message
    path = _long_bag(tmp_path / 'message', 300, CompressionMode.MESSAGE)
    assert _assert_blocks_match(path, '/joint_states') == 300


def test_blocks_of_sqlite3_and_lone_mcap(tmp_path):
    _write_bag(tmp_path / 'db', 'sqlite3')
    assert _assert_blocks_match(tmp_path / 'db', '/joint_states') == 50
    path = _one_topic_bag(tmp_path / 'lone')
    (path / 'metadata.yaml').unlink()
    assert _assert_blocks_match(path / 'lone.mcap', '/joint_states') == 1


def test_blocks_corrupt_message_names_topic_and_time(tmp_path):
    path = tmp_path / 'bag'
    good = encode_joint_state(0.0, ARM, [1, 2, 3])
    with BagWriter(path) as w:
        w.add_topic('/joint_states', JOINT_STATE)
        for i in range(10):
            w.write_raw('/joint_states', T0 + i, good)
        w.write_raw('/joint_states', T0 + 10, good[:-5])
    with open_bag(path) as bag:
        it = iter_joint_state_blocks(bag, '/joint_states')
        log, block = next(it)
        assert len(log) == 10 and block.names == ARM
        with pytest.raises(IdentificationError, match=f"'/joint_states' at log time {T0 + 10}"):
            next(it)
    with open_bag(path) as bag:
        with pytest.raises(IdentificationError, match='not in bag'):
            next(iter_joint_state_blocks(bag, '/nope'))
