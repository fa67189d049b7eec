"""Payload detection and identification with the shipped defaults, on arms the suite did not
have: each arm identified first by the default pipeline (automatic smoother), then watched
through a sequence of payload changes (payload_scenarios.py). Targets in every cell: each
change detected within 0.5 s, mass within 2 %, centre of mass within 5 mm, nothing else
declared. The bench (bench/bench_payload.py) runs the full matrix; this is a spread of it:
every arm, every rate, both noise ends, with and without friction, every sequence."""
import numpy as np
import pytest

from identification_node.payload.fit import PayloadChange

import payload_scenarios as ps

pytestmark = pytest.mark.slow

PICK = (0.03, -0.02, 0.06)      # centres of mass, m, in the flange link's frame
OTHER = (-0.05, 0.08, 0.04)
SEQUENCES = {
    'pick': [PayloadChange(4.0, None, 1.0, PICK)],
    'pick-place': [PayloadChange(4.0, None, 3.0, OTHER), PayloadChange(9.0, None, 0.0)],
    'pick-place-pick': [PayloadChange(3.0, None, 1.0, PICK), PayloadChange(8.0, None, 0.0),
                        PayloadChange(13.0, None, 0.25, OTHER)],
    'two payloads': [PayloadChange(3.0, None, 2.0, PICK), PayloadChange(8.0, None, 0.0),
                     PayloadChange(13.0, None, 0.5, OTHER)],
}
NIL = 0.02   # kg: no payload is reported within the default payload.tolerance.mass
# arm, rate Hz, torque noise N m, joint friction, sequence
CELLS = [('ur5', 1000.0, 0.1, True, 'pick-place-pick'),
         ('panda', 500.0, 0.2, True, 'two payloads'),
         ('kinova', 250.0, 0.05, False, 'pick-place'),
         ('fixture', 2000.0, 0.2, True, 'pick')]


def check_cell(name: str, rate: float, noise: float, friction: bool, changes: list,
               seed: int = 3) -> None:
    arm = ps.make_arm(name, friction)
    mon, events, segments = ps.run(arm, ps.identify_arm(arm, rate, noise), rate, noise, seed,
                                   changes)
    detected = [ps.seconds(e.detected) for e in events if e.kind == 'change']
    truth = [c.time for c in changes]
    assert len(detected) == len(truth), (detected, truth)
    for d, t in zip(detected, truth):
        assert t <= d <= t + 0.5, (d, t)
    assert mon.warnings() == []
    for seg, c in zip(segments[1:], changes):
        p = seg.payload
        assert abs(p.mass - c.mass) <= max(0.02 * c.mass, NIL), (p.mass, c.mass)
        if c.mass:
            assert np.abs(p.com - c.com).max() <= 0.005, (p.com, c.com)
    assert abs(segments[0].payload.mass) <= NIL


@pytest.mark.parametrize('name, rate, noise, friction, sequence', CELLS)
def test_payload_changes_meet_targets_with_defaults(name, rate, noise, friction, sequence):
    check_cell(name, rate, noise, friction, SEQUENCES[sequence])


def test_light_payload_errors_stay_within_their_stddev():
    """UR5 at 250 Hz, 0.2 N m, friction, the arm identified on 30 s: with the arm taken as
    exact its error moved a 0.25 kg payload's centre of mass by 9-13 mm, 2-5 of the stddev
    reported. With the arm's covariance every segment's error lies within 3 stddev (the
    0.25 kg's CoM stddev is 3-5 mm here: the 5 mm target is beyond its information, 4.1 mm
    with the true arm), and the 1 kg payload meets the targets."""
    arm = ps.make_arm('ur5', True)
    changes = SEQUENCES['pick-place-pick']
    *_, segments = ps.run(arm, ps.identify_arm(arm, 250.0, 0.2), 250.0, 0.2, 3, changes)
    assert len(segments) == len(changes) + 1
    for seg, c in zip(segments[1:], changes):
        p = seg.payload
        assert abs(p.mass - c.mass) <= 3 * p.stddev['mass'], (p.mass, c.mass, p.stddev)
        if c.mass:
            sd = np.array([p.stddev[f'com.{a}'] for a in 'xyz'])
            assert (np.abs(p.com - c.com) <= 3 * sd).all(), (p.com, c.com, sd)
    first = segments[1].payload
    assert abs(first.mass - 1.0) <= 0.02 and np.abs(first.com - PICK).max() <= 0.005


def test_a_late_onset_leaves_the_segment_before_unbiased():
    """UR5 at 2 kHz, 0.2 N m, the true arm: the place at 8 s is dated 8.06 s; the samples
    between, cut at the estimated onset, had made the 2 kg segment before it 10 g light (5.4
    stddev). Every segment's mass now lies within 3 stddev."""
    arm = ps.make_arm('ur5', True)
    changes = SEQUENCES['two payloads']
    *_, segments = ps.run(arm, arm.phi, 2000.0, 0.2, 13, changes)
    assert len(segments) == len(changes) + 1
    for seg, c in zip(segments[1:], changes):
        p = seg.payload
        assert abs(p.mass - c.mass) <= 3 * p.stddev['mass'], (p.mass, c.mass, p.stddev)


def test_segments_tell_the_arm_no_more_than_they_know():
    """Kinova at 500 Hz, 0.05 N m, friction: every segment's end adds what it told of the
    arm to the prior the next are fitted with. Counted with the long-run noise alone, blind
    to the derivatives' noise in the regressor, the arm's error had reached chi-square 235
    in the refined prior's metric (54 parameters) and the 0.5 kg payload after the place was
    5.7 mm off, 8 stddev. The arm's error stays within the prior's 99.9 % region; every
    payload within 3 stddev and the targets."""
    from scipy.stats import chi2

    arm = ps.make_arm('kinova', True)
    ident = ps.identify_arm(arm, 500.0, 0.05)
    changes = SEQUENCES['two payloads']
    mon, _, segments = ps.run(arm, ident, 500.0, 0.05, 13, changes)
    base = ident.prior.base
    e = mon.prior.mean() - (base.to_base(arm.phi) - base.to_base(ident.phi))
    chi_square = float(e @ mon.prior.information @ e)
    assert chi_square <= chi2.ppf(0.999, base.num_base), chi_square
    assert len(segments) == len(changes) + 1
    for seg, c in zip(segments[2:], changes[1:]):   # after the first segment's information
        p = seg.payload
        assert abs(p.mass - c.mass) <= min(3 * p.stddev['mass'], max(0.02 * c.mass, NIL))
        if c.mass:
            sd = np.array([p.stddev[f'com.{a}'] for a in 'xyz'])
            assert (np.abs(p.com - c.com) <= np.minimum(3 * sd, 0.005)).all(), (p.com, sd)


def test_a_change_the_window_tells_well_is_declared_at_a_low_rate():
    """Kinova at 250 Hz, 0.2 N m, the arm identified: the 2 kg payload placed at 8 s while
    the motion tells the mass less well than before (its window's mass stddev 0.05-0.08 kg).
    The change (-1.9 kg, 23-36 of its stddev from 8.3 s) waited until 9.1 s for the window
    to know the mass within 0.05 kg (a quarter of min_change), its onset placed at 8.75 s
    and the 2 kg segment fitted 2.4 % light. Within half of min_change it is declared in
    0.35 s, and every change within 0.5 s."""
    arm = ps.make_arm('kinova', False)
    changes = SEQUENCES['two payloads']
    _, events, segments = ps.run(arm, ps.identify_arm(arm, 250.0, 0.2), 250.0, 0.2, 43,
                                 changes)
    detected = [ps.seconds(e.detected) for e in events if e.kind == 'change']
    assert len(detected) == len(changes)
    for d, c in zip(detected, changes):
        assert c.time <= d <= c.time + 0.5, (d, c.time)
    assert abs(segments[1].payload.mass - 2.0) <= 0.04, segments[1].payload.mass


def test_unidentified_arm_is_named_and_nothing_declared():
    """The arm's friction is not in the URDF's model: the monitor says so (the issue's
    message) instead of reporting 'not excited' silently, and declares no change."""
    arm = ps.make_arm('ur5', True)
    mon = ps.monitor(arm, arm.robot.phi_model)      # friction absent from the arm's model
    events = ps.watch(mon, ps.simulate(arm, 500.0, 4.0, 0.1, 5))
    assert not [e for e in events if e.kind == 'change']
    [warning] = mon.warnings()
    assert warning.startswith("the arm's residual is ") and warning.endswith(
        'times the noise: identify the arm first and pass --arm')
    assert mon.arm_residual_ratio > 10


def test_samples_after_a_change_stay_out_of_the_segment_before():
    """A change is declared up to window + confirm after its onset: the samples between
    stay out of the fit of the segment it ends. Exact data (true arm, exact encoders, no
    torque noise), Kinova at 250 Hz: the 1 kg segment before the place at 8 s was fitted
    2.9 % light when they entered it."""
    import identification_node.simulation.simulator as simulation

    arm = ps.make_arm('kinova', False)
    changes = SEQUENCES['pick-place-pick']
    sim = ps.simulate(arm, 250.0, changes[-1].time + 5.0, 0.0, 12, changes)
    exact = simulation.SensorNoise()
    sim = simulation.measure(arm.robot, sim.t, sim.q, sim.qd, sim.qdd, sim.tau, exact,
                             np.random.default_rng(0), None)
    mon = ps.monitor(arm, arm.phi)
    ps.watch(mon, sim)
    segments = mon.finish()
    assert len(segments) == len(changes) + 1
    for seg, c in zip(segments[1:], changes):
        error = seg.payload.mass - c.mass
        assert abs(error) <= 0.002 * max(c.mass, 1.0), (seg.payload.mass, c.mass)


def test_arm_estimate_file_brings_its_covariance(tmp_path):
    """--arm / payload.arm with an estimate.yaml as ~/save writes it: the monitor fits with
    the arm's base-parameter covariance as its prior; an estimate of other base parameters
    is refused naming the parameter."""
    import yaml

    from identification_node.errors import IdentificationError
    from identification_node.payload.monitor import monitor_from_settings
    from identification_node.results.documents import estimate_document, write_results
    from identification_node.settings import Settings

    arm = ps.make_arm('ur5', True)
    pipe = arm.settings.build(arm.robot)
    ps.stream(pipe, ps.simulate(arm, 250.0, 20.0, 0.1, 7))
    pipe.process(flush=True)
    [path, _] = write_results(tmp_path, estimate_document(pipe), arm.robot, inconsistent=True)
    settings = Settings(dict(arm.settings.values, **{'payload.arm': str(path)}),
                        arm.settings.given)
    mon = monitor_from_settings(settings, arm.robot)
    assert mon.columns == 10 + pipe.base.num_base and mon.prior is not None
    np.testing.assert_allclose(mon.prior.information @ pipe.covariance,
                               np.eye(pipe.base.num_base), atol=1e-6)
    np.testing.assert_allclose(mon.phi_arm, pipe.standard_parameters())
    doc = yaml.safe_load(path.read_text())
    doc['base_parameters'][0]['name'] = 'other'
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(IdentificationError, match='parameter payload.arm: .* base parameters'):
        monitor_from_settings(settings, arm.robot)
