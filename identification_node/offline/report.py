"""The identification report: ``report.md`` and PNG figures in one directory.

Contents, after the two papers: measured torque against the torque the identified parameters
predict and the torque the model's own (URDF/CAD) parameters predict (An, Atkeson, Hollerbach,
Figure 4); the base parameters with standard deviations and the standard parameters per link
(their Table 2 style); the identifiable combinations, estimated against model values (Table 3
style; for the MIT arm also the paper's own Table 3); how the estimate converged; the
excitation condition number; physical consistency; the error on a held-out validation bag.

Every figure is drawn from a plain dictionary of arrays that a ``*_figure_data`` function
returns and ``write_report`` keeps (Report.data), so what is plotted can be checked without
looking at pixels. Figures use matplotlib's Agg canvas (no display, no pyplot state); every file
is written to a temporary name in the directory and renamed into place.
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.fileio import atomic_file, atomic_write_text
from identification_node.model.identifiability import BaseParameters, format_expression
from identification_node.model.papers import MIT_TABLE1, MIT_TABLE3
from identification_node.model.robot import LINK_PARAMS, RobotModel
from identification_node.offline.identification import Identification, TorqueSeries, Validation
from identification_node.offline.replay import Checkpoint

REPORT_FILE = 'report.md'
TORQUE_FIGURE = 'torque.png'
CONVERGENCE_FIGURE = 'convergence.png'
VALIDATION_FIGURE = 'validation.png'


@dataclass
class Report:
    """The files written (name -> path) and the data handed to each figure (name -> dict)."""
    directory: Path
    files: dict[str, Path] = field(default_factory=dict)
    data: dict[str, dict] = field(default_factory=dict)


def check_writable(directory: str | os.PathLike) -> Path:
    """Create ``directory`` if needed and make sure files can be written in it, before any
    long computation; IdentificationError otherwise."""
    path = Path(directory)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix='.probe.', dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise IdentificationError(f'cannot write the report into {directory}: '
                                  f'{exc.strerror or exc}') from None
    return path


# -- figure data ----------------------------------------------------------------------------------
def torque_figure_data(series: TorqueSeries, theta: np.ndarray, theta_model: np.ndarray,
                       joints: list[str]) -> dict:
    """Measured torque (N m) and the torques predicted by the estimate (Yb theta) and by the
    model's own parameters (Yb theta_model) at the series' rows; ``t`` in s from the series'
    origin (the bag's first sample), else from its first row."""
    stamps = np.asarray(series.stamps_ns, dtype=np.int64)
    origin = series.origin_ns if series.origin_ns is not None else (
        int(stamps[0]) if len(stamps) else 0)
    return {'joints': list(joints), 'stamps_ns': stamps, 't': (stamps - origin) * 1e-9,
            'measured': np.asarray(series.measured, dtype=float),
            'predicted': series.predicted(theta), 'model': series.predicted(theta_model)}


def convergence_figure_data(history: list[Checkpoint], theta: np.ndarray, stddev: np.ndarray,
                            names: list[str]) -> dict:
    """Per checkpoint k: (theta_k - theta) / stddev (the final estimate and its standard
    deviations; NaN where stddev is 0) and the relative standard deviation
    100 stddev_k / |theta| in percent."""
    samples = np.array([c.num_samples for c in history], dtype=np.int64)
    values = np.array([c.values for c in history], dtype=float).reshape(len(history), -1)
    sds = np.array([c.stddev for c in history], dtype=float).reshape(len(history), -1)
    with np.errstate(divide='ignore', invalid='ignore'):
        normalised = np.where(stddev > 0, (values - theta) / stddev, np.nan)
        rel = np.where(theta != 0, 100.0 * sds / np.abs(theta), np.nan)
    return {'names': list(names), 'num_samples': samples, 'normalised': normalised,
            'rel_stddev': rel}


# -- figures --------------------------------------------------------------------------------------
def _save(fig, path: Path) -> Path:
    """Render ``fig`` to PNG at ``path`` atomically."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    with atomic_file(path, 'wb') as f:
        fig.savefig(f, format='png', dpi=100)
    return path


def plot_torque(data: dict, path: str | os.PathLike, title: str, xlabel: str = 'time (s)'
                ) -> Path:
    """One panel per joint: measured, identified and model torque against time."""
    from matplotlib.figure import Figure

    n = len(data['joints'])
    fig = Figure(figsize=(10, 1.0 + 2.2 * n))
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    for j, ax in enumerate(axes):
        ax.plot(data['t'], data['measured'][:, j], color='0.2', lw=0.8, label='measured')
        ax.plot(data['t'], data['predicted'][:, j], color='tab:blue', lw=1.0,
                label='identified')
        ax.plot(data['t'], data['model'][:, j], color='tab:red', lw=1.0, ls='--',
                label='model (URDF/CAD)')
        ax.set_ylabel(f"{data['joints'][j]} (N m)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc='upper right', fontsize='small', ncol=3)
    axes[0].set_title(title)
    axes[-1].set_xlabel(xlabel)
    fig.tight_layout()
    return _save(fig, Path(path))


def plot_convergence(data: dict, path: str | os.PathLike) -> Path:
    """Top: estimate minus final estimate, in final standard deviations; bottom: relative
    standard deviations; both against the samples used."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 7))
    top, bottom = fig.subplots(2, 1, sharex=True)
    x = data['num_samples']
    for k, name in enumerate(data['names']):
        top.plot(x, data['normalised'][:, k], lw=0.8, marker='.', ms=3, label=name)
        bottom.plot(x, data['rel_stddev'][:, k], lw=0.8, marker='.', ms=3)
    top.set_yscale('symlog', linthresh=1.0)
    top.axhspan(-1, 1, color='0.9')
    top.set_ylabel('(estimate - final) / final stddev')
    top.set_title('Convergence of the estimate')
    if len(data['names']) <= 20:
        top.legend(fontsize='x-small', ncol=4)
    bottom.set_yscale('log')
    bottom.set_ylabel('relative stddev (%)')
    bottom.set_xlabel('samples')
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, Path(path))


# -- tables ---------------------------------------------------------------------------------------
def _fmt(x: float | None, digits: int = 6) -> str:
    if x is None or not np.isfinite(x):
        return 'inf' if x is not None and np.isinf(x) else '-'
    return f'{x:.{digits}g}'


def _table(header: list[str], rows: list[list[str]], text: int = 1) -> list[str]:
    """Markdown table; the first ``text`` columns left-aligned, the numbers right-aligned."""
    out = ['| ' + ' | '.join(header) + ' |', '|' + '|'.join(
        ['---'] * text + ['---:'] * (len(header) - text)) + '|']
    return out + ['| ' + ' | '.join(r) + ' |' for r in rows]


def is_mit_arm(robot: RobotModel) -> bool:
    """Whether ``robot`` is the MIT direct drive arm with its Table 1 parameters."""
    return (robot.dof == 3 and robot.n_inertial == 30
            and np.allclose(robot.phi_model[:30], np.ravel(MIT_TABLE1), atol=1e-3))


def paper_table3_rows(base: BaseParameters, theta: np.ndarray, covariance: np.ndarray,
                      theta_model: np.ndarray) -> list[dict]:
    """An, Atkeson, Hollerbach (1986) Table 3: each identifiable combination with the
    identified value, its stddev, the model's value and the paper's CAD and estimated values."""
    rows = []
    for terms, paper_est, paper_cad in MIT_TABLE3:
        try:
            w = base.combination(terms)
        except IdentificationError:
            continue
        rows.append({'combination': format_expression(terms), 'identified': float(w @ theta),
                     'stddev': float(np.sqrt(max(w @ covariance @ w, 0.0))),
                     'model': float(w @ theta_model), 'paper_cad': paper_cad,
                     'paper_estimate': paper_est})
    return rows


def base_parameter_table(ident: Identification) -> list[str]:
    b = ident.base
    rows = [[f'`{n}`', e, _fmt(v), _fmt(s, 3), _fmt(r, 3), _fmt(m)] for n, e, v, s, r, m in zip(
        b.names, b.expressions, ident.estimate, ident.stddev, ident.rel_stddev, ident.theta_model)]
    return _table(['base parameter', 'expression', 'estimate', 'stddev', 'rel. stddev (%)',
                   'model'], rows, text=2)


def standard_parameter_table(ident: Identification) -> list[str]:
    """Table 2 style: per link the standard parameters of the estimate (the consistent solve's,
    else the closest to the model's reproducing it), with the relative stddev of those
    identifiable alone; * unidentifiable (model value kept),
    + identifiable only in combinations (one of the combinations' solutions)."""
    robot, b = ident.robot, ident.base
    phi = ident.standard_parameters()
    alone = {b.param_names[j]: k for k, j in enumerate(b.base_index)
             if len(b.terms[k]) == 1}
    unidentifiable, combined = set(b.unidentifiable), set(b.combined)

    def cell(name: str) -> str:
        v = _fmt(phi[robot.param_index(name)], 5)
        if name in alone:
            return f'{v} ({_fmt(ident.rel_stddev[alone[name]], 2)} %)'
        return v + ('\\*' if name in unidentifiable else ' +' if name in combined else '')

    rows = [[p] + [cell(f'{link}.{p}') for link in robot.link_names] for p in LINK_PARAMS]
    out = _table(['parameter'] + list(robot.link_names), rows)
    if robot.extras:
        out += [''] + _table(['joint'] + list(robot.extras), [
            [j] + [cell(f'{j}.{e}') for e in robot.extras] for j in robot.joint_names])
    return out


def combination_table(ident: Identification) -> list[str]:
    """Table 3 style: every base parameter that regroups several standard parameters."""
    rows = [[f'`{n}`', e, _fmt(v), _fmt(s, 3), _fmt(m)]
            for n, e, t, v, s, m in zip(ident.base.names, ident.base.expressions,
                                        ident.base.terms, ident.estimate, ident.stddev,
                                        ident.theta_model) if len(t) > 1]
    if not rows:
        return ['Every base parameter is a single standard parameter.']
    return _table(['base parameter', 'combination', 'estimated', 'stddev', 'model'], rows,
                  text=2)


# -- the report -----------------------------------------------------------------------------------
def markdown(ident: Identification, validation: Validation | None = None,
             figures: dict[str, Path] | None = None) -> str:
    """The text of report.md (figures referenced by file name)."""
    figures = figures or {}
    robot = ident.robot
    lines = [f'# Inertial parameter identification: {robot.name}', '',
             f'- bag: `{ident.bag}`', f"- joints: {', '.join(robot.joint_names)}",
             f'- method: {ident.method} ({ident.processing}); {ident.num_samples} samples used '
             f'from {ident.messages} messages',
             '- rejected messages: '
             + (', '.join(f'{k} {v}' for k, v in ident.rejected.items()) or 'none')]
    for k, v in ident.details.items():
        if k != 'processing':
            lines.append(f'- {k.replace("_", " ")}: {_plain(v)}')
    lines += ['', '## Measured and predicted torque', '',
              'Measured torque, the torque the identified parameters predict and the torque the '
              "model's own (URDF/CAD) parameters predict, from the same processed motion (An, "
              'Atkeson, Hollerbach, Figure 4).', '']
    if TORQUE_FIGURE in figures:
        lines += [f'![torque]({TORQUE_FIGURE})', '']
    noise = np.sqrt(ident.noise_variance)
    lines += _table(['joint', 'relative error, identified (%)', 'relative error, model (%)',
                     'residual rms (N m)', 'noise std (N m)'], [
        [j, _fmt(e, 4), _fmt(m, 4), _fmt(r, 4), _fmt(s, 4)] for j, e, m, r, s in zip(
            robot.joint_names, ident.relative_error(), ident.relative_error(ident.theta_model),
            ident.residual_rms, noise)])
    lines += ['', 'Relative error: 100 ||tau - tau_predicted|| / ||tau|| over the rows fitted.',
              '', '## Excitation and convergence', '',
              f'- excitation condition number (information matrix of the rows fitted): '
              f'{_fmt(ident.condition_number, 4)}',
              f"- converged: {'yes' if ident.converged else 'no'}", '']
    if CONVERGENCE_FIGURE in figures:
        lines += [f'![convergence]({CONVERGENCE_FIGURE})', '',
                  'Top: the estimate at each checkpoint minus the final one, in final standard '
                  'deviations (grey band: +-1); bottom: relative standard deviations.', '']
    lines += ['## Base parameters', '', 'SI units; model: the base parameters of the '
              "description's own parameters.", ''] + base_parameter_table(ident)
    lines += ['', '## Standard parameters per link', '',
              'The full parameter set of the estimate: the physically consistent solve\'s (else '
              'the one closest to the model that reproduces it; Table 2 style). In '
              'parentheses: relative standard deviation of parameters identifiable alone; '
              '\\* unidentifiable (model value kept); + identifiable only in the '
              'combinations below.', ''] + standard_parameter_table(ident)
    lines += ['', '## Identifiable combinations', '', 'Base parameters that regroup several '
              'standard parameters (Table 3 style).', ''] + combination_table(ident)
    if is_mit_arm(robot):
        rows = paper_table3_rows(ident.base, ident.estimate, ident.covariance, ident.theta_model)
        lines += ['', '### An, Atkeson, Hollerbach (1986), Table 3', ''] + _table(
            ['combination', 'identified', 'stddev', 'model (Table 1)', 'paper CAD',
             'paper estimate'],
            [[r['combination'], _fmt(r['identified'], 5), _fmt(r['stddev'], 3),
              _fmt(r['model'], 5), _fmt(r['paper_cad'], 5), _fmt(r['paper_estimate'], 5)]
             for r in rows])
    problems = ident.consistency_problems()
    solver = ident.consistent
    lines += ['', '## Physical consistency', '',
              ('Constrained solve: ' + (solver.status if solver is not None else 'off') + '. ')
              + 'The full parameter set is ' + ('physically consistent.' if not problems
                                                else 'not physically consistent:')]
    lines += [f'- {p}' for p in problems]
    lines += [f'- note: {n}' for n in (solver.notes if solver is not None else [])]
    if validation is not None:
        lines += ['', '## Validation on a held-out bag', '',
                  f'`{validation.bag}`: {validation.num_samples} samples ({validation.rows} '
                  'rows), processed as the training bag and not used for fitting.', '']
        lines += _table(['joint', 'training (%)', 'validation (%)', 'model on validation (%)'],
                        [[j, _fmt(a, 4), _fmt(v, 4), _fmt(m, 4)] for j, a, v, m in zip(
                            robot.joint_names, ident.relative_error(),
                            validation.relative_error, validation.model_relative_error)])
        if VALIDATION_FIGURE in figures:
            lines += ['', f'![validation]({VALIDATION_FIGURE})']
    return '\n'.join(lines) + '\n'


def _plain(v) -> str:
    if isinstance(v, (list, tuple)):
        return ', '.join(_plain(x) for x in v)
    if isinstance(v, float):
        return _fmt(v, 4)
    return str(v)


def write_report(directory: str | os.PathLike, ident: Identification,
                 validation: Validation | None = None) -> Report:
    """Write report.md and its figures into ``directory``; returns the files and the data each
    figure was drawn from."""
    report = Report(check_writable(directory))
    xlabel = 'phase in the averaged period (s)' if ident.processing == 'periodic' else \
        'time (s)'
    if ident.series is not None and len(ident.series.stamps_ns):
        data = torque_figure_data(ident.series, ident.estimate, ident.theta_model,
                                  ident.robot.joint_names)
        report.data['torque'] = data
        report.files['torque'] = plot_torque(
            data, report.directory / TORQUE_FIGURE,
            f'{ident.robot.name}: measured, identified and model torque', xlabel)
    if ident.history:
        data = convergence_figure_data(ident.history, ident.theta, ident.stddev,
                                       ident.base.names)
        report.data['convergence'] = data
        report.files['convergence'] = plot_convergence(
            data, report.directory / CONVERGENCE_FIGURE)
    if validation is not None and validation.series is not None \
            and len(validation.series.stamps_ns):
        data = torque_figure_data(validation.series, ident.estimate, ident.theta_model,
                                  ident.robot.joint_names)
        report.data['validation'] = data
        report.files['validation'] = plot_torque(
            data, report.directory / VALIDATION_FIGURE,
            'validation bag: measured, identified and model torque', xlabel)
    names = {p.name: p for p in report.files.values()}
    report.files['report'] = atomic_write_text(report.directory / REPORT_FILE,
                                               markdown(ident, validation, names))
    return report
