"""RobotModel's regressor against independent truth: the Newton-Euler formulation of An,
Atkeson and Hollerbach (test/newton_euler.py, numpy + the URDF only), pinocchio's RNEA on a model
built straight from the URDF, closed forms (pendulum, friction/offset/rotor columns)."""
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from identification_node.errors import IdentificationError
from identification_node.model.robot import load_robot

from newton_euler import Chain, GRAVITY

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / 'test' / 'fixtures' / 'six_dof_arm.urdf'
MIT = ROOT / 'identification_node' / 'robots' / 'mit_dd_arm.urdf'
CRS = ROOT / 'identification_node' / 'robots' / 'crs_a465.urdf'
EXTRAS = ('fv', 'fc', 'fo', 'Ia')

ROBOTS = [
    pytest.param('mit_dd_arm', MIT, id='mit_dd_arm'),
    pytest.param(str(FIXTURE), FIXTURE, id='six_dof_arm'),
    pytest.param('crs_a465', CRS, id='crs_a465',
                 marks=pytest.mark.skipif(not CRS.exists(), reason='crs_a465.urdf not written')),
]


def samples(robot, n, seed=0, wide=7.0):
    """Random (q, qd, qdd) (n, dof): inside finite position limits, within +-wide rad for
    continuous joints (beyond +-pi)."""
    rng = np.random.default_rng(seed)
    lo, hi = robot.position_limits.T
    lo, hi = np.where(np.isfinite(lo), lo, -wide), np.where(np.isfinite(hi), hi, wide)
    q = rng.uniform(lo, hi, (n, robot.dof))
    qd = rng.normal(0.0, 1.5, (n, robot.dof))
    qdd = rng.normal(0.0, 4.0, (n, robot.dof))
    return q, qd, qdd


def assert_rel_close(actual, expected, rel=1e-9):
    """max |actual - expected| <= rel * ||expected|| (Frobenius norm over all samples)."""
    scale = np.linalg.norm(expected)
    assert scale > 0
    err = np.max(np.abs(np.asarray(actual) - expected))
    assert err <= rel * scale, f'max error {err:.3e} > {rel:g} * {scale:.3e}'


def plain_rnea(urdf_path, names, q, qd, qdd, locked=None):
    """Torques at ``names`` from pin.rnea on the full model read straight from the URDF file;
    other movable joints held at ``locked`` (default 0) with zero velocity and acceleration."""
    model = pin.buildModelFromUrdf(str(urdf_path))
    data = model.createData()
    locked = dict(locked or {})
    Q = np.tile(pin.neutral(model), (q.shape[0], 1))
    V, A = np.zeros((q.shape[0], model.nv)), np.zeros((q.shape[0], model.nv))
    angles = {name: np.full(q.shape[0], float(v)) for name, v in locked.items()}
    angles.update({name: q[:, i] for i, name in enumerate(names)})
    for name, angle in angles.items():
        jm = model.joints[model.getJointId(name)]
        if jm.nq == 2:
            Q[:, jm.idx_q], Q[:, jm.idx_q + 1] = np.cos(angle), np.sin(angle)
        else:
            Q[:, jm.idx_q] = angle
    idx_v = [model.joints[model.getJointId(name)].idx_v for name in names]
    V[:, idx_v], A[:, idx_v] = qd, qdd
    return np.array([pin.rnea(model, data, Q[k], V[k], A[k])[idx_v] for k in range(len(Q))])


# -- the regressor against the second formulation and pinocchio's RNEA --------------------------
@pytest.mark.parametrize('name,path', ROBOTS)
def test_regressor_matches_newton_euler(name, path):
    robot = load_robot(name)
    q, qd, qdd = samples(robot, 40)
    chain = Chain(path.read_text(), robot.joint_names)
    assert_rel_close(robot.regressor(q, qd, qdd), chain.regressor(q, qd, qdd))


@pytest.mark.parametrize('name,path', ROBOTS)
def test_phi_model_is_urdf_inertia_about_joint_origin(name, path):
    robot = load_robot(name)
    expected = Chain(path.read_text(), robot.joint_names).standard_parameters()
    assert robot.param_names[:10] == [f'{robot.link_names[0]}.{p}' for p in
                                      ('m', 'mx', 'my', 'mz', 'Ixx', 'Ixy', 'Ixz', 'Iyy',
                                       'Iyz', 'Izz')]
    np.testing.assert_allclose(robot.phi_model, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('name,path', ROBOTS)
def test_torques_match_pinocchio_rnea(name, path):
    robot = load_robot(name)
    q, qd, qdd = samples(robot, 25, seed=1)
    tau = robot.regressor(q, qd, qdd) @ robot.phi_model
    assert_rel_close(tau, robot.rnea(q, qd, qdd))
    assert_rel_close(tau, plain_rnea(path, robot.joint_names, q, qd, qdd))
    assert_rel_close(robot.inverse_dynamics(q, qd, qdd), tau)
    # Other parameters than the model's: pinocchio's model rebuilt from phi.
    phi = robot.phi_model * np.random.default_rng(2).uniform(0.5, 1.5, robot.num_params)
    assert_rel_close(robot.regressor(q, qd, qdd) @ phi, robot.rnea(q, qd, qdd, phi))


def test_newton_euler_pendulum_and_slider_closed_forms():
    """The reference itself against hand-derived torques: a pendulum about a horizontal axis,
    tau = (Izz_c + m l^2) qdd + m g l cos q, and a vertical slider, f = m (qdd + g)."""
    m, l_c, izz, m2 = 2.0, 0.3, 0.05, 1.5
    xml = f'''<robot name="pendulum"><link name="base"/>
      <joint name="hinge" type="continuous"><parent link="base"/><child link="arm"/>
        <origin xyz="0 0 1" rpy="1.5707963267948966 0 0"/><axis xyz="0 0 1"/></joint>
      <link name="arm"><inertial><origin xyz="{l_c} 0 0"/><mass value="{m}"/>
        <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.04" iyz="0" izz="{izz}"/></inertial></link>
      <joint name="slide" type="prismatic"><parent link="base"/><child link="carriage"/>
        <origin xyz="0.5 0 0"/><axis xyz="0 0 1"/>
        <limit lower="-1" upper="1" effort="100" velocity="1"/></joint>
      <link name="carriage"><inertial><mass value="{m2}"/>
        <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
    </robot>'''
    q, qd, qdd = samples(load_robot(xml), 20, seed=3)
    g = -GRAVITY[2]
    expected = np.stack([(izz + m * l_c ** 2) * qdd[:, 0] + m * g * l_c * np.cos(q[:, 0]),
                         m2 * (qdd[:, 1] + g)], axis=1)
    chain = Chain(xml, ['hinge', 'slide'])
    np.testing.assert_allclose(chain.regressor(q, qd, qdd) @ chain.standard_parameters(),
                               expected, rtol=1e-12, atol=1e-12)
    robot = load_robot(xml, ['hinge', 'slide'])
    np.testing.assert_allclose(robot.inverse_dynamics(q, qd, qdd), expected, rtol=1e-12,
                               atol=1e-12)
    assert robot.prismatic.tolist() == [False, True]
    assert robot.continuous.tolist() == [True, False]


def test_urdf_xml_string_equals_file():
    from_file = load_robot(str(FIXTURE))
    from_xml = load_robot(FIXTURE.read_text())
    assert from_xml.joint_names == from_file.joint_names
    assert from_xml.param_names == from_file.param_names
    q, qd, qdd = samples(from_file, 10, seed=4)
    np.testing.assert_array_equal(from_xml.regressor(q, qd, qdd),
                                  from_file.regressor(q, qd, qdd))
    np.testing.assert_array_equal(from_xml.phi_model, from_file.phi_model)


def test_fixture_joint_kinds_and_limits():
    robot = load_robot(str(FIXTURE))
    assert robot.joint_names == [f'joint{i}' for i in range(1, 7)]
    assert robot.link_names == [f'link{i}' for i in range(1, 7)]
    assert robot.prismatic.tolist() == [False, False, False, True, False, False]
    assert robot.continuous.tolist() == [False, False, False, False, True, False]
    np.testing.assert_array_equal(robot.position_limits[3], [-0.15, 0.2])
    assert np.isinf(robot.position_limits[4]).all()
    np.testing.assert_array_equal(robot.effort_limits, [150, 120, 80, 400, 30, 20])
    np.testing.assert_array_equal(robot.velocity_limits, [2.5, 2.0, 2.5, 0.5, 4.0, 5.0])


# -- per-joint extra columns -------------------------------------------------------------------
@pytest.mark.parametrize('coulomb_velocity', [0.0, 0.05])
def test_extra_columns_closed_forms(coulomb_velocity):
    robot = load_robot(str(FIXTURE), extras=EXTRAS, coulomb_velocity=coulomb_velocity)
    plain = load_robot(str(FIXTURE))
    n, ni = robot.dof, robot.n_inertial
    q, qd, qdd = samples(robot, 15, seed=5)
    qd[:3, :] = 0.0  # sign(0) = tanh(0) = 0
    qd[3, :] = 1e-3  # inside the tanh smoothing band
    Y = robot.regressor(q, qd, qdd)
    assert robot.param_names[ni:] == [f'{j}.{e}' for j in robot.joint_names for e in EXTRAS]
    np.testing.assert_array_equal(Y[:, :, :ni], plain.regressor(q, qd, qdd))
    # joint4 is prismatic: coulomb_velocity / 10 in m/s
    fc = (np.tanh(qd / (coulomb_velocity * np.array([1, 1, 1, 0.1, 1, 1])))
          if coulomb_velocity else np.sign(qd))
    expected = np.zeros((len(q), n, 4 * n))
    for i in range(n):
        expected[:, i, 4 * i:4 * i + 4] = np.stack([qd[:, i], fc[:, i], np.ones(len(q)),
                                                    qdd[:, i]], axis=1)
    np.testing.assert_allclose(Y[:, :, ni:], expected, rtol=1e-15, atol=0)
    # With friction, offset and rotor inertia in phi the torque adds their closed forms.
    coef = np.random.default_rng(6).uniform(0.1, 2.0, (n, 4))
    phi = np.concatenate([plain.phi_model, coef.ravel()])
    tau_rb = plain_rnea(FIXTURE, robot.joint_names, q, qd, qdd)
    tau = tau_rb + coef[:, 0] * qd + coef[:, 1] * fc + coef[:, 2] + coef[:, 3] * qdd
    assert_rel_close(Y @ phi, tau)
    assert_rel_close(robot.rnea(q, qd, qdd, phi), tau)
    # given Coulomb column values (the smoothed sign) take the fc columns' place only
    given = np.random.default_rng(7).uniform(-1.0, 1.0, qd.shape)
    Yg = robot.regressor(q, qd, qdd, coulomb=given)
    fc_columns = ni + 4 * np.arange(n) + 1
    np.testing.assert_array_equal(Yg[:, np.arange(n), fc_columns], given)
    Yg[:, np.arange(n), fc_columns] = Y[:, np.arange(n), fc_columns]
    np.testing.assert_array_equal(Yg, Y)


def test_extras_keep_canonical_order():
    robot = load_robot('mit_dd_arm', extras=('Ia', 'fv'))
    assert robot.extras == ('fv', 'Ia')
    assert robot.param_names[30:] == ['joint1.fv', 'joint1.Ia', 'joint2.fv', 'joint2.Ia',
                                      'joint3.fv', 'joint3.Ia']
    q, qd, qdd = samples(robot, 5, seed=7)
    Y = robot.regressor(q, qd, qdd)
    np.testing.assert_array_equal(Y[:, 1, 32], qd[:, 1])
    np.testing.assert_array_equal(Y[:, 1, 33], qdd[:, 1])
    np.testing.assert_array_equal(Y[:, 0, 32:34], 0.0)


# -- joint order, locked joints, continuous joints -----------------------------------------------
@pytest.mark.parametrize('name,order', [
    ('mit_dd_arm', ['joint3', 'joint1', 'joint2']),
    (str(FIXTURE), ['joint5', 'joint2', 'joint6', 'joint4', 'joint1', 'joint3']),
])
def test_joint_order_permutes_rows_and_blocks(name, order):
    base = load_robot(name, extras=('fv', 'Ia'))
    perm = [base.joint_names.index(j) for j in order]
    moved = load_robot(name, order, extras=('fv', 'Ia'))
    assert moved.joint_names == order
    assert moved.link_names == [base.link_names[p] for p in perm]
    n = base.dof
    cols = np.concatenate([np.arange(10 * p, 10 * p + 10) for p in perm]
                          + [10 * n + np.arange(2 * p, 2 * p + 2) for p in perm])
    assert moved.param_names == [base.param_names[c] for c in cols]
    np.testing.assert_array_equal(moved.phi_model, base.phi_model[cols])
    q, qd, qdd = samples(base, 12, seed=8)
    Y = base.regressor(q, qd, qdd)
    Ym = moved.regressor(q[:, perm], qd[:, perm], qdd[:, perm])
    assert_rel_close(Ym, Y[:, perm][:, :, cols], rel=1e-12)
    assert_rel_close(Ym @ moved.phi_model, (Y @ base.phi_model)[:, perm], rel=1e-12)


@pytest.mark.parametrize('path,joints,locked', [
    (MIT, ['joint1', 'joint2'], {'joint3': 0.3}),
    (FIXTURE, ['joint1', 'joint2', 'joint3', 'joint4'], {'joint5': 0.7, 'joint6': -0.4}),
    (FIXTURE, ['joint6', 'joint1', 'joint2', 'joint3', 'joint5'], {'joint4': 0.12}),
])
def test_locked_joints_merge_into_reduced_chain(path, joints, locked):
    name = 'mit_dd_arm' if path == MIT else str(path)
    robot = load_robot(name, joints, locked_positions=locked)
    assert robot.joint_names == joints and robot.dof == len(joints)
    assert len(robot.param_names) == 10 * len(joints)
    chain = Chain(path.read_text(), joints, locked)
    q, qd, qdd = samples(robot, 25, seed=9)
    Y = robot.regressor(q, qd, qdd)
    assert_rel_close(Y, chain.regressor(q, qd, qdd))
    np.testing.assert_allclose(robot.phi_model, chain.standard_parameters(), rtol=1e-12,
                               atol=1e-12)
    # Held fixed with zero velocity and acceleration in the full model: same torques.
    tau_full = plain_rnea(path, joints, q, qd, qdd, locked)
    assert_rel_close(Y @ robot.phi_model, tau_full)
    assert_rel_close(robot.rnea(q, qd, qdd), tau_full)
    # The lock position matters (guards against a lock silently at 0).
    moved = {k: v + 0.5 for k, v in locked.items()}
    assert not np.allclose(plain_rnea(path, joints, q, qd, qdd, moved), tau_full, rtol=1e-6)


@pytest.mark.parametrize('renamed,joints,locked', [
    ('joint5', ['joint1', 'joint2', 'joint3', 'joint4', 'joint6'], {'link3': 0.7}),
    ('joint5', ['joint1', 'joint2', 'joint3', 'joint4', 'link3'], {'joint6': -0.4}),
    ('camera_joint', ['joint1', 'joint2', 'joint3', 'joint4', 'joint6'], {'joint5': 0.7}),
])
def test_a_joint_named_like_a_link_is_locked_or_identified(tmp_path, renamed, joints, locked):
    """URDF keeps joint and link names apart (SO-100: joint and link 'gripper'); pinocchio's
    reduction refuses a name two frames carry. A joint of the fixture renamed 'link3' (a
    link's name), locked, identified or fixed (camera_joint): the Newton-Euler chain's
    regressor and the link frame found by its name."""
    urdf = tmp_path / 'clash.urdf'
    urdf.write_text(FIXTURE.read_text().replace(f'<joint name="{renamed}"',
                                                '<joint name="link3"'))
    robot = load_robot(str(urdf), joints, locked_positions=locked)
    assert robot.joint_names == joints
    chain = Chain(urdf.read_text(), joints, locked)
    q, qd, qdd = samples(robot, 25, seed=4)
    assert_rel_close(robot.regressor(q, qd, qdd), chain.regressor(q, qd, qdd))
    assert_rel_close(robot.rnea(q, qd, qdd), plain_rnea(urdf, joints, q, qd, qdd, locked))
    names = [(f.name, f.type) for f in robot.model.frames]
    assert ('link3', pin.FrameType.BODY) in names and 'link3#joint' not in str(names)


def test_so100_with_its_gripper_locked():
    """example-robot-data's SO-100: its jaw joint is named 'gripper' like the link it moves
    from; the arm's five joints load with it locked, as pinocchio's RNEA of the whole arm."""
    from arms import robots_dir
    path = robots_dir() / 'so_arm_description' / 'urdf' / 'so100.urdf'
    joints = ['shoulder_pan', 'shoulder_lift', 'elbow_flex', 'wrist_flex', 'wrist_roll']
    robot = load_robot(str(path), joints)
    q, qd, qdd = samples(robot, 20, seed=5)
    assert_rel_close(robot.regressor(q, qd, qdd) @ robot.phi_model,
                     plain_rnea(path, joints, q, qd, qdd))


def test_massless_links_keep_their_rotational_inertia():
    """example-robot-data's human arm writes each ball joint as three revolute joints with
    massless links between them: the model rebuilt from the standard parameters (rnea, the
    simulator) is the URDF's, as pinocchio's RNEA of the file and the regressor say."""
    from arms import robots_dir
    path = robots_dir() / 'human_description' / 'robots' / 'human.urdf'
    joints = ['right_shoulder_Z', 'right_shoulder_X', 'right_shoulder_Y', 'right_elbow_Z',
              'right_elbow_Y', 'right_wrist_Z', 'right_wrist_X']
    robot = load_robot(str(path), joints)
    assert robot.phi_model[robot.param_index('right_upperarm_virtual.m')] == 0.0
    q, qd, qdd = samples(robot, 20, seed=6)
    want = plain_rnea(path, joints, q, qd, qdd)
    assert_rel_close(robot.rnea(q, qd, qdd, robot.phi_model), want)   # rebuilt from phi
    assert_rel_close(robot.regressor(q, qd, qdd) @ robot.phi_model, want)
    phi = robot.phi_model.copy()
    phi[robot.param_index('right_upperarm_virtual.mx')] = 0.01
    with pytest.raises(IdentificationError, match='right_upperarm_virtual: a first moment'):
        robot.pinocchio_model(phi)


def test_locked_link_mass_merged_mit():
    full = load_robot('mit_dd_arm')
    reduced = load_robot('mit_dd_arm', ['joint1', 'joint2'], locked_positions={'joint3': 0.3})
    assert reduced.link_names == ['link1', 'link2']
    m2 = reduced.phi_model[reduced.param_index('link2.m')]
    assert m2 == pytest.approx(53.01 + 19.67, rel=1e-12)
    np.testing.assert_allclose(reduced.phi_model[:10], full.phi_model[:10], rtol=1e-12)
    # Default lock position is 0.
    at_zero = load_robot('mit_dd_arm', ['joint1', 'joint2'])
    chain = Chain(MIT.read_text(), ['joint1', 'joint2'], {'joint3': 0.0})
    np.testing.assert_allclose(at_zero.phi_model, chain.standard_parameters(), rtol=1e-12,
                               atol=1e-12)


def test_continuous_joints_beyond_pi():
    robot = load_robot('mit_dd_arm')
    assert robot.continuous.all() and not robot.prismatic.any()
    assert np.isinf(robot.position_limits).all()
    q, qd, qdd = samples(robot, 20, seed=10, wide=12.0)
    assert np.abs(q).max() > 2 * np.pi
    Y = robot.regressor(q, qd, qdd)
    assert_rel_close(Y, Chain(MIT.read_text(), robot.joint_names).regressor(q, qd, qdd))
    turns = np.random.default_rng(11).integers(-3, 4, q.shape) * 2 * np.pi
    assert_rel_close(robot.regressor(q + turns, qd, qdd), Y, rel=1e-12)
    assert_rel_close(Y @ robot.phi_model, plain_rnea(MIT, robot.joint_names, q, qd, qdd))


# -- batch output and input checks ---------------------------------------------------------------
def test_batch_out_preallocated():
    robot = load_robot(str(FIXTURE), extras=EXTRAS)
    q, qd, qdd = samples(robot, 8, seed=12)
    out = np.full((8, robot.dof, robot.num_params), np.nan)
    result = robot.regressor(q, qd, qdd, out=out)
    assert result is out
    np.testing.assert_array_equal(out, robot.regressor(q, qd, qdd))
    one = robot.regressor(q[0], qd[0], qdd[0])
    assert one.shape == (1, robot.dof, robot.num_params)
    np.testing.assert_array_equal(one[0], out[0])
    for shape in [(9, robot.dof, robot.num_params), (8, robot.dof, robot.num_params - 1),
                  (robot.dof, robot.num_params)]:
        with pytest.raises(ValueError, match='out has shape'):
            robot.regressor(q, qd, qdd, out=np.empty(shape))


@pytest.mark.parametrize('which,value', [(0, np.nan), (1, np.inf), (2, -np.inf)])
def test_non_finite_samples_raise(which, value):
    robot = load_robot('mit_dd_arm')
    arrays = list(samples(robot, 6, seed=13))
    arrays[which][4, 1] = value
    name = ('q', 'qd', 'qdd')[which]
    with pytest.raises(IdentificationError, match=f'^{name} contains NaN or inf .*sample 4'):
        robot.regressor(*arrays)
    with pytest.raises(IdentificationError, match='NaN or inf'):
        robot.inverse_dynamics(*arrays)


def test_wrong_sample_shapes_raise():
    robot = load_robot('mit_dd_arm')
    q, qd, qdd = samples(robot, 6, seed=14)
    with pytest.raises(IdentificationError, match=r'q has shape \(6, 2\); expected \(N, 3\)'):
        robot.regressor(q[:, :2], qd, qdd)
    with pytest.raises(IdentificationError, match='qdd has shape'):
        robot.regressor(q, qd, qdd[:, :, None])
    with pytest.raises(IdentificationError, match='sample counts differ'):
        robot.regressor(q, qd[:5], qdd)
    with pytest.raises(IdentificationError, match='parameter vector has shape'):
        robot.inverse_dynamics(q, qd, qdd, np.zeros(29))


def test_bad_joint_selection_raises():
    with pytest.raises(IdentificationError, match="joint 'joint7' is not a movable joint.*"
                       'joint1, joint2, joint3'):
        load_robot('mit_dd_arm', ['joint1', 'joint7'])
    with pytest.raises(IdentificationError, match='not a movable joint'):
        load_robot(str(FIXTURE), ['joint1', 'camera_joint'])
    with pytest.raises(IdentificationError, match='more than once'):
        load_robot('mit_dd_arm', ['joint1', 'joint2', 'joint1'])
    with pytest.raises(IdentificationError, match='locked_positions name unknown joints'):
        load_robot('mit_dd_arm', ['joint1'], locked_positions={'elbow': 0.1})
    with pytest.raises(IdentificationError, match='unknown extra columns'):
        load_robot('mit_dd_arm', extras=('fv', 'stiction'))
    with pytest.raises(IdentificationError, match='coulomb_velocity'):
        load_robot('mit_dd_arm', extras=('fc',), coulomb_velocity=-1.0)


FLOATING = '''<robot name="floating_tool"><link name="base"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0.1 0.2" rpy="0.3 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="10" velocity="1"/></joint>
  <link name="l1"><inertial><origin xyz="0.2 0 0"/><mass value="1.0"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
  <joint name="free" type="floating"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.4 0 0"/></joint>
  <link name="l2"><inertial><origin xyz="0.05 0 0"/><mass value="0.5"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.001"/></inertial></link>
</robot>'''


def test_multi_dof_joint_raises_unless_locked():
    with pytest.raises(IdentificationError, match="joint 'free'.* 6 degrees of freedom"):
        load_robot(FLOATING, ['j1', 'free'])
    with pytest.raises(IdentificationError, match='degrees of freedom'):
        load_robot(FLOATING)
    robot = load_robot(FLOATING, ['j1'])  # the floating joint locked at its zero pose
    chain = Chain(FLOATING, ['j1'])
    q, qd, qdd = samples(robot, 10, seed=15)
    assert_rel_close(robot.regressor(q, qd, qdd), chain.regressor(q, qd, qdd))
    np.testing.assert_allclose(robot.phi_model, chain.standard_parameters(), atol=1e-12)
    assert robot.phi_model[0] == pytest.approx(1.5)


def test_bad_robot_descriptions_raise(tmp_path):
    with pytest.raises(IdentificationError, match="unknown robot 'no_such_robot'.*mit_dd_arm"):
        load_robot('no_such_robot')
    with pytest.raises(IdentificationError, match='no robot given'):
        load_robot('  ')
    with pytest.raises(IdentificationError, match='does not parse'):
        load_robot('<robot name="broken"><link name="a"></robot>')
    with pytest.raises(IdentificationError, match='does not parse'):
        load_robot('<notarobot/>')
    truncated = tmp_path / 'truncated.urdf'
    truncated.write_text(FIXTURE.read_text()[:900])
    with pytest.raises(IdentificationError, match='robot truncated: URDF does not parse'):
        load_robot(str(truncated))
    garbage = tmp_path / 'garbage.urdf'
    garbage.write_text('this is not xml at all')
    with pytest.raises(IdentificationError, match='does not parse'):
        load_robot(garbage)
    binary = tmp_path / 'binary.urdf'
    binary.write_bytes(b'\xff\xfe\x00\x81robot')
    with pytest.raises(IdentificationError, match='cannot read robot file'):
        load_robot(str(binary))
