"""Reference trajectories: boundary conditions, analytic derivatives, the papers' tables, files."""
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from identification_node.errors import IdentificationError
from identification_node.excitation.quintic_moves import QuinticMoves
from identification_node.excitation.sampled import SampledTrajectory
from identification_node.excitation.trajectories import FourierTrajectory, load_trajectory
from identification_node.excitation.trajectory_base import check_limits
from identification_node.model.robot import load_robot

CRS_URDF = Path(__file__).resolve().parents[1] / 'identification_node' / 'robots' / \
    'crs_a465.urdf'


def finite_differences(traj, t, h=1e-5):
    """Central differences of q and qd: independent of the analytic derivatives."""
    qp, qdp, _ = traj.sample(t + h)
    qm, qdm, _ = traj.sample(t - h)
    return (qp - qm) / (2 * h), (qdp - qdm) / (2 * h)


@pytest.fixture(scope='module')
def mit():
    return load_robot('mit_dd_arm')


# -- Fourier --------------------------------------------------------------------------------
def test_fourier_matches_the_paper_formula_and_is_periodic():
    rng = np.random.default_rng(3)
    a, b, q0 = rng.normal(size=(2, 3)), rng.normal(size=(2, 3)), rng.normal(size=2)
    traj = FourierTrajectory(a, b, q0, period=4.0)
    t = rng.uniform(0, 8, 50)
    w = 2 * np.pi / 4.0
    expected = np.array([[sum(a[i, h - 1] / (w * h) * np.sin(w * h * tk)
                              - b[i, h - 1] / (w * h) * np.cos(w * h * tk) for h in (1, 2, 3))
                          + q0[i] for i in range(2)] for tk in t])
    q, qd, qdd = traj.sample(t)
    np.testing.assert_allclose(q, expected, atol=1e-12)
    for x, y in zip(traj.sample(t + 4.0), (q, qd, qdd)):
        np.testing.assert_allclose(x, y, atol=1e-9)
    assert traj.duration == math.inf and traj.period == 4.0


def test_fourier_derivatives_match_finite_differences():
    traj = FourierTrajectory.crs_table1()
    t = np.linspace(0.1, 9.9, 37)
    _, qd, qdd = traj.sample(t)
    fd_qd, fd_qdd = finite_differences(traj, t)
    np.testing.assert_allclose(qd, fd_qd, atol=1e-7)
    np.testing.assert_allclose(qdd, fd_qdd, atol=1e-6)


def test_table1_layout_reproduces_the_papers_start_points():
    traj = FourierTrajectory.crs_table1()
    assert traj.a.shape == (6, 5) and traj.b.shape == (6, 5)
    # Spot checks of the table: joint 2's fifth a and b, joint 4's second b, q0 row.
    assert traj.a[1, 4] == 1.046 and traj.b[1, 4] == 0.964 and traj.b[3, 1] == -0.714
    np.testing.assert_allclose(traj.q0, [0, 1.813, -1.184, 0.087, -0.415, 0.124])
    # Section IV.C start points (deg) of joints 2-6; joint 3 printed without its sign, and
    # joint 1 (-23.04 in the text) does not match any period together with the others.
    q_start = np.degrees(traj.sample(0.0)[0][0])
    np.testing.assert_allclose(q_start[[1, 3, 4, 5]], [82.94, -28.08, -73.00, 20.64], atol=0.1)
    assert abs(abs(q_start[2]) - 38.01) < 0.1
    # Speeds stay inside the A465 limits (180, 180, 180, 171, 173, 171 deg/s).
    _, qd, _ = traj.sample(np.linspace(0, traj.period, 4001))
    assert np.all(np.degrees(np.abs(qd).max(axis=0)) < [180, 180, 180, 171, 173, 171])


def test_fourier_dict_round_trip_and_yaml_file(tmp_path, mit):
    rng = np.random.default_rng(0)
    traj = FourierTrajectory(rng.normal(size=(3, 4)), rng.normal(size=(3, 4)),
                             rng.normal(size=3), 7.5, ['joint3', 'joint1', 'joint2'])
    back = FourierTrajectory.from_dict(yaml.safe_load(yaml.safe_dump(traj.to_dict())))
    t = np.linspace(0, 10, 30)
    for x, y in zip(traj.sample(t), back.sample(t)):
        np.testing.assert_array_equal(x, y)
    path = tmp_path / 'traj.yaml'
    path.write_text(yaml.safe_dump(traj.to_dict()))
    loaded = load_trajectory(str(path), mit)
    assert loaded.joint_names == mit.joint_names
    # Columns reordered to the robot's joints by name.
    np.testing.assert_allclose(loaded.sample(t)[0], traj.sample(t)[0][:, [1, 2, 0]])


# -- quintic moves -----------------------------------------------------------------------------
def test_quintic_moves_rest_to_rest_boundary_conditions():
    wp = np.array([[0.0, 1.0], [2.0, -1.0], [2.5, 0.5]])
    traj = QuinticMoves(wp, [1.0, 0.5], rest=0.25)
    assert traj.duration == pytest.approx(2.0)
    ends = np.array([0.0, 1.0, 1.25, 1.75, 2.0])
    q, qd, qdd = traj.sample(ends)
    np.testing.assert_allclose(q, wp[[0, 1, 1, 2, 2]], atol=1e-12)
    np.testing.assert_allclose(qd, 0, atol=1e-12)
    np.testing.assert_allclose(qdd, 0, atol=1e-12)
    # Rest holds; after the end the last waypoint holds.
    q, qd, _ = traj.sample(np.array([1.1, 1.2, 5.0]))
    np.testing.assert_allclose(q, wp[[1, 1, 2]])
    np.testing.assert_allclose(qd, 0)
    # Midpoint of a quintic: half way, peak speed 15/8 D/T.
    q, qd, qdd = traj.sample(0.5)
    np.testing.assert_allclose(q[0], [1.0, 0.0])
    np.testing.assert_allclose(qd[0], 15 / 8 * np.array([2.0, -2.0]))
    t = np.linspace(0.01, 1.99, 61)
    _, qd, qdd = traj.sample(t)
    fd_qd, fd_qdd = finite_differences(traj, t, h=1e-6)
    np.testing.assert_allclose(qd, fd_qd, atol=1e-6)
    np.testing.assert_allclose(qdd, fd_qdd, atol=1e-4)


def test_mit_paper_moves_hit_the_papers_points():
    traj = QuinticMoves.mit_paper()
    moves = [((330, 289.1, 230), (80, 39.1, -10)), ((330, 269.1, -30), (80, 19.1, 220)),
             ((80, 269.1, -30), (330, 19.1, 220))]
    # Segments: move 1, transfer, move 2, transfer, move 3.
    np.testing.assert_allclose(traj.durations[[0, 2, 4]], 1.3)
    starts = np.concatenate([[0.0], np.cumsum(traj.durations)])
    for k, (a, b) in enumerate(moves):
        q, qd, qdd = traj.sample(starts[[2 * k, 2 * k + 1]])
        np.testing.assert_allclose(np.degrees(q), [a, b], atol=1e-9)
        np.testing.assert_allclose(qd, 0, atol=1e-12)
        np.testing.assert_allclose(qdd, 0, atol=1e-12)
    # Transfers no faster than the moves; 250 deg in 1.3 s peaks at 15/8 D/T.
    _, qd, _ = traj.sample(np.linspace(0, traj.duration, 5001))
    assert np.abs(qd).max() == pytest.approx(15 / 8 * np.radians(250) / 1.3, rel=1e-3)


def test_mit_paper_repeat_is_periodic_and_smooth():
    traj = QuinticMoves.mit_paper(repeat=True, rest=0.1)
    assert traj.duration == math.inf and traj.period > 3 * 1.3
    t = np.linspace(0, traj.period, 200)
    for x, y in zip(traj.sample(t), traj.sample(t + 2 * traj.period)):
        np.testing.assert_allclose(x, y, atol=1e-9)
    # The return move (270 deg for joint 2) is stretched to keep the moves' peak speed.
    _, qd, _ = traj.sample(np.linspace(0, traj.period, 20001))
    assert np.abs(qd).max() <= 15 / 8 * np.radians(250) / 1.3 * (1 + 1e-6)


def test_quintic_errors():
    with pytest.raises(IdentificationError):
        QuinticMoves(np.zeros((1, 2)), 1.0)
    with pytest.raises(IdentificationError):
        QuinticMoves(np.zeros((3, 2)), [1.0, -1.0])
    with pytest.raises(IdentificationError):
        QuinticMoves(np.zeros((3, 2)), [1.0, 1.0, 1.0])


# -- sampled -------------------------------------------------------------------------------------
def test_sampled_csv_round_trip_and_spline_derivatives(tmp_path, mit):
    ref = FourierTrajectory.random(mit, harmonics=3, period=4.0, seed=5)
    t = np.arange(0, 4.0001, 0.01) + 2.0  # shifted to start at 0 on construction
    traj = SampledTrajectory(t, ref.sample(t - 2.0)[0], mit.joint_names)
    assert traj.duration == pytest.approx(4.0)
    path = tmp_path / 'sub' / 'traj.csv'
    traj.to_csv(path)
    assert path.read_text().splitlines()[0] == 't,joint1,joint2,joint3'
    assert [p.name for p in path.parent.iterdir()] == ['traj.csv']  # no temporary left
    back = load_trajectory(str(path), mit)
    np.testing.assert_array_equal(back.t, traj.t)
    np.testing.assert_array_equal(back.q, traj.q)
    # Spline derivatives against the analytic ones inside the span.
    ti = np.linspace(0.2, 3.8, 41)
    _, qd, qdd = back.sample(ti)
    _, qd_ref, qdd_ref = ref.sample(ti)
    np.testing.assert_allclose(qd, qd_ref, atol=1e-4 * np.abs(qd_ref).max())
    np.testing.assert_allclose(qdd, qdd_ref, atol=1e-2 * np.abs(qdd_ref).max())
    # Outside the span: end positions held, at rest.
    q, qd, qdd = back.sample(np.array([-1.0, 9.0]))
    np.testing.assert_allclose(q, traj.q[[0, -1]])
    assert not qd.any() and not qdd.any()


def test_sampled_errors(tmp_path):
    with pytest.raises(IdentificationError, match='increase'):
        SampledTrajectory([0.0, 1.0, 1.0], np.zeros((3, 2)))
    with pytest.raises(IdentificationError, match='at least 2'):
        SampledTrajectory([0.0], np.zeros((1, 2)))
    with pytest.raises(IdentificationError, match='NaN'):
        SampledTrajectory([0.0, 1.0], [[0.0], [np.nan]])
    bad = tmp_path / 'bad.csv'
    bad.write_text('x,joint1\n0,1\n1,2\n')
    with pytest.raises(IdentificationError, match='header'):
        SampledTrajectory.from_csv(bad)
    bad.write_text('t,joint1\n0,1\n1,oops\n')
    with pytest.raises(IdentificationError, match='cannot read'):
        SampledTrajectory.from_csv(bad)


# -- loading and limits ------------------------------------------------------------------------
def test_load_trajectory_names_and_errors(tmp_path, mit):
    assert isinstance(load_trajectory('paper_moves', mit), QuinticMoves)
    f = load_trajectory('fourier', mit)
    assert f.dof == 3 and f.joint_names == mit.joint_names
    with pytest.raises(IdentificationError, match='6 joints'):
        load_trajectory('table1', mit)
    with pytest.raises(IdentificationError, match='unknown trajectory'):
        load_trajectory('circle', mit)
    with pytest.raises(IdentificationError, match='does not exist'):
        load_trajectory(str(tmp_path / 'none.yaml'), mit)
    y = tmp_path / 't.yaml'
    y.write_text('period: 5\nq0: [0, 0]\na: [[1], [1]]\nb: [[0], [0]]\n')
    with pytest.raises(IdentificationError, match='2 joints'):
        load_trajectory(str(y), mit)
    y.write_text('period: 5\nq0: [0, 0, 0]\n')
    with pytest.raises(IdentificationError, match='missing'):
        load_trajectory(str(y), mit)
    y.write_text('period: -1\nq0: [0, 0, 0]\na: [[1], [1], [1]]\nb: [[0], [0], [0]]\n')
    with pytest.raises(IdentificationError, match='period'):
        load_trajectory(str(y), mit)
    y.write_text('period: 5\nq0: [0, 0, 0]\na: [[1], [1], [1]]\nb: [[0], [0], [0]]\n'
                 'joints: [joint1, joint2, elbow]\n')
    with pytest.raises(IdentificationError, match='names joints'):
        load_trajectory(str(y), mit)
    y.write_text('period: [5\n')
    with pytest.raises(IdentificationError, match='YAML'):
        load_trajectory(str(y), mit)


def test_check_limits_against_closed_form():
    # One harmonic: q = (a/w) sin(w t) + q0, qd = a cos(w t), qdd = -a w sin(w t).
    w = 2 * np.pi / 2.0
    traj = FourierTrajectory([[1.0], [0.5]], [[0.0], [0.0]], [0.2, 0.0], period=2.0)
    limits = {'position': [[-1.0, 1.0], [-np.inf, np.inf]], 'velocity': [2.0, 0.25],
              'acceleration': [np.inf, 1.0]}
    r = check_limits(traj, limits)
    np.testing.assert_allclose(r['per_joint']['position'], [0.2 + 1 / w, 0.0], rtol=1e-5)
    np.testing.assert_allclose(r['per_joint']['velocity'], [0.5, 2.0], rtol=1e-5)
    np.testing.assert_allclose(r['per_joint']['acceleration'], [0.0, 0.5 * w], rtol=1e-5)
    assert r['velocity'] == pytest.approx(2.0, rel=1e-5) and r['worst_joint']['velocity'] == 1


@pytest.mark.skipif(not CRS_URDF.is_file(), reason='crs_a465.urdf not there')
def test_random_fourier_stays_inside_the_crs_limits():
    crs = load_robot(str(CRS_URDF))
    assert load_trajectory('table1', crs).dof == 6
    traj = load_trajectory('fourier', crs)
    r = check_limits(traj, crs, np.linspace(0, traj.period, 5001))
    # Designed on a 4001-point grid: peaks between its points exceed it by < 1e-4.
    assert r['position'] <= 0.8 * (1 + 1e-4) and r['velocity'] <= 0.8 * (1 + 1e-4)
    # One of the two limits is binding on every joint (amplitudes are scaled to it).
    binding = np.maximum(r['per_joint']['position'], r['per_joint']['velocity'])
    np.testing.assert_allclose(binding, 0.8, rtol=1e-3)
