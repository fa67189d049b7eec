"""identify's text output and report.md as a user reads them, on a simulated UR5 (an arm the
suite's own bags do not have) with the shipped defaults: the base-parameter table fits 100
columns (the regrouping below it), the relative stddev only where the estimate is not about
zero, the files --save, --report and --predictions wrote named; report.md's torque noise
against the simulated sensor noise, the smoother in words, distinct trace colours and
figure labels naming their quantity."""
import re
from pathlib import Path

import numpy as np
import pytest

from arms import arm_urdf
from identification_node.cli import main
from identification_node.results.text import ABOUT_ZERO
from identification_node.results import report

TORQUE_STD = 0.2


@pytest.fixture(scope='module')
def ur5_run(tmp_path_factory):
    """(stdout, report.md, output paths) of identify on a simulated UR5 bag."""
    path = tmp_path_factory.mktemp('ur5')
    urdf = str(arm_urdf('ur5'))
    bag = str(path / 'bag')
    assert main(['simulate', '--urdf', urdf, '--trajectory', 'fourier', '--rate', '1000',
                 '--duration', '12', '--encoder-counts', '262144', '--velocity-std', '0.01',
                 '--torque-std', str(TORQUE_STD), '--seed', '7', '--out', bag]) == 0
    outputs = {'save': path / 'saved', 'report': path / 'report',
               'predictions': path / 'predictions.csv'}
    import contextlib
    import io
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(['identify', bag, '--urdf', urdf, '--save', str(outputs['save']),
                     '--report', str(outputs['report']), '--predictions',
                     str(outputs['predictions'])]) == 0
    return out.getvalue(), (outputs['report'] / 'report.md').read_text(), outputs


@pytest.mark.slow
def test_table_fits_100_columns_and_regroupings_go_below(ur5_run):
    text, _, _ = ur5_run
    lines = text.splitlines()
    start = lines.index('base parameters (SI units):')
    end = lines.index('', start)
    table = lines[start + 1:end]
    assert len(table) > 20 and all(len(line) <= 100 for line in table)
    header = table[0].split()
    assert header == ['name', 'estimate', 'unconstrained', 'stddev', 'rel', '%', 'model']
    regrouped = lines[lines.index(next(x for x in lines if x.startswith('regrouped base'))):]
    assert any(' = ' in x for x in regrouped[:5])
    section = regrouped[:regrouped.index('')]
    assert all(len(line) <= 100 for line in section), [x for x in section if len(x) > 100]
    # rel % shown exactly where the estimate is beyond ABOUT_ZERO stddev from zero
    for row in table[1:]:
        parts = row.split()
        if len(parts) != 6 or parts[1] == 'not':
            continue
        est, sd, rel = float(parts[1]), float(parts[3]), parts[4]
        if abs(est) <= ABOUT_ZERO * sd:
            assert rel == '-', row
        else:
            assert float(rel) == pytest.approx(100 * sd / abs(est), rel=0.02, abs=0.01), row
            assert float(rel) < 100 / ABOUT_ZERO + 0.01


@pytest.mark.slow
def test_written_files_are_named(ur5_run):
    text, _, outputs = ur5_run
    named = text[text.index('files written:'):]
    files = [p for d in (outputs['save'], outputs['report']) for p in Path(d).iterdir()]
    files.append(outputs['predictions'])
    assert len(files) >= 6
    for path in files:
        assert str(path) in named, path


@pytest.mark.slow
def test_report_noise_is_the_sensor_noise_and_smoother_in_words(ur5_run):
    _, md, _ = ur5_run
    section = md[md.index('torque noise std (N m) |'):]
    section = section[:section.index('\n\n')]
    rows = re.findall(r'^\| (\S+) \| [^|]+ \| [^|]+ \| [^|]+ \| ([0-9.e-]+) \|$', section,
                      re.M)
    noise = {j: float(v) for j, v in rows}
    assert len(noise) == 6
    for joint, value in noise.items():
        assert value == pytest.approx(TORQUE_STD, rel=0.05), joint
    smoother = next(line for line in md.splitlines() if line.startswith('- smoother:'))
    assert '{' not in smoother and "'" not in smoother and 'Hz' in smoother


def _captured(monkeypatch, make):
    figs = []
    monkeypatch.setattr(report, 'save_figure', lambda fig, path: figs.append(fig) or path)
    make()
    return figs[0]


def test_torque_traces_have_distinct_colours_and_labelled_quantities(monkeypatch, tmp_path):
    from matplotlib.colors import to_rgb
    t = np.linspace(0, 1, 50)
    data = {'t': t, 'joints': ['j1', 'j2'], 'measured': np.ones((50, 2)),
            'predicted': np.ones((50, 2)), 'model': np.ones((50, 2)),
            'residual': np.zeros((50, 2))}
    fig = _captured(monkeypatch, lambda: report.plot_torque(data, tmp_path / 't.png', 'x'))
    colours = {line.get_label(): np.array(to_rgb(line.get_color()))
               for line in fig.axes[0].get_lines()}
    assert set(colours) == {'measured (raw)', 'identified', 'model (URDF/CAD)'}
    names = list(colours)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert np.linalg.norm(colours[a] - colours[b]) > 0.4, (a, b)
    for ax in fig.axes:
        assert 'torque' in ax.get_ylabel() and '(N m)' in ax.get_ylabel()
    assert fig.axes[-1].get_xlabel() == 'time (s)'


def test_other_figures_label_their_quantities(monkeypatch, tmp_path):
    k = 3
    data = {'num_samples': np.arange(1, 5), 'percentiles': {50: np.ones(4), 100: np.ones(4)},
            'normalised': np.ones((4, k)), 'worst': [0, 1], 'names': ['a', 'b', 'c'],
            'rel_stddev': np.ones((4, k))}
    fig = _captured(monkeypatch, lambda: report.plot_convergence(data, tmp_path / 'c.png'))
    assert all('stddev' in ax.get_ylabel() for ax in fig.axes)
    est = {'names': ['a', 'b'], 'scale': np.ones(2), 'estimate': np.ones(2),
           'stddev': np.ones(2), 'model': np.ones(2)}
    fig = _captured(monkeypatch, lambda: report.plot_estimates(est, tmp_path / 'e.png'))
    assert 'base parameter value' in fig.axes[0].get_xlabel()
