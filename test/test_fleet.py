"""Fleet identification: simulated bags of two robots over three periods, one robot's friction
drifting, one bag corrupt; map/reduce on Dask equals ``identify`` of the same data."""
import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from identification_node.bags.reader import iter_joint_states, open_bag
from identification_node.bags.writer import BagWriter
from identification_node.cli import main
from identification_node.results.documents import result_document
from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import ConsistentSolver
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import load_robot
from identification_node.fleet import fleet
from identification_node.replay import segments
from identification_node.replay.stream import replay_identify
from identification_node.results.identification import make_consistent
from identification_node.settings import Settings
from test_offline import simulate, write_bag

REPO = Path(__file__).resolve().parents[1]
PYTHON = sys.executable
EXTRAS = ['fv', 'fc']
PERIODS = ('day1', 'day2', 'day3')
FRICTION = {'fv': 0.5, 'fc': 0.3}
DRIFT = 0.3          # arm_b's joint2.fv grows by this per period (N m s/rad)
DURATION = 4.0       # s per bag, at 1 kHz


@pytest.fixture(scope='module')
def robot():
    return load_robot('mit_dd_arm', extras=EXTRAS)


@pytest.fixture(scope='module')
def settings():
    return Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS})


def true_phi(robot, robot_name, period):
    phi = robot.phi_model.copy()
    for j in robot.joint_names:
        for k, v in FRICTION.items():
            phi[robot.param_index(f'{j}.{k}')] = v
    if robot_name == 'arm_b':
        phi[robot.param_index('joint2.fv')] += DRIFT * PERIODS.index(period)
    return phi


@pytest.fixture(scope='module')
def fleet_dir(tmp_path_factory, robot):
    """12 bags (2 robots x 3 periods x 2 bags) and a truncated 13th; manifest.csv."""
    root = tmp_path_factory.mktemp('fleet')
    traj = FourierTrajectory.random(robot, seed=3, period=DURATION)
    rows, seed = [], 0
    for name in ('arm_a', 'arm_b'):
        for period in PERIODS:
            for k in range(2):
                seed += 1
                t, q, qd, tau = simulate(robot, traj, DURATION, seed=seed,
                                         phi=true_phi(robot, name, period))
                bag = f'bags/{name}_{period}_{k}'
                write_bag(root / bag, robot, t, q, qd, tau)
                rows.append((bag, name, period))
    shutil.copytree(root / 'bags/arm_a_day2_0', root / 'bags/corrupt')
    mcap = next((root / 'bags/corrupt').glob('*.mcap'))
    data = mcap.read_bytes()
    mcap.write_bytes(data[:len(data) // 2])
    rows.insert(3, ('bags/corrupt', 'arm_a', 'day2'))
    (root / 'arm.yaml').write_text(f'robot: mit_dd_arm\nextras: {EXTRAS}\n')
    with open(root / 'manifest.csv', 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(['bag', 'robot', 'period', 'config'])
        w.writerows(r + ('arm.yaml',) for r in rows)
    return root


def concatenated(bags, out, robot):
    """One bag holding ``bags`` one after another, as recorded (each bag's stamps start
    again: a new stream for the pipeline)."""
    with BagWriter(out) as w:
        w.write_string('/robot_description', 0, robot.description)
        k = 0
        for bag in bags:
            with open_bag(bag) as r:
                for _, _, rec in iter_joint_states(r, ['/joint_states']):
                    k += 1
                    w.write_joint_state('/joint_states', k, rec.stamp_ns * 1e-9, rec.names,
                                        rec.position, rec.velocity, rec.effort)
    return out


def values(doc):
    return (np.array([p['estimate'] for p in doc['base_parameters']]),
            np.array([p['stddev'] for p in doc['base_parameters']]))


def assert_same_identification(doc, ref, rtol=1e-9, figures_rtol=None):
    """Estimates and stddevs to rtol of the parameter vector's scale; the sums' figures to
    ``figures_rtol`` (default rtol)."""
    (e, s), (re, rs) = values(doc), values(ref)
    np.testing.assert_allclose(e, re, rtol=rtol, atol=rtol * np.abs(re).max())
    np.testing.assert_allclose(s, rs, rtol=rtol, atol=rtol * np.abs(rs).max())
    rtol = rtol if figures_rtol is None else figures_rtol
    assert doc['num_samples'] == ref['num_samples']
    assert doc['converged'] == ref['converged']
    assert doc['rejected'] == ref['rejected']
    for key in ('relative_error', 'residual_rms', 'noise_std'):
        np.testing.assert_allclose(list(doc[key].values()), list(ref[key].values()),
                                   rtol=rtol)
    np.testing.assert_allclose(doc['condition_number'], ref['condition_number'], rtol=rtol)


def assert_same_as_identify(doc, ref):
    """``doc`` against identify's document ``ref`` (physically consistent): the consistent
    estimate to the solver's tolerance, the unconstrained one and the rest to rounding."""
    assert_same_identification(doc, ref, rtol=1e-6)
    u, ru = doc['unconstrained_estimate'], ref['unconstrained_estimate']
    np.testing.assert_allclose(u, ru, rtol=1e-9, atol=1e-9 * np.abs(ru).max())
    assert doc['consistency_solver']['status'] == ref['consistency_solver']['status']


def manifest_groups(root):
    groups = {}
    for e in fleet.read_manifest(root / 'manifest.csv'):
        if 'corrupt' not in e.bag:
            groups.setdefault((e.robot, e.period), []).append(e.bag)
    return groups


# -- statistics: exact merging ------------------------------------------------------------------
def test_an_estimator_from_normal_equations_is_the_streamed_one():
    rng = np.random.default_rng(4)
    Y, tau = rng.standard_normal((500, 3, 6)), rng.standard_normal((500, 3))
    streamed = RecursiveLeastSquares(6)
    for a in range(0, 500, 50):
        streamed.update(Y[a:a + 50], tau[a:a + 50])
    merged = RecursiveLeastSquares.from_normal_equations(
        NormalEquations.from_rows(Y[:200], tau[:200])
        + NormalEquations.from_rows(Y[200:], tau[200:]), 500)
    np.testing.assert_allclose(merged.theta, streamed.theta, rtol=1e-12)
    np.testing.assert_allclose(merged.covariance, streamed.covariance, rtol=1e-11)
    assert merged.num_samples == 500 and merged.rank == 6
    theta = np.arange(6.0)
    held = RecursiveLeastSquares.from_normal_equations(merged.normal_equations(), 500,
                                                       theta=theta)
    np.testing.assert_array_equal(held.theta, theta)
    np.testing.assert_allclose(held.residual_rms ** 2 * 500, np.sum(
        (tau - Y @ theta) ** 2, axis=0), rtol=1e-12)


def test_residual_statistics_of_two_recordings_add_with_their_blocks_apart():
    rng = np.random.default_rng(5)
    Y, tau = rng.standard_normal((300, 2, 4)), rng.standard_normal((300, 2))
    a, b, c = (ResidualStatistics(4, 2, 16) for _ in range(3))
    a.add(Y[:130], tau[:130])
    b.add(Y[130:], tau[130:])
    c.add(Y[:130], tau[:130])
    c.close_block()
    c.add(Y[130:], tau[130:])
    merged = a + b
    theta = rng.standard_normal(4)
    assert merged.blocks == c.blocks == 130 // 16 + 170 // 16 and merged.count == 300
    np.testing.assert_allclose(merged.long_run_variance(theta), c.long_run_variance(theta),
                               rtol=1e-13)
    np.testing.assert_allclose(merged.rss(theta), np.sum((tau - Y @ theta) ** 2, axis=0),
                               rtol=1e-12)
    with pytest.raises(IdentificationError, match='cannot merge'):
        a + ResidualStatistics(4, 2, 8)


@pytest.mark.slow
def test_one_bag_statistics_give_identify(fleet_dir, robot, settings):
    bag = fleet_dir / 'bags/arm_a_day1_0'
    stats = segments.bag_statistics(bag, settings, robot)
    doc = result_document(segments.identification(stats, settings, robot))
    ref = make_consistent(replay_identify(bag, settings, robot), settings.consistency_options())
    assert_same_as_identify(doc, result_document(ref))


@pytest.mark.slow
def test_merged_statistics_give_identify_of_the_concatenated_bags(fleet_dir, robot, settings,
                                                                  tmp_path):
    # The robust gate judges a sample against the model of everything before it, so with it
    # on, identify of the concatenation gates day2's drifted friction by day1's model while
    # the fleet's map gates each bag by its own: exact merging is a property of the sums.
    settings = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                                  'robust': {'enabled': False}})
    bags = [fleet_dir / f'bags/arm_b_{p}_{k}' for p in PERIODS[:2] for k in range(2)]
    # one smoother for all, chosen on the first bag, as identify on the concatenation does
    one = segments.pinned(settings, segments.bag_smoother(bags[0], settings, robot))
    merged = sum((segments.bag_statistics(b, one, robot) for b in bags[1:]),
                 segments.bag_statistics(bags[0], one, robot))
    doc = result_document(segments.identification(merged, settings, robot,
                                                  physical_consistency=False))
    ref = replay_identify(concatenated(bags, tmp_path / 'cat', robot), settings, robot)
    assert ref.pipeline.smoother.half_window == one['smoother.half_window']
    with pytest.raises(IdentificationError, match='different smoothers'):
        merged + segments.bag_statistics(bags[0], segments.pinned(settings, (
            ('smoother.half_window', one['smoother.half_window'] + 1),)), robot)
    assert ref.pipeline.restarts == 3
    # (identify holds the first bag back for the smoother's choice, so its rows enter the
    # sums in other batches: the relative errors' small residuals differ by rounding, 1e-8)
    assert_same_identification(doc, result_document(ref), rtol=1e-9, figures_rtol=1e-8)


@pytest.mark.slow
def test_a_group_is_solved_physically_consistent_as_identify(fleet_dir, robot, tmp_path):
    """A group's document has identify's shape; its consistent estimate is ConsistentSolver's
    on the merged normal equations and identify's (make_consistent) of the concatenated
    bags, to solver tolerance; physical_consistency=False gives the unconstrained one."""
    settings = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                                  'robust': {'enabled': False}})
    bags = [fleet_dir / f'bags/arm_b_{PERIODS[0]}_{k}' for k in range(2)]
    one = segments.pinned(settings, segments.bag_smoother(bags[0], settings, robot))
    merged = segments.bag_statistics(bags[0], one, robot) + segments.bag_statistics(
        bags[1], one, robot)
    ident = segments.identification(merged, settings, robot)
    doc = result_document(ident)
    assert doc['consistency_solver']['status'] == 'optimal' and doc['links']
    options = settings.consistency_options()
    base = fleet_base(robot, settings)
    weight = 1.0 / float(np.mean(ident.pipeline.noise_variance()))
    direct = ConsistentSolver.for_robot(robot, base, options).solve(
        merged.normal_equations, weight)
    scale = np.abs(direct.theta).max()
    np.testing.assert_allclose(doc['estimate'], direct.theta, atol=1e-6 * scale)
    ref = make_consistent(replay_identify(concatenated(bags, tmp_path / 'cat', robot),
                                          settings, robot), options)
    ref_doc = result_document(ref)
    np.testing.assert_allclose(doc['estimate'], ref_doc['estimate'], atol=1e-6 * scale)
    np.testing.assert_allclose(doc['unconstrained_estimate'],
                               ref_doc['unconstrained_estimate'], rtol=1e-9,
                               atol=1e-9 * np.abs(ref_doc['unconstrained_estimate']).max())
    assert set(doc) == set(ref_doc)
    assert not np.allclose(doc['estimate'], doc['unconstrained_estimate'], rtol=1e-6)
    plain = result_document(segments.identification(merged, settings, robot,
                                                    physical_consistency=False))
    assert plain['estimate'] == plain['unconstrained_estimate'] == doc['unconstrained_estimate']
    assert plain['consistency_solver']['status'] == 'disabled'


LONG = 250.0        # s of the long bag, at 100 Hz: cut at the residual grid (10 s)


@pytest.fixture(scope='module')
def long_bag(tmp_path_factory, robot):
    t, q, qd, tau = simulate(robot, FourierTrajectory.random(robot, seed=5, period=10.0), LONG,
                             rate=100.0, seed=21, phi=true_phi(robot, 'arm_a', 'day1'))
    return write_bag(tmp_path_factory.mktemp('long') / 'long', robot, t, q, qd, tau)


@pytest.mark.slow
def test_segments_give_the_whole_bag_and_identify(long_bag, robot):
    """A bag cut at multiples of the residual grid into 2 or 5 segments (the smoother's
    overlap handled) merges to the whole bag's statistics: the same rows, normal equations
    and residual blocks, so estimate and stddev equal the unsplit run's and identify's on the
    bag to 1e-9. (Robust gate off: a segment's gate arms on that segment's own fit.)"""
    from identification_node.pipeline.estimate import RESIDUAL_GRID

    settings = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                                  'robust': {'enabled': False}})
    whole = segments.bag_statistics(long_bag, settings, robot)
    assert whole.residuals.blocks >= 100   # the long-run variance is in use (>= 10 blocks)
    ref = result_document(make_consistent(replay_identify(long_bag, settings, robot),
                                          settings.consistency_options()))
    docs = []
    for cuts in ([None, None], [None, 2 * RESIDUAL_GRID, None],
                 [None] + [k * RESIDUAL_GRID for k in range(1, 5)] + [None],
                 [None, 5 * RESIDUAL_GRID, None]):     # a segment after the bag's end: empty
        parts = [segments.bag_statistics(long_bag, settings, robot, a, b)
                 for a, b in zip(cuts, cuts[1:])]
        merged = sum(parts[1:], parts[0])
        assert merged.used == whole.used and merged.messages == whole.messages
        assert merged.residuals.blocks == whole.residuals.blocks
        assert merged.residuals.count == whole.residuals.count
        A, B = merged.normal_equations.augmented, whole.normal_equations.augmented
        np.testing.assert_allclose(A, B, rtol=1e-11, atol=1e-13 * np.abs(B).max())
        docs.append(result_document(segments.identification(merged, settings, robot)))
    for doc in docs:   # the errors are the consistent estimate's: two conic solves, 1e-8
        assert_same_identification(doc, docs[0], figures_rtol=1e-8)
        assert_same_as_identify(doc, ref)    # the consistent estimate to solver tolerance
        np.testing.assert_allclose(values(doc)[1], values(ref)[1], rtol=1e-9)
    # the unsplit stddev uses the long-run variance: not the white-noise one
    plain = replay_identify(long_bag, settings, robot).pipeline
    white = plain.residuals.variance(plain.rls.theta) * plain.estimator._white_scale
    assert not np.allclose(plain.noise_variance(), white, rtol=0.01)


def test_a_cut_off_the_grid_moves_only_the_residual_blocks(long_bag, robot, settings):
    """Cut elsewhere, the segments still give the whole bag's rows and estimate; only the
    block partition, and with it the long-run variance, differs (hence the grid)."""
    whole = segments.bag_statistics(long_bag, settings, robot)
    cuts = [None, whole.first_ns + 61_234_567_891, None]
    parts = [segments.bag_statistics(long_bag, settings, robot, a, b)
             for a, b in zip(cuts, cuts[1:])]
    merged = parts[0] + parts[1]
    A, B = merged.normal_equations.augmented, whole.normal_equations.augmented
    np.testing.assert_allclose(A, B, rtol=1e-11, atol=1e-13 * np.abs(B).max())
    assert merged.residuals.blocks == whole.residuals.blocks - 1
    a = segments.identification(merged, settings, robot, physical_consistency=False)
    b = segments.identification(whole, settings, robot, physical_consistency=False)
    np.testing.assert_allclose(a.theta, b.theta, rtol=1e-9, atol=1e-9 * np.abs(b.theta).max())
    assert not np.allclose(a.stddev, b.stddev, rtol=1e-6)


def test_the_solve_seam_takes_normal_equations_and_gives_the_estimate(
        fleet_dir, robot, settings):
    """Another solve (here: the model's own parameters) plugs in with one call; residuals
    are then those of its estimate."""
    bag = fleet_dir / 'bags/arm_b_day1_0'
    stats = segments.bag_statistics(bag, settings, robot)
    seen = []

    def model_solve(equations):
        seen.append(equations)
        return fleet_base(robot, settings).to_base(robot.phi_model)

    doc = result_document(segments.identification(stats, settings, robot, solve=model_solve,
                                                  physical_consistency=False))
    assert len(seen) == 1 and isinstance(seen[0], NormalEquations)
    np.testing.assert_array_equal(values(doc)[0], fleet_base(robot, settings).to_base(
        robot.phi_model))
    ref = result_document(replay_identify(bag, settings, robot))
    np.testing.assert_allclose(list(doc['relative_error'].values()),
                               list(ref['model_relative_error'].values()), rtol=1e-9)


def fleet_base(robot, settings):
    return settings.build(robot).base


def test_statistics_of_other_robots_do_not_merge(fleet_dir, robot, settings):
    other = load_robot('mit_dd_arm', extras=['fv'])
    a = segments.bag_statistics(fleet_dir / 'bags/arm_a_day1_0', settings, robot)
    b = segments.bag_statistics(fleet_dir / 'bags/arm_a_day1_1',
                                Settings.from_dict({'robot': 'mit_dd_arm', 'extras': ['fv']}),
                                other)
    with pytest.raises(IdentificationError, match='different robot models'):
        a + b
    # in a fleet run: the bag of the other model is reported, the rest reduced
    pairs = [(fleet.MapTask(fleet.FleetEntry(s.bags[0], 'arm', 'day1')), s) for s in (a, b)]
    groups, failed = fleet.reduce_statistics(pairs)
    assert list(groups) == [('arm', 'day1')] and groups['arm', 'day1'].bags == a.bags
    assert [f['bag'] for f in failed] == list(b.bags)
    assert 'different robot models' in failed[0]['error']


def test_forgetting_is_refused(fleet_dir, robot):
    s = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                            'forgetting_factor': 0.999})
    with pytest.raises(IdentificationError, match='forgetting_factor 1'):
        segments.bag_statistics(fleet_dir / 'bags/arm_a_day1_0', s, robot)


# -- manifest -----------------------------------------------------------------------------------
@pytest.mark.parametrize('text, error', [
    ('bag,robot\nx,y\n', 'missing period'),
    ('bag,robot,period,colour\nx,y,z,red\n', 'unknown columns colour'),
    ('bag,robot,period\nx,,z\n', 'line 2'),
    ('bag,robot,period\n', 'it has no rows'),
    ('bag,robot,period\nx,a,1\nx,a,2\n', 'line 3: bag x is listed twice'),
    ('bag,robot,period\nx,a,1,extra\n', 'line 2: more fields than the header')])
def test_manifest_errors_are_clear(tmp_path, text, error):
    (tmp_path / 'm.csv').write_text(text)
    with pytest.raises(IdentificationError, match=error):
        fleet.read_manifest(tmp_path / 'm.csv')


def test_manifest_paths_are_relative_to_it(tmp_path):
    sub = tmp_path / 'sub'
    sub.mkdir()
    (sub / 'm.csv').write_text('bag,robot,period,urdf\nb1,a,1,arm.urdf\n')
    assert fleet.read_manifest(sub / 'm.csv') == [
        fleet.FleetEntry(str(sub / 'b1'), 'a', '1', str(sub / 'arm.urdf'))]


def test_outliers_need_a_fleet_and_flag_the_odd_robot():
    def doc(x, sd=0.01):
        # the flags read the unconstrained estimate (the consistent one is a decoy here)
        return {'base_parameters': [
            {'name': 'a', 'estimate': 1.0, 'unconstrained_estimate': x, 'stddev': sd},
            {'name': 'b', 'estimate': 9.0, 'unconstrained_estimate': 1.0, 'stddev': sd}]}
    totals = {'r1': doc(1.0), 'r2': doc(1.01), 'r3': doc(0.99), 'r4': doc(1.5)}
    flags = fleet.outlier_flags(totals, dict.fromkeys(totals, 'm'))
    assert [(f['robot'], f['parameter']) for f in flags] == [('r4', 'a')]
    assert not fleet.outlier_flags({'r1': doc(1.0), 'r4': doc(1.5)}, {'r1': 'm', 'r4': 'm'})
    assert not fleet.outlier_flags(totals, {'r1': 'm', 'r2': 'm', 'r3': 'n', 'r4': 'n'})


ODD = 'joint1.fv'     # arm_4's is 4 times the others' (0.5 N m s/rad): a worn joint


@pytest.fixture(scope='module')
def four_arms(tmp_path_factory, robot):
    """One 4 s bag each of four arms of one model on the same motion (own noise): arm_4's
    joint1 viscous friction 2.0 instead of 0.5 N m s/rad."""
    root = tmp_path_factory.mktemp('four')
    traj = FourierTrajectory.random(robot, seed=3, period=DURATION)
    (root / 'arm.yaml').write_text(f'robot: mit_dd_arm\nextras: {EXTRAS}\n')
    entries = []
    for k in range(1, 5):
        phi = true_phi(robot, 'arm_a', 'day1')
        if k == 4:
            phi[robot.param_index(ODD)] *= 4
        t, q, qd, tau = simulate(robot, traj, DURATION, seed=40 + k, phi=phi)
        write_bag(root / f'arm_{k}', robot, t, q, qd, tau)
        entries.append(fleet.FleetEntry(str(root / f'arm_{k}'), f'arm_{k}', 'day1',
                                        config=str(root / 'arm.yaml')))
    return entries


@pytest.mark.slow
def test_the_odd_arm_of_a_simulated_fleet_is_the_outlier(four_arms, robot, settings):
    """Four simulated arms of one model, one with four times the viscous friction on joint1:
    it, and only it, is flagged against the fleet, on that parameter, and by about the
    change over its standard deviation; the three alike arms are not."""
    from distributed import Client

    with Client(processes=False, n_workers=1, threads_per_worker=2,
                dashboard_address='127.0.0.1:0') as client:
        result = fleet.run_fleet(four_arms, client, physical_consistency=False)
    assert not result.failed
    doc = fleet.fleet_document(result)
    assert [(f['robot'], f['parameter'], f['kind']) for f in doc['flags']] == [
        ('arm_4', ODD, 'fleet_outlier')]
    flag = doc['flags'][0]
    names = [p['name'] for p in doc['totals']['arm_4']['base_parameters']]
    sd = doc['totals']['arm_4']['base_parameters'][names.index(ODD)]['stddev']
    change = 3 * FRICTION['fv']
    np.testing.assert_allclose(flag['estimate'] - flag['fleet_median'], change, rtol=0.05)
    assert flag['change_sigma'] > 5 and flag['change_sigma'] < 1.1 * change / sd
    # without the odd arm (three alike): nothing is flagged
    alike = fleet.outlier_flags({r: doc['totals'][r] for r in ('arm_1', 'arm_2', 'arm_3')},
                                dict.fromkeys(('arm_1', 'arm_2', 'arm_3'), 'm'))
    assert not alike


def test_a_folder_of_bags_is_grouped_by_their_robot_description(fleet_dir, robot, tmp_path):
    folder = tmp_path / 'bags'
    folder.mkdir()
    for name in ('arm_a_day1_0', 'arm_b_day3_1', 'corrupt'):
        shutil.copytree(fleet_dir / 'bags' / name, folder / name)
    # a bag of another arm: the same motion, a heavier last link in its description
    heavy = robot.description.replace('<mass value="', '<mass value="1', 1)
    assert heavy != robot.description
    t, q, qd, tau = simulate(robot, FourierTrajectory.random(robot, seed=3, period=DURATION),
                             1.0, seed=99)
    write_bag(folder / 'other', robot, t, q, qd, tau)
    shutil.rmtree(folder / 'other')
    with BagWriter(folder / 'other') as w:
        w.write_string('/robot_description', 0, heavy)
        for k in range(len(t)):
            ns = int(round(t[k] * 1e9))
            w.write_joint_state('/joint_states', ns, ns * 1e-9, robot.joint_names, q[k], qd[k],
                                tau[k])
    entries, failed = fleet.scan_directory(folder)
    groups = {}
    for e in entries:
        groups.setdefault(e.robot, []).append(Path(e.bag).name)
    assert sorted(groups.values()) == [['arm_a_day1_0', 'arm_b_day3_1'], ['other']]
    assert {e.period for e in entries} == {'1970-01-01'}
    assert [Path(f['bag']).name for f in failed] == ['corrupt']
    assert all(r.startswith('mit_dd_arm-') for r in groups)


@pytest.mark.slow
def test_a_segmented_run_equals_the_whole_bags(long_bag, robot, settings):
    from distributed import Client

    entries = [fleet.FleetEntry(str(long_bag), 'arm', 'day1')]
    tasks = fleet.plan_tasks(entries, segment_seconds=55.0)     # rounded to the 10 s grid
    assert [(t.start_ns, t.stop_ns) for t in tasks] == [
        (a, b) for a, b in zip([None, 60e9, 120e9, 180e9, 240e9],
                               [60e9, 120e9, 180e9, 240e9, None])]
    with Client(processes=False, n_workers=1, threads_per_worker=2,
                dashboard_address='127.0.0.1:0') as client:
        whole = fleet.run_fleet(entries, client, physical_consistency=False)
        split = fleet.run_fleet(entries, client, segment_seconds=55.0,
                                physical_consistency=False)
    assert_same_identification(result_document(split.identifications['arm', 'day1']),
                               result_document(whole.identifications['arm', 'day1']))


# -- the fleet run on Dask --------------------------------------------------------------------
def check_fleet_document(doc, root, robot, settings, tmp_path):
    assert set(doc['robots']) == {'arm_a', 'arm_b'}
    for name, periods in doc['robots'].items():
        assert list(periods) == list(PERIODS)
    groups = manifest_groups(root)
    # one smoother per robot: the one identify chooses on its first bag in manifest order
    firsts = {}
    for e in fleet.read_manifest(root / 'manifest.csv'):
        firsts.setdefault(e.robot, e.bag)
    assert set(doc['smoothers']) == set(firsts)
    for name, bag in firsts.items():
        assert doc['smoothers'][name] == dict(segments.bag_smoother(bag, settings, robot))
    # per robot and period: identify of the same data (the two bags one after the other)
    # through the robot's smoother
    for (name, period), bags in groups.items():
        ref = replay_identify(concatenated(bags, tmp_path / f'{name}_{period}', robot),
                              segments.pinned(settings, tuple(doc['smoothers'][name].items())),
                              robot)
        make_consistent(ref, settings.consistency_options())
        assert_same_as_identify(doc['robots'][name][period], result_document(ref))
    # the drifting robot, and only it, is flagged, on the drifting parameter
    assert doc['flags'], 'the drift is not flagged'
    assert {f['robot'] for f in doc['flags']} == {'arm_b'}
    assert {f['parameter'] for f in doc['flags']} == {'joint2.fv'}
    assert {f['period'] for f in doc['flags']} == {'day2', 'day3'}
    est = [values(doc['robots']['arm_b'][p])[0] for p in PERIODS]
    fv = doc['robots']['arm_b']['day1']['base_parameters']
    i = [p['name'] for p in fv].index('joint2.fv')
    np.testing.assert_allclose(np.diff([e[i] for e in est]), DRIFT, rtol=0.1)
    # the corrupt bag is reported, and only it
    assert [Path(f['bag']).name for f in doc['failed']] == ['corrupt']
    assert doc['failed'][0]['error']


@pytest.mark.slow
def test_fleet_on_the_default_local_cluster(fleet_dir, robot, settings, tmp_path, capsys):
    report = tmp_path / 'report'
    assert main(['fleet', str(fleet_dir / 'manifest.csv'), '--workers', '2', '--json',
                 '--report', str(report)]) == 0
    out = capsys.readouterr()
    doc = json.loads(out.out)
    check_fleet_document(doc, fleet_dir, robot, settings, tmp_path)
    assert 'fleet: 13/13 bags done' in out.err
    assert 'corrupt' in out.err
    text = (report / 'fleet.md').read_text()
    assert '## arm_a' in text and 'joint2.fv' in text
    for name in ('arm_a_friction', 'arm_a_inertial', 'arm_b_friction', 'arm_b_inertial'):
        assert Path(doc['report'][name]).read_bytes()[:4] == b'\x89PNG'
    assert not list(report.glob('.*.tmp'))


def free_port():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@pytest.fixture
def cluster(tmp_path):
    """``dask scheduler`` and two ``dask worker`` processes (no nanny) on 127.0.0.1."""
    port = free_port()
    address = f'tcp://127.0.0.1:{port}'
    env = dict(os.environ, PYTHONPATH=str(REPO), OPENBLAS_NUM_THREADS='1')
    dask = str(Path(PYTHON).parent / 'dask')
    log = open(tmp_path / 'dask.log', 'w')
    procs = [subprocess.Popen([dask, 'scheduler', '--host', '127.0.0.1', '--port', str(port),
                               '--no-dashboard'], env=env, stdout=log, stderr=log)]
    from distributed import Client
    client = Client(address, timeout='30s')
    for _ in range(2):
        procs.append(subprocess.Popen(
            [dask, 'worker', address, '--nthreads', '1', '--no-nanny', '--no-dashboard',
             '--host', '127.0.0.1'], env=env, stdout=log, stderr=log))
    client.wait_for_workers(2, timeout=60)
    yield address, client, procs
    client.close()
    for p in procs[::-1]:
        if p.poll() is None:
            p.terminate()
            p.wait(timeout=30)
    log.close()


@pytest.mark.slow
def test_fleet_on_a_scheduler_with_two_workers_and_one_killed(
        fleet_dir, robot, settings, tmp_path, cluster):
    address, client, procs = cluster
    entries = fleet.read_manifest(fleet_dir / 'manifest.csv')
    doc = fleet.fleet_document(fleet.run_fleet(entries, client))
    check_fleet_document(doc, fleet_dir, robot, settings, tmp_path)

    killed = []

    def kill_one(done, total):
        if not killed:   # mid-run: the other tasks are queued or running on both workers
            procs[2].send_signal(signal.SIGKILL)
            killed.append(done)

    again = fleet.fleet_document(fleet.run_fleet(entries, client, progress=kill_one))
    assert killed and procs[2].wait(timeout=30) == -signal.SIGKILL
    assert len(client.scheduler_info()['workers']) == 1
    assert without_solve_times(again) == without_solve_times(doc)


def without_solve_times(doc):
    """The document as JSON with the consistent solves' wall-clock times removed (the rest,
    the consistent estimates too, is deterministic)."""
    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k != 'solve_time'}
        return [strip(v) for v in x] if isinstance(x, list) else x
    return json.dumps(strip(doc), sort_keys=True)


@pytest.mark.slow
def test_missing_scheduler_is_a_clear_error(fleet_dir):
    r = subprocess.run([PYTHON, '-m', 'identification_node', 'fleet',
                        str(fleet_dir / 'manifest.csv'), '--scheduler',
                        f'tcp://127.0.0.1:{free_port()}', '--timeout', '2'],
                       capture_output=True, text=True, timeout=60,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert r.returncode == 2
    assert r.stderr.count('\n') == 1 and 'cannot reach the dask scheduler' in r.stderr


@pytest.mark.slow
def test_a_scheduler_without_workers_is_a_clear_error(fleet_dir, tmp_path):
    port = free_port()
    dask = str(Path(PYTHON).parent / 'dask')
    with open(tmp_path / 'dask.log', 'w') as log:
        scheduler = subprocess.Popen([dask, 'scheduler', '--host', '127.0.0.1', '--port',
                                      str(port), '--no-dashboard'], stdout=log, stderr=log)
        try:
            from distributed import Client
            Client(f'tcp://127.0.0.1:{port}', timeout='30s').close()   # it is up
            r = subprocess.run([PYTHON, '-m', 'identification_node', 'fleet',
                                str(fleet_dir / 'manifest.csv'), '--scheduler',
                                f'tcp://127.0.0.1:{port}', '--timeout', '2'],
                               capture_output=True, text=True, timeout=60,
                               env=dict(os.environ, PYTHONPATH=str(REPO)))
        finally:
            scheduler.terminate()
            scheduler.wait(timeout=30)
    assert r.returncode == 2
    assert r.stderr.count('\n') == 1 and 'has no workers' in r.stderr


# -- duplicate content and nothing identified (issue 31) ------------------------------------------
def test_duplicate_content_is_recognised_whatever_the_path(fleet_dir):
    bags = fleet_dir / 'bags'
    copy = fleet_dir / 'copy_of_a'
    if not copy.exists():
        shutil.copytree(bags / 'arm_a_day1_0', copy)
    entries = [fleet.FleetEntry(str(p), 'arm_a', 'day1') for p in (
        bags / 'arm_a_day1_0', bags / 'arm_a_day1_1', copy,
        bags / '..' / 'bags' / 'arm_a_day1_0', bags / 'corrupt', bags / 'corrupt')]
    kept, duplicates = fleet.drop_duplicates(entries)
    assert [e.bag for e in kept] == [entries[i].bag for i in (0, 1, 4, 5)]  # unreadable: kept
    assert duplicates == [{'bag': str(copy), 'duplicate_of': str(bags / 'arm_a_day1_0')},
                          {'bag': entries[3].bag, 'duplicate_of': str(bags / 'arm_a_day1_0')}]
    assert fleet.content_hash(bags / 'arm_a_day1_0') != fleet.content_hash(bags / 'arm_a_day1_1')


@pytest.mark.slow
def test_fleet_counts_a_copy_once_and_exits_2_when_nothing_is_identified(fleet_dir, capsys):
    copy = fleet_dir / 'copy_of_a'
    if not copy.exists():
        shutil.copytree(fleet_dir / 'bags' / 'arm_a_day1_0', copy)
    once, twice = fleet_dir / 'once.csv', fleet_dir / 'twice.csv'
    once.write_text('bag,robot,period,config\nbags/arm_a_day1_0,arm_a,day1,arm.yaml\n')
    twice.write_text(once.read_text() + 'copy_of_a,arm_a,day1,arm.yaml\n'
                     'bags/../bags/arm_a_day1_0,arm_a,day1,arm.yaml\n')
    docs = []
    for manifest in (once, twice):
        assert main(['fleet', str(manifest), '--workers', '1', '--json']) == 0
        out = capsys.readouterr()
        docs.append(json.loads(out.out))
    assert 'holds the same messages as' in out.err and 'counted once' in out.err
    assert [Path(d['bag']).name for d in docs[1]['duplicates']] == ['copy_of_a', 'arm_a_day1_0']
    a, b = (d['robots']['arm_a']['day1'] for d in docs)
    assert a['num_samples'] == b['num_samples']
    np.testing.assert_allclose(b['stddev'], a['stddev'], rtol=1e-9)
    bad = fleet_dir / 'bad.csv'
    bad.write_text('bag,robot,period,config\nbags/corrupt,arm_a,day1,arm.yaml\n')
    assert main(['fleet', str(bad), '--workers', '1']) == 2
    err = capsys.readouterr().err
    assert 'nothing identified' in err and 'skipped' in err
