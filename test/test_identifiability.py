"""Base parameters: checked against the papers' tables, Khalil's regrouping rules and a second
formulation (the paper's literal rank test, the null space of the stacked regressor)."""
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from identification_node.errors import IdentificationError
from identification_node.model import papers
from identification_node.model.identifiability import BaseParameters, sample_motion
from identification_node.model.robot import LINK_PARAMS, load_robot

PANDA = str(Path(__file__).resolve().parent / 'fixtures' / 'panda_like.urdf')

MIT_TABLE1 = np.array(papers.MIT_TABLE1).ravel()
MIT_TABLE3 = [(terms, cad) for terms, _, cad in papers.MIT_TABLE3]
# Table 2: unmarked estimates (identifiable alone), 0.0* (unidentifiable), dagger (combinations).
MIT_IDENTIFIABLE = ['link2.mx', 'link2.Ixy', 'link2.Ixz', 'link3.mx', 'link3.my', 'link3.Ixy',
                    'link3.Ixz', 'link3.Iyz', 'link3.Izz']
MIT_UNIDENTIFIABLE = ['link1.m', 'link1.mx', 'link1.my', 'link1.mz', 'link1.Ixx', 'link1.Ixy',
                      'link1.Ixz', 'link1.Iyy', 'link1.Iyz', 'link2.m', 'link2.mz']
MIT_COMBINED = ['link1.Izz', 'link2.my', 'link2.Ixx', 'link2.Iyy', 'link2.Iyz', 'link2.Izz',
                'link3.m', 'link3.mz', 'link3.Ixx', 'link3.Iyy']
ALL_EXTRAS = ('fv', 'fc', 'fo', 'Ia')


def stacked(robot, seed, num=60):
    """A fresh stacked regressor (rows, p) at other random samples than from_robot's."""
    q, qd, qdd = sample_motion(robot, num, seed)
    return robot.regressor(q, qd, qdd).reshape(-1, robot.num_params)


def null_space(W):
    """Null space of W from its SVD (columns scaled to unit norm, then unscaled)."""
    norms = np.linalg.norm(W, axis=0)
    scale = np.where(norms > 1e-12 * norms.max(), norms, 1.0)
    _, s, Vt = np.linalg.svd(W / scale, full_matrices=True)
    rank = int((s > 1e-9 * s[0]).sum())
    N = Vt[rank:].T / scale[:, None]
    return N / np.linalg.norm(N, axis=0), rank


def combination(base, terms):
    c = np.zeros(base.num_params)
    for name, coef in terms.items():
        c[base.param_names.index(name)] = coef
    return c


# -- MIT Serial Link Direct Drive Arm: An, Atkeson, Hollerbach (1986) --
def test_mit_urdf_carries_table1(mit):
    robot, _ = mit
    np.testing.assert_allclose(robot.phi_model, MIT_TABLE1, atol=1e-9)


def test_mit_counts_and_groups_match_the_paper(mit):
    _, base = mit
    assert (base.num_params, base.num_base) == (30, 15)
    assert base.identifiable == MIT_IDENTIFIABLE
    assert base.unidentifiable == MIT_UNIDENTIFIABLE
    assert base.combined == MIT_COMBINED


def test_mit_table3_combinations_are_identifiable(mit):
    robot, base = mit
    N, rank = null_space(stacked(robot, seed=11))
    assert rank == 15
    for terms, _ in MIT_TABLE3:
        c = combination(base, terms)
        # identifiable <=> orthogonal to every motion-invisible parameter change
        assert np.abs(N.T @ c).max() < 1e-8 * np.linalg.norm(c), terms
        # ... and then a combination of our base parameters: c = K^T x
        x, *_ = np.linalg.lstsq(base.K.T, c, rcond=None)
        np.testing.assert_allclose(base.K.T @ x, c, atol=1e-9)
    # a parameter of a combination on its own is not identifiable (the test can fail)
    assert np.abs(N.T @ combination(base, {'link2.Ixx': 1.0})).max() > 1e-3


def test_mit_table3_values_follow_table1(mit):
    _, base = mit
    values = [combination(base, terms) @ MIT_TABLE1 for terms, _ in MIT_TABLE3]
    paper = [v for _, v in MIT_TABLE3]
    for k, (ours, theirs) in enumerate(zip(values, paper)):
        if k == 1:  # Ixx3 - Iyy3: 0.1825 - 0.4560 = -0.2735, the paper prints -0.2702
            assert ours == pytest.approx(-0.2735, abs=1e-9)
            assert ours == pytest.approx(theirs, rel=0.02)
            assert abs(ours - theirs) > 1e-3
        else:
            assert ours == pytest.approx(theirs, abs=1e-3), MIT_TABLE3[k][0]


def test_mit_representatives_and_names(mit):
    _, base = mit
    table = dict(zip(base.names, base.expressions))
    assert table['link2.IyzR'] == 'link2.Iyz + 0.45 link3.mz'
    assert table['link3.IxxR'] == 'link3.Ixx - link3.Iyy'
    assert table['link1.IzzR'] == 'link1.Izz + link2.Iyy + 0.2025 link3.m'
    assert table['link2.myR'] == 'link2.my - link3.mz'
    assert table['link3.Izz'] == 'link3.Izz'
    k = base.names.index('link1.IzzR')
    assert base.terms[k] == {'link1.Izz': 1.0, 'link2.Iyy': 1.0, 'link3.m': 0.2025}
    # the representative is the first column of its group, with coefficient 1
    for k, j in enumerate(base.base_index):
        first = min(base.param_names.index(n) for n in base.terms[k])
        assert first == j and base.terms[k][base.param_names[j]] == 1.0
    np.testing.assert_array_equal(base.K[:, base.base_index], np.eye(base.num_base))


# -- the paper's literal procedure as a second formulation --
@pytest.mark.parametrize('name', ['mit_dd_arm', 'crs_a465'])
def test_identifiable_alone_is_the_papers_rank_test(name):
    """Radkhah et al. II.B step 5: theta_i is identifiable alone iff dropping its column
    lowers the rank of the stacked regressor."""
    robot = load_robot(name)
    base = BaseParameters.from_robot(robot)
    W = stacked(robot, seed=5)
    norms = np.linalg.norm(W, axis=0)
    zero = norms < 1e-9 * norms.max()
    Wn = np.where(zero, 0.0, W / np.where(zero, 1.0, norms))
    rank = np.linalg.matrix_rank(Wn, tol=1e-8 * np.sqrt(W.shape[0]))
    assert rank == base.num_base
    alone = [p for i, p in enumerate(robot.param_names)
             if np.linalg.matrix_rank(np.delete(Wn, i, axis=1), tol=1e-8) < rank]
    assert alone == base.identifiable
    assert [p for p, z in zip(robot.param_names, zero) if z] == base.unidentifiable
    assert sorted(base.identifiable + base.unidentifiable + base.combined) == \
        sorted(robot.param_names)


# -- counts of the other robots --
def test_crs_a465_has_the_papers_36_base_parameters():
    robot = load_robot('crs_a465')
    base = BaseParameters.from_robot(robot)
    assert (base.num_params, base.num_base) == (60, 36)
    # link 1 turns about the vertical only: all but its Izz are invisible (the paper's 9)
    assert [p for p in base.unidentifiable if p.startswith('link1.')] == \
        [f'link1.{p}' for p in LINK_PARAMS[:-1]]


def test_panda_like_has_43_base_parameters():
    robot = load_robot(PANDA)
    base = BaseParameters.from_robot(robot)
    assert (base.num_params, base.num_base) == (70, 43)
    assert null_space(stacked(robot, seed=3))[1] == 43


def test_extras_add_the_expected_columns(mit):
    """fv, fc, fo of every joint are independent; a rotor inertia Ia_j joins link j's Izz when
    Izz_j's column is qdd_j alone (joint 1, and joint 2 perpendicular to joint 1: Khalil's rule),
    otherwise it is a new base parameter."""
    robot = load_robot('mit_dd_arm', extras=ALL_EXTRAS)
    base = BaseParameters.from_robot(robot)
    assert base.num_base == 15 + 3 * 3 + 1
    q, qd, qdd = sample_motion(robot, 20, 7)
    Y = robot.regressor(q, qd, qdd)
    izz2 = Y[:, :, robot.param_index('link2.Izz')]
    np.testing.assert_allclose(izz2, qdd * [0, 1, 0], atol=1e-12)  # the closed form
    for joint, link in [('joint1', 'link1.Izz'), ('joint2', 'link2.Izz')]:
        k = [i for i, t in enumerate(base.terms) if f'{joint}.Ia' in t]
        assert len(k) == 1 and link in base.terms[k[0]]
        assert base.terms[k[0]][f'{joint}.Ia'] == pytest.approx(1.0)
    for j in ('joint1', 'joint2', 'joint3'):
        for e in ('fv', 'fc', 'fo'):
            assert f'{j}.{e}' in base.identifiable
    assert 'joint3.Ia' in base.identifiable
    crs = BaseParameters.from_robot(load_robot('crs_a465', extras=ALL_EXTRAS))
    assert crs.num_base == 36 + 6 * 3 + 4


# -- the maps --
@pytest.mark.parametrize('name,extras', [
    ('mit_dd_arm', ()), ('crs_a465', ALL_EXTRAS), (PANDA, ALL_EXTRAS)])
def test_base_regressor_reproduces_the_torques(name, extras):
    robot = load_robot(name, extras=extras)
    base = BaseParameters.from_robot(robot)
    rng = np.random.default_rng(42)
    q, qd, qdd = sample_motion(robot, 30, seed=99)
    Y = robot.regressor(q, qd, qdd)
    for phi in (robot.phi_model, rng.standard_normal(robot.num_params)):
        tau = Y @ phi
        tau_b = base.base_regressor(Y) @ base.to_base(phi)
        assert np.abs(tau - tau_b).max() <= 1e-9 * max(1.0, np.abs(tau).max())
    assert base.base_regressor(Y).shape == (30, robot.dof, base.num_base)


def test_closest_standard(mit):
    robot, base = mit
    rng = np.random.default_rng(1)
    phi_ref = robot.phi_model
    np.testing.assert_allclose(base.closest_standard(base.to_base(phi_ref), phi_ref), phi_ref,
                               atol=1e-12)
    beta = base.to_base(phi_ref) + rng.standard_normal(base.num_base)
    phi = base.closest_standard(beta, phi_ref)
    np.testing.assert_allclose(base.to_base(phi), beta, atol=1e-10)
    # least change: phi - phi_ref has no part along the null space of K, so no other
    # solution phi + z (K z = 0) is closer to phi_ref
    _, s, Vt = np.linalg.svd(base.K)
    Z = Vt[base.num_base:].T
    assert np.abs(Z.T @ (phi - phi_ref)).max() < 1e-10
    z = Z @ rng.standard_normal(Z.shape[1])
    assert np.linalg.norm(phi + z - phi_ref) > np.linalg.norm(phi - phi_ref)
    with pytest.raises(IdentificationError):
        base.closest_standard(beta[:-1], phi_ref)


def test_to_dict(mit):
    robot, base = mit
    d = base.to_dict(robot.phi_model)
    assert d['robot'] == 'mit_dd_arm' and d['joints'] == ['joint1', 'joint2', 'joint3']
    assert d['parameters'] == robot.param_names
    assert (d['num_params'], d['num_base']) == (30, 15)
    assert d['unidentifiable'] == MIT_UNIDENTIFIABLE
    entry = {b['name']: b for b in d['base_parameters']}['link2.IyzR']
    assert entry['expression'] == 'link2.Iyz + 0.45 link3.mz'
    assert entry['terms'] == {'link2.Iyz': 1.0, 'link3.mz': 0.45}
    assert entry['value'] == pytest.approx(-1.5036 + 0.45 * 0.3268)


# -- names, sampling and errors --
TWO_LINKS = """<robot name="odd">
  <link name="base"/>
  <joint name="slide" type="prismatic"><parent link="base"/><child link="carriage-1"/>
    <axis xyz="1 0 0"/><limit lower="0" upper="0" effort="100" velocity="1"/></joint>
  <link name="carriage-1"><inertial><origin xyz="0.1 0.02 0.03"/><mass value="2"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
  <joint name="spin" type="continuous"><parent link="carriage-1"/><child link="arm link"/>
    <origin xyz="0 0 0.1" rpy="1.5707963267948966 0 0"/><axis xyz="0 0 1"/>
    <limit effort="10" velocity="5"/></joint>
  <link name="arm link"><inertial><origin xyz="0.2 0.01 0"/><mass value="1"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
</robot>"""


def test_names_are_valid_ros_parameter_names():
    for robot in (load_robot('crs_a465', extras=ALL_EXTRAS), load_robot(TWO_LINKS)):
        base = BaseParameters.from_robot(robot)
        assert len(set(base.names)) == base.num_base
        assert all(re.fullmatch(r'[A-Za-z0-9_.]+', n) for n in base.names), base.names
    assert 'carriage_1.m' in base.names or 'carriage_1.mR' in base.names


def test_sampling_ranges():
    robot = load_robot(TWO_LINKS)  # unlimited prismatic and continuous joints
    q, qd, qdd = sample_motion(robot, 2000, seed=0)
    assert np.all(np.abs(q[:, 0]) <= 0.5) and q[:, 0].max() > 0.45
    assert np.all(np.abs(q[:, 1]) <= np.pi) and q[:, 1].max() > 3.0
    crs = load_robot('crs_a465')
    q, _, _ = sample_motion(crs, 2000, seed=0)
    lower, upper = crs.position_limits.T
    assert np.all((q >= lower) & (q <= upper))
    assert np.all(q.max(axis=0) - q.min(axis=0) > 0.9 * (upper - lower))
    again = sample_motion(crs, 5, seed=3)[0]
    np.testing.assert_array_equal(again, sample_motion(crs, 5, seed=3)[0])


def test_bad_regressors_raise():
    robot = load_robot('mit_dd_arm')
    Y = robot.regressor(*sample_motion(robot, 10, 0))
    with pytest.raises(IdentificationError, match='NaN'):
        bad = Y.copy()
        bad[0, 0, 5] = np.nan
        BaseParameters.from_regressor(bad, robot.param_names)
    with pytest.raises(IdentificationError, match='more samples'):
        BaseParameters.from_regressor(Y[:3], robot.param_names)
    with pytest.raises(IdentificationError, match='columns'):
        BaseParameters.from_regressor(Y[..., :-1], robot.param_names)
    with pytest.raises(IdentificationError, match='zero'):
        BaseParameters.from_regressor(np.zeros_like(Y), robot.param_names)


# -- the bundled CRS A465 and the Panda-like fixture --
def _consistent(inertia: pin.Inertia) -> bool:
    ev = np.linalg.eigvalsh(inertia.inertia)
    return inertia.mass > 0 and ev.min() > 0 and 2 * ev.max() <= ev.sum() + 1e-12


def test_crs_a465_description():
    robot = load_robot('crs_a465')
    assert robot.joint_names == [f'joint{i}' for i in range(1, 7)]
    assert robot.link_names == [f'link{i}' for i in range(1, 7)]
    m = robot.model
    assert all(_consistent(m.inertias[j]) for j in robot.joint_ids)
    assert sum(i.mass for i in m.inertias) == pytest.approx(31.0)
    deg = np.degrees(robot.position_limits[:, 1])
    np.testing.assert_allclose(deg, [175, 90, 110, 180, 105, 180])
    np.testing.assert_allclose(np.degrees(robot.velocity_limits),
                               [180, 180, 180, 171, 173, 171])
    assert np.all(robot.effort_limits > 0)
    data = m.createData()
    flange = m.getFrameId('tool0')

    def tool(q):
        pin.framesForwardKinematics(m, data, np.asarray(q, float))
        return data.oMf[flange].translation.copy()
    # upright: 0.330 + 0.305 + 0.330 + 0.076 above the base; arm stretched out: 0.711 m reach
    np.testing.assert_allclose(tool([0, 0, 0, 0, 0, 0]), [0, 0, 1.041], atol=1e-12)
    np.testing.assert_allclose(tool([0, np.pi / 2, 0, 0, 0, 0]), [0.711, 0, 0.330], atol=1e-12)
    np.testing.assert_allclose(tool([0, 0, np.pi / 2, 0, 0, 0]), [0.406, 0, 0.635], atol=1e-12)
    np.testing.assert_allclose(tool([0, 0, 0, 0, np.pi / 2, 0]), [0.076, 0, 0.965], atol=1e-12)


def test_panda_like_fixture_follows_the_dh_table():
    robot = load_robot(PANDA)
    a = [0, 0, 0, 0.0825, -0.0825, 0, 0.088]
    d = [0.333, 0, 0.316, 0, 0.384, 0, 0]
    alpha = [0, -np.pi / 2, np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, np.pi / 2]

    def craig(q):
        T = np.eye(4)
        for ai, di, al, th in zip(a, d, alpha, q):
            ca, sa, ct, st = np.cos(al), np.sin(al), np.cos(th), np.sin(th)
            T = T @ np.array([[ct, -st, 0, ai], [st * ca, ct * ca, -sa, -sa * di],
                              [st * sa, ct * sa, ca, ca * di], [0, 0, 0, 1]])
        return T
    m, data = robot.model, robot.model.createData()
    q, _, _ = sample_motion(robot, 5, seed=2)
    for qk in q:
        pin.forwardKinematics(m, data, robot.configuration(qk)[0])
        np.testing.assert_allclose(data.oMi[robot.joint_ids[-1]].homogeneous, craig(qk),
                                   atol=1e-12)
    phi = robot.phi_model.reshape(7, 10)
    assert np.all(np.abs(phi) > 1e-6), 'every inertial parameter nonzero'
    assert all(_consistent(m.inertias[j]) for j in robot.joint_ids)


def test_table3_combinations_evaluate_from_the_base_parameters(mit):
    robot, base = mit
    beta = base.to_base(robot.phi_model)
    for terms, _, cad in papers.MIT_TABLE3:
        direct = sum(c * robot.phi_model[robot.param_names.index(n)] for n, c in terms.items())
        assert base.combination(terms) @ beta == pytest.approx(direct, abs=1e-9)
    with pytest.raises(IdentificationError, match='not identifiable'):
        base.combination({'link1.m': 1.0})
