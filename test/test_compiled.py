"""The compiled per-run step against the Python path it stands in for (smoother, pinocchio's
regressor, base rows, RLS), on the same streams."""
import os
import struct
from pathlib import Path

import numpy as np
import pytest

from identification_node import bagio, compiled
from identification_node.identifiability import BaseParameters
from identification_node.pipeline import IdentificationPipeline, PipelineConfig
from identification_node.records import JointStateRecord
from identification_node.robot import load_robot
from identification_node.signals import FixedLagSmoother
from identification_node.simulation import SensorNoise, simulate_kinematic
from identification_node.torque import JointTorqueConfig, TorqueConverter
from identification_node.trajectories import FourierTrajectory

FIXTURES = Path(__file__).parent / 'fixtures'
SIX = str(FIXTURES / 'six_dof_arm.urdf')
EXTRAS = ('fv', 'fc', 'fo', 'Ia')

if not compiled.AVAILABLE:
    # `make test` builds the extension: there its absence is a failure, not a skip
    if os.environ.get('IDENTIFICATION_NODE_REQUIRE_COMPILED') == '1':
        raise ImportError('identification_node._kernel is not built (see setup.py)')
    pytest.skip('identification_node._kernel not built', allow_module_level=True)


def close(actual, expected, rel):
    scale = max(np.abs(expected).max(), 1e-300)
    err = np.abs(np.asarray(actual) - expected).max()
    assert err <= rel * scale, f'max error {err:.3e} > {rel:g} * {scale:.3e}'


@pytest.mark.parametrize('name, joints, locked, extras, coulomb', [
    ('panda_like', None, None, (), 0.0),
    ('mit_dd_arm', None, None, EXTRAS, 0.0),
    ('crs_a465', None, None, EXTRAS, 0.05),
    (SIX, None, None, EXTRAS, 0.0),       # unaligned axes, a prismatic and a continuous joint
    (SIX, ['joint5', 'joint1', 'joint4', 'joint3'], {'joint2': 0.3, 'joint6': -1.1}, (), 0.0),
])
def test_regressor_equals_pinocchio(name, joints, locked, extras, coulomb):
    path = str(FIXTURES / 'panda_like.urdf') if name == 'panda_like' else name
    robot = load_robot(path, joints, extras=extras, locked_positions=locked,
                       coulomb_velocity=coulomb)
    step = compiled.make_step(robot, np.arange(3), 10, 3, 0.05)
    rng = np.random.default_rng(3)
    q, qd, qdd = rng.normal(size=(3, 20, robot.dof))
    qd[0, 0] = 0.0   # the Coulomb column's sign at rest
    close(step.regress(q, qd, qdd), robot.regressor(q, qd, qdd, method='pinocchio'), 1e-14)


def test_smoother_rows_and_prediction_equal_the_python_path():
    """Jittered stamps, a gap wider than max_gap (the windows restart), runs of 1 to 9
    samples; both channel layouts."""
    robot = load_robot(SIX, extras=EXTRAS)
    base = BaseParameters.from_robot(robot)
    n, N = robot.dof, 700
    rng = np.random.default_rng(5)
    t = np.arange(N) * 1e-3 + rng.uniform(-2e-4, 2e-4, N)
    t[400:] += 0.2
    theta = rng.normal(size=base.num_base)
    for c in (2, 3):
        x = np.cumsum(rng.normal(size=(N, c * n)), axis=0) * 1e-2
        step = compiled.make_step(robot, base.base_index, 10, 3, 0.05)
        smoother = FixedLagSmoother(c * n, 10, 3, 0.05)
        got, ref, k = [], [], 0
        while k < N:
            m = int(rng.integers(1, 10))
            got.append(step.push(t[k:k + m], x[k:k + m], theta, c == 3))
            ref.append(smoother.push(t[k:k + m], x[k:k + m]))
            k += m
        tc, q, qd, qdd, tau, rows, predicted = (np.concatenate(a) for a in zip(*got))
        t_ref, x_ref, xd_ref, xdd_ref = (np.concatenate(a) for a in zip(*ref))
        assert len(tc) == N - 2 * 2 * 10 and np.array_equal(tc, t_ref)
        close(q, x_ref[:, :n], 1e-12)
        close(tau, x_ref[:, -n:], 1e-12)
        if c == 3:
            close(qd, x_ref[:, n:2 * n], 1e-12)
            close(qdd, xd_ref[:, n:2 * n], 1e-9)
        else:
            close(qd, xd_ref[:, :n], 1e-10)
            close(qdd, xdd_ref[:, :n], 1e-9)
        Yb = robot.regressor(q, qd, qdd)[:, :, base.base_index]
        close(rows[:, :, :-1], Yb, 1e-12)
        assert np.array_equal(rows[:, :, -1], tau)
        close(predicted, Yb @ theta, 1e-12)
        assert step.buffered == 2 * 10
        step.reset()
        assert step.buffered == 0


def test_pipeline_compiled_equals_python():
    """The same messages through a pipeline with and one without the compiled step: same
    outputs, counters and estimate (Coulomb exclusion weights, a restart, a gap, frozen)."""
    robot = load_robot('mit_dd_arm', extras=('fv', 'fc'))
    traj = FourierTrajectory.random(robot, harmonics=4, period=5.0, seed=2)
    t = np.arange(6000) / 1000.0
    sim = simulate_kinematic(robot, None, traj, t, SensorNoise(torque_std=0.3), seed=2)
    stamps = 10**18 + np.round(t * 1e9).astype(np.int64)
    stamps[3000:] += 200_000_000            # a gap
    stamps[4500:] -= 3 * 10**9              # a restart
    records = [JointStateRecord(int(s), tuple(robot.joint_names), sim.q_meas[k],
                                sim.qd_meas[k], sim.tau_meas[k]) for k, s in enumerate(stamps)]
    records[100] = records[100]._replace(position=np.full(3, np.nan))
    pipes = [IdentificationPipeline(robot, PipelineConfig(compiled=flag, forgetting=0.999))
             for flag in (True, False)]
    assert pipes[0]._step is not None and pipes[1]._step is None
    outs = [[], []]
    rng = np.random.default_rng(1)
    k = 0
    while k < len(records):
        m = int(rng.integers(1, 8)) if k < 5000 else 400
        for p, out in zip(pipes, outs):
            p.frozen = 2000 <= k < 2500
            for r in records[k:k + m]:
                p.add_joint_state(r)
            out.append(p.process())
        k += m
    fields = ('stamps_ns', 'q', 'qd', 'qdd', 'measured', 'predicted')
    got, ref = ({f: np.concatenate([getattr(o, f) for o in out]) for f in fields}
                for out in outs)
    assert np.array_equal(got['stamps_ns'], ref['stamps_ns'])
    for f in fields[1:]:
        close(got[f], ref[f], 1e-9)
    a, b = (p.estimate() for p in pipes)
    assert pipes[0].rejected == pipes[1].rejected and pipes[0].rejected['non_finite'] == 1
    assert pipes[0].restarts == pipes[1].restarts == 1
    assert pipes[0].excluded_rows == pipes[1].excluded_rows > 0
    assert a.num_samples == b.num_samples
    close(a.values, b.values, 1e-8)
    close(a.stddev, b.stddev, 1e-7)


def _cdr_stream(robot, n_samples: int, seed: int):
    """CDR JointState messages of a simulated stream with every kind of bad message the
    pipeline must reject (each counted as the Python validation counts it) and layouts the
    compiled call must map (reordered names, an extra joint, frame ids shifting alignment)."""
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
        order, frame = list(range(robot.dof)), ''
        extra = False
        if k % 997 == 5:
            order = order[::-1]                         # reordered names
        if k % 1013 == 7:
            extra = True                                # an extra joint, NaN in it
        if k % 11 == 3:
            frame = 'f' * int(rng.integers(1, 8))       # alignment shifts
        row_names = [names[i] for i in order] + (['gripper'] if extra else [])
        arrays = [np.append(a[order], np.nan) if extra else a[order] for a in (q, qd, tau)]
        raw = bagio.encode_joint_state(0.0, row_names, *arrays, frame_id=frame)
        messages.append(raw[:4] + struct.pack('<iI', *divmod(int(stamp), 10**9)) + raw[12:])
    bad = {
        101: bagio.encode_joint_states([stamps[101]], names, np.full((1, robot.dof), np.nan),
                                       sim.qd_meas[101:102], sim.tau_meas[101:102])[0],
        202: messages[201],                                             # repeated stamp
        303: messages[290],                                             # out of order
        404: b'\x00\x01garbage',
        505: bagio.encode_joint_states([stamps[505]], names, sim.q_meas[505:506], None,
                                       sim.tau_meas[505:506])[0],       # no velocity
        606: bagio.encode_joint_states([stamps[606]], names, sim.q_meas[606:607],
                                       sim.qd_meas[606:607], None)[0],  # no effort
        707: bagio.encode_joint_states([stamps[707]], names[:-1], sim.q_meas[707:708, :-1],
                                       sim.qd_meas[707:708, :-1],
                                       sim.tau_meas[707:708, :-1])[0],  # a joint missing
    }
    msg = bagio.make_joint_state(0.0, names, sim.q_meas[808], sim.qd_meas[808],
                                 sim.tau_meas[808])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamps[808]), 10**9)
    bad[808] = bytes(bagio.jazzy_typestore().serialize_cdr(msg, bagio.JOINT_STATE,
                                                           little_endian=False))  # big-endian
    for k, raw in bad.items():
        messages[k] = raw
    return messages


def test_pipeline_on_cdr_messages_compiled_equals_python():
    """The node's input (CDR messages per run) through the compiled call and through the
    Python decoding and validation: same outputs, counters (every rejection reason the stream
    holds) and estimate; the compiled call takes the clean runs."""
    robot = load_robot('mit_dd_arm', extras=('fv', 'fc'))
    messages = _cdr_stream(robot, 6000, seed=2)
    pipes = [IdentificationPipeline(robot, PipelineConfig(compiled=flag, forgetting=0.999))
             for flag in (True, False)]
    reference = IdentificationPipeline(robot, PipelineConfig(compiled=False, forgetting=0.999))
    outs, runs = [[], [], []], 0
    rng = np.random.default_rng(1)
    k = 0
    while k < len(messages):
        m = int(rng.integers(1, 6)) if k < 5000 else 300
        for p, out in zip(pipes + [reference], outs):
            p.frozen = 2000 <= k < 2500
            if p is reference:   # decoded beforehand, record by record
                for raw in messages[k:k + m]:
                    try:
                        p.add_joint_state(bagio.decode_joint_state(raw))
                    except Exception:   # noqa: BLE001 (the garbage message)
                        p.add_malformed()
            else:
                p.add_joint_state_cdr(messages[k:k + m])
            out.append(p.process())
        k += m
        runs += 1
    fields = ('stamps_ns', 'q', 'qd', 'qdd', 'measured', 'predicted')
    got, python, ref = ({f: np.concatenate([getattr(o, f) for o in out]) for f in fields}
                        for out in outs)
    for other in (python, ref):
        assert np.array_equal(got['stamps_ns'], other['stamps_ns'])
        for f in fields[1:]:
            close(got[f], other[f], 1e-9)
    expected = {'non_finite': 1, 'repeated_stamp': 1, 'out_of_order': 1, 'malformed': 1,
                'missing_velocity': 1, 'missing_effort': 1, 'missing_joints': 1}
    for p in pipes + [reference]:
        assert {r: c for r, c in p.rejected.items() if c and r != 'stream_restart'} == expected
        assert p.restarts == 1 and p.received == len(messages)
    assert pipes[0].excluded_rows == pipes[1].excluded_rows > 0
    assert pipes[1].compiled_runs == 0 and pipes[0].compiled_runs > 0.9 * runs
    a, b = pipes[0].estimate(), pipes[1].estimate()
    assert a.num_samples == b.num_samples > 5000
    close(a.values, b.values, 1e-8)
    close(a.stddev, b.stddev, 1e-7)


def test_joint_state_filler_equals_numpy_encoder(monkeypatch):
    """bagio.encode_joint_states through the compiled filler and through its numpy path: the
    same bytes (negative stamps, empty fields, no message, any memory layout), and both
    decode back to the inputs."""
    rng = np.random.default_rng(4)
    for k in range(60):
        n = int(rng.integers(0, 8))
        names = [f'joint_{i}' * int(rng.integers(1, 4)) for i in range(n)]
        N = int(rng.integers(0, 6))
        stamps = rng.integers(-3 * 10**9, 2 * 10**18, N)
        fields = [None if rng.random() < 0.3 else rng.standard_normal((N, n)) for _ in range(3)]
        if fields[0] is not None and N and n:
            fields[0] = np.asfortranarray(fields[0])
            fields[0][0, 0] = np.nan
        got = bagio.encode_joint_states(stamps, names, *fields)
        with monkeypatch.context() as m:
            m.setattr(bagio, '_kernel', None)
            want = bagio.encode_joint_states(stamps, names, *fields)
        assert got == want and len(got) == N
        for i, raw in enumerate(got):
            back = bagio.decode_joint_state_reference(raw)
            assert back.stamp_ns == stamps[i] and back.names == tuple(names)
            for f, a in zip(fields, back[2:]):
                np.testing.assert_array_equal(a, np.empty(0) if f is None else f[i])
    assert bagio._kernel is not None
    with pytest.raises(ValueError):
        bagio._kernel.fill_joint_states(*bagio._joint_state_layout(('a',), (1, 0, 0))[::2],
                                        np.zeros(2, dtype=np.int64), np.zeros((3, 1)), None,
                                        None)


def test_block_decoder_equals_decoding_message_by_message():
    """JointStateDecoder.block (the compiled decoder): runs of one layout (frame ids shifting
    the alignment, NaN/inf/-0 values, negative stamps, empty arrays) decode to the stacked
    records of decoding them one by one, names from the cache or decoded afresh; None for
    anything the fast path does not take alike, which the caller then decodes one by one."""
    rng = np.random.default_rng(11)
    dec = bagio.JointStateDecoder()
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
        messages = [bagio.encode_joint_state(0.0, names, *(v[m] for v in values),
                                             frame_id='f' * int(rng.integers(0, 8)))
                    for m in range(M)]
        messages = [raw[:4] + struct.pack('<iI', *divmod(int(t), 10**9)) + raw[12:]
                    for raw, t in zip(messages, stamps)]
        block = dec.block(messages)
        assert block.names == tuple(names) and block.stamp_ns.dtype == np.int64
        one_by_one = [bagio.decode_joint_state_reference(raw) for raw in messages]
        np.testing.assert_array_equal(block.stamp_ns, [r.stamp_ns for r in one_by_one])
        for f in range(2, 5):
            assert block[f].shape == (M, widths[f - 2])
            np.testing.assert_array_equal(block[f], np.stack([r[f] for r in one_by_one]))
            assert np.array_equal(np.signbit(block[f]), np.signbit(np.stack(
                [r[f] for r in one_by_one])))
    good = bagio.encode_joint_states(np.arange(3) * 10**6, ARM3, *[np.ones((3, 3))] * 3)
    other_names = bagio.encode_joint_state(0.0, ('a', 'b', 'c'), *[[1.0, 2.0, 3.0]] * 3)
    no_velocity = bagio.encode_joint_state(0.0, ARM3, [1.0, 2.0, 3.0], [], [1.0, 2.0, 3.0])
    msg = bagio.make_joint_state(0.0, ARM3, [1.0, 2.0, 3.0], [], [])
    big_endian = bytes(bagio.jazzy_typestore().serialize_cdr(msg, bagio.JOINT_STATE,
                                                             little_endian=False))
    bad_name = good[0].replace(b'elbow', b'elb\xffw')
    for odd in ([], [other_names], [no_velocity], [good[0][:-9]], [big_endian],
                [bytearray(good[0])], [bad_name]):
        assert dec.block(good + odd if odd else odd) is None
    assert dec.block(good).names == ARM3


ARM3 = ('shoulder', 'elbow', 'wrist')


def test_pipeline_on_current_messages_compiled_equals_python(monkeypatch):
    """Joint states and 3-phase motor currents as CDR messages in runs of 1-5, as the node
    takes them (reordered channels, a NaN current, a garbage message, unknown channels, a NaN
    position among them): with the compiled decoding and step, with the Python path, and
    decoded beforehand record by record, the same outputs, counters and estimate; the
    compiled pipeline decodes runs of one layout as blocks."""
    robot = load_robot('mit_dd_arm')
    motor = {'source': 'three_phase', 'kt': 0.5, 'gear_ratio': 50.0, 'pole_pairs': 7}
    converter = TorqueConverter(robot.joint_names, [motor] * robot.dof)
    N = 3000
    t = np.arange(N) / 1000.0
    traj = FourierTrajectory.random(robot, harmonics=4, period=5.0, seed=3)
    sim = simulate_kinematic(robot, None, traj, t, SensorNoise(torque_std=0.3), seed=3)
    stamps = 10**18 + np.round(t * 1e9).astype(np.int64)
    slots = converter.current_channel_slots()
    amps = converter.currents_from_torque(sim.tau_meas, sim.q_meas)
    values = amps[:, [s[1] for s in slots], [s[2] for s in slots]]
    channels = [s[0] for s in slots]
    js = bagio.encode_joint_states(stamps, robot.joint_names, sim.q_meas, sim.qd_meas, None)
    cur = bagio.encode_joint_states(stamps + 20_000, channels, None, None, values)

    def current(k, names, v):
        return bagio.encode_joint_states(stamps[k:k + 1] + 20_000, names, None, None, v)[0]
    for k in range(500, N, 700):
        cur[k] = current(k, channels[::-1], values[k:k + 1, ::-1])   # reordered, valid
    cur[1001] = current(1001, channels, np.where(np.arange(len(channels)) == 4, np.nan,
                                                 values[1001:1002]))
    cur[1502] = b'\x00\x01garbage'
    cur[2003] = current(2003, [f'x{i}/ia' for i in range(len(channels))], values[2003:2004])
    js[2504] = bagio.encode_joint_states(stamps[2504:2505], robot.joint_names,
                                         np.full((1, robot.dof), np.nan),
                                         sim.qd_meas[2504:2505], None)[0]
    blocks = [0]
    original = bagio.JointStateDecoder.block

    def counted(self, messages):
        out = original(self, messages)
        blocks[0] += out is not None
        return out
    monkeypatch.setattr(bagio.JointStateDecoder, 'block', counted)
    torque = {j: JointTorqueConfig(**motor) for j in robot.joint_names}
    pipes = [IdentificationPipeline(robot, PipelineConfig(torque=torque, compiled=flag))
             for flag in (True, False, False)]
    outs, used = [[], [], []], []
    rng = np.random.default_rng(2)
    k = 0
    while k < N:
        m = int(rng.integers(1, 6))
        for i, (p, out) in enumerate(zip(pipes, outs)):
            if i == 2:   # decoded beforehand, record by record
                for raw, add in [(r, p.add_joint_state) for r in js[k:k + m]] + [
                        (r, p.add_currents) for r in cur[k:k + m]]:
                    try:
                        add(bagio.decode_joint_state(raw))
                    except Exception:   # noqa: BLE001 (the garbage message)
                        p.add_malformed()
            else:
                before = blocks[0]
                p.add_joint_state_cdr(js[k:k + m])
                p.add_currents_cdr(cur[k:k + m])
                out.append(p.process())
                used.append((i, blocks[0] - before))
                continue
            out.append(p.process())
        k += m
    for p, out in zip(pipes, outs):
        out.append(p.process(flush=True))
    fields = ('stamps_ns', 'q', 'qd', 'qdd', 'measured', 'predicted')
    got, python, ref = ({f: np.concatenate([getattr(o, f) for o in out]) for f in fields}
                        for out in outs)
    assert len(got['stamps_ns']) > N - 100
    for f in fields:
        np.testing.assert_array_equal(python[f], ref[f])
    assert np.array_equal(got['stamps_ns'], python['stamps_ns'])
    for f in fields[1:-1]:
        close(got[f], python[f], 1e-9)
    close(got['predicted'], python['predicted'], 1e-8)   # the first estimates: ill-conditioned
    # a joint state whose current was rejected takes its neighbour's (within align_tolerance)
    expected = {'non_finite': 2, 'malformed': 1, 'unknown_channels': 1, 'unmatched_current': 1}
    for p in pipes:
        assert {r: c for r, c in p.rejected.items() if c} == expected
    assert sum(b for i, b in used if i == 1) == 0            # compiled: false decodes alone
    assert sum(b for i, b in used if i == 0) > 1.5 * len(used) / 2   # both streams, mostly
    a, b, c = (p.estimate() for p in pipes)
    assert a.num_samples == b.num_samples == c.num_samples > N - 100
    close(a.values, b.values, 1e-8)
    np.testing.assert_array_equal(b.values, c.values)


def test_information_factor_equals_the_python_path():
    """factor_information against _cholesky_augmented and _solve on the same information: a
    triangular old factor, one with the forgetting regulariser's rows stacked below, badly
    scaled columns; None where the Python path finds no Cholesky factor."""
    from identification_node import estimators as est
    rng = np.random.default_rng(7)
    p = 12
    A = rng.normal(size=(300, p + 1)) * np.logspace(-3, 3, p + 1)
    info = np.stack([A[k:k + 100].T @ A[k:k + 100] for k in (0, 100)])
    triangular = np.linalg.qr(A[200:], mode='r')
    for old in (triangular, np.vstack([triangular, rng.normal(size=(p, p + 1))])):
        F, theta, R_inv, bound = est._factor_compiled(old, info)
        F_py = est._cholesky_augmented(old.T @ old + info.sum(axis=0))
        theta_py, rank, G, determined = est._solve(F_py[:p, :p], F_py[:p, p], 1e-10)
        assert rank == p and determined.all()
        close(F, F_py, 1e-13)
        close(theta, theta_py, 1e-10)
        close(R_inv, G, 1e-12)
        d = est._column_scale(F_py[:p, :p])
        close(bound, np.linalg.norm(F_py[:p, :p] / d) * np.linalg.norm(d[:, None] * G), 1e-12)
        assert np.all(np.tril(F, -1) == 0)
    singular = A[:5].T @ A[:5]   # rank 5 < p
    assert est._cholesky_augmented(singular) is None
    assert est._factor_compiled(np.zeros((0, p + 1)), singular[None]) is None
    bad = info.copy()
    bad[1, 3, 4] = np.nan
    assert est._factor_compiled(triangular, bad) is None


@pytest.mark.parametrize('lam', [1.0, 0.99])
def test_rls_with_compiled_factor_equals_python(monkeypatch, lam):
    """A stream of batches through the RLS with the compiled factorisation and without: same
    estimate, covariance and information (the compiled one used on every excited batch)."""
    from identification_node import estimators as est
    rng = np.random.default_rng(8)
    N, n, p = 3000, 3, 10
    Y = rng.normal(size=(N, n, p)) * np.logspace(-1, 1, p)
    tau = Y @ rng.normal(size=p) + 0.1 * rng.normal(size=(N, n))
    calls = []
    factor = est._factor_compiled
    monkeypatch.setattr(est, '_factor_compiled', lambda *a: calls.append(1) or factor(*a))
    runs = []
    for use in (True, False):
        rls = est.RecursiveLeastSquares(p, lam, compiled=use)
        for k in range(0, N, 50):
            rls.update(Y[k:k + 50], tau[k:k + 50])
        runs.append(rls)
    assert len(calls) == N // 50
    a, b = runs
    close(a.theta, b.theta, 1e-11)
    close(a.covariance, b.covariance, 1e-10)
    close(a.information, b.information, 1e-12)
    assert a.rank == b.rank == p
