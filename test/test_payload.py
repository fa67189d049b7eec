"""Payload identification and change detection against simulated arms with known payloads."""
import json
import math
import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest
import yaml

from identification_node.errors import IdentificationError
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.excitation.trajectories import load_trajectory
from identification_node.model.robot import PIN_ORDER, load_robot
from identification_node.simulation.simulator import ArmSimulator, SensorNoise, simulate_kinematic
from identification_node.payload.fit import (INERTIA_KEYS, PayloadChange, QUANTITIES, attachment,
                                             fit_payload, frame_transform, given_payload,
                                             payload_regressor, pseudo_inertia,
                                             read_payload_changes, true_parameter_changes,
                                             urdf_with_payload)
from identification_node.payload.monitor import MonitorConfig, PayloadMonitor
from identification_node.pipeline import IdentificationPipeline, PipelineConfig
from identification_node.wire.records import JointStateRecord

SIX = 'test/fixtures/six_dof_arm.urdf'
SEVEN = 'test/fixtures/panda_like.urdf'
# torque sensor noise and a 20-bit encoder (velocities differentiated by the smoother)
NOISE = SensorNoise(torque_std=0.05, encoder_counts=2 ** 20)


def run_monitor(robot, changes, duration, noise=NOISE, seed=0, link=None, drop=None,
                config=None):
    """Simulate the arm with payload events, stream it through the pipeline (1000-sample
    batches) and the monitor; returns (monitor, events)."""
    phi = robot.phi_model
    sim = ArmSimulator(robot, phi).run(load_trajectory('fourier', robot), duration, noise,
                                       seed, changes=true_parameter_changes(robot, phi, changes))
    keep = np.ones(len(sim), dtype=bool) if drop is None else ~(
        (sim.t >= drop[0]) & (sim.t < drop[1]))
    ns = np.round(sim.t[keep] * 1e9).astype(np.int64)
    pipe = IdentificationPipeline(robot, PipelineConfig())   # shipped defaults
    mon = PayloadMonitor(robot, attachment(robot, link), phi, config)
    events = []
    names = tuple(robot.joint_names)
    for a in range(0, len(ns), 1000):
        s = slice(a, a + 1000)
        pipe.add_joint_states(JointStateRecord(ns[s], names, sim.q_meas[keep][s],
                                               np.zeros((len(ns[s]), 0)), sim.tau_meas[keep][s]))
        out = pipe.process()
        events += mon.add_output(out)
    return mon, events


def test_frame_transform_is_pinocchios_inertia_action():
    rng = np.random.default_rng(1)
    for _ in range(5):
        M = pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3))
        body = pin.Inertia.Random()
        np.testing.assert_allclose(
            frame_transform(M) @ body.toDynamicParameters()[PIN_ORDER],
            M.act(body).toDynamicParameters()[PIN_ORDER], atol=1e-12)


def test_payload_regressor_is_the_torque_of_a_urdf_payload_link():
    """A payload on the fixed flange frame: Y_payload phi equals the torque difference of
    pinocchio's rnea with the payload written into the URDF as a fixed link."""
    robot = load_robot(SIX)
    att = attachment(robot, 'flange')
    phi = given_payload('flange', _params(1.2, (0.02, -0.03, 0.05),
                                          (0.004, 0.0002, -0.0001, 0.003, 0.0003, 0.002)))
    loaded = load_robot(urdf_with_payload(robot.description, phi))
    rng = np.random.default_rng(2)
    q, qd, qdd = (rng.uniform(-1, 1, (5, robot.dof)) for _ in range(3))
    tau = robot.rnea(q, qd, qdd)
    np.testing.assert_allclose(loaded.rnea(q, qd, qdd) - tau,
                               payload_regressor(att, robot.regressor(q, qd, qdd)) @ phi.phi,
                               atol=1e-10)


def _params(mass, com, inertia):
    return PayloadChange(0.0, None, mass, com, inertia).parameters()


CASES = [(SEVEN, None, 0.5, (0.0, 0.0, 0.03), (0.0004, 0, 0, 0.0004, 0, 0.0003)),
         (SEVEN, None, 1.0, (0.03, -0.02, 0.08), (0.003, 0.0002, 0, 0.004, 0, 0.002)),
         (SEVEN, None, 3.0, (-0.05, 0.04, 0.12), (0.012, 0, 0.001, 0.015, 0, 0.008)),
         (SIX, 'flange', 0.5, (0.01, 0.02, 0.04), (0.0005, 0, 0, 0.0006, 0, 0.0004)),
         (SIX, 'flange', 2.0, (0.06, 0.0, 0.1), (0.006, 0, 0.0005, 0.008, 0, 0.004))]


@pytest.mark.slow
@pytest.mark.parametrize('urdf, link, mass, com, inertia', CASES)
def test_payload_identified_within_targets(urdf, link, mass, com, inertia):
    """Mass within 2 %, centre of mass within 5 mm, inertia within 3 stddev, consistent:
    the segment after the pick, fitted from the pipeline's smoothed samples."""
    robot = load_robot(urdf)
    mon, events = run_monitor(robot, [PayloadChange(1.5, link, mass, com, inertia)], 7.0,
                              link=link)
    segments = mon.finish()
    assert [e.kind for e in events if e.kind != 'refresh'] == ['start', 'change', 'estimate']
    est = segments[-1].payload
    assert abs(est.mass - mass) <= 0.02 * mass
    assert np.abs(est.com - com).max() <= 0.005
    assert set(est.excited) == set(QUANTITIES)
    sd = np.array([est.stddev[f'inertia.{k}'] for k in INERTIA_KEYS])
    assert np.all(np.abs(est.inertia - inertia) <= 3 * sd), (est.inertia, inertia, sd)
    assert est.consistent and np.linalg.eigvalsh(pseudo_inertia(est.phi))[0] > 0
    doc = est.document()
    assert doc['link'] == (link or 'link7') and doc['not_excited'] == []


@pytest.mark.slow
def test_pick_and_place_detected_quickly_without_false_alarms():
    """7-DOF at 1 kHz: 1 kg picked at 4 s and placed at 10 s, detected within 0.5 s each,
    and nothing else declared over 16 s."""
    robot = load_robot(SEVEN)
    changes = [PayloadChange(4.0, None, 1.0, (0.0, 0.02, 0.06)), PayloadChange(10.0, None, 0.0)]
    mon, events = run_monitor(robot, changes, 16.0, seed=3)
    detected = [e for e in events if e.kind == 'change']
    assert len(detected) == 2
    for e, truth in zip(detected, (4.0, 10.0)):
        assert truth <= e.detected <= truth + 0.5
        assert abs(e.stamp - truth) <= 0.1      # the estimated onset
    segments = mon.finish()
    assert abs(segments[1].payload.mass - 1.0) <= 0.02
    assert abs(segments[2].payload.mass) <= 0.02


@pytest.mark.slow
def test_stream_drop_is_not_a_change():
    robot = load_robot(SEVEN)
    mon, events = run_monitor(robot, [PayloadChange(0.0, None, 0.8, (0, 0, 0.05))], 8.0,
                              drop=(3.0, 3.7))
    assert [e.kind for e in events if e.kind != 'refresh'] == ['start']
    assert mon.detector.gaps >= 1
    assert abs(mon.finish()[0].payload.mass - 0.8) <= 0.016


def test_no_motion_says_not_excited_never_nan():
    """At rest the gravity torque gives the mass (and the centre of mass across gravity),
    never the inertia; without samples nothing is excited. No value is NaN."""
    robot = load_robot(SEVEN)
    att = attachment(robot)
    truth = _params(1.0, (0.01, 0.02, 0.05), (0.002, 0, 0, 0.002, 0, 0.001))
    q = np.tile(np.array([0.3, -0.5, 0.2, -1.8, 0.1, 1.5, 0.4]), (3000, 1))
    zero = np.zeros_like(q)
    Y = robot.regressor(q, zero, zero)
    Yp = payload_regressor(att, Y)
    rng = np.random.default_rng(4)
    residual = Yp @ truth + 0.05 * rng.standard_normal(q.shape)
    est = fit_payload(NormalEquations.from_rows(Yp, residual), np.full(7, 0.05 ** 2), 'link7')
    assert 'mass' in est.excited and abs(est.mass - 1.0) < 0.02
    assert not any(k.startswith('inertia.') for k in est.excited)
    doc = est.document()
    assert doc['inertia'] == [None] * 6 and 'inertia.ixx' in doc['not_excited']
    text = json.dumps(doc)
    assert 'NaN' not in text and 'Infinity' not in text
    empty = fit_payload(NormalEquations.zeros(10, 7), np.full(7, 0.01), 'link7').document()
    assert empty['status'] == 'not excited' and empty['mass'] is None
    assert 'NaN' not in json.dumps(empty)


def test_a_fit_of_negative_mass_is_no_payload(monkeypatch):
    """Residuals that a negative mass would explain (an arm model too heavy, a glitch): the
    payload is none, consistent, with the mass's stddev, and no conic solve is tried."""
    import identification_node.payload.fit as fit
    robot = load_robot(SEVEN)
    att = attachment(robot)
    q = np.random.default_rng(5).uniform(-1.5, 1.5, (2000, 7))
    zero = np.zeros_like(q)
    Yp = payload_regressor(att, robot.regressor(q, zero, zero))
    residual = Yp @ -_params(0.5, (0.0, 0.0, 0.05), (0.001, 0, 0, 0.001, 0, 0.001))
    residual += 0.05 * np.random.default_rng(6).standard_normal(residual.shape)

    def refuse(*args):
        raise AssertionError('consistent_payload called')
    monkeypatch.setattr(fit, 'consistent_payload', refuse)
    est = fit_payload(NormalEquations.from_rows(Yp, residual), np.full(7, 0.05 ** 2), 'link7')
    assert est.mass == 0.0 and not est.phi.any() and est.consistent
    assert 0 < est.stddev['mass'] < 0.01 and 'mass' in est.excited


def test_unknown_or_unmoved_payload_link_refused():
    robot = load_robot(SIX)
    with pytest.raises(IdentificationError, match="payload.link: 'gripper'"):
        attachment(robot, 'gripper')
    with pytest.raises(IdentificationError, match='payload.link'):
        attachment(robot, 'pedestal')   # fixed to the base: no joint torque sees it
    assert attachment(robot).link == 'link6'


def test_payload_events_parsed_and_checked():
    c = read_payload_changes('[{time: 2, mass: 1.5, com: [0, 0, 0.1]}, {time: 1, mass: 0}]')
    assert [x.time for x in c] == [1.0, 2.0] and c[1].mass == 1.5
    for bad in ('[{mass: 1}]', '[{time: 1, mass: -1}]', '[{time: 1, weight: 2}]', '3'):
        with pytest.raises(IdentificationError, match='payload event'):
            read_payload_changes(bad)


@pytest.mark.slow
def test_simulate_and_identify_cli(tmp_path):
    """simulate --payload-events writes the true payloads; identify --payload --json gives
    payload_changes, the first at the bag's start."""
    bag = tmp_path / 'bag'
    env = {'PYTHONPATH': '.', 'OPENBLAS_NUM_THREADS': '1'}
    events = '[{time: 2.0, mass: 1.2, com: [0.0, 0.03, 0.07]}]'
    subprocess.run([sys.executable, '-m', 'identification_node', 'simulate', '--urdf', SEVEN,
                    '--duration', '5', '--torque-std', '0.05', '--encoder-counts', '1048576',
                    '--no-velocity', '--payload-events', events, '--out', str(bag)],
                   check=True, env=env, capture_output=True)
    truth = yaml.safe_load((bag / 'true_parameters.yaml').read_text())
    assert truth['payload_events'][0]['mass'] == 1.2
    assert truth['payload_events'][0]['link'] == 'link7'
    out = subprocess.run([sys.executable, '-m', 'identification_node', 'identify', str(bag),
                          '--urdf', SEVEN, '--payload', '--json'],
                         check=True, env=env, capture_output=True, text=True).stdout
    changes = json.loads(out)['payload_changes']
    assert len(changes) == 2
    assert changes[0]['detected'] is None and changes[0]['stamp'] < 0.05
    assert abs(changes[1]['stamp'] - 2.0) < 0.1
    p = changes[1]['payload']
    assert abs(p['mass'] - 1.2) < 0.024 and abs(p['com'][2] - 0.07) < 0.005
    assert set(p['stddev']) == {'mass', 'com', 'inertia'} and len(p['inertia']) == 6
    bad = subprocess.run([sys.executable, '-m', 'identification_node', 'identify', str(bag),
                          '--urdf', SEVEN, '--payload', '--payload-link', 'nothing'],
                         env=env, capture_output=True, text=True)
    assert bad.returncode == 2 and 'payload.link' in bad.stderr


def test_given_payload_is_watched():
    """A payload set by the user is the model the detector watches: a matching arm raises
    nothing, and its document reports it exactly."""
    robot = load_robot(SEVEN)
    mon = PayloadMonitor(robot, attachment(robot), robot.phi_model, MonitorConfig())
    est = mon.set_payload(_params(0.5, (0, 0, 0.04), (0.0003, 0, 0, 0.0003, 0, 0.0002)))
    assert math.isclose(est.document()['mass'], 0.5)


@pytest.mark.slow
def test_restarted_stream_is_not_a_change():
    """A bag played twice (stamps jump back): the payload stays, no change is declared."""
    robot = load_robot(SEVEN)
    phi = robot.phi_model
    changes = true_parameter_changes(robot, phi, [PayloadChange(0.0, None, 0.8, (0, 0, 0.05))])
    sim = ArmSimulator(robot, phi).run(load_trajectory('fourier', robot), 4.0, NOISE, 5,
                                       changes=changes)
    ns = np.round(sim.t * 1e9).astype(np.int64)
    pipe = IdentificationPipeline(robot, PipelineConfig())   # shipped defaults
    mon = PayloadMonitor(robot, attachment(robot), phi)
    events = []
    for _ in range(2):
        for a in range(0, len(ns), 500):
            s = slice(a, a + 500)
            pipe.add_joint_states(JointStateRecord(ns[s], tuple(robot.joint_names),
                                                   sim.q_meas[s], np.zeros((len(ns[s]), 0)),
                                                   sim.tau_meas[s]))
            out = pipe.process()
            events += mon.add_output(out)
    assert pipe.restarts == 1
    assert [e.kind for e in events if e.kind != 'refresh'] == ['start']
    assert abs(mon.finish()[0].payload.mass - 0.8) <= 0.016


@pytest.mark.slow
def test_stalled_and_bursting_stream_is_not_a_change():
    """A publisher stalls for 5-40 ms every 3 s and then sends the held samples at once with
    compressed stamps (as a loaded machine does): the smoothed accelerations go wild for a
    moment, the payload does not change, and no change is declared."""
    robot = load_robot(SEVEN)
    N = 12000
    t = np.arange(N) / 1000.0
    sim = simulate_kinematic(robot, None, load_trajectory('fourier', robot), t,
                             SensorNoise(torque_std=0.2), seed=6)
    rng = np.random.default_rng(6)
    stamp = t.copy()
    for k0 in range(2000, N, 3000):
        stall = rng.uniform(0.005, 0.04)
        m = int(stall * 1000)
        stamp[k0:k0 + m] = t[k0] + stall + np.arange(m) * 2e-5
    ns = np.round(np.maximum.accumulate(stamp + np.arange(N) * 1e-9) * 1e9).astype(np.int64)
    pipe = IdentificationPipeline(robot, PipelineConfig())   # shipped defaults
    mon = PayloadMonitor(robot, attachment(robot), robot.phi_model)
    events = []
    for a in range(0, N, 20):
        s = slice(a, a + 20)
        pipe.add_joint_states(JointStateRecord(ns[s], tuple(robot.joint_names), sim.q_meas[s],
                                               sim.qd_meas[s], sim.tau_meas[s]))
        out = pipe.process()
        events += mon.add_output(out)
    assert [e.kind for e in events if e.kind != 'refresh'] == ['start']
    assert mon.burst_samples > 0   # the compressed stamps were dropped, not smoothed


def _arm_error_case(seed: int, prior_samples: int = 60, samples: int = 300, sigma: float = 0.05):
    """Residuals of a payload plus an arm error drawn from the prior of an identification on
    ``prior_samples`` other samples (noise ``sigma`` N m): (normal equations of the payload's
    and the arm's base columns, the prior, the true payload, Yp, Yb, r)."""
    from identification_node.model.identifiability import BaseParameters, sample_motion
    from identification_node.payload.fit import ArmPrior
    robot = load_robot(SEVEN)
    base = BaseParameters.from_robot(robot)
    att = attachment(robot)
    rng = np.random.default_rng(seed)
    Yb_prev = base.base_regressor(robot.regressor(*sample_motion(robot, prior_samples, 100)))
    info = np.einsum('tjp,tjq->pq', Yb_prev, Yb_prev) / sigma ** 2
    cov = np.linalg.inv(info)
    prior = ArmPrior.from_covariance(base, cov)
    delta = rng.multivariate_normal(np.zeros(base.num_base), cov)
    Y = robot.regressor(*sample_motion(robot, samples, seed + 1))
    Yp, Yb = payload_regressor(att, Y), base.base_regressor(Y)
    truth = _params(0.8, (0.03, -0.02, 0.06), (0.02, 0, 0, 0.03, 0, 0.015))
    r = Yp @ truth + Yb @ delta + sigma * rng.standard_normal((samples, robot.dof))
    A = np.concatenate([Yp, Yb], axis=2)
    return NormalEquations.from_rows(A, r), prior, truth, Yp, Yb, r


def test_arm_prior_fit_is_the_joint_least_squares():
    """With the arm's uncertainty the payload is the joint weighted least squares of payload
    and arm correction with the prior's rows stacked below the data (a second formulation),
    and its covariance that solution's payload block."""
    ne, prior, truth, Yp, Yb, r = _arm_error_case(3)
    sigma = 0.05
    est = fit_payload(ne, np.full(7, sigma ** 2), 'link7', prior=prior)
    A = np.concatenate([Yp, Yb], axis=2).reshape(-1, ne.num_params) / sigma
    root = np.linalg.cholesky(prior.information).T
    stacked = np.vstack([A, np.hstack([np.zeros((len(root), 10)), root])])
    x = np.linalg.lstsq(stacked, np.concatenate([r.ravel() / sigma, np.zeros(len(root))]),
                        rcond=None)[0]
    assert est.consistent
    np.testing.assert_allclose(est.phi, x[:10], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(est.arm_correction, x[10:], rtol=1e-5, atol=1e-9)
    cov = np.linalg.inv(stacked.T @ stacked)[:10, :10]
    np.testing.assert_allclose(est.covariance, cov, rtol=1e-6, atol=1e-14)
    # the arm taken as exact: the same normal equations' payload columns alone
    exact = fit_payload(ne, np.full(7, sigma ** 2), 'link7')
    alone = np.linalg.lstsq(Yp.reshape(-1, 10), r.ravel(), rcond=None)[0]
    np.testing.assert_allclose(exact.phi, alone, rtol=1e-6, atol=1e-9)


def test_arm_prior_makes_the_payload_stddev_honest():
    """Arm errors drawn from the arm's own covariance: taken as exact, the arm's error leaks
    into the payload far beyond its reported stddev; with the prior the errors are of the
    size the stddev says (mass and centre of mass z-scores' RMS about 1), and no larger (the
    joint fit is the least-squares estimate given the prior)."""
    z_exact, z_prior, err_exact, err_prior = [], [], [], []
    for seed in range(40):
        ne, prior, truth, *_ = _arm_error_case(10 + seed)
        true_mass, true_com = truth[0], truth[1:4] / truth[0]
        for prior_or_none, zs, errs in ((None, z_exact, err_exact),
                                        (prior, z_prior, err_prior)):
            est = fit_payload(ne, np.full(7, 0.05 ** 2), 'link7', prior=prior_or_none)
            zs.append((est.mass - true_mass) / est.stddev['mass'])
            zs += [(est.com[k] - true_com[k]) / est.stddev[f'com.{a}']
                   for k, a in enumerate('xyz')]
            errs.append(np.abs(est.com - true_com).max())
    rms = lambda z: float(np.sqrt(np.mean(np.square(z))))   # noqa: E731
    assert 0.7 < rms(z_prior) < 1.4, rms(z_prior)
    assert rms(z_exact) > 2.5, rms(z_exact)
    mse = lambda e: float(np.mean(np.square(e)))   # noqa: E731
    assert mse(err_prior) <= mse(err_exact), (mse(err_prior), mse(err_exact))


def test_a_segments_arm_information_carries_into_the_next_fit():
    """Two spans, each with payload parameters of its own: the second span's fit with the
    prior updated by what the first told of the arm (arm_information) is the joint least
    squares of both spans' payloads and one arm correction, stacked with the prior."""
    from identification_node.payload.fit import arm_information
    sigma = 0.05
    ne1, prior, _, Yp1, Yb1, r1 = _arm_error_case(21)
    ne2, _, _, Yp2, Yb2, r2 = _arm_error_case(22)
    var = np.full(7, sigma ** 2)
    est = fit_payload(ne2, var, 'link7', prior=prior.updated(*arm_information(ne1, var)))
    nb = Yb1.shape[2]
    rows1 = np.concatenate([Yp1, np.zeros_like(Yp1), Yb1], axis=2).reshape(-1, 20 + nb)
    rows2 = np.concatenate([np.zeros_like(Yp2), Yp2, Yb2], axis=2).reshape(-1, 20 + nb)
    root = np.linalg.cholesky(prior.information).T
    stacked = np.vstack([rows1 / sigma, rows2 / sigma,
                         np.hstack([np.zeros((nb, 20)), root])])
    x = np.linalg.lstsq(stacked, np.concatenate([r1.ravel(), r2.ravel(), np.zeros(nb)])
                        / np.r_[np.full(r1.size + r2.size, sigma), np.ones(nb)], rcond=None)[0]
    assert est.consistent
    np.testing.assert_allclose(est.phi, x[10:20], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(est.arm_correction, x[20:], rtol=1e-5, atol=1e-9)
    cov = np.linalg.inv(stacked.T @ stacked)[10:20, 10:20]
    np.testing.assert_allclose(est.covariance, cov, rtol=1e-6, atol=1e-14)
