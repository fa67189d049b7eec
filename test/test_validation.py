"""Honest validation (replay/validation.py, identify --validate/--start/--end/--predictions):
the torque error against the raw torque of every sample with valid motion, checked against
numpy on the simulated truth, the predictions files, windows and report permissions."""
import csv
import json
import os
import stat

import numpy as np
import pytest

from identification_node.bags.reader import iter_joint_states, open_bag
from identification_node.bags.writer import BagWriter
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.fileio import atomic_write_text
from identification_node.model.robot import load_robot
from identification_node.batch.solve import offline_identify
from identification_node.results.predictions import PredictionsWriter
from identification_node.replay.validation import evaluate
from identification_node.results.torque_error import relative_error
from identification_node.bags.windows import TimeWindow
from identification_node.settings import Settings
from identification_node.replay.validation import bag_error

RATE = 500.0
DURATION = 3.0
NOISE = np.array([0.8, 0.4, 0.2])          # N m per joint
EXTRAS = ['fv', 'fc', 'fo']
FRICTION = {'fv': [0.8, 0.5, 0.2], 'fc': [1.5, 0.8, 0.3], 'fo': [0.2, -0.1, 0.05]}
# the smoother pinned: the numpy references leave out its half window at each end
SETTINGS = {'robot': 'mit_dd_arm', 'extras': EXTRAS, 'coulomb_velocity': 0.05,
            'coulomb_exclusion_speed': 0.2, 'smoother.half_window': 10}


@pytest.fixture(scope='module')
def robot():
    return load_robot('mit_dd_arm', extras=EXTRAS, coulomb_velocity=0.05)


@pytest.fixture(scope='module')
def settings():
    return Settings.from_dict(SETTINGS)


@pytest.fixture(scope='module')
def phi(robot):
    """The true parameters: the model's inertials and known friction."""
    phi = robot.phi_model.copy()
    for e, values in FRICTION.items():
        for j, v in zip(robot.joint_names, values):
            phi[robot.param_index(f'{j}.{e}')] = v
    return phi


def simulate(robot, phi, seed):
    """Perfect motion of a random Fourier trajectory, its true torque Y(q, qd, qdd) phi (from
    the trajectory's analytic derivatives) and the measured torque with Gaussian noise."""
    t = np.arange(int(DURATION * RATE)) / RATE
    q, qd, qdd = FourierTrajectory.random(robot, period=DURATION, seed=seed).sample(t)
    true = robot.regressor(q, qd, qdd) @ phi
    measured = true + NOISE * np.random.default_rng(seed).standard_normal(true.shape)
    return {'t': t, 'q': q, 'qd': qd, 'true': true, 'measured': measured}


def write(path, robot, sim, offset=0.25):
    """Joint states at log time = stamp = offset + t; the description first, at offset."""
    with BagWriter(path) as bag:
        bag.write_string('/robot_description', int(offset * 1e9), robot.description)
        for k, tk in enumerate(sim['t']):
            ns = int(round((offset + tk) * 1e9))
            bag.write_joint_state('/joint_states', ns, ns * 1e-9, robot.joint_names,
                                  sim['q'][k], sim['qd'][k], sim['measured'][k])
    return path


@pytest.fixture(scope='module')
def bags(tmp_path_factory, robot, phi):
    tmp = tmp_path_factory.mktemp('validation')
    out = {}
    for name, seed in (('a', 1), ('b', 2)):
        sim = simulate(robot, phi, seed)
        out[name] = (write(tmp / name, robot, sim), sim)
    return out


def expected(sim, window, half):
    """numpy: the samples of the window but the smoother's half window at each end; the
    relative error of the true torque against the measured one there."""
    t = sim['t']
    keep = np.ones(len(t), dtype=bool)
    if window.start is not None:
        keep &= t >= window.start - 1e-12
    if window.end is not None:
        keep &= t < window.end - 1e-12
    idx = np.flatnonzero(keep)[half:-half]
    m, p = sim['measured'][idx], sim['true'][idx]
    per_joint = 100 * np.linalg.norm(m - p, axis=0) / np.linalg.norm(m, axis=0)
    return len(idx), 100 * np.linalg.norm(m - p) / np.linalg.norm(m), per_joint


@pytest.mark.parametrize('window', [TimeWindow(), TimeWindow(0.5, 2.0), TimeWindow(1.2, None),
                                    TimeWindow(None, 1.0)], ids=str)
def test_error_is_the_raw_torque_error_of_every_sample_with_motion(bags, robot, settings,
                                                                   phi, window):
    base = settings.build(robot).base
    half = settings.build(robot).row_builder.half_window
    theta = base.to_base(phi)
    for bag, sim in bags.values():
        e = evaluate(bag, settings, robot, base, {'true': theta, 'zero': 0 * theta}, window)
        count, stacked, per_joint = expected(sim, window, half)
        # every sample but the smoother's edges: none left out near velocity reversals,
        # although Coulomb friction is identified (coulomb_exclusion_speed)
        assert e.num_samples == count
        # the prediction from the smoothed motion is the truth to far below the noise
        np.testing.assert_allclose(e.errors['true'].per_joint, per_joint, rtol=2e-3)
        assert e.errors['true'].stacked == pytest.approx(stacked, rel=2e-3)
        assert e.errors['zero'].stacked == pytest.approx(100.0)
        # the smoothed reference flatters: noise averaged away
        assert np.all(e.smoothed['true'].per_joint < 0.6 * per_joint)


def test_relative_error_of_arrays():
    rng = np.random.default_rng(3)
    m, p = rng.standard_normal((50, 4)), rng.standard_normal((50, 4))
    e = relative_error(m, p)
    assert e.stacked == pytest.approx(100 * np.sqrt(((m - p) ** 2).sum() / (m ** 2).sum()))
    np.testing.assert_allclose(e.per_joint, 100 * np.sqrt(((m - p) ** 2).sum(0)
                                                          / (m ** 2).sum(0)))
    z = relative_error(np.zeros((3, 2)), np.zeros((3, 2)))
    assert z.stacked == 0 and np.all(z.per_joint == 0)


def test_validation_of_an_identification_on_several_bags(bags, robot, settings, phi):
    ident = offline_identify(bags['a'][0], settings, robot)
    half = settings.build(robot).row_builder.half_window
    for bag, sim in bags.values():
        v = bag_error(ident, bag, settings)
        count, stacked, per_joint = expected(sim, TimeWindow(), half)
        assert v.num_samples == count
        # the estimate predicts about as well as the truth: the error is the noise's
        np.testing.assert_allclose(v.errors['estimate'].per_joint, per_joint, rtol=0.05)
        assert v.errors['estimate'].stacked >= 0.99 * stacked


@pytest.mark.slow
def test_cli_validate_several_bags_windows_and_predictions(bags, robot, tmp_path, capsys):
    (a, sim_a), (b, sim_b) = bags['a'], bags['b']
    config = tmp_path / 'config.yaml'
    config.write_text(json.dumps(SETTINGS))
    pred = tmp_path / 'pred'
    assert main(['identify', str(a), '--config', str(config), '--method', 'batch',
                 '--validate', str(b), str(a), '--start', '0.5', '--end', '2.5',
                 '--predictions', str(pred), '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    train, validations = doc['training_error'], doc['validation']
    assert [v['bag'] for v in validations] == [str(b), str(a)]
    assert train['window_s'] == {'start': 0.5, 'end': 2.5}
    # the training bag as validation bag gives the training error
    assert validations[1]['estimate'] == train['estimate']
    half = Settings.from_dict(SETTINGS).build(robot).row_builder.half_window
    count, _, _ = expected(sim_b, TimeWindow(0.5, 2.5), half)
    assert validations[0]['num_samples'] == count
    assert set(validations[0]['estimate']['per_joint']) == set(robot.joint_names)
    # the text output shows the same numbers
    assert main(['identify', str(a), '--config', str(config), '--method', 'batch',
                 '--validate', str(b), '--start', '0.5', '--end', '2.5']) == 0
    text = capsys.readouterr().out
    assert f"stacked {validations[0]['estimate']['stacked']:.3f}" in text
    assert f"stacked {train['estimate']['stacked']:.3f}" in text

    # predictions: an mcap bag with measured and predicted effort per sample, and CSV
    assert len(list(pred.glob('*.mcap'))) == 1
    with open_bag(pred) as reader:
        got = {}
        for topic, log_ns, rec in iter_joint_states(reader, sorted(reader.topic_counts)):
            assert rec.stamp_ns == log_ns and list(rec.names) == robot.joint_names
            got.setdefault(topic, []).append((rec.stamp_ns, rec.effort))
    labels = ('training', 'validation1', 'validation2')
    assert set(got) == {f'/{s}/{k}_effort' for s in labels for k in ('measured', 'predicted')}
    for label, sim, v in (('training', sim_a, train), ('validation1', sim_b, validations[0])):
        stamps = np.array([s for s, _ in got[f'/{label}/measured_effort']])
        measured = np.array([e for _, e in got[f'/{label}/measured_effort']])
        predicted = np.array([e for _, e in got[f'/{label}/predicted_effort']])
        assert len(stamps) == v['num_samples']
        np.testing.assert_array_equal(stamps, [s for s, _ in got[f'/{label}/predicted_effort']])
        k = np.round((stamps * 1e-9 - 0.25) * RATE).astype(int)
        np.testing.assert_array_equal(measured, sim['measured'][k])     # raw, unfiltered
        e = relative_error(measured, predicted)
        assert e.stacked == pytest.approx(v['estimate']['stacked'], rel=1e-9)
        # the estimate's prediction is near the truth (well below the noise)
        assert np.all(np.sqrt(np.mean((predicted - sim['true'][k]) ** 2, axis=0))
                      < 0.25 * NOISE)
    with open(tmp_path / 'pred.csv') as f:
        rows = list(csv.DictReader(f))
    bag_rows = sum(len(v) for v in got.values()) // 2
    assert len(rows) == bag_rows
    first = [r for r in rows if r['bag'] == 'validation1']
    ms, ps = got['/validation1/measured_effort'], got['/validation1/predicted_effort']
    for r, (s, m), (_, p) in zip(first, ms, ps):
        assert int(r['stamp_ns']) == s
        assert float(r['t']) == pytest.approx(s * 1e-9 - 0.25, abs=1e-9)
        assert [float(r[f'measured.{j}']) for j in robot.joint_names] == m.tolist()
        assert [float(r[f'predicted.{j}']) for j in robot.joint_names] == p.tolist()


def test_predictions_csv_alone_and_refusing_to_replace_other_files(tmp_path, bags, robot,
                                                                   settings, capsys):
    a, _ = bags['a']
    out = tmp_path / 'only.csv'
    base = settings.build(robot).base
    with PredictionsWriter(out, robot.joint_names) as writer:
        evaluate(a, settings, robot, base, {'estimate': base.to_base(robot.phi_model)},
                 predictions=writer, label='training')
    assert out.is_file() and not (tmp_path / 'only').exists()
    (tmp_path / 'taken').mkdir()
    assert main(['identify', str(a), '--robot', 'mit_dd_arm', '--predictions',
                 str(tmp_path / 'taken')]) == 2
    assert 'not a bag' in capsys.readouterr().err


@pytest.mark.parametrize('args, words', [
    (['--start', '2', '--end', '1'], '--end 1 s must be after --start 2 s'),
    (['--start', '-1'], '--start must be a finite number of seconds >= 0'),
    (['--end', 'nan'], '--end must be a finite number'),
    (['--start', '10'], 'is after the end of the bag'),
    (['--start', '1.0001', '--end', '1.0015'], 'no messages between --start 1.0001 s'),
])
def test_invalid_or_empty_windows_are_clear_errors(bags, args, words, capsys):
    a, _ = bags['a']
    for method in ('rls', 'batch'):
        assert main(['identify', str(a), '--robot', 'mit_dd_arm', '--method', method]
                    + args) == 2
        err = capsys.readouterr().err
        assert words in err and 'Traceback' not in err, err


def test_window_bounds():
    w = TimeWindow(0.5, 1.5)
    assert w.bounds_ns('bag', 10, 5_000_000_000) == (500_000_010, 1_500_000_010)
    assert TimeWindow().bounds_ns('bag', 10, 20) == (10, 21)
    with pytest.raises(IdentificationError, match='after the end'):
        TimeWindow(6.0).bounds_ns('bag', 0, 5_000_000_000)


@pytest.mark.slow
def test_report_and_atomic_files_get_0644_under_a_normal_umask(tmp_path, bags, capsys):
    old = os.umask(0o022)
    try:
        path = atomic_write_text(tmp_path / 'x.txt', 'x')
        assert stat.S_IMODE(path.stat().st_mode) == 0o644
        a, _ = bags['a']
        assert main(['identify', str(a), '--robot', 'mit_dd_arm', '--report',
                     str(tmp_path / 'rep')]) == 0
        files = list((tmp_path / 'rep').iterdir())
        assert {f.name for f in files} >= {'report.md', 'torque.png', 'convergence.png',
                                           'estimates.png'}
        assert all(stat.S_IMODE(f.stat().st_mode) == 0o644 for f in files)
        os.umask(0o077)
        path = atomic_write_text(tmp_path / 'y.txt', 'y')
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
    finally:
        os.umask(old)
    capsys.readouterr()


def test_reference_of_a_current_driven_bag_is_the_converted_torque_unfiltered(tmp_path):
    """The bundled MIT bag carries 3-phase currents with electrical angles: the reference is
    the first paper's eq. 10 of each sample's currents (numpy here), not smoothed."""
    from pathlib import Path

    from identification_node.settings import read_parameter_file
    repo = Path(__file__).resolve().parents[1]
    bag = repo / 'bags' / 'mit_paper_moves'
    values = read_parameter_file(repo / 'config' / 'identification.yaml')
    settings = Settings.from_dict(values)
    robot = settings.load_robot()
    base = settings.build(robot).base
    with PredictionsWriter(tmp_path / 'p.csv', robot.joint_names) as writer:
        e = evaluate(bag, settings, robot, base, {'estimate': base.to_base(robot.phi_model)},
                     predictions=writer, label='training')
    rows = np.loadtxt(tmp_path / 'p.csv', delimiter=',', skiprows=1,
                      usecols=range(1, 3 + 2 * robot.dof))
    with open_bag(bag) as reader:
        records = iter_joint_states(reader, ['/motor_currents'])
        currents = {rec.stamp_ns: rec for _, _, rec in records}
    kt = np.array(values['kt'])
    want = []
    for stamp in rows[:, 0].astype(np.int64):
        rec = currents[int(stamp)]
        i = rec.effort.reshape(robot.dof, 3)
        th = rec.position.reshape(robot.dof, 3)[:, 0]
        want.append(kt * (i[:, 0] * np.sin(th) + i[:, 1] * np.sin(th + 2 * np.pi / 3)
                          + i[:, 2] * np.sin(th + 4 * np.pi / 3)))
    want = np.array(want)
    np.testing.assert_allclose(rows[:, 2:2 + robot.dof], want, rtol=1e-12,
                               atol=1e-12 * np.abs(want).max())
    half = settings.build(robot).row_builder.half_window
    assert e.num_samples == len(rows) == len(currents) - 2 * half
    err = relative_error(want, rows[:, 2 + robot.dof:])
    assert err.stacked == pytest.approx(e.errors['estimate'].stacked, rel=1e-9)


def test_against_the_smoothed_torque_the_coulomb_sign_is_smoothed_too(tmp_path):
    """Coulomb friction alone (sign model, 3, 2, 1 N m; no inertia, no noise) and a long
    pinned window (121 samples at 500 Hz): the smoothed torque is scipy's Savitzky-Golay
    filter of fc sign(qd). Against it the prediction holds the smoothed sign, as the
    estimator's rows do: its error is under a third of the one sign(qd) itself has there (each
    reversal smoothed over the window), which is what was compared before."""
    from scipy.signal import savgol_filter

    robot = load_robot('mit_dd_arm', extras=EXTRAS)
    phi = np.zeros(robot.num_params)
    fc = np.array([3.0, 2.0, 1.0])
    for j, v in zip(robot.joint_names, fc):
        phi[robot.param_index(f'{j}.fc')] = v
    half = 60
    settings = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                                   'smoother.half_window': half})
    sim = simulate(robot, phi, 5)
    sim['measured'] = sim['true']
    bag = write(tmp_path / 'coulomb', robot, sim)
    base = settings.build(robot).base
    e = evaluate(bag, settings, robot, base, {'true': base.to_base(phi)})
    assert e.num_samples == expected(sim, TimeWindow(), half)[0]
    np.testing.assert_allclose(sim['true'], fc * np.sign(sim['qd']))
    idx = np.arange(len(sim['t']))[half:-half]
    smooth = savgol_filter(sim['true'], 2 * half + 1, 3, axis=0)[idx]
    hard = 100 * np.linalg.norm(smooth - sim['true'][idx], axis=0) / np.linalg.norm(
        smooth, axis=0)
    assert np.all(hard > 5.0), hard     # reversals within the window: a visible difference
    assert np.all(e.smoothed['true'].per_joint < 0.3 * hard), (e.smoothed['true'], hard)
