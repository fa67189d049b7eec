"""The node's input, lists of JointState CDR messages per processing run, decoded in blocks
(decode_joint_states) against rosbags' deserializer message by message."""
import struct

import numpy as np

from identification_node.bags.writer import make_joint_state
from identification_node.errors import IdentificationError
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.pipeline import IdentificationPipeline, PipelineConfig
from identification_node.wire.cdr import (JOINT_STATE, JointStateDecoder,
                                          decode_joint_state_reference, decode_joint_states,
                                          encode_joint_state, encode_joint_states, jazzy_typestore)

ARM3 = ('shoulder', 'elbow', 'wrist')


def _stamped(raw: bytes, stamp_ns: int) -> bytes:
    return raw[:4] + struct.pack('<iI', *divmod(int(stamp_ns), 10**9)) + raw[12:]


def _cdr_stream(robot, n_samples: int, seed: int):
    """CDR JointState messages of a simulated stream with every kind of bad message the
    pipeline must reject and layouts it must map (reordered names, an extra joint, frame ids
    shifting the alignment)."""
    traj = FourierTrajectory.random(robot, harmonics=4, period=5.0, seed=seed)
    t = np.arange(n_samples) / 1000.0
    sim = simulate_kinematic(robot, None, traj, t, SensorNoise(torque_std=0.3), seed=seed)
    stamps = 10**18 + np.round(t * 1e9).astype(np.int64)
    stamps[3000:] += 200_000_000            # a gap
    stamps[4500:] -= 3 * 10**9              # a restart
    names = list(robot.joint_names)
    rng = np.random.default_rng(seed)
    messages = []
    for k, stamp in enumerate(stamps):
        q, qd, tau = sim.q_meas[k], sim.qd_meas[k], sim.tau_meas[k]
        order, frame, extra = list(range(robot.dof)), '', k % 1013 == 7   # extra: NaN in it
        if k % 997 == 5:
            order = order[::-1]
        if k % 11 == 3:
            frame = 'f' * int(rng.integers(1, 8))
        row_names = [names[i] for i in order] + (['gripper'] if extra else [])
        arrays = [np.append(a[order], np.nan) if extra else a[order] for a in (q, qd, tau)]
        raw = encode_joint_state(0.0, row_names, *arrays, frame_id=frame)
        messages.append(_stamped(raw, stamp))

    def one(k, names=names, q=True, qd=True, tau=True, cut=None):
        return encode_joint_states(
            [stamps[k]], names, sim.q_meas[k:k + 1, :cut] if q is True else q,
            sim.qd_meas[k:k + 1, :cut] if qd else None,
            sim.tau_meas[k:k + 1, :cut] if tau else None)[0]
    msg = make_joint_state(0.0, names, sim.q_meas[808], sim.qd_meas[808],
                           sim.tau_meas[808])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamps[808]), 10**9)
    bad = {101: one(101, q=np.full((1, robot.dof), np.nan)), 202: messages[201],
           303: messages[290], 404: b'\x00\x01garbage', 505: one(505, qd=False),
           606: one(606, tau=False), 707: one(707, names=names[:-1], cut=-1),
           808: bytes(jazzy_typestore().serialize_cdr(msg, JOINT_STATE,
                                                      little_endian=False))}
    for k, raw in bad.items():
        messages[k] = raw
    return messages


def test_cdr_runs_give_what_records_decoded_by_rosbags_give():
    """Runs of 1-5 messages and of 300 (as the node polls them) through add_joint_state_cdr,
    and the same messages decoded one by one by rosbags into records: the same outputs, the
    same counted rejections (every reason the stream holds) and the same estimate."""
    robot = load_robot('mit_dd_arm', extras=('fv', 'fc'))
    messages = _cdr_stream(robot, 6000, seed=2)
    config = PipelineConfig(forgetting=0.999, coulomb_exclusion_speed=0.1)
    cdr, records = (IdentificationPipeline(robot, config) for _ in range(2))
    outs = [[], []]
    rng = np.random.default_rng(1)
    k = 0
    while k < len(messages):
        m = int(rng.integers(1, 6)) if k < 5000 else 300
        for p in (cdr, records):
            p.frozen = 2000 <= k < 2500
        cdr.add_joint_state_cdr(messages[k:k + m])
        for raw in messages[k:k + m]:
            try:
                records.add_joint_state(decode_joint_state_reference(raw))
            except IdentificationError:   # the garbage message
                records.add_malformed()
        for p, out in zip((cdr, records), outs):
            out.append(p.process())
        k += m
    fields = ('stamps_ns', 'q', 'qd', 'qdd', 'measured', 'predicted')
    got, ref = ({f: np.concatenate([getattr(o, f) for o in out]) for f in fields}
                for out in outs)
    assert len(got['stamps_ns']) > 5000
    np.testing.assert_array_equal(got['stamps_ns'], ref['stamps_ns'])
    for f in fields[1:]:
        np.testing.assert_allclose(got[f], ref[f], rtol=1e-9, atol=1e-9 * np.abs(ref[f]).max())
    expected = {'non_finite': 1, 'repeated_stamp': 1, 'out_of_order': 1, 'malformed': 1,
                'missing_velocity': 1, 'missing_effort': 1, 'missing_joints': 1}
    for p in (cdr, records):
        assert {r: c for r, c in p.rejected.items() if c and r != 'stream_restart'} == expected
        assert p.restarts == 1 and p.received == len(messages)
    assert cdr.excluded_rows == records.excluded_rows > 0
    a, b = cdr.estimate(), records.estimate()
    assert a.num_samples == b.num_samples > 5000
    np.testing.assert_allclose(a.values, b.values, rtol=1e-8, atol=1e-8 * np.abs(b.values).max())


def test_decode_joint_states_equals_rosbags_message_by_message():
    """Runs of one layout (frame ids of any length, NaN/inf/-0 values, negative stamps, empty
    arrays) come as blocks equal to the stacked records rosbags decodes one by
    one; messages of other layouts, big-endian or broken ones among them come alone (or as
    the error)."""
    rng = np.random.default_rng(11)
    dec = JointStateDecoder()
    good = encode_joint_states(np.arange(3) * 10**6, ARM3, *[np.ones((3, 3))] * 3)
    msg = make_joint_state(0.0, ARM3, [1.0, 2.0, 3.0], [], [])
    odd = [encode_joint_state(0.0, ('a', 'b', 'c'), *[[1.0, 2.0, 3.0]] * 3),
           encode_joint_state(0.0, ARM3, [1.0, 2.0, 3.0], [], [1.0, 2.0, 3.0]),
           bytes(jazzy_typestore().serialize_cdr(msg, JOINT_STATE,
                                                 little_endian=False)),
           good[0][:-9], good[0].replace(b'elbow', b'elb\xffw')]
    for k in range(60):
        names = [f'j{i}' + 'x' * int(rng.integers(0, 5)) for i in range(int(rng.integers(1, 8)))]
        if k % 3 == 0:
            names = ['shoulder', 'elbow']   # the same names again: from the cache
        M, n = int(rng.integers(1, 6)), len(names)
        widths = [n if rng.random() < 0.7 else 0 for _ in range(3)]
        values = [rng.standard_normal((M, w)) for w in widths]
        if widths[0]:
            values[0][0, 0], values[0][-1, -1] = np.inf, -0.0
        stamps = rng.integers(-3 * 10**9, 2 * 10**18, M)
        frame = 'f' * int(rng.integers(0, 8))
        messages = [_stamped(encode_joint_state(0.0, names, *(v[m] for v in values),
                                                frame_id=frame), t)
                    for m, t in enumerate(stamps)]
        extra = [odd[k % len(odd)]] if k % 2 else []
        messages = messages + extra + good
        decoded = list(decode_joint_states(messages, dec))
        rows = []
        for item in decoded:
            if isinstance(item, IdentificationError):
                rows.append(item)
            elif np.ndim(item.stamp_ns):
                assert item.stamp_ns.dtype == np.int64
                rows += [type(item)(item.stamp_ns[i], item.names,
                                    *(a[i] for a in item[2:])) for i in range(len(item[0]))]
            else:
                rows.append(item)
        assert len(rows) == len(messages)
        assert np.ndim(decoded[0].stamp_ns) == (M > 1)   # a run of one layout: one block
        for raw, row in zip(messages, rows):
            try:
                ref = decode_joint_state_reference(raw)
            except IdentificationError:
                assert isinstance(row, IdentificationError)
                continue
            assert row.names == ref.names and row.stamp_ns == ref.stamp_ns
            for f in range(2, 5):
                np.testing.assert_array_equal(row[f], ref[f])
                assert np.array_equal(np.signbit(row[f]), np.signbit(ref[f]))


def test_a_decoder_takes_no_layout_for_another_of_the_same_length():
    """The decoder keeps the last block's layout across polls: messages of the same length
    but other names, frame id or counts (in one poll and in the next) are decoded as
    rosbags decodes them, not read with the layout kept."""
    rng = np.random.default_rng(5)
    stamps = 10**18 + np.arange(4) * 10**6

    def batch(names, frame='ab', counts=(2, 2, 2)):
        return [_stamped(encode_joint_state(0.0, names, *(rng.standard_normal(c) for c in counts),
                                            frame_id=frame), t) for t in stamps]
    batches = [batch(('j1', 'j2')), batch(('k1', 'k2')), batch(('j1', 'j2'), 'cd'),
               batch(('j1', 'j2', 'j3'), counts=(3, 0, 3))]
    assert len({len(b[0]) for b in batches}) == 1   # one length: only the bytes tell them apart
    polls = batches + [batches[0][:2] + batches[1][:2] + batches[3][:1] + batches[0][2:]]
    dec = JointStateDecoder()
    for poll in polls:
        rows = []
        for item in decode_joint_states(poll, dec):
            assert not isinstance(item, IdentificationError)
            stamps_ns = np.atleast_1d(item.stamp_ns)
            arrays = [np.atleast_2d(a) if np.ndim(item.stamp_ns) == 0 else a for a in item[2:]]
            rows += [(t, item.names, *(a[i] for a in arrays)) for i, t in enumerate(stamps_ns)]
        assert len(rows) == len(poll)
        for raw, (stamp, names, *arrays) in zip(poll, rows):
            ref = decode_joint_state_reference(raw)
            assert names == ref.names and stamp == ref.stamp_ns
            for got, want in zip(arrays, ref[2:]):
                np.testing.assert_array_equal(got, want)
