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
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.fileio import atomic_write_text, save_figure, writable_directory
from identification_node.model.identifiability import BaseParameters, format_expression
from identification_node.model.papers import MIT_TABLE1, MIT_TABLE3
from identification_node.model.robot import LINK_PARAMS, RobotModel
from identification_node.results.identification import Checkpoint, Identification, TorqueSeries
from identification_node.results.torque_error import BagError

__all__ = ['REPORT_FILE', 'TORQUE_FIGURE', 'CONVERGENCE_FIGURE', 'VALIDATION_FIGURE',
           'ESTIMATES_FIGURE', 'PERCENTILES', 'WORST', 'Report', 'check_writable',
           'torque_figure_data', 'convergence_figure_data', 'estimates_figure_data', 'COLOURS',
           'plot_torque', 'plot_convergence', 'plot_estimates', 'number_text',
           'markdown_table', 'is_mit_arm', 'paper_table3_rows', 'base_parameter_table',
           'standard_parameter_table', 'combination_table', 'error_table', 'markdown',
           'smoother_words', 'validation_figure', 'write_report']

REPORT_FILE = 'report.md'
TORQUE_FIGURE = 'torque.png'
CONVERGENCE_FIGURE = 'convergence.png'
VALIDATION_FIGURE = 'validation.png'      # the first validation bag; validation_2.png, ...
ESTIMATES_FIGURE = 'estimates.png'
PERCENTILES = (50, 90, 100)               # of |estimate - final| / stddev in the convergence
WORST = 10                                # parameters drawn by name in the convergence


@dataclass
class Report:
    """The files written (name -> path) and the data handed to each figure (name -> dict)."""
    directory: Path
    files: dict[str, Path] = field(default_factory=dict)
    data: dict[str, dict] = field(default_factory=dict)


def check_writable(directory: str | os.PathLike) -> Path:
    """Create ``directory`` if needed and make sure files can be written in it, before any
    long computation; IdentificationError otherwise."""
    return writable_directory(directory, 'the report')


# -- figure data ----------------------------------------------------------------------------------
def torque_figure_data(series: TorqueSeries, theta: np.ndarray, theta_model: np.ndarray,
                       joints: list[str]) -> dict:
    """Measured torque (N m) and the torques predicted by the estimate (Yb theta) and by the
    model's own parameters (Yb theta_model) at the series' rows; ``t`` in s from the series'
    origin (the bag's first sample), else from its first row."""
    stamps = np.asarray(series.stamps_ns, dtype=np.int64)
    origin = series.origin_ns if series.origin_ns is not None else (
        int(stamps[0]) if len(stamps) else 0)
    measured = np.asarray(series.measured, dtype=float)
    predicted = series.predicted(theta)
    return {'joints': list(joints), 'stamps_ns': stamps, 't': (stamps - origin) * 1e-9,
            'measured': measured, 'predicted': predicted, 'model': series.predicted(theta_model),
            'residual': measured - predicted}


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
    dev = np.abs(normalised)
    finite = np.asarray(np.isfinite(dev).any(axis=0))
    with np.errstate(invalid='ignore'):
        percentiles = {p: (np.nanpercentile(dev[:, finite], p, axis=1) if finite.any()
                           else np.full(len(history), np.nan)) for p in PERCENTILES}
    # the parameters furthest from their final value over the second half of the checkpoints
    late = dev[len(history) // 2:]
    score = np.where(finite, np.nanmax(np.where(np.isfinite(late), late, -1.0), axis=0)
                     if len(late) else 0.0, -np.inf)
    worst = [int(k) for k in np.argsort(-score, kind='stable')[:WORST] if finite[k]]
    return {'names': list(names), 'num_samples': samples, 'normalised': normalised,
            'rel_stddev': rel, 'percentiles': percentiles, 'worst': worst}


def estimates_figure_data(ident: Identification) -> dict:
    """The base estimate, its standard deviation and the model's values, each divided by
    the parameter's scale max(|estimate|, |model|, stddev) so that all share one axis."""
    estimate, stddev, model = ident.estimate, ident.stddev, ident.theta_model
    scale = np.maximum.reduce([np.abs(estimate), np.abs(model), stddev])
    scale = np.where(scale > 0, scale, 1.0)
    return {'names': list(ident.base.names), 'estimate': estimate, 'stddev': stddev,
            'model': model, 'scale': scale}


# -- figures --------------------------------------------------------------------------------------
# measured: light and wide beneath; identified and model: saturated, distinct hues on top
COLOURS = {'measured': '0.72', 'identified': 'tab:blue', 'model': 'tab:orange',
           'residual': 'tab:purple'}


def plot_torque(data: dict, path: str | os.PathLike, title: str, xlabel: str = 'time (s)',
                measured: str = 'measured (raw)') -> Path:
    """Per joint: measured, identified and model torque against time, and below it the
    residual measured - identified."""
    from matplotlib.figure import Figure

    n = len(data['joints'])
    fig = Figure(figsize=(10, 1.0 + 3.0 * n))
    axes = fig.subplots(2 * n, 1, sharex=True, squeeze=False,
                        gridspec_kw={'height_ratios': [3, 1] * n})[:, 0]
    for j in range(n):
        ax, res = axes[2 * j], axes[2 * j + 1]
        ax.plot(data['t'], data['measured'][:, j], color=COLOURS['measured'], lw=1.8,
                label=measured)
        ax.plot(data['t'], data['predicted'][:, j], color=COLOURS['identified'], lw=1.0,
                label='identified')
        ax.plot(data['t'], data['model'][:, j], color=COLOURS['model'], lw=1.0, ls='--',
                label='model (URDF/CAD)')
        ax.set_ylabel(f"{data['joints'][j]} torque (N m)")
        res.plot(data['t'], data['residual'][:, j], color=COLOURS['residual'], lw=0.6)
        res.axhline(0.0, color='0.5', lw=0.5)
        res.set_ylabel('torque residual\n(N m)', fontsize='small')
        for a in (ax, res):
            a.grid(alpha=0.3)
    axes[0].legend(loc='upper right', fontsize='small', ncol=3)
    axes[0].set_title(title)
    axes[-1].set_xlabel(xlabel)
    fig.tight_layout()
    return save_figure(fig, Path(path))


def plot_convergence(data: dict, path: str | os.PathLike) -> Path:
    """Top: percentiles over the parameters of |estimate - final| in final standard
    deviations; middle: the same for the parameters that stay furthest, by name; bottom:
    median and largest relative standard deviation; all against the samples used."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 9))
    top, middle, bottom = fig.subplots(3, 1, sharex=True)
    x = data['num_samples']
    for p, values in data['percentiles'].items():
        top.plot(x, values, lw=1.2, marker='.', ms=3,
                 label='largest' if p == 100 else f'{p}th percentile')
    dev = np.abs(data['normalised'])
    for k in data['worst']:
        middle.plot(x, dev[:, k], lw=0.9, marker='.', ms=3, label=data['names'][k])
    with np.errstate(invalid='ignore'), warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)     # checkpoints without any value
        rel = data['rel_stddev']
        bottom.plot(x, np.nanmedian(rel, axis=1), lw=1.2, label='median')
        bottom.plot(x, np.nanmax(rel, axis=1), lw=1.2, label='largest')
    top.set_title('Convergence of the estimate')
    top.set_ylabel('|estimate - final| / stddev')
    middle.set_ylabel(f'|estimate - final| / stddev,\nthe {len(data["worst"])} furthest')
    bottom.set_ylabel('relative stddev of the\nestimates (%)')
    bottom.set_xlabel('samples used')
    for ax in (top, middle, bottom):
        ax.set_yscale('symlog', linthresh=1.0) if ax is not bottom else ax.set_yscale('log')
        if ax is not bottom:
            ax.axhspan(0, 1, color='0.9')
        ax.grid(alpha=0.3)
        ax.legend(fontsize='x-small', ncol=5 if ax is middle else 3, loc='upper right')
    fig.tight_layout()
    return save_figure(fig, Path(path))


def plot_estimates(data: dict, path: str | os.PathLike) -> Path:
    """Each base parameter's estimate with +-1 and +-2 standard deviations and the model's
    value, over the parameter's scale (so all share one axis; the table has the values)."""
    from matplotlib.figure import Figure

    names, scale = data['names'], data['scale']
    y = np.arange(len(names))[::-1]
    fig = Figure(figsize=(8, 1.5 + 0.28 * len(names)))
    ax = fig.subplots()
    est, sd = data['estimate'] / scale, data['stddev'] / scale
    ax.errorbar(est, y, xerr=2 * sd, fmt='none', ecolor='tab:blue', alpha=0.35, lw=4,
                label='+-2 stddev')
    ax.errorbar(est, y, xerr=sd, fmt='o', color='tab:blue', ms=4, lw=1.5, capsize=2,
                label='estimate +-1 stddev')
    ax.plot(data['model'] / scale, y, 'x', color='tab:red', label='model (URDF/CAD)')
    ax.axvline(0.0, color='0.5', lw=0.5)
    ax.set_yticks(y, [f'{n} ({s:.3g})' for n, s in zip(names, scale)], fontsize='x-small')
    ax.set_xlabel('base parameter value / its scale (scale in parentheses, SI units)')
    ax.set_title('Base parameter estimates')
    ax.grid(alpha=0.3, axis='x')
    ax.legend(fontsize='small', loc='lower right')
    fig.tight_layout()
    return save_figure(fig, Path(path))


# -- tables ---------------------------------------------------------------------------------------
def number_text(x: float | None, digits: int = 6) -> str:
    if x is None or not np.isfinite(x):
        return 'inf' if x is not None and np.isinf(x) else '-'
    return f'{x:.{digits}g}'


def markdown_table(header: list[str], rows: list[list[str]], text: int = 1) -> list[str]:
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
    rows = [[f'`{n}`', e, number_text(v), number_text(s, 3), number_text(r, 3), number_text(m)]
            for n, e, v, s, r, m in zip(b.names, b.expressions, ident.estimate, ident.stddev,
                                        ident.rel_stddev, ident.theta_model)]
    return markdown_table(['base parameter', 'expression', 'estimate', 'stddev',
                           'rel. stddev (%)', 'model'], rows, text=2)


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
        v = number_text(phi[robot.param_index(name)], 5)
        if name in alone:
            return f'{v} ({number_text(ident.rel_stddev[alone[name]], 2)} %)'
        return v + ('\\*' if name in unidentifiable else ' +' if name in combined else '')

    rows = [[p] + [cell(f'{link}.{p}') for link in robot.link_names] for p in LINK_PARAMS]
    out = markdown_table(['parameter'] + list(robot.link_names), rows)
    if robot.extras:
        out += [''] + markdown_table(['joint'] + list(robot.extras), [
            [j] + [cell(f'{j}.{e}') for e in robot.extras] for j in robot.joint_names])
    return out


def combination_table(ident: Identification) -> list[str]:
    """Table 3 style: every base parameter that regroups several standard parameters."""
    rows = [[f'`{n}`', e, number_text(v), number_text(s, 3), number_text(m)]
            for n, e, t, v, s, m in zip(ident.base.names, ident.base.expressions,
                                        ident.base.terms, ident.estimate, ident.stddev,
                                        ident.theta_model) if len(t) > 1]
    if not rows:
        return ['Every base parameter is a single standard parameter.']
    return markdown_table(['base parameter', 'combination', 'estimated', 'stddev', 'model'],
                          rows, text=2)


# -- the report -----------------------------------------------------------------------------------
def error_table(errors: list[tuple[str, BagError]], joints: list[str]) -> list[str]:
    """Per bag: the stacked and per-joint relative errors (percent) of the estimate and of
    the model's parameters against the raw torque, and of the estimate against the smoothed
    torque (labelled)."""
    rows = []
    for what, e in errors:
        for label, err in (('identified', e.errors['estimate']),
                           ('model (URDF/CAD)', e.errors['model']),
                           ('identified, smoothed torque', e.smoothed['estimate'])):
            rows.append([what, label, number_text(err.stacked, 4)]
                        + [number_text(v, 4) for v in err.per_joint])
    return markdown_table(['bag', 'prediction', 'stacked (%)'] + [f'{j} (%)' for j in joints],
                          rows, text=2)


def _span(e: BagError) -> str:
    w = e.window
    if w is None or w.whole:
        return 'the whole bag'
    return f"{w.start or 0:g} s to {'the end' if w.end is None else f'{w.end:g} s'}"


def markdown(ident: Identification, validations: list[BagError] | tuple = (),
             figures: dict[str, Path] | None = None, training: BagError | None = None) -> str:
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
        if k == 'smoother' and isinstance(v, dict):
            lines.append(f'- smoother: {smoother_words(v)}')
        elif k != 'processing':
            lines.append(f'- {k.replace("_", " ")}: {_plain(v)}')
    lines += ['', '## Measured and predicted torque', '']
    if training is not None:
        lines += ['The raw measured torque (or the torque converted from the motor currents, '
                  'unfiltered) of every sample the smoother gives motion for, the torque the '
                  "identified parameters and the model's own (URDF/CAD) parameters predict from "
                  'that motion, and the residual measured - identified (An, Atkeson, '
                  f'Hollerbach, Figure 4); training bag, {_span(training)}.', '']
    else:
        lines += [f'The {ident.processing} torque of the rows fitted and the torque the '
                  "identified and the model's own parameters predict.", '']
    if TORQUE_FIGURE in figures:
        lines += [f'![torque]({TORQUE_FIGURE})', '']
    errors = ([('training', training)] if training is not None else []) + [
        (f'validation {k}' if len(validations) > 1 else 'validation', v)
        for k, v in enumerate(validations, 1)]
    if errors:
        lines += ['Relative error 100 ||tau - tau_predicted|| / ||tau|| against the raw '
                  'torque, stacked over all joints and per joint; against the smoothed torque '
                  'for comparison (smoothing the reference flatters it).', '']
        lines += error_table(errors, robot.joint_names) + ['']
    # The sensor's noise: from the training bag's raw minus smoothed torque (validation.py).
    # Not the fit's noise level (noise_variance: the residual's white-noise equivalent, which
    # also counts what the fit leaves at the motion's frequencies, scaled up by the smoother).
    noise = (training.noise_std if training is not None and training.noise_std is not None
             else np.full(robot.dof, np.nan))
    lines += [f'On the {ident.processing} rows fitted (filtered torque); torque noise: the '
              'std of the raw minus the smoothed torque, divided by sqrt(1 - the smoother\'s '
              'white-noise gain):', '']
    lines += markdown_table([
        'joint', 'relative error, identified (%)', 'relative error, model (%)',
        'residual rms (N m)', 'torque noise std (N m)'], [
        [j, number_text(e, 4), number_text(m, 4), number_text(r, 4), number_text(s, 4)]
        for j, e, m, r, s in zip(
            robot.joint_names, ident.relative_error(), ident.relative_error(ident.theta_model),
            ident.residual_rms, noise)])
    lines += ['', '## Excitation and convergence', '',
              f'- excitation condition number (information matrix of the rows fitted): '
              f'{number_text(ident.condition_number, 4)}',
              f"- converged: {'yes' if ident.converged else 'no'}", '']
    if CONVERGENCE_FIGURE in figures:
        lines += [f'![convergence]({CONVERGENCE_FIGURE})', '',
                  'Top: percentiles over the base parameters of |estimate at the checkpoint - '
                  'final estimate| in final standard deviations (grey band: below 1); middle: '
                  f'the {WORST} parameters furthest from their final value over the second '
                  'half, by name; bottom: median and largest relative standard deviation.', '']
    if ESTIMATES_FIGURE in figures:
        lines += [f'![estimates]({ESTIMATES_FIGURE})', '',
                  'Each base parameter\'s estimate with +-1 and +-2 standard deviations and the '
                  "model's value, divided by the parameter's scale (in parentheses).", '']
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
        lines += ['', '### An, Atkeson, Hollerbach (1986), Table 3', ''] + markdown_table(
            ['combination', 'identified', 'stddev', 'model (Table 1)', 'paper CAD',
             'paper estimate'],
            [[r['combination'], number_text(r['identified'], 5), number_text(r['stddev'], 3),
              number_text(r['model'], 5), number_text(r['paper_cad'], 5),
              number_text(r['paper_estimate'], 5)]
             for r in rows])
    problems = ident.consistency_problems()
    solver = ident.consistent
    lines += ['', '## Physical consistency', '',
              ('Constrained solve: ' + (solver.status if solver is not None else 'off') + '. ')
              + 'The full parameter set is ' + ('physically consistent.' if not problems
                                                else 'not physically consistent:')]
    lines += [f'- {p}' for p in problems]
    lines += [f'- note: {n}' for n in (solver.notes if solver is not None else [])]
    for k, v in enumerate(validations, 1):
        number = f' ({k})' if len(validations) > 1 else ''
        lines += ['', f'## Validation on a held-out bag{number}', '',
                  f'`{v.bag}`, {_span(v)}: {v.num_samples} samples, not used for fitting; '
                  'errors in the table above.', '']
        name = validation_figure(k)
        if name in figures:
            lines += [f'![validation]({name})']
    return '\n'.join(lines) + '\n'


def smoother_words(sm: dict) -> str:
    """The smoother (SmootherChoice.document) in words."""
    def known(v, scale=1.0):
        return '?' if v is None or not np.isfinite(v) else f'{scale * v:.4g}'
    words: dict[object, str] = {'half_window': 'half window given', 'cutoff': 'cut-off given',
                                'fallback': 'fallback cut-off'}
    source = words.get(sm.get('source'), sm.get('source'))
    return (f"cut-off {known(sm.get('cutoff_hz'))} Hz ({source}), half window "
            f"{sm.get('half_window')} samples at {known(sm.get('rate_hz'))} Hz, delay "
            f"{known(sm.get('delay_s'), 1e3)} ms, polynomial order {sm.get('order')}")


def _plain(v) -> str:
    if isinstance(v, (list, tuple)):
        return ', '.join(_plain(x) for x in v)
    if isinstance(v, float):
        return number_text(v, 4)
    return str(v)


def validation_figure(k: int) -> str:
    """The figure file of the k-th validation bag (1-based)."""
    return VALIDATION_FIGURE if k == 1 else f'validation_{k}.png'


def write_report(directory: str | os.PathLike, ident: Identification,
                 validations: list[BagError] | tuple = (),
                 training: BagError | None = None) -> Report:
    """Write report.md and its figures into ``directory``; returns the files and the data each
    figure was drawn from. ``training`` and ``validations``: the torque errors on the
    training and validation bags (validation.py); the torque figures show their raw
    torque, else (no ``training``) the rows fitted."""
    report = Report(check_writable(directory))
    names = ident.robot.joint_names
    if training is not None and training.series is not None \
            and len(training.series.stamps_ns):
        data = torque_figure_data(training.series, ident.estimate, ident.theta_model, names)
        report.data['torque'] = data
        report.files['torque'] = plot_torque(
            data, report.directory / TORQUE_FIGURE,
            f'{ident.robot.name}: measured, identified and model torque')
    elif ident.series is not None and len(ident.series.stamps_ns):
        xlabel = 'phase in the averaged period (s)' if ident.processing == 'periodic' else \
            'time (s)'
        data = torque_figure_data(ident.series, ident.estimate, ident.theta_model, names)
        report.data['torque'] = data
        report.files['torque'] = plot_torque(
            data, report.directory / TORQUE_FIGURE,
            f'{ident.robot.name}: {ident.processing} torque of the rows fitted', xlabel,
            measured=f'measured ({ident.processing})')
    if ident.history:
        data = convergence_figure_data(ident.history, ident.theta, ident.stddev,
                                       ident.base.names)
        report.data['convergence'] = data
        report.files['convergence'] = plot_convergence(
            data, report.directory / CONVERGENCE_FIGURE)
    data = estimates_figure_data(ident)
    report.data['estimates'] = data
    report.files['estimates'] = plot_estimates(data, report.directory / ESTIMATES_FIGURE)
    for k, v in enumerate(validations, 1):
        if v.series is None or not len(v.series.stamps_ns):
            continue
        key = 'validation' if k == 1 else f'validation_{k}'
        data = torque_figure_data(v.series, ident.estimate, ident.theta_model, names)
        report.data[key] = data
        report.files[key] = plot_torque(
            data, report.directory / validation_figure(k),
            f'validation bag {v.bag}: measured, identified and model torque')
    files = {p.name: p for p in report.files.values()}
    report.files['report'] = atomic_write_text(report.directory / REPORT_FILE,
                                               markdown(ident, validations, files, training))
    return report
