"""Robustness of the pipeline to implausible input and poisoned samples (no ROS): the cases of
an outside attack run (issue 16) as tests. Truth: the same stream without the poison, the
simulation's known parameters, the URDF's own numbers."""
import resource
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from identification_node.estimation.robust import InnovationGate, RobustSettings
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.identifiability import BaseParameters
from identification_node.model.plausibility import PlausibilityBounds, PlausibilitySettings
from identification_node.model.robot import BUNDLED_DIR, load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.model.torque import JointTorqueConfig, TorqueConverter
from identification_node.pipeline import IdentificationPipeline, PipelineConfig
from identification_node.wire.cdr import encode_joint_states

RATE = 1000.0
T0_NS = 1_700_000_000_000_000_000
ROBOT = load_robot('mit_dd_arm')
BASE = BaseParameters.from_robot(ROBOT)
TRUE = BASE.to_base(ROBOT.phi_model)
NAMES = tuple(ROBOT.joint_names)
THREE_PHASE = {j: JointTorqueConfig(source='three_phase', kt=kt, pole_pairs=8)
               for j, kt in zip(ROBOT.joint_names, (12.0, 6.0, 6.0))}


def simulate(duration=20.0, phi=None, seed=1, converter=None, torque_std=0.5):
    traj = FourierTrajectory.random(ROBOT, harmonics=4, period=10.0, seed=seed)
    t = np.arange(int(duration * RATE)) / RATE
    return simulate_kinematic(ROBOT, phi, traj, t, SensorNoise(torque_std=torque_std),
                              seed=seed, converter=converter)


def stamps(sim):
    return T0_NS + np.round(sim.t * 1e9).astype(np.int64)


def run(sim, config=None, position=None, velocity=None, effort=None, cdr=False, chunk=50):
    """The pipeline fed the simulated stream (optionally with some arrays replaced), in
    chunks as the node does; as CDR messages (the node's path) or as records."""
    # the smoother pinned: the gate acts once converged, and the automatic choice would
    # hold the first 5 s back and give them to the estimator at once, ungated
    p = IdentificationPipeline(ROBOT, config or PipelineConfig(half_window=10), BASE)
    q = sim.q_meas if position is None else position
    qd = sim.qd_meas if velocity is None else velocity
    tau = sim.tau_meas if effort is None else effort
    st = stamps(sim)
    for a in range(0, len(st), chunk):
        b = slice(a, a + chunk)
        if cdr:
            p.add_joint_state_cdr(encode_joint_states(st[b], NAMES, q[b], qd[b], tau[b]))
        else:
            from identification_node.wire.records import JointStateRecord
            p.add_joint_states(JointStateRecord(st[b], NAMES, q[b], qd[b], tau[b]))
        p.process()
    p.process(flush=True)
    return p


@pytest.fixture(scope='module')
def clean():
    sim = simulate()
    return sim, run(sim).estimate()


def moved(est, ref):
    """How far ``est`` moved from ``ref``, in ``ref``'s standard deviations (max)."""
    return float(np.max(np.abs(est.values - ref.values) / ref.stddev))


# -- bounds ------------------------------------------------------------------------------------
def test_bounds_come_from_the_urdf_limits_times_the_margin():
    root = ET.parse(BUNDLED_DIR / 'crs_a465.urdf').getroot()
    limits = {j.get('name'): j.find('limit') for j in root.iter('joint')}
    robot = load_robot('crs_a465')
    b = PlausibilityBounds.from_robot(robot, PlausibilitySettings(margin=1.5))
    for i, name in enumerate(robot.joint_names):
        lim = limits[name]
        lo, hi = float(lim.get('lower')), float(lim.get('upper'))
        c, h = (lo + hi) / 2, (hi - lo) / 2
        assert b.position_lower[i] == pytest.approx(c - 1.5 * h)
        assert b.position_upper[i] == pytest.approx(c + 1.5 * h)
        assert b.velocity[i] == pytest.approx(1.5 * float(lim.get('velocity')))
        assert b.effort[i] == pytest.approx(1.5 * float(lim.get('effort')))
        assert b.current[i] == pytest.approx(1.5 * float(lim.get('effort')))   # kt 1, ratio 1


def test_defaults_where_the_urdf_has_no_limit_and_a_current_limit_per_joint():
    # mit_dd_arm: continuous joints (no range), velocity 10 rad/s, effort 660 / 230 N m
    s = PlausibilitySettings(margin=2.0, position=500.0, acceleration=300.0)
    b = PlausibilityBounds.from_robot(ROBOT, s, gear_ratio=[1, 2, 1], kt=[12, 6, 6])
    assert np.all(b.position_upper == 500.0) and np.all(b.position_lower == -500.0)
    np.testing.assert_allclose(b.velocity, 20.0)
    np.testing.assert_allclose(b.acceleration, 300.0)
    np.testing.assert_allclose(b.effort, [1320, 460, 460])
    np.testing.assert_allclose(b.current, [1320 / 12, 460 / 12, 460 / 6])
    b = PlausibilityBounds.from_robot(ROBOT, PlausibilitySettings(current_limit=[30, 0, 7]))
    np.testing.assert_allclose(b.current, [30, 460, 7])
    six = load_robot('test/fixtures/six_dof_arm.urdf')   # a prismatic joint, a continuous one
    b = PlausibilityBounds.from_robot(six)
    k = six.joint_names.index(next(j for j, p in zip(six.joint_names, six.prismatic) if p))
    assert b.position_upper[k] == pytest.approx(0.025 + 2 * 0.175)
    assert np.isinf(six.position_limits).any() and np.isfinite(b.position_upper).all()


@pytest.mark.parametrize('field, value', [('margin', 0.5), ('velocity', -1.0),
                                          ('current_limit', [1.0, 2.0])])
def test_bad_plausibility_settings_name_the_parameter(field, value):
    from identification_node.errors import IdentificationError
    with pytest.raises(IdentificationError, match=f'plausibility.{field}'):
        PlausibilitySettings(**{field: value}).validate(3)


# -- implausible samples -----------------------------------------------------------------------
@pytest.mark.parametrize('cdr', [False, True], ids=['records', 'cdr'])
def test_one_absurd_velocity_does_not_move_a_converged_estimate(clean, cdr):
    sim, ref = clean
    qd = sim.qd_meas.copy()
    qd[15000, 0] = 1e5      # the attack: 1e5 rad/s, the URDF's limit is 10
    p = run(sim, velocity=qd, cdr=cdr)
    est = p.estimate()
    assert p.rejected['implausible'] >= 1
    assert est.converged and moved(est, ref) < 0.1


@pytest.mark.parametrize('value', [1e10, 1e60, 1e77, 1e100, 1e300])
@pytest.mark.parametrize('cdr', [False, True], ids=['records', 'cdr'])
def test_huge_finite_values_are_rejected_with_finite_results(clean, value, cdr):
    sim, ref = clean
    qd, q, tau = sim.qd_meas.copy(), sim.q_meas.copy(), sim.tau_meas.copy()
    qd[3000:3010, 1] = value
    q[8000, 2] = -value
    tau[12000, 0] = value
    p = run(sim, position=q, velocity=qd, effort=tau, cdr=cdr)
    est = p.estimate()
    assert p.rejected['implausible'] >= 12
    assert np.isfinite(est.values).all() and np.isfinite(est.stddev).all()
    assert moved(est, ref) < 0.2


@pytest.mark.parametrize('cdr', [False, True], ids=['records', 'cdr'])
def test_non_finite_and_absurd_rows_of_one_block_are_told_apart(clean, cdr):
    """A NaN velocity, an infinite position and an absurd finite velocity in one block: two
    rows counted non_finite, one implausible, and the others of the block used."""
    sim, _ = clean
    q, qd = sim.q_meas.copy(), sim.qd_meas.copy()
    qd[5010, 0], q[5020, 1], qd[5030, 2] = np.nan, np.inf, 1e5
    p = run(sim, position=q, velocity=qd, cdr=cdr)
    assert p.rejected['non_finite'] == 2 and p.rejected['implausible'] == 1
    assert p.received == len(q) and np.isfinite(p.estimate().values).all()


def test_an_infinite_value_fails_an_unbounded_gate():
    """Bounds of inf (no bound) pass every finite value, and not inf or NaN."""
    n = 2
    b = PlausibilityBounds(np.full(n, -np.inf), np.full(n, np.inf), np.full(n, np.inf),
                           np.full(n, np.inf), np.full(n, np.inf), np.full(n, np.inf))
    qd = np.array([[1e300, -1e300], [np.inf, 0.0], [0.0, -np.inf], [np.nan, 0.0]])
    np.testing.assert_array_equal(b.ok(qd=qd), [True, False, False, False])
    np.testing.assert_array_equal(b.ok(q=qd), [True, False, False, False])


def test_absurd_currents_and_an_infinite_electrical_angle_are_counted():
    conv = TorqueConverter(ROBOT.joint_names, [THREE_PHASE[j] for j in ROBOT.joint_names])
    sim = simulate(duration=6.0, converter=conv, torque_std=0.0)
    p = IdentificationPipeline(ROBOT, PipelineConfig(torque=THREE_PHASE), BASE)
    slots = conv.current_channel_slots()
    names = tuple(n for n, _, _ in slots)
    cur = np.stack([sim.currents[:, i, k] for _, i, k in slots], axis=1)
    cur[2000, 0] = 1e200                     # the attack: 1e200 A
    theta = np.full_like(cur, np.nan)        # electrical angles not given ...
    theta[4000:4200] = np.inf                # ... but infinite in 200 messages
    st = stamps(sim)
    from identification_node.wire.records import JointStateRecord
    for a in range(0, len(st), 50):
        b = slice(a, a + 50)
        p.add_joint_states(JointStateRecord(st[b], NAMES, sim.q_meas[b], sim.qd_meas[b],
                                            np.empty((len(st[b]), 0))))
        for k in range(a, min(a + 50, len(st))):
            p.add_currents(JointStateRecord(int(st[k]), names, theta[k], np.empty(0), cur[k]))
        p.process()
    p.process(flush=True)
    assert p.rejected['implausible'] == 1
    assert p.rejected['non_finite'] == 200
    est = p.estimate()
    assert np.isfinite(est.values).all() and np.isfinite(est.stddev).all()
    # every joint state accounted for: used, without a current, at the smoother's edges
    # around the gap they leave, or in the smoother's delay at the end
    assert p.rejected['no_current'] >= 190
    assert p.used + p.rejected['no_current'] + p.smoother_edge + int(p.delay) \
        == len(st)


# -- robust estimation -------------------------------------------------------------------------
def poisoned(sim, fraction, seed=0, contiguous=False, size=100.0, start=12000):
    """Measured torques with ``fraction`` of the samples after ``start`` replaced by outliers
    of +-``size`` N m on one joint (plausible: within the effort limit)."""
    rng = np.random.default_rng(seed)
    tau = sim.tau_meas.copy()
    n = int(fraction * (len(tau) - start))
    idx = (start + np.arange(n) if contiguous
           else rng.choice(np.arange(start, len(tau)), n, replace=False))
    tau[idx, rng.integers(0, ROBOT.dof, n)] += size * rng.choice([-1, 1], n)
    return tau


@pytest.mark.parametrize('contiguous', [False, True], ids=['scattered', 'burst'])
def test_one_percent_outliers_move_a_converged_estimate_less_than_one_stddev(clean, contiguous):
    sim, ref = clean
    tau = poisoned(sim, 0.01, contiguous=contiguous)
    est = run(sim, effort=tau).estimate()
    ungated = run(sim, PipelineConfig(half_window=10, robust=RobustSettings(enabled=False)),
                  effort=tau)
    assert moved(est, ref) < 1.0
    assert moved(ungated.estimate(), ref) > 1.0     # what the gate prevents


def test_one_sample_outlier_is_gated_and_counted(clean):
    sim, ref = clean
    tau = sim.tau_meas.copy()
    tau[16000, 1] += 200.0
    p = run(sim, effort=tau)
    assert p.gate.armed and p.rejected['outlier'] >= 1
    assert moved(p.estimate(), ref) < 0.2


@pytest.mark.slow
def test_twenty_percent_outliers_no_worse_than_without_gating(clean):
    sim, _ = clean
    tau = poisoned(sim, 0.2, start=0)
    gated = run(sim, effort=tau).estimate()
    ungated = run(sim, PipelineConfig(half_window=10, robust=RobustSettings(enabled=False)),
                  effort=tau)
    err = np.linalg.norm((gated.values - TRUE) / gated.stddev)
    err_ungated = np.linalg.norm((ungated.estimate().values - TRUE) / gated.stddev)
    assert err <= err_ungated * 1.01


@pytest.mark.slow
def test_a_sustained_shift_is_reported_and_not_hidden():
    """A payload change: the last link 5 kg heavier after 12 s. The gate reports a residual
    shift and stops gating, so the estimate follows the data as without gating."""
    heavy = ROBOT.phi_model.copy()
    heavy[20] += 5.0          # link3.m
    before, after = simulate(duration=12.0), simulate(duration=24.0, phi=heavy)
    sim = before
    for name in ('q_meas', 'qd_meas', 'tau_meas'):
        setattr(sim, name, np.concatenate([getattr(before, name),
                                           getattr(after, name)[12000:]]))
    sim.t = np.arange(24000) / RATE
    events = []
    config = PipelineConfig(half_window=10, robust=RobustSettings(window=500))
    p = IdentificationPipeline(ROBOT, config, BASE)
    p.gate.listeners.append(events.append)
    st = stamps(sim)
    from identification_node.wire.records import JointStateRecord
    for a in range(0, len(st), 50):
        b = slice(a, a + 50)
        p.add_joint_states(JointStateRecord(st[b], NAMES, sim.q_meas[b], sim.qd_meas[b],
                                            sim.tau_meas[b]))
        p.process()
    p.process(flush=True)
    ungated = run(sim, PipelineConfig(half_window=10, robust=RobustSettings(enabled=False)))
    assert p.gate.shifts >= 1 and events and events[0].stamp > 12.0
    assert events[0].fraction >= 0.5
    # nothing held back for good: outliers only before the shift was seen, fewer than a window
    assert p.rejected['outlier'] < 500
    est, ref = p.estimate(), ungated.estimate()
    assert moved(est, ref) < 1.0


@pytest.mark.parametrize('chunk', [1, 50, 997, 2000])
def test_clean_samples_are_not_gated_however_they_are_batched(chunk):
    """No outlier in the stream, none gated: the gate arms on whichever batch comes once the
    estimate converged, and the next samples' motion is not yet the fit's. Their innovation
    has the estimate's own variance too (y P y'); the residual's alone gated 45 (chunks of
    997) and 75 (2000) of these clean samples, as a live node's batches did under load."""
    p = run(simulate(), chunk=chunk)
    assert p.gate.armed and p.rejected['outlier'] == 0


def test_gate_unit_behaviour():
    gate = InnovationGate(RobustSettings(k=3.0, window=100, shift_fraction=0.5))
    r = np.zeros((10, 2))
    r[3, 1] = 10.0
    keep, back = gate.screen(r, np.ones(2))
    assert keep.all() and not back                 # not armed: everything passes
    gate.armed = True
    keep, back = gate.screen(r, np.ones(2), held=lambda g: g.nonzero()[0])
    assert keep.tolist() == [k != 3 for k in range(10)] and gate.outliers == 1
    shifted = np.full((60, 2), 10.0)
    keep, back = gate.screen(shifted, np.ones(2), held=lambda g: 'held')
    assert keep.all() and gate.suspended and gate.shifts == 1
    assert [b.tolist() for b in back] == [[3]] and gate.outliers == 0
    keep, _ = gate.screen(np.zeros((200, 2)), np.ones(2))
    assert keep.all() and not gate.suspended       # the fraction fell: gating again
    keep, _ = gate.screen(r, np.ones(2))
    assert not keep[3]
    sigma = np.ones((10, 2))
    sigma[3] = 4.0                                 # this sample's innovation is wider
    keep, _ = gate.screen(r, sigma)
    assert keep.all()


def test_gate_arms_only_on_a_batch_the_estimate_predicts():
    gate = InnovationGate(RobustSettings(k=3.0))
    rng = np.random.default_rng(2)
    r = rng.standard_normal((200, 2)) * 0.5
    r[:20, 0] = 10.0                                # 10 % of the batch beyond 3 sigma
    assert not gate.arm(r, np.ones(2)) and not gate.armed
    keep, _ = gate.screen(r, np.ones(2))
    assert keep.all()                               # not armed: nothing held back
    r[4:20, 0] = 0.0                                # 2 %: a few spikes
    assert gate.arm(r, np.ones(2)) and gate.armed
    assert gate.arm(np.zeros((0, 2)), np.ones(2))   # an empty batch leaves it armed


# -- numerical failure ---------------------------------------------------------------------------
def test_a_failing_update_rolls_back_to_the_last_finite_state(clean, monkeypatch):
    sim, _ = clean
    p = run(sim)
    before = p.estimate()
    rls = p.rls

    def broken(*args, **kwargs):
        rls._theta = rls._theta * np.nan    # half-way through, as a failing update would
        raise np.linalg.LinAlgError('Eigenvalues did not converge')

    monkeypatch.setattr(rls, 'update_rows', broken)
    from identification_node.wire.records import JointStateRecord
    st = stamps(sim) + 10**11
    p.add_joint_states(JointStateRecord(st[:500], NAMES, sim.q_meas[:500], sim.qd_meas[:500],
                                        sim.tau_meas[:500]))
    p.process(flush=True)
    after = p.estimate()
    assert p.numerical_failures >= 1 and p.rejected['numerical_failure'] > 0
    np.testing.assert_array_equal(after.values, before.values)
    assert np.isfinite(after.stddev).all()


# -- bounded memory ------------------------------------------------------------------------------
def _rss_bytes() -> int:
    with open('/proc/self/statm') as f:
        return int(f.read().split()[1]) * resource.getpagesize()


@pytest.mark.slow
def test_names_per_message_are_capped_and_the_layout_cache_is_bounded_in_bytes():
    limit = 1 << 20
    p = IdentificationPipeline(ROBOT, PipelineConfig(layout_cache_bytes=limit), BASE)
    rng = np.random.default_rng(0)
    rss0 = _rss_bytes()
    for k in range(40):   # 10^4 names per message: rejected before any layout is made
        names = NAMES + tuple(f'x{k}_{i}' for i in range(10_000))
        p.add_joint_state_cdr(encode_joint_states([T0_NS + k], names,
                                                  rng.random((1, len(names)))))
        p.process()
    assert p.rejected['too_many_names'] == 40
    for k in range(3000):   # many distinct layouts of 250 names each: about 40 kB apiece
        names = NAMES + tuple(f'layout{k}_{i}' for i in range(247))
        p.add_joint_state_cdr(encode_joint_states([T0_NS + 10**6 * (k + 1)], names,
                                                  rng.random((1, 250)), None,
                                                  rng.random((1, 250))))
        p.process()
    assert 0 < p.layout_cache_bytes <= limit
    assert len(p.samples.validate.cache) < 3000
    # unbounded, the 3000 layouts alone would hold over 100 MB
    assert _rss_bytes() - rss0 < 60 << 20
