"""The identification pipeline on simulated streams with known parameters (no ROS)."""
import numpy as np
import pytest

from identification_node.errors import IdentificationError
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.estimation.robust import RobustSettings
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.model.torque import JointTorqueConfig, TorqueConverter
from identification_node.pipeline import IdentificationPipeline, PipelineConfig
from identification_node.pipeline import signals
from identification_node.pipeline.estimate import OnlineEstimate
from identification_node.pipeline.rows import AUTO_WAIT, MOTION
from identification_node.pipeline.window import SegmentWindow
from identification_node.wire.records import JointStateRecord

RATE = 1000.0
T0_NS = 1_700_000_000_123_456_789   # epoch-sized stamps: nanoseconds must survive
ROBOT = load_robot('mit_dd_arm')
BASE = BaseParameters.from_robot(ROBOT)
TRUE = BASE.to_base(ROBOT.phi_model)
THREE_PHASE = {j: JointTorqueConfig(source='three_phase', kt=kt, pole_pairs=8, angle_offset=0.3)
               for j, kt in zip(ROBOT.joint_names, (12.0, 6.0, 6.0))}


def simulate(duration=20.0, noise=SensorNoise(torque_std=0.5), converter=None, seed=1):
    traj = FourierTrajectory.random(ROBOT, harmonics=4, period=10.0, seed=seed)
    t = np.arange(int(duration * RATE)) / RATE
    return simulate_kinematic(ROBOT, None, traj, t, noise, seed=seed, converter=converter)


def stamps(sim):
    return T0_NS + np.round(sim.t * 1e9).astype(np.int64)


def joint_records(sim, velocity=True, effort=True):
    """Messages with the joints shuffled and a gripper joint the model does not know."""
    names = ('gripper', 'joint3', 'joint1', 'joint2')
    order = [2, 0, 1]
    out = []
    for k, ns in enumerate(stamps(sim)):
        pos = np.concatenate([[0.01], sim.q_meas[k, order]])
        vel = np.concatenate([[0.0], sim.qd_meas[k, order]]) if velocity else np.empty(0)
        eff = np.concatenate([[0.0], sim.tau_meas[k, order]]) if effort else np.empty(0)
        out.append(JointStateRecord(int(ns), names, pos, vel, eff))
    return out


def current_records(sim, converter, offset_ns=300_000):
    slots = converter.current_channel_slots()
    names = tuple(name for name, _, _ in slots)
    cur = np.stack([sim.currents[:, i, k] for _, i, k in slots], axis=1)
    return [JointStateRecord(int(ns) + offset_ns, names, np.empty(0), np.empty(0), cur[k])
            for k, ns in enumerate(stamps(sim))]


def feed(pipeline, js, cur=None, chunk=50):
    """Interleave the streams in chunks as a node's callbacks would, processing each chunk."""
    outs = []
    for start in range(0, len(js), chunk):
        for r in js[start:start + chunk]:
            if r is not None:   # None: not delivered
                pipeline.add_joint_state(r)
        for r in (cur or [])[start:start + chunk]:
            pipeline.add_currents(r)
        outs.append(pipeline.process())
    outs.append(pipeline.process(flush=True))
    return {name: np.concatenate([getattr(o, name) for o in outs])
            for name in ('stamps_ns', 'q', 'qd', 'qdd', 'measured', 'predicted')}


def index_of(sim, stamps_ns):
    return np.round((stamps_ns - T0_NS) * 1e-9 * RATE).astype(int)


def assert_within_3_sigma(est):
    err = np.abs(est.values - TRUE)
    assert np.all(err <= 3 * est.stddev), (err / est.stddev).round(2)


def test_measured_torque_converges_to_truth():
    sim = simulate()
    p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
    out = feed(p, joint_records(sim))
    est = p.estimate()
    assert sum(p.rejected.values()) == 0
    assert est.num_samples == len(sim) - 2 * p.smoother.half_window
    assert_within_3_sigma(est)
    # Output stamps are the samples' own stamps, to the nanosecond.
    k = index_of(sim, out['stamps_ns'])
    assert np.array_equal(out['stamps_ns'], stamps(sim)[k])
    # The torque the final estimate predicts, against the raw measured torque.
    Yb = BASE.base_regressor(ROBOT.regressor(sim.q[k], sim.qd[k], sim.qdd[k]))
    rms = np.sqrt(np.mean((Yb @ est.values - sim.tau_meas[k]) ** 2, axis=0))
    assert np.all(rms <= 1.2 * 0.5), rms
    # The running prediction over the last half agrees too, and the run converged.
    half = len(k) // 2
    run_rms = np.sqrt(np.mean((out['predicted'][half:] - sim.tau_meas[k[half:]]) ** 2, axis=0))
    assert np.all(run_rms <= 1.2 * 0.5), run_rms
    assert est.converged
    # relative_error from running sums equals the direct computation over the smoothed data.
    Yb = BASE.base_regressor(ROBOT.regressor(out['q'], out['qd'], out['qdd']))
    direct = 100 * (np.linalg.norm(out['measured'] - Yb @ est.values, axis=0)
                    / np.linalg.norm(out['measured'], axis=0))
    np.testing.assert_allclose(p.relative_error(), direct, rtol=1e-6)


@pytest.mark.slow
def test_three_phase_currents_converge_to_truth():
    converter = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    current_std = 0.02
    sim = simulate(noise=SensorNoise(current_std=current_std), converter=converter)
    p = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE), BASE)
    out = feed(p, joint_records(sim, effort=False), current_records(sim, converter))
    assert sum(p.rejected.values()) == 0, p.rejected
    est = p.estimate()
    assert_within_3_sigma(est)
    k = index_of(sim, out['stamps_ns'])
    torque_std = np.array([12.0, 6.0, 6.0]) * current_std * np.sqrt(1.5)
    raw = converter.torque(sim.q_meas[k], currents=sim.currents[k])
    Yb = BASE.base_regressor(ROBOT.regressor(sim.q[k], sim.qd[k], sim.qdd[k]))
    rms = np.sqrt(np.mean((Yb @ est.values - raw) ** 2, axis=0))
    assert np.all(rms <= 1.2 * torque_std), (rms, torque_std)


def test_a_segment_window_gives_the_whole_streams_rows_inside_it():
    """Three-phase currents offset from the joint states, a fixed smoother: the windowed
    pipeline, fed the whole stream, takes only the messages within its margin, and its rows
    are the unwindowed pipeline's rows inside [start, stop), no more; the messages inside are
    counted, and received. CDR input (the node's) is refused: its stamps are known only once
    decoded."""
    converter = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    sim = simulate(duration=4.0, noise=SensorNoise(current_std=0.02), converter=converter)
    js, cur = joint_records(sim, effort=False), current_records(sim, converter)
    config = PipelineConfig(torque=THREE_PHASE, half_window=15)
    whole = feed(IdentificationPipeline(ROBOT, config, BASE), js, cur)
    start, stop = T0_NS + 1_500_000_000, T0_NS + 2_500_000_000
    p = IdentificationPipeline(ROBOT, config, BASE)
    p.window = SegmentWindow(start, stop, margin_ns=100_000_000)
    part = feed(p, js, cur)
    inside = (whole['stamps_ns'] >= start) & (whole['stamps_ns'] < stop)
    np.testing.assert_array_equal(part['stamps_ns'], whole['stamps_ns'][inside])
    for key in ('q', 'qd', 'qdd', 'measured'):
        np.testing.assert_allclose(part[key], whole[key][inside], rtol=0, atol=1e-9)
    both = [r.stamp_ns for r in js + cur]
    assert p.window.messages == sum(start <= s < stop for s in both)
    # received: the joint states of [start, stop) at 1 kHz; the margins' are its neighbours'
    assert p.received == 1000
    with pytest.raises(IdentificationError, match='segment window takes decoded'):
        p.add_joint_state_cdr([b''])


def test_differentiated_positions_without_velocity():
    sim = simulate(noise=SensorNoise(torque_std=0.5, encoder_counts=2 ** 20))
    p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
    feed(p, joint_records(sim, velocity=False))
    assert not p.velocity_measured and p.estimate().num_samples > 0
    assert_within_3_sigma(p.estimate())


@pytest.mark.slow
def test_chunking_does_not_change_the_result():
    sim = simulate(duration=4.0)
    js = joint_records(sim)
    results = []
    for chunk in (7, 100, 1000):
        p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
        feed(p, js, chunk=chunk)
        results.append(p.estimate().values)
    np.testing.assert_allclose(results[0], results[1], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(results[0], results[2], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize('update', [True, False])
def test_deferred_updates_change_nothing_but_when(update):
    """defer_updates (the node: the estimator's update after the outputs are published):
    the same outputs and estimate as the immediate updates, bit for bit, whether update()
    is called after each run or left to the next process(); with rows of 100 samples per
    run and update_batch 100 they live in the work array the next run reuses."""
    sim = simulate(duration=6.0)
    js = joint_records(sim)
    config = PipelineConfig(update_batch=100, half_window=10)
    now = IdentificationPipeline(ROBOT, config, BASE)
    later = IdentificationPipeline(ROBOT, config, BASE)
    later.defer_updates = True
    pending = []
    for start in range(0, len(js), 100):
        outs = []
        for p in (now, later):
            for r in js[start:start + 100]:
                p.add_joint_state(r)
            outs.append(p.process())
        pending.append(not later.estimator.batch_due)   # rows gathered, not yet applied
        if update:
            later.update()
        for name in ('stamps_ns', 'measured', 'predicted'):
            np.testing.assert_array_equal(getattr(outs[0], name), getattr(outs[1], name))
    assert all(pending[1:])         # each run's full batch waited for update() or the next run
    np.testing.assert_array_equal(now.estimate().values, later.estimate().values)
    np.testing.assert_array_equal(now.covariance, later.covariance)


def test_bad_messages_are_counted_and_the_estimate_stays_finite():
    sim = simulate(duration=6.0)
    js = joint_records(sim)
    good = len(js)
    r = js[3000]
    bad = [
        r._replace(stamp_ns=r.stamp_ns + 1, position=np.array([0.0, np.nan, 0.1, 0.2])),
        r._replace(stamp_ns=r.stamp_ns + 2, effort=np.array([0.0, np.inf, 0.1, 0.2])),
        r._replace(stamp_ns=r.stamp_ns + 3, names=('joint1', 'joint2', 'elbow', 'gripper')),
        r._replace(stamp_ns=r.stamp_ns + 4, position=r.position[:2]),
        r._replace(stamp_ns=r.stamp_ns + 5, names=(), position=np.empty(0),
                   velocity=np.empty(0), effort=np.empty(0)),
        r._replace(stamp_ns=r.stamp_ns + 6, names=('joint1', 'joint1', 'joint2', 'joint3')),
        r._replace(stamp_ns=r.stamp_ns + 7, velocity=np.array([1.0])),
    ]
    # A repeated and an out-of-order stamp, after the good message they refer to.
    stream = js[:3001] + bad + [js[3000], js[2990]] + js[3001:]
    p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
    feed(p, stream)
    expected = {'non_finite': 2, 'missing_joints': 1, 'length_mismatch': 2, 'empty': 1,
                'duplicate_names': 1, 'repeated_stamp': 1, 'out_of_order': 1}
    assert {k: v for k, v in p.rejected.items() if v} == expected
    assert p.received == good + len(bad) + 2
    est = p.estimate()
    assert np.all(np.isfinite(est.values)) and np.all(np.isfinite(est.stddev))
    assert_within_3_sigma(est)


def test_currents_with_no_joint_state_and_joint_states_with_no_current():
    converter = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    sim = simulate(duration=3.0, noise=SensorNoise(current_std=0.01), converter=converter)
    js = joint_records(sim, effort=False)
    cur = current_records(sim, converter)
    # 100 joint states lose their currents; 50 currents lose their joint states.
    cur_kept = cur[:1000] + cur[1100:]
    js_kept = js[:2000] + js[2050:]
    # Currents lag by 0.3 ms; a 0.5 ms tolerance keeps neighbours (1 ms apart) from matching.
    p = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE, align_tolerance=5e-4),
                               BASE)
    feed(p, js_kept, cur_kept)
    assert p.rejected['no_current'] == 100
    assert p.rejected['unmatched_current'] == 50
    assert np.all(np.isfinite(p.estimate().values))


@pytest.mark.parametrize('late', ['currents', 'joint_states'])
def test_a_stream_starting_late_is_told_apart_from_lost_messages(late):
    """One topic starting (or discovered) 0.5 s after the other: the other's messages before
    its first count 'before_currents' (joint states) or 'before_joint_states' (currents), a
    start-up transient; messages lost later in the stream still count 'no_current' and
    'unmatched_current'."""
    converter = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    sim = simulate(duration=3.0, noise=SensorNoise(current_std=0.01), converter=converter)
    js, cur = joint_records(sim, effort=False), current_records(sim, converter)
    p = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE, align_tolerance=5e-4),
                               BASE)
    gone = {'currents': (set(range(2500, 2550)), set(range(500)) | set(range(2000, 2100))),
            'joint_states': (set(range(500)) | set(range(2000, 2050)), set(range(2500, 2550)))}
    for start in range(0, len(js), 50):     # both streams in step, as published
        chunk = range(start, min(start + 50, len(js)))
        for k in chunk:
            if k not in gone[late][0]:
                p.add_joint_state(js[k])
            if k not in gone[late][1]:
                p.add_currents(cur[k])
        p.process()
    p.process(flush=True)
    early = {'before_currents': 500 if late == 'currents' else 0,
             'before_joint_states': 500 if late == 'joint_states' else 0}
    lost = {'no_current': 100 if late == 'currents' else 50, 'unmatched_current': 50}
    assert {k: p.rejected[k] for k in (*early, *lost)} == {**early, **lost}
    assert np.all(np.isfinite(p.estimate().values))


def test_currents_just_before_the_first_joint_state_are_a_start_up_transient():
    """Joint states discovered 0.5 s after the currents, the default 2 ms tolerance (two
    samples at 1 kHz): the currents within the tolerance before the first joint state, which
    took its own, are not lost messages either (the quick start saw 2 'unmatched_current')."""
    converter = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    sim = simulate(duration=1.5, noise=SensorNoise(current_std=0.01), converter=converter)
    js, cur = joint_records(sim, effort=False), current_records(sim, converter)
    p = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE), BASE)
    assert p.config.align_tolerance == 0.002
    feed(p, [None] * 500 + js[500:], cur)
    assert p.rejected['before_joint_states'] == 500
    assert p.rejected['unmatched_current'] == 0 and p.rejected['no_current'] == 0


@pytest.mark.parametrize('live', [False, True])
def test_late_currents_of_a_live_stream_are_waited_for(live):
    """Live topics are not delivered in step: 300 ms of joint states in one processing run,
    their currents in the next. By stamps alone the joint states more than hold_time (0.1 s)
    older than the newest are given up (no current had come yet: 'before_currents'); with the
    node's clock (live) they wait hold_time of it too, and all are matched. Currents that
    never come are still given up once the clock passed hold_time ('no_current')."""
    converter = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    sim = simulate(duration=1.0, noise=SensorNoise(current_std=0.01), converter=converter)
    js, cur = joint_records(sim, effort=False), current_records(sim, converter)
    p = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE), BASE)
    now = [0.0]
    if live:
        p.live_clock(lambda: now[0])
    for r in js[:300]:
        p.add_joint_state(r)
    p.process()
    now[0] += 0.05                               # the next run, 50 ms later
    for r in cur[:300]:
        p.add_currents(r)
    p.process()
    assert p.rejected['before_currents'] == (0 if live else 200)
    assert p.rejected['no_current'] == 0
    # joint states whose currents never come: given up once hold_time of the clock passed
    # (all but the newest hold_time of stamps, and the first within align_tolerance)
    before = p.rejected['no_current']
    for r in js[300:600]:
        p.add_joint_state(r)
    p.process()
    if live:
        assert p.rejected['no_current'] == before
    now[0] += 0.2
    p.process()
    assert 190 <= p.rejected['no_current'] - before <= 200


def test_current_messages_validated_and_mapped_by_channel_name():
    """Channels in any order with an unknown one among them, the electrical angle in position:
    the currents and angles land in their (joint, phase) slots; bad messages are counted by
    reason and leave the outputs exactly as without them."""
    converter = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    sim = simulate(duration=3.0, noise=SensorNoise(current_std=0.01), converter=converter)
    slots = converter.current_channel_slots()
    perm = np.random.default_rng(4).permutation(len(slots))
    names = tuple(slots[i][0] for i in perm) + ('gripper/ia',)
    angle = sim.theta_e + 0.01    # not what the position gives
    cur = []
    for k, ns in enumerate(stamps(sim)):
        values = [sim.currents[k, slots[i][1], slots[i][2]] for i in perm] + [5.0]
        angles = [angle[k, slots[i][1]] for i in perm] + [0.0]
        cur.append(JointStateRecord(int(ns), names, np.array(angles), np.empty(0),
                                    np.array(values)))
    r = cur[1500]
    drop = names.index(slots[0][0])
    bad = [
        r._replace(stamp_ns=r.stamp_ns + 1,
                   effort=np.where(np.arange(len(names)) == 2, np.nan, r.effort)),
        r._replace(stamp_ns=r.stamp_ns + 2, position=r.position[:3]),
        r._replace(stamp_ns=r.stamp_ns + 3, effort=r.effort[:-1]),
        r._replace(stamp_ns=r.stamp_ns + 4, names=(), position=np.empty(0), effort=np.empty(0)),
        r._replace(stamp_ns=r.stamp_ns + 5, names=('gripper/ia',), position=np.empty(0),
                   effort=np.array([1.0])),
        r._replace(stamp_ns=r.stamp_ns + 6, names=names[:drop] + names[drop + 1:],
                   position=np.delete(r.position, drop), effort=np.delete(r.effort, drop)),
        r._replace(stamp_ns=r.stamp_ns + 7, names=(names[1],) + names[1:]),
    ]
    p = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE), BASE)
    converted = p.samples.validate_currents(cur[:10])
    np.testing.assert_array_equal(converted.currents, sim.currents[:10])
    np.testing.assert_array_equal(converted.theta, angle[:10])
    js = joint_records(sim, effort=False)
    outputs = []
    for stream, expected in ((list(cur), {}), (cur[:1501] + bad + cur[1501:], {
            'non_finite': 1, 'length_mismatch': 2, 'empty': 1, 'unknown_channels': 1,
            'missing_joints': 1, 'duplicate_names': 1})):
        p = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE), BASE)
        outs = []
        for start in range(0, len(js), 50):   # the currents up to the chunk's last stamp
            for r in js[start:start + 50]:
                p.add_joint_state(r)
            while stream and stream[0].stamp_ns <= js[min(start + 49, len(js) - 1)].stamp_ns:
                p.add_currents(stream.pop(0))
            outs.append(p.process())
        outs.append(p.process(flush=True))
        outputs.append({name: np.concatenate([getattr(o, name) for o in outs])
                        for name in ('stamps_ns', 'measured', 'predicted')})
        assert not stream and {k: v for k, v in p.rejected.items() if v} == expected
    for name in ('stamps_ns', 'measured', 'predicted'):
        np.testing.assert_array_equal(outputs[0][name], outputs[1][name])


def test_currents_out_of_stamp_order_within_a_batch_are_sorted():
    """Current messages arrive in any order within what one run takes (two publishers, a
    reordering transport): the outputs equal those of the currents in stamp order."""
    converter = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    sim = simulate(duration=1.0, noise=SensorNoise(current_std=0.01), converter=converter)
    js, cur = joint_records(sim, effort=False), current_records(sim, converter)
    shuffled = list(cur)
    rng = np.random.default_rng(3)
    for start in range(0, len(cur), 50):   # feed's chunks: each run's currents shuffled
        shuffled[start:start + 50] = [cur[start + i] for i in rng.permutation(
            len(cur[start:start + 50]))]
    outs = [feed(IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE), BASE),
                 js, c) for c in (cur, shuffled)]
    assert len(outs[0]['stamps_ns']) > 900
    np.testing.assert_array_equal(outs[0]['stamps_ns'], outs[1]['stamps_ns'])
    for name in ('q', 'qd', 'qdd', 'measured'):   # to rounding (numpy's SIMD loops)
        np.testing.assert_allclose(outs[0][name], outs[1][name], rtol=1e-12, atol=1e-12)
    # the first estimates are ill-conditioned: rounding differences grow
    np.testing.assert_allclose(outs[0]['predicted'], outs[1]['predicted'], rtol=1e-6)


@pytest.mark.parametrize('offset_ns', [-300_000, 0, 300_000])
def test_joint_states_decided_once_their_currents_are_in(offset_ns):
    """Processing after every message pair gives what the whole stream at once gives (the
    nearest current, known in full), and holds back only the joint states whose nearest
    current may still come: none when currents are stamped at or after the joint state."""
    converter = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    sim = simulate(duration=1.0, noise=SensorNoise(current_std=0.01), converter=converter)
    js, cur = joint_records(sim, effort=False), current_records(sim, converter, offset_ns)
    live = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE), BASE)
    outs = []
    for j, c in zip(js, cur):
        live.add_joint_state(j)
        live.add_currents(c)
        outs.append(live.process())
        assert len(live.samples.alignment.pending) == (offset_ns < 0)
    outs.append(live.process(flush=True))
    whole = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE), BASE)
    ref = feed(whole, js, cur, chunk=len(js))
    np.testing.assert_array_equal(np.concatenate([o.stamps_ns for o in outs]), ref['stamps_ns'])
    # to rounding: the smoother's matrix products differ with the batch size
    np.testing.assert_allclose(np.concatenate([o.measured for o in outs]), ref['measured'],
                               rtol=1e-12, atol=1e-12)
    assert sum(live.rejected.values()) == sum(whole.rejected.values()) == 0


def test_stream_stops_and_restarts():
    sim = simulate(duration=6.0)
    js = joint_records(sim)
    shift = -10 * 10 ** 9   # the restarted stream's clock is 10 s earlier
    restarted = [r._replace(stamp_ns=r.stamp_ns + shift) for r in js[4000:]]
    p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
    # A pause (gap > max_gap: the smoother restarts), then a restart with earlier stamps.
    feed(p, js[:2000] + js[2500:4000] + restarted)
    assert p.restarts == 1
    assert sum(p.rejected.values()) == 0
    assert np.all(np.isfinite(p.estimate().values))
    # Each smoother restart loses one window: 3 segments.
    assert p.used == len(js) - 500 - 3 * 2 * p.smoother.half_window


def test_freeze_and_reset():
    sim = simulate(duration=3.0)
    js = joint_records(sim)
    p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
    feed(p, js[:1500])
    before = p.estimate()
    p.frozen = True
    feed(p, js[1500:])
    after = p.estimate()
    assert after.num_samples == before.num_samples
    np.testing.assert_array_equal(after.values, before.values)
    p.reset()
    assert p.estimate().num_samples == 0 and p.received == 0


def as_blocks(records):
    """Runs of records sharing names and array lengths as blocks (add_joint_states), single
    records where a run has one."""
    out, run = [], []

    def close():
        if len(run) == 1:
            out.append(run[0])
        elif run:
            out.append(JointStateRecord(
                np.array([r.stamp_ns for r in run], dtype=np.int64), run[0].names,
                *(np.array([r[f] for r in run]).reshape(len(run), -1) for f in (2, 3, 4))))
        run.clear()

    for r in records:
        if run and (r.names, *map(len, r[2:])) != (run[0].names, *map(len, run[0][2:])):
            close()
        run.append(r)
    close()
    return out


@pytest.mark.slow
def test_blocks_equal_records_one_by_one():
    sim = simulate(duration=6.0)
    js = joint_records(sim)
    r = js[3000]
    odd = [  # structural rejections as runs (blocks) of 3, non-finite rows inside runs
        *(r._replace(stamp_ns=r.stamp_ns + i, names=('joint1', 'joint2', 'elbow', 'gripper'))
          for i in (1, 2, 3)),
        *(r._replace(stamp_ns=r.stamp_ns + i, velocity=np.array([1.0])) for i in (4, 5, 6)),
        *(r._replace(stamp_ns=r.stamp_ns + i, velocity=np.empty(0)) for i in (7, 8, 9)),
        r._replace(stamp_ns=r.stamp_ns + 10, position=np.array([0.0, np.nan, 0.1, 0.2])),
    ]
    shift = -10 * 10 ** 9
    restarted = [x._replace(stamp_ns=x.stamp_ns + shift) for x in js[4000:]]
    # out of order and repeated stamps inside runs, a restart in the middle of a run
    stream = js[:2990] + js[2995:3001] + odd + [js[3000], js[2990]] + js[3001:4000] + restarted
    blocks = as_blocks(stream)
    assert len(blocks) < 20 and any(np.ndim(b.stamp_ns) for b in blocks)
    results = []
    for items in (stream, blocks):
        p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
        outs, count = [], 0
        for item in items:  # processed every 50 messages, blocks cut there
            if not np.ndim(item.stamp_ns):
                p.add_joint_state(item)
                count += 1
                if count % 50 == 0:
                    outs.append(p.process())
                continue
            start = 0
            while start < len(item.stamp_ns):
                stop = min(len(item.stamp_ns), start + 50 - count % 50)
                p.add_joint_states(JointStateRecord(item.stamp_ns[start:stop], item.names,
                                                    *(a[start:stop] for a in item[2:])))
                count += stop - start
                start = stop
                if count % 50 == 0:
                    outs.append(p.process())
        outs.append(p.process(flush=True))
        results.append((p, np.concatenate([o.predicted for o in outs])))
    (one, pred_one), (blk, pred_blk) = results
    assert one.rejected == blk.rejected
    assert {k: v for k, v in blk.rejected.items() if v} == {
        'missing_joints': 3, 'length_mismatch': 3, 'missing_velocity': 3, 'non_finite': 1,
        'repeated_stamp': 1, 'out_of_order': 1, 'stream_restart': 7}
    assert (one.received, one.used, one.restarts) == (blk.received, blk.used, blk.restarts)
    np.testing.assert_allclose(blk.estimate().values, one.estimate().values, rtol=1e-10)
    np.testing.assert_allclose(pred_blk, pred_one, rtol=1e-9, atol=1e-9)


def test_bad_block_shapes_are_refused():
    p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
    names = ('joint1', 'joint2', 'joint3')
    with pytest.raises(IdentificationError, match='block'):
        p.add_joint_states(JointStateRecord(np.arange(3), names, np.zeros((2, 3)),
                                            np.zeros((3, 3)), np.zeros((3, 0))))
    with pytest.raises(IdentificationError, match='block'):
        p.add_joint_states(JointStateRecord(5, names, np.zeros(3), np.zeros(3), np.zeros(3)))
    p.add_joint_states(JointStateRecord(np.zeros(0, dtype=np.int64), names, *np.zeros((3, 0, 3))))
    p.process(flush=True)
    assert p.received == 0


class _CheckedEstimate(OnlineEstimate):
    """The pipeline's estimate stage, also feeding a reference RLS and residual sums by their
    public, checked methods with the base regressor rows and the weights it gives them."""

    def reset(self):
        super().reset()
        self.ref_rls = RecursiveLeastSquares(self.num_base, self.config.forgetting)
        self.ref_res = ResidualStatistics(self.num_base, self.dof, self._block)

    def _row_weights(self, t, qd, qdd):
        self.weights = super()._row_weights(t, qd, qdd)
        return self.weights

    def add(self, rows, t, qd, qdd, stamps_ns=None, q=None, defer=False):
        assert len(rows) >= self.config.update_batch and not defer  # (the same batches)
        Yb, tau = rows[:, :, :-1].copy(), rows[:, :, -1].copy()
        super().add(rows, t, qd, qdd, stamps_ns, q)   # (3 s: no residual grid line crossed)
        w = self.weights
        self.ref_rls.update(Yb, tau, w)
        root = np.sqrt(np.broadcast_to(np.ones(tau.shape) if w is None else w, tau.shape))
        self.ref_res.add(Yb * root[..., None], tau * root)


@pytest.mark.parametrize('forgetting, extras', [(1.0, ()), (0.998, ('fv', 'fc'))])
def test_shared_information_equals_the_checked_estimator_calls(forgetting, extras):
    robot = load_robot('mit_dd_arm', extras=extras)
    base = BaseParameters.from_robot(robot)
    sim = simulate(duration=3.0)
    config = PipelineConfig(forgetting=forgetting, joint_noise_std=[0.5, 1.0, 2.0],
                            coulomb_exclusion_speed=0.1)
    p = IdentificationPipeline(robot, config, base)
    p.estimator = checked = _CheckedEstimate(base.num_base, robot.dof, config, bool(extras))
    feed(p, joint_records(sim), chunk=400)
    p.ref_rls, p.ref_res = checked.ref_rls, checked.ref_res
    assert p.excluded_rows > 0 or not extras  # zero weights (Coulomb exclusion) were there
    np.testing.assert_allclose(p.rls.theta, p.ref_rls.theta, rtol=1e-9,
                               atol=1e-9 * np.abs(p.ref_rls.theta).max())
    np.testing.assert_allclose(p.rls.covariance, p.ref_rls.covariance, rtol=1e-8,
                               atol=1e-9 * np.abs(p.ref_rls.covariance).max())
    assert p.rls.num_samples == p.ref_rls.num_samples
    for f in ('gram', 'cross', 'sq'):
        a, b = getattr(p.residuals, f), getattr(p.ref_res, f)
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12 * np.abs(b).max())
    theta = p.rls.theta
    np.testing.assert_allclose(p.residuals.long_run_variance(theta),
                               p.ref_res.long_run_variance(theta), rtol=1e-8)
    assert p.residuals.blocks == p.ref_res.blocks


def test_joint_weights_leave_the_reported_torque_figures_in_newton_metres():
    """joint_noise_std weights the rows; the residual RMS and the noise level are reported in
    N m all the same: as without weights, and the noise near the simulated 0.5 N m."""
    sim = simulate(duration=10.0)
    runs = []
    for std in ([], [0.5, 1.0, 2.0]):
        p = IdentificationPipeline(ROBOT, PipelineConfig(half_window=10, joint_noise_std=std),
                                   BASE)
        feed(p, joint_records(sim), chunk=500)
        runs.append((p.residual_rms(), p.noise_std(), p.estimate().residual_rms))
    (rms, noise, reported), (w_rms, w_noise, w_reported) = runs
    np.testing.assert_allclose(w_rms, rms, rtol=0.02)
    np.testing.assert_allclose(w_reported, w_rms)
    np.testing.assert_allclose(w_noise, noise, rtol=0.15)
    np.testing.assert_allclose(w_noise, 0.5, rtol=0.3)


@pytest.mark.parametrize('field, value', [
    ('forgetting', 1.5), ('half_window', -1), ('velocity', 'guess'), ('align_tolerance', -1.0),
    ('joint_noise_std', [1.0]), ('max_gap', float('nan'))])
def test_bad_configuration_names_the_parameter(field, value):
    from identification_node.errors import IdentificationError
    with pytest.raises(IdentificationError, match=field):
        IdentificationPipeline(ROBOT, PipelineConfig(**{field: value}), BASE)


@pytest.mark.parametrize('bad', [np.nan, 1e200])
def test_non_finite_or_overflowing_rows_are_dropped_and_counted(bad):
    p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
    rows = np.ones((60, ROBOT.dof, BASE.num_base + 1))
    rows[7, 1, 2] = bad
    p.estimator.add(rows, np.arange(60) * 1e-3, np.ones((60, 3)), np.zeros((60, 3)))
    p.estimator.apply()
    assert p.rejected['regressor_overflow'] == 1
    assert p.rls.num_samples == 59 and np.isfinite(p.rls.theta).all()


def test_automatic_smoother_holds_the_first_seconds_of_motion_then_takes_them_all():
    sim = simulate(duration=10.0)
    js = joint_records(sim)
    # the robust gate off: its outliers depend on when the estimate converged
    off = RobustSettings(enabled=False)
    auto = IdentificationPipeline(ROBOT, PipelineConfig(robust=off), BASE)
    first = []
    for start in range(0, len(js), 100):
        for r in js[start:start + 100]:
            auto.add_joint_state(r)
        if len(auto.process().stamps_ns) and not first:
            first.append(start + 100)
    out_auto = auto.process(flush=True)
    choice = auto.smoother
    assert choice.source == 'automatic' and choice.rate == pytest.approx(RATE)
    assert choice.seconds == pytest.approx(5.0, abs=2 / RATE)
    # nothing came out before 5 s of motion were in (the arm moves from the first sample);
    # then one candidate window is tried per processing run
    assert 5.0 * RATE < first[0] <= 5.0 * RATE + 100 * 40
    assert choice.cutoff == pytest.approx(
        signals.smoother_cutoff(choice.half_window, 3, RATE)) and choice.delay == \
        pytest.approx(choice.half_window / RATE)
    # the same as the pipeline given that window from the start, to rounding
    fixed = IdentificationPipeline(
        ROBOT, PipelineConfig(half_window=choice.half_window, robust=off), BASE)
    want = feed(fixed, js, chunk=100)
    assert auto.used == fixed.used == len(js) - 2 * choice.half_window
    np.testing.assert_allclose(auto.rls.theta, fixed.rls.theta, rtol=1e-9,
                               atol=1e-9 * np.abs(TRUE).max())
    assert len(out_auto.stamps_ns) < len(want['stamps_ns'])
    assert_within_3_sigma(auto.estimate())


def test_automatic_smoother_waits_for_motion_held_over_many_runs():
    """2 s at rest, then motion: the choice is made on the first 5 s of motion, in the run
    where they are in (not before, not on the rest); a stream that never moves is decided
    after AUTO_WAIT times auto_seconds of samples (auto_seconds 0.5 s here)."""
    sim = simulate(duration=8.0)
    moving = joint_records(sim)

    def rest(count: int) -> list:   # the first moving sample's values, 1 ms apart, before it
        return [JointStateRecord(moving[0].stamp_ns - (count - k) * 10 ** 6, moving[0].names,
                                 moving[0].position, np.zeros(4), moving[0].effort)
                for k in range(count)]

    def run(p, records) -> tuple[int | None, list[int]]:
        """The samples in when the first output came, and the samples held after each run."""
        first, held = None, []
        for start in range(0, len(records), 100):
            for r in records[start:start + 100]:
                p.add_joint_state(r)
            if len(p.process().stamps_ns) and first is None:
                first = start + 100
            held.append(p.row_builder.holding)
        return first, held

    p = IdentificationPipeline(ROBOT, PipelineConfig(), BASE)
    first, _ = run(p, rest(2000) + moving)
    moved = 2000 + int(np.argmax(np.abs(sim.q_meas - sim.q_meas[0]).max(axis=1) > MOTION))
    assert p.smoother.source == 'automatic'
    assert p.smoother.seconds == pytest.approx(5.0, abs=2 / RATE)
    # a candidate per 50 samples after the 5 s: up to 40 candidates
    assert moved + 5.0 * RATE < first <= moved + 5.0 * RATE + 100 * 20

    still = IdentificationPipeline(ROBOT, PipelineConfig(auto_seconds=0.5), BASE)
    first, held = run(still, rest(6000))
    waited = int(AUTO_WAIT * 0.5 * RATE)
    assert held[:waited // 100] == list(range(100, waited + 1, 100))   # none decided before
    assert held[-1] == 0 and first is not None   # then decided: the held samples came out


def test_smoothed_sign_column_identifies_sign_friction_through_reversals():
    """Sign friction (fc 1, 0.5, 0.2 N m) at 100 Hz, noise-free, no equation left out
    (coulomb_exclusion_speed 0): the Coulomb column as the smoother makes of sign(qd)
    recovers fc, where sign(qd) itself (tanh(qd / 1e-9)) is biased by the smoothed torque's
    reversals; with the default exclusion speed fewer equations are left out than the
    former rule's |qd| < speed + |qdd| half window."""
    rate, fc = 100.0, [1.0, 0.5, 0.2]
    truth = load_robot('mit_dd_arm', extras=['fv', 'fc', 'fo'])
    phi = truth.phi_model.copy()
    for j, v in zip(truth.joint_names, fc):
        phi[truth.param_index(f'{j}.fc')], phi[truth.param_index(f'{j}.fv')] = v, 0.3
    t = np.arange(int(30 * rate)) / rate
    sim = simulate_kinematic(truth, phi, FourierTrajectory.random(truth, period=5.0, seed=4), t)
    ns = T0_NS + np.round(t * 1e9).astype(np.int64)

    def fit(velocity: float, speed: float):
        robot = load_robot('mit_dd_arm', extras=['fv', 'fc', 'fo'], coulomb_velocity=velocity)
        p = IdentificationPipeline(robot, PipelineConfig(half_window=8,
                                                         coulomb_exclusion_speed=speed))
        p.add_joint_states(JointStateRecord(ns, tuple(robot.joint_names), sim.q_meas,
                                            sim.qd_meas, sim.tau_meas))
        p.process(flush=True)
        est = [p.rls.theta[p.base.names.index(f'{j}.fc')] for j in robot.joint_names]
        return np.array(est), p.excluded_rows

    smoothed, none_out = fit(0.0, 0.0)
    assert none_out == 0
    np.testing.assert_allclose(smoothed, fc, rtol=0.02)
    plain, _ = fit(1e-9, 0.0)
    assert np.abs(plain / fc - 1).max() > 0.05
    (_, fewer), (_, former) = fit(0.0, 0.1), fit(1e-9, 0.1)
    assert 0 < fewer < former / 2
