"""The batched numpy regressor (identification_node/regressor_batch.py) against pinocchio: the
per-sample computeJointTorqueRegressor path of RobotModel, pinocchio's RNEA, and random tree
models with every joint kind it handles, tilted axes and a non-default gravity."""
import pickle
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from identification_node.errors import IdentificationError
from identification_node.regressor_batch import BatchRegressor, supports
from identification_node.robot import PIN_ORDER, load_robot

ROOT = Path(__file__).resolve().parents[1]
SIX = str(ROOT / 'test' / 'fixtures' / 'six_dof_arm.urdf')
PANDA = str(ROOT / 'test' / 'fixtures' / 'panda_like.urdf')
EXTRAS = ('fv', 'fc', 'fo', 'Ia')


def samples(robot, n, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = robot.position_limits.T
    lo, hi = np.where(np.isfinite(lo), lo, -7.0), np.where(np.isfinite(hi), hi, 7.0)
    return (rng.uniform(lo, hi, (n, robot.dof)), rng.normal(0, 1.5, (n, robot.dof)),
            rng.normal(0, 4.0, (n, robot.dof)))


def assert_rel(actual, expected, rel=1e-10):
    """Every entry within rel * (largest entry of ``expected``)."""
    scale = np.abs(expected).max()
    assert scale > 0
    err = np.abs(actual - expected).max()
    assert err <= rel * scale, f'max error {err:.3e} > {rel:g} * {scale:.3e}'


CASES = [
    pytest.param('mit_dd_arm', None, None, id='mit'),
    pytest.param('crs_a465', None, None, id='crs_a465'),
    pytest.param(SIX, None, None, id='six_dof_arm'),
    pytest.param(PANDA, None, None, id='panda_like'),
    pytest.param('mit_dd_arm', ['joint3', 'joint1'], {'joint2': 0.4}, id='mit_locked'),
    pytest.param(SIX, ['joint5', 'joint1', 'joint4', 'joint3'], {'joint2': 0.3, 'joint6': -1.1},
                 id='six_dof_locked'),
]


@pytest.mark.parametrize('extras', [(), EXTRAS], ids=['inertial', 'extras'])
@pytest.mark.parametrize('name,joints,locked', CASES)
def test_batch_equals_pinocchio_per_sample(name, joints, locked, extras):
    robot = load_robot(name, joints, extras=extras, coulomb_velocity=0.02,
                       locked_positions=locked)
    assert robot._batch is not None  # the batched path is the one under test
    q, qd, qdd = samples(robot, 300, seed=1)
    Yb = robot.regressor(q, qd, qdd)
    Yp = robot.regressor(q, qd, qdd, method='pinocchio')
    assert Yb.shape == Yp.shape == (300, robot.dof, robot.num_params)
    assert_rel(Yb, Yp)
    # and the torques it gives are pinocchio's RNEA for the model's own parameters
    assert_rel(Yb @ robot.phi_model, robot.rnea(q, qd, qdd))


def test_method_attribute_and_argument():
    robot = load_robot(SIX)
    q, qd, qdd = samples(robot, 20, seed=2)
    robot.regressor_method = 'pinocchio'
    Yp = robot.regressor(q, qd, qdd)
    assert_rel(robot.regressor(q, qd, qdd, method='batch'), Yp)
    with pytest.raises(IdentificationError, match='regressor method'):
        robot.regressor(q, qd, qdd, method='fast')


def test_rows_independent_of_batch_size_and_position():
    """A sample's rows are bit for bit the same alone, in small batches and across chunks."""
    robot = load_robot(SIX, extras=EXTRAS)
    q, qd, qdd = samples(robot, 700, seed=3)
    Y = robot.regressor(q, qd, qdd, method='batch')
    for k in (0, 5, 255, 256, 511, 699):
        np.testing.assert_array_equal(robot.regressor(q[k], qd[k], qdd[k], method='batch')[0],
                                      Y[k])
        lo = max(k - 2, 0)
        np.testing.assert_array_equal(robot.regressor(
            q[lo:k + 3], qd[lo:k + 3], qdd[lo:k + 3], method='batch')[k - lo], Y[k])


def test_small_batches_use_pinocchio_large_ones_the_batch_path():
    robot = load_robot('crs_a465')
    q, qd, qdd = samples(robot, robot.batch_threshold, seed=4)
    np.testing.assert_array_equal(robot.regressor(q[:3], qd[:3], qdd[:3]),
                                  robot.regressor(q[:3], qd[:3], qdd[:3], method='pinocchio'))
    np.testing.assert_array_equal(robot.regressor(q, qd, qdd),
                                  robot.regressor(q, qd, qdd, method='batch'))


def test_preallocated_out_and_zero_samples():
    robot = load_robot('crs_a465', extras=('fv',))
    q, qd, qdd = samples(robot, 40, seed=4)
    out = np.full((40, robot.dof, robot.num_params), np.nan)
    assert robot.regressor(q, qd, qdd, out=out) is out
    assert np.isfinite(out).all()
    assert_rel(out, robot.regressor(q, qd, qdd, method='pinocchio'))
    empty = np.empty((0, robot.dof))
    assert robot.regressor(empty, empty, empty).shape == (0, robot.dof, robot.num_params)


# -- random tree models built in pinocchio, every joint kind, tilted gravity --------------------
KINDS = [
    lambda rng: pin.JointModelRX(), lambda rng: pin.JointModelRY(), lambda rng: pin.JointModelRZ(),
    lambda rng: pin.JointModelRevoluteUnaligned(*_unit(rng)),
    lambda rng: pin.JointModelRUBZ(), lambda rng: pin.JointModelRUBX(),
    lambda rng: pin.JointModelRevoluteUnboundedUnaligned(),  # axis x: no setter in python
    lambda rng: pin.JointModelPX(), lambda rng: pin.JointModelPZ(),
    lambda rng: pin.JointModelPrismaticUnaligned(*_unit(rng)),
]


def _unit(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def random_tree(seed, njoints=9):
    """A branching pinocchio model: random parents, placements, joint kinds and inertias."""
    rng = np.random.default_rng(seed)
    model = pin.Model()
    for j in range(1, njoints + 1):
        parent = int(rng.integers(0, j))
        placement = pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(scale=0.3, size=3))
        jid = model.addJoint(parent, KINDS[(j + seed) % len(KINDS)](rng), placement, f'j{j}')
        inertia = pin.Inertia.Random()
        model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
    model.gravity.linear = np.array([0.8, -1.5, -9.6])
    return model


def pin_rows(model, q, qd, qdd):
    """pinocchio's regressor (N, nv, 10 nv) in our column order, angles for RUB joints."""
    data = model.createData()
    out = []
    for k in range(len(q)):
        Q = np.empty(model.nq)
        for j in range(1, model.njoints):
            jm = model.joints[j]
            if jm.nq == 2:
                Q[jm.idx_q:jm.idx_q + 2] = np.cos(q[k, j - 1]), np.sin(q[k, j - 1])
            else:
                Q[jm.idx_q] = q[k, j - 1]
        Y = pin.computeJointTorqueRegressor(model, data, Q, qd[k], qdd[k])
        cols = np.concatenate([10 * c + PIN_ORDER for c in range(model.nv)])
        out.append((Y[:, cols], pin.rnea(model, data, Q, qd[k], qdd[k])))
    return np.array([o[0] for o in out]), np.array([o[1] for o in out])


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_random_trees_against_pinocchio(seed):
    model = random_tree(seed)
    assert supports(model)
    rng = np.random.default_rng(10 + seed)
    n = model.nv
    q, qd, qdd = rng.uniform(-4, 4, (60, n)), rng.normal(0, 2, (60, n)), rng.normal(0, 5, (60, n))
    Yp, tau = pin_rows(model, q, qd, qdd)
    Yb = BatchRegressor(model, range(1, model.njoints))(q, qd, qdd)
    assert_rel(Yb, Yp)
    phi = np.concatenate([model.inertias[j].toDynamicParameters()[PIN_ORDER]
                          for j in range(1, model.njoints)])
    assert_rel(Yb @ phi, tau)
    # rows and blocks follow joint_ids
    order = list(rng.permutation(np.arange(1, model.njoints)))
    Yo = BatchRegressor(model, order)(q[:, np.array(order) - 1], qd[:, np.array(order) - 1],
                                      qdd[:, np.array(order) - 1])
    cols = np.concatenate([np.arange(10 * (j - 1), 10 * j) for j in order])
    assert_rel(Yo, Yb[:, np.array(order) - 1][:, :, cols])


def test_unsupported_joints_and_bad_ids():
    model = pin.Model()
    jid = model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), 'ball')
    model.appendBodyToJoint(jid, pin.Inertia.Random(), pin.SE3.Identity())
    assert not supports(model)
    with pytest.raises(ValueError, match='not revolute, continuous or prismatic'):
        BatchRegressor(model, [1])
    tree = random_tree(5, njoints=3)
    with pytest.raises(ValueError, match='every joint'):
        BatchRegressor(tree, [1, 2])


def test_batch_regressor_pickles():
    robot = load_robot('crs_a465')
    q, qd, qdd = samples(robot, 5, seed=6)
    Y = robot.regressor(q, qd, qdd, method='batch')
    batch = pickle.loads(pickle.dumps(robot._batch))
    np.testing.assert_array_equal(batch(q, qd, qdd), Y)
