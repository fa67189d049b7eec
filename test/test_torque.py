"""Torque sources: paper 000 eq. 10, its inverse, single-current law, wiring errors, configs."""
import numpy as np
import pytest

from identification_node.errors import IdentificationError
from identification_node.model.torque import (JointTorqueConfig, TorqueConverter, electrical_angle,
                                              phase_currents, three_phase_torque)

DEG = np.pi / 180.0


def _random_configs(rng, names):
    out = {}
    for k, j in enumerate(names):
        source = ('measured', 'current', 'three_phase')[k % 3]
        out[j] = dict(source=source, kt=float(rng.uniform(0.05, 2.0)),
                      gear_ratio=float(rng.uniform(1.0, 160.0)),
                      pole_pairs=int(rng.integers(1, 12)),
                      angle_offset=float(rng.uniform(-np.pi, np.pi)),
                      phase_order=('abc', 'acb')[rng.integers(2)])
    return out


def test_balanced_currents_closed_form():
    # Independent of phase_currents: balanced currents I sin(th + phi + k 120 deg) give
    # tau = 3/2 kt I cos(phi) (q-axis component of the current vector).
    rng = np.random.default_rng(0)
    th = rng.uniform(-10, 10, 500)
    amp, phi, kt = rng.uniform(-5, 5, 500), rng.uniform(-np.pi, np.pi, 500), 0.37
    i = [amp * np.sin(th + phi + k * 120 * DEG) for k in range(3)]
    np.testing.assert_allclose(three_phase_torque(*i, th, kt), 1.5 * kt * amp * np.cos(phi),
                               atol=1e-12)


def test_phase_currents_inverts_eq10():
    rng = np.random.default_rng(1)
    tau, th, kt = rng.normal(size=(50, 4)), rng.uniform(-20, 20, (50, 4)), rng.uniform(.1, 2, 4)
    ia, ib, ic = phase_currents(tau, th, kt)
    np.testing.assert_allclose(ia + ib + ic, 0.0, atol=1e-12)   # star point: no neutral current
    np.testing.assert_allclose(np.sqrt((ia**2 + ib**2 + ic**2) * 2 / 3),
                               np.abs(2 * tau / (3 * kt)), rtol=1e-12)
    np.testing.assert_allclose(three_phase_torque(ia, ib, ic, th, kt), tau, atol=1e-12)


def test_electrical_angle():
    assert electrical_angle(0.1, 4, 50.0, 0.3) == pytest.approx(4 * 50 * 0.1 + 0.3)


@pytest.mark.parametrize('seed', range(4))
def test_round_trip_all_sources(seed):
    rng = np.random.default_rng(seed)
    names = [f'j{k}' for k in range(6)]
    conv = TorqueConverter(names, _random_configs(rng, names))
    N = 200
    q = rng.uniform(-3, 3, (N, 6))
    tau = rng.normal(0, 20, (N, 6))
    cur = conv.currents_from_torque(tau, q)
    meas = np.where(conv._measured, tau, np.nan)    # efforts only reported for measured joints
    assert np.isnan(cur[:, conv._measured]).all()
    np.testing.assert_allclose(conv.torque(q, measured=meas, currents=cur), tau,
                               rtol=1e-10, atol=1e-9)


def test_three_phase_against_hand_built_wires():
    # Currents built here from the physics, not by currents_from_torque.
    kt, gear, poles, off = 0.2, 50.0, 4, 0.7
    conv = TorqueConverter(['a', 'b'], {
        'a': dict(source='three_phase', kt=kt, gear_ratio=gear, pole_pairs=poles,
                  angle_offset=off),
        'b': dict(source='three_phase', kt=kt, gear_ratio=gear, pole_pairs=poles,
                  angle_offset=off, phase_order='acb')})
    rng = np.random.default_rng(5)
    q, tau_j = rng.uniform(-2, 2, 300), rng.normal(0, 30, 300)
    th = poles * gear * q + off
    amp = 2 * (tau_j / gear) / (3 * kt)
    pa, pb, pc = (amp * np.sin(th + k * 2 * np.pi / 3) for k in range(3))
    cur = np.zeros((300, 2, 3))
    cur[:, 0] = np.stack([pa, pb, pc], axis=1)
    cur[:, 1] = np.stack([pa, pc, pb], axis=1)     # wires b and c swapped
    tau = conv.torque(np.stack([q, q], 1), currents=cur)
    np.testing.assert_allclose(tau, np.stack([tau_j, tau_j], 1), atol=1e-9)


def _one_three_phase(**kw):
    cfg = dict(source='three_phase', kt=0.5, gear_ratio=20.0, pole_pairs=3, angle_offset=0.4)
    cfg.update(kw)
    return TorqueConverter(['j'], {'j': cfg})


def test_wrong_phase_order_is_visible():
    # Swapping b and c: sin^2 th + 2 sin(th+120) sin(th+240) = -3/2 cos(2 th), so the converter
    # returns -tau cos(2 th): RMS relative error sqrt(3/2) over a uniform spread of angles.
    truth, wrong = _one_three_phase(), _one_three_phase(phase_order='acb')
    q = np.linspace(0, 2 * np.pi / (3 * 20), 2000, endpoint=False)[:, None]  # one el. turn
    tau = np.full_like(q, 7.0)
    got = wrong.torque(q, currents=truth.currents_from_torque(tau, q))
    th = truth.theta_e(q)
    np.testing.assert_allclose(got, -tau * np.cos(2 * th), atol=1e-9)
    rel = np.sqrt(np.mean((got - tau) ** 2)) / 7.0
    assert rel == pytest.approx(np.sqrt(1.5), rel=1e-6)
    assert rel > 1.0


@pytest.mark.parametrize('err_deg', [10.0, 30.0, 90.0, 180.0])
def test_wrong_angle_offset_scales_by_cos(err_deg):
    truth, wrong = _one_three_phase(), _one_three_phase(angle_offset=0.4 + err_deg * DEG)
    rng = np.random.default_rng(2)
    q, tau = rng.uniform(-1, 1, (100, 1)), rng.normal(0, 5, (100, 1))
    got = wrong.torque(q, currents=truth.currents_from_torque(tau, q))
    np.testing.assert_allclose(got, tau * np.cos(err_deg * DEG), atol=1e-9)
    rel = np.linalg.norm(got - tau) / np.linalg.norm(tau)
    assert rel == pytest.approx(1 - np.cos(err_deg * DEG), abs=1e-9)
    assert rel > 0.015                                  # 10 deg off already costs 1.5 %


def test_measured_theta_overrides_q_where_given():
    conv = _one_three_phase()
    rng = np.random.default_rng(3)
    q, tau = rng.uniform(-1, 1, (40, 1)), rng.normal(0, 5, (40, 1))
    th_true = conv.theta_e(q)
    cur = conv.currents_from_torque(tau, q, theta_e=th_true)
    q_bad = q + 0.01                             # 0.6 rad electrical off: visible if used
    th_meas = th_true.copy()
    th_meas[::2] = np.nan
    got = conv.torque(q_bad, currents=cur, theta_e=th_meas)
    np.testing.assert_allclose(got[1::2], tau[1::2], atol=1e-9)
    np.testing.assert_allclose(got[::2], tau[::2] * np.cos(3 * 20 * 0.01), atol=1e-9)


def test_single_current_law():
    conv = TorqueConverter(['j1', 'j2'], {'j1': dict(source='current', kt=0.1, gear_ratio=100),
                                          'j2': {}})
    cur = np.full((3, 2, 3), np.nan)
    cur[:, 0, 0] = [2.0, -1.0, 0.0]
    tau = conv.torque(np.zeros((3, 2)), measured=[[0, 4]] * 3, currents=cur)
    np.testing.assert_allclose(tau, [[20.0, 4.0], [-10.0, 4.0], [0.0, 4.0]])
    assert conv.current_joints == ['j1'] and conv.measured_joints == ['j2']
    assert conv.needs_currents and conv.needs_measured


def test_channel_names_and_packing():
    conv = TorqueConverter(['s', 'm', 't'], {
        's': dict(source='current', kt=1.0),
        't': dict(source='three_phase', kt=0.3, phase_order='acb')})
    assert conv.current_channel_names() == ['s/i', 't/ia', 't/ib', 't/ic']
    assert [s[1:] for s in conv.current_channel_slots()] == [(0, 0), (2, 0), (2, 1), (2, 2)]
    rng = np.random.default_rng(4)
    q, tau = rng.uniform(-1, 1, (10, 3)), rng.normal(size=(10, 3))
    cur = conv.currents_from_torque(tau, q)
    flat = cur[:, [0, 2, 2, 2], [0, 0, 1, 2]]
    packed = conv.pack_currents(flat)
    np.testing.assert_array_equal(np.isnan(packed), np.isnan(cur))
    np.testing.assert_allclose(conv.torque(q, measured=tau, currents=packed), tau, atol=1e-12)
    with pytest.raises(IdentificationError, match='expected'):
        conv.pack_currents(flat[:, :3])
    assert TorqueConverter(['a']).current_channel_names() == []
    assert not TorqueConverter(['a']).needs_currents


@pytest.mark.parametrize('bad,field', [
    (dict(kt=-1.0), 'kt'), (dict(kt=0.0), 'kt'), (dict(kt='1'), 'kt'),
    (dict(kt=float('nan')), 'kt'), (dict(gear_ratio=0), 'gear_ratio'),
    (dict(gear_ratio=-50), 'gear_ratio'), (dict(pole_pairs=0), 'pole_pairs'),
    (dict(pole_pairs=2.5), 'pole_pairs'), (dict(pole_pairs=True), 'pole_pairs'),
    (dict(angle_offset=float('inf')), 'angle_offset'), (dict(phase_order='bac'), 'phase_order'),
    (dict(source='torque'), 'source'), (dict(kt_motor=1.0), 'kt_motor'),
])
def test_config_validation(bad, field):
    d = dict(source='three_phase', kt=1.0)
    d.update(bad)
    with pytest.raises(IdentificationError, match=f"(?s)'elbow'.*{field}"):
        JointTorqueConfig.from_dict(d, 'elbow')
    with pytest.raises(IdentificationError, match=f"(?s)'elbow'.*{field}"):
        TorqueConverter(['elbow'], {'elbow': d})


def test_config_defaults_and_required_kt():
    c = JointTorqueConfig.from_dict({'pole_pairs': 4.0}, 'j')
    assert (c.source, c.pole_pairs, c.phase_order) == ('measured', 4, 'abc')
    assert isinstance(c.pole_pairs, int)
    for source in ('current', 'three_phase'):
        with pytest.raises(IdentificationError, match="'wrist'.*needs kt"):
            JointTorqueConfig.from_dict({'source': source}, 'wrist')
    with pytest.raises(IdentificationError, match='mapping'):
        JointTorqueConfig.from_dict([1, 2], 'j')
    with pytest.raises(IdentificationError, match='kt'):
        JointTorqueConfig(source='current', kt=-2.0)


def test_converter_input_errors():
    conv = TorqueConverter(['a', 'b'], {'b': dict(source='current', kt=1.0)})
    q = np.zeros((4, 2))
    cur = np.full((4, 2, 3), np.nan)
    cur[:, 1, 0] = 1.0
    meas = np.full((4, 2), np.nan)
    meas[:, 0] = 2.0
    np.testing.assert_allclose(conv.torque(q, measured=meas, currents=cur), [[2.0, 1.0]] * 4)
    with pytest.raises(IdentificationError, match='currents needed'):
        conv.torque(q, measured=meas)
    with pytest.raises(IdentificationError, match='efforts needed'):
        conv.torque(q, currents=cur)
    bad = cur.copy()
    bad[2, 1, 0] = np.nan
    with pytest.raises(IdentificationError, match="'b'.*sample 2"):
        conv.torque(q, measured=meas, currents=bad)
    bad = meas.copy()
    bad[3, 0] = np.inf
    with pytest.raises(IdentificationError, match="'a'.*sample 3"):
        conv.torque(q, measured=bad, currents=cur)
    with pytest.raises(IdentificationError, match='shape'):
        conv.torque(q, measured=meas, currents=cur[:, :, :2])
    with pytest.raises(IdentificationError, match='shape'):
        conv.torque(q, measured=meas[:3], currents=cur)
    with pytest.raises(IdentificationError, match='unknown joint'):
        TorqueConverter(['a'], {'z': {}})
    with pytest.raises(IdentificationError, match='more than once'):
        TorqueConverter(['a', 'a'])
    with pytest.raises(IdentificationError, match='2 joints'):
        TorqueConverter(['a', 'b'], [{}])
