"""The identification report: its files, and the data its figures are drawn from checked against
independent computations from the bags (not pixels)."""
import json
from pathlib import Path

import numpy as np
import pytest

from identification_node.bags.reader import iter_joint_states, open_bag
from identification_node.bags.writer import BagWriter
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.batch.rows import BatchOptions
from identification_node.batch.solve import offline_identify
from identification_node.replay.stream import replay_identify
from identification_node.results.identification import SeriesSampler
from identification_node.results.report import (check_writable, convergence_figure_data,
                                                is_mit_arm, write_report)
from identification_node.pipeline.signals import (FixedLagSmoother, central_derivatives,
                                                  period_average, zero_phase_lowpass)
from identification_node.settings import Settings, read_parameter_file
from identification_node.replay.validation import bag_error

REPO = Path(__file__).resolve().parents[1]
CRS = REPO / 'bags' / 'crs_a465_fourier'
PNG = b'\x89PNG\r\n\x1a\n'


@pytest.fixture(scope='module')
def crs_settings():
    return Settings.from_dict(read_parameter_file(REPO / 'config' / 'crs_a465.yaml'))


@pytest.fixture(scope='module')
def crs_bag_arrays(crs_settings):
    """The CRS bag's joint states read directly: stamps (ns), q, qd, effort."""
    robot = crs_settings.load_robot()
    with open_bag(CRS) as reader:
        recs = [r for _, _, r in iter_joint_states(reader, ['/joint_states'])]
    idx = [list(recs[0].names).index(j) for j in robot.joint_names]
    return (np.array([r.stamp_ns for r in recs], dtype=np.int64),
            *(np.array([getattr(r, f)[idx] for r in recs]) for f in
              ('position', 'velocity', 'effort')))


@pytest.fixture(scope='module')
def crs_batch(crs_settings):
    robot = crs_settings.load_robot()
    ident = offline_identify(CRS, crs_settings, robot)
    return ident, bag_error(ident, CRS, crs_settings)


def assert_png(path):
    data = Path(path).read_bytes()
    assert len(data) > 5000 and data[:8] == PNG


@pytest.mark.slow
def test_report_files_and_tables(crs_batch, crs_settings, crs_bag_arrays, tmp_path):
    ident, validation = crs_batch
    training = bag_error(ident, CRS, crs_settings, training=True)
    report = write_report(tmp_path / 'rep', ident, [validation], training)
    figures = ('torque', 'convergence', 'estimates', 'validation')
    assert set(report.files) == {'report', *figures}
    for name in figures:
        assert_png(report.files[name])
        assert report.files[name].parent == tmp_path / 'rep'
    assert sorted(p.name for p in (tmp_path / 'rep').iterdir()) == [
        'convergence.png', 'estimates.png', 'report.md', 'torque.png',
        'validation.png']   # no temporaries
    # the torque figure: the raw measured effort of the bag at its samples, the residual
    stamps, _, _, effort = crs_bag_arrays
    data = report.data['torque']
    idx = np.searchsorted(stamps, data['stamps_ns'])
    np.testing.assert_array_equal(stamps[idx], data['stamps_ns'])
    np.testing.assert_array_equal(data['measured'], effort[idx])
    np.testing.assert_allclose(data['residual'], data['measured'] - data['predicted'])
    # the estimates chart: the estimate and its stddev over one scale per parameter
    est = report.data['estimates']
    np.testing.assert_array_equal(est['estimate'], ident.estimate)
    np.testing.assert_array_equal(est['stddev'], ident.stddev)
    assert np.all(np.abs(est['estimate']) <= est['scale'])
    md = report.files['report'].read_text()
    for name in ident.base.names:
        assert f'`{name}`' in md
    for figure in ('torque.png', 'convergence.png', 'estimates.png', 'validation.png'):
        assert f']({figure})' in md
    # the same errors as the JSON's, stacked and per joint, raw and smoothed torque
    for what, e in (('training', training), ('validation', validation)):
        row = (f'| {what} | identified | {e.errors["estimate"].stacked:.4g} | '
               + ' | '.join(f'{v:.4g}' for v in e.errors['estimate'].per_joint) + ' |')
        assert row in md
        assert f'| {what} | identified, smoothed torque | {e.smoothed["estimate"].stacked:.4g}' \
            in md
    # Table 2 style: every standard parameter name of every link is a row or column.
    for heading in ('| parameter | link1 |', '| joint | fv | fc |', '## Identifiable combinations',
                    '## Validation on a held-out bag', 'excitation condition number'):
        assert heading in md
    assert 'Atkeson, Hollerbach (1986), Table 3' not in md   # not the MIT arm
    combined = [n for n, t in zip(ident.base.names, ident.base.terms) if len(t) > 1]
    section = md.split('## Identifiable combinations')[1].split('##')[0]
    assert all(f'`{n}`' in section for n in combined)
    assert f'{ident.condition_number:.4g}' in md


@pytest.mark.slow
def test_mit_report_has_the_papers_table3_and_the_validation(tmp_path, capsys):
    out = tmp_path / 'mit'
    assert main(['identify', str(REPO / 'bags' / 'mit_paper_moves'), '--config',
                 str(REPO / 'config' / 'identification.yaml'), '--validate',
                 str(REPO / 'bags' / 'mit_paper_moves_sqlite3'), '--report', str(out),
                 '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['report']['report'] == str(out / 'report.md')
    md = (out / 'report.md').read_text()
    section = md.split('(1986), Table 3')[1].split('##')[0]
    rows = [line for line in section.splitlines() if line.startswith('| link')]
    assert len(rows) == 6 and '| link3.Ixx - link3.Iyy |' in section
    assert '-1.0589' in section and '-3.0814' in section       # the paper's columns
    (v,) = doc['validation']
    for joint, err in v['estimate']['per_joint'].items():
        assert f'| {joint} (%) |' in md.split('## Measured')[1]
        assert 0 < err < 10
    assert f"| validation | identified | {v['estimate']['stacked']:.4g} |" in md
    for name in ('torque.png', 'convergence.png', 'validation.png'):
        assert_png(out / name)


def test_batch_torque_figure_data_is_the_filtered_bag(crs_batch, crs_bag_arrays, tmp_path):
    ident, _ = crs_batch
    report = write_report(tmp_path, ident)
    data = report.data['torque']
    stamps, q, qd, effort = crs_bag_arrays
    robot, base = ident.robot, ident.base
    # Independently: the whole bag filtered at once, the regressor of the filtered motion
    # filtered alike (parallel filtering), rows picked by their stamps.
    rate, cutoff = 1000.0, ident.details['cutoff_hz']
    t = (stamps - stamps[0]) * 1e-9
    qf, qdf = zero_phase_lowpass(q, rate, cutoff), zero_phase_lowpass(qd, rate, cutoff)
    Yb = base.base_regressor(robot.regressor(qf, qdf, central_derivatives(t, qdf)[0]))
    Yf = zero_phase_lowpass(Yb.reshape(len(t), -1), rate, cutoff).reshape(Yb.shape)
    idx = np.searchsorted(stamps, data['stamps_ns'])
    np.testing.assert_array_equal(stamps[idx], data['stamps_ns'])
    assert len(idx) == ident.details['rows']
    assert np.all(np.diff(idx) == int(rate / (2 * cutoff)))
    np.testing.assert_allclose(data['t'], t[idx])
    tau = zero_phase_lowpass(effort, rate, cutoff)[idx]
    np.testing.assert_allclose(data['measured'], tau, atol=1e-9 * np.abs(tau).max())
    for key, theta in (('predicted', ident.theta), ('model', base.to_base(robot.phi_model))):
        want = Yf[idx] @ theta
        np.testing.assert_allclose(data[key], want, atol=1e-8 * np.abs(want).max())
    assert data['joints'] == robot.joint_names


def test_rls_torque_figure_data_is_the_smoothed_bag(crs_settings, crs_bag_arrays, tmp_path):
    robot = crs_settings.load_robot()
    ident = replay_identify(CRS, crs_settings, robot, series_points=1000)
    data = write_report(tmp_path, ident).data['torque']
    stamps, q, qd, effort = crs_bag_arrays
    n = robot.dof
    # Independently: the pipeline's fixed-lag smoother run over the whole bag at once.
    smoother = FixedLagSmoother(3 * n, half_window=10, order=3, max_gap=0.05)
    ts, x, xd, _ = smoother.push((stamps - stamps[0]) * 1e-9, np.hstack([q, qd, effort]))
    out_ns = stamps[0] + np.round(ts * 1e9).astype(np.int64)
    idx = np.searchsorted(out_ns, data['stamps_ns'])
    np.testing.assert_array_equal(out_ns[idx], data['stamps_ns'])
    assert 500 < len(idx) <= 1000 and len(set(np.diff(idx))) == 1     # evenly strided
    np.testing.assert_allclose(data['measured'], x[idx, 2 * n:], rtol=1e-9, atol=1e-9)
    Yb = ident.base.base_regressor(robot.regressor(x[idx, :n], x[idx, n:2 * n],
                                                   xd[idx, n:2 * n]))
    np.testing.assert_allclose(data['predicted'], Yb @ ident.theta, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(data['model'], Yb @ ident.theta_model, rtol=1e-7, atol=1e-9)


def test_convergence_figure_data(crs_batch):
    ident, _ = crs_batch
    data = convergence_figure_data(ident.history, ident.theta, ident.stddev, ident.base.names)
    assert data['names'] == ident.base.names
    assert data['normalised'].shape == (len(ident.history), ident.base.num_base)
    assert np.all(np.diff(data['num_samples']) > 0)
    np.testing.assert_array_equal(data['normalised'][-1], 0.0)
    k = len(ident.history) // 2
    c = ident.history[k]
    np.testing.assert_allclose(data['normalised'][k], (c.values - ident.theta) / ident.stddev)
    np.testing.assert_allclose(data['rel_stddev'][k], 100 * c.stddev / np.abs(ident.theta))
    # Early estimates are worse than late ones, in final standard deviations.
    assert np.median(np.abs(data['normalised'][1])) > np.median(np.abs(data['normalised'][-2]))
    # the percentiles over the parameters, and the ten furthest over the second half
    dev = np.abs((np.array([c.values for c in ident.history]) - ident.theta) / ident.stddev)
    for p in (50, 90, 100):
        np.testing.assert_allclose(data['percentiles'][p], np.percentile(dev, p, axis=1))
    late = dev[len(dev) // 2:].max(axis=0)
    assert len(data['worst']) == 10
    assert set(data['worst']) == set(np.argsort(-late)[:10])


def test_periodic_report_shows_the_averaged_period(tmp_path):
    robot = load_robot('mit_dd_arm')
    traj = FourierTrajectory.random(robot, period=1.0, seed=2)
    t = np.arange(4000) / 1000.0
    sim = simulate_kinematic(robot, None, traj, t, SensorNoise(torque_std=0.3), seed=1)
    with BagWriter(tmp_path / 'bag') as bag:
        for k in range(len(t)):
            bag.write_joint_state('/joint_states', k * 10 ** 6, k * 1e-3, robot.joint_names,
                                  sim.q_meas[k], sim.qd_meas[k], sim.tau_meas[k])
    # this fast trajectory needs 3.6 times joint1's rated effort (the default bounds: 2)
    settings = Settings.from_dict({'robot': 'mit_dd_arm', 'plausibility.margin': 4.0})
    ident = offline_identify(tmp_path / 'bag', settings, robot, BatchOptions(period=1.0))
    report = write_report(tmp_path / 'rep', ident)
    data = report.data['torque']
    avg = period_average(t, sim.tau_meas, 1.0)
    np.testing.assert_allclose(data['t'], avg.t, atol=1e-9)
    np.testing.assert_allclose(data['measured'], avg.mean, rtol=1e-12, atol=1e-12)
    assert np.sqrt(np.mean((data['predicted'] - data['model']) ** 2)) < 0.3 / np.sqrt(4)
    md = report.files['report'].read_text()
    assert 'batch (periodic)' in md and 'periods: 4' in md
    assert len(report.data['convergence']['num_samples']) == 3    # 2, 3 and 4 periods


def test_series_sampler_keeps_an_even_bounded_subsample():
    sampler = SeriesSampler(capacity=100)
    for start in range(0, 1037, 50):       # batches of 50, the last one shorter
        idx = np.arange(start, min(start + 50, 1037))
        sampler.add(i=idx, x=np.column_stack([idx, 2 * idx]))
    kept = sampler.arrays()
    assert sampler.stride == 16 and len(kept['i']) <= 100
    np.testing.assert_array_equal(kept['i'], np.arange(0, 1037, 16))
    np.testing.assert_array_equal(kept['x'][:, 1], 2 * kept['i'])


def test_report_directory_not_writable_is_a_clear_error(tmp_path, capsys):
    blocker = tmp_path / 'file'
    blocker.write_text('not a directory')
    with pytest.raises(IdentificationError, match='cannot write the report into'):
        check_writable(blocker / 'report')
    assert main(['identify', str(CRS), '--report', str(blocker / 'report')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('error: cannot write the report into') and 'Traceback' not in err


def test_is_mit_arm():
    assert is_mit_arm(load_robot('mit_dd_arm'))
    assert not is_mit_arm(load_robot('crs_a465'))
