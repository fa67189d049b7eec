"""The text output of an identification: its document (documents.result_document) as tables,
the payload changes, the MIT paper's Table 3 and the files written."""
from __future__ import annotations

import textwrap

import numpy as np

__all__ = ['format_report', 'format_payload_changes', 'paper_table3', 'ABOUT_ZERO',
           'TEXT_WIDTH', 'text_table', 'format_outputs',
           'identify_text']


def format_report(doc: dict) -> str:
    lines = [f"{doc['robot']} from {doc['bag']}: {doc['num_samples']} samples used "
             f"({doc['messages']} messages)",
             f"method: {doc['method']} ({doc['processing'].get('processing', '')})"]
    if doc.get('smoother'):
        sm = doc['smoother']

        def known(v, scale=1.0):
            return '?' if v is None else f'{scale * v:.4g}'
        lines.append(f"smoother: cut-off {known(sm['cutoff_hz'])} Hz ({sm['source']}), half "
                     f"window {sm['half_window']} samples at {known(sm['rate_hz'])} Hz, delay "
                     f"{known(sm['delay_s'], 1e3)} ms")
    elif doc['processing'].get('cutoff_hz') is not None:
        lines.append(f"filter: cut-off {_number(doc['processing']['cutoff_hz'])} Hz "
                     f"({doc['processing'].get('cutoff_source', 'given')})")
    if doc['rejected']:
        lines.append('rejected: ' + ', '.join(f'{k} {v}' for k, v in doc['rejected'].items()))
    rows = [(b['name'], f"{b['estimate']:.6g}", f"{b['unconstrained_estimate']:.6g}",
             f"{b['stddev']:.3g}" if b['stddev'] is not None else 'inf',
             _relative(b['estimate'], b['stddev']), f"{b['model']:.6g}")
            if b['estimate'] is not None else
            (b['name'], 'not excited', '', '', '', f"{b['model']:.6g}")
            for b in doc['base_parameters']]
    lines += ['', 'base parameters (SI units):'] + text_table(
        ('name', 'estimate', 'unconstrained', 'stddev', 'rel %', 'model'), rows) + [
        f'  rel %: stddev / |estimate|; - where the estimate is within {ABOUT_ZERO:g} stddev '
        'of zero']
    regrouped = [b for b in doc['base_parameters'] if b['expression'] != b['name']]
    if regrouped:
        lines += ['', 'regrouped base parameters (sums of standard parameters; `structure` '
                  'explains them):']
        for b in regrouped:
            lines += textwrap.wrap(f"{b['name']} = {b['expression']}", TEXT_WIDTH,
                                   initial_indent='  ', subsequent_indent='      ',
                                   break_on_hyphens=False)
        lines.append('')
    solver = doc['consistency_solver']
    lines.append(f"physically consistent solve: {solver['status']}" + (
        f" by {solver['method']}" if solver.get('method') else '') + (
        f" ({solver['solve_time']:.3f} s)" if solver['solve_time'] is not None else '')
        + ''.join(f'; {a} failed' for a in solver.get('attempts', [])))
    for n in solver['notes']:
        lines += textwrap.wrap(f'note: {n}', TEXT_WIDTH, initial_indent='  ',
                               subsequent_indent='    ')
    lines += [f'error: {e}' for e in doc.get('errors', [])]
    lines += textwrap.wrap('link masses, kg (ratio to the URDF): ' + ', '.join(
        f"{k} {v['mass']:.4g}"
        + ('' if v.get('mass_ratio') is None else f" ({v['mass_ratio']:.2f})")
        for k, v in doc['links'].items()), TEXT_WIDTH, subsequent_indent='  ')
    lines += ['']
    for what, e in ([('training bag', doc['training_error'])] if 'training_error' in doc
                    else []) + [(f"validation bag {v['bag']}", v)
                                for v in doc.get('validation', [])]:
        lines += _torque_errors(what, e)
    lines += [f"on the {doc['processing'].get('processing', '')} rows fitted, percent: "
              + _per_joint(doc['relative_error']),
              'with the model\'s own parameters: ' + _per_joint(doc['model_relative_error']),
              'excitation condition number: ' + _number(doc['condition_number'])
              + f"   converged: {'yes' if doc['converged'] else 'no'}"]
    if not doc['excited']:
        lines += [f"not excited: the motion does not determine {len(doc['unexcited_directions'])}"
                  ' direction(s) of the base parameters (no estimate for the parameters in '
                  'them; excite the arm more):'] + [
                      f'  {d}' for d in doc['unexcited_directions']]
    if not doc['physically_consistent']:
        lines.append('closest full parameter set is not physically consistent: '
                     + '; '.join(doc['consistency_problems']))
        if doc['model_consistency_problems']:
            lines.append('(the model\'s own parameters, which it stays closest to, are not '
                         'either: ' + '; '.join(doc['model_consistency_problems']) + ')')
    if any(doc['excluded_equations'].values()):
        lines.append('equations left out near velocity reversals (coulomb_exclusion_speed): '
                     + ', '.join(f'{j} {k}' for j, k in doc['excluded_equations'].items()))
    lines += [f'warning: {w}' for w in doc['warnings']]
    lines += ['', 'convergence (estimate change to final, in final standard deviations):']
    final = np.array([np.nan if b['estimate'] is None else b['estimate']
                      for b in doc['base_parameters']])
    sd = np.array([b['stddev'] if b['stddev'] else np.inf for b in doc['base_parameters']])
    picks = _spread(len(doc['convergence']), 8)
    spread: list[tuple] = []
    for c in (doc['convergence'][k] for k in picks):
        dev = np.abs(np.array(c['estimate'], dtype=float) - final) / sd
        dev = dev[np.isfinite(dev)]   # not the unexcited parameters
        spread.append((str(c['num_samples']),
                       *(f'{f(dev):.2f}' if len(dev) else '-' for f in (np.max, np.median))))
    lines += text_table(('samples', 'max', 'median'), spread)
    return '\n'.join(lines)


def _torque_errors(what: str, e: dict) -> list[str]:
    """The lines of one bag's torque errors (validation.BagError.document)."""
    window = e['window_s']
    span = '' if window is None else ' from {} to {}'.format(
        f"{window['start'] or 0:g} s", 'the end' if window['end'] is None
        else f"{window['end']:g} s")
    lines = [f"relative torque error on the {what}{span} ({e['num_samples']} samples, raw "
             'torque), percent:']
    for key, label in (('estimate', 'identified'), ('model', 'model')):
        lines.append(f"  {label}: stacked {_number(e[key]['stacked'], '.3f')}; "
                     + _per_joint(e[key]['per_joint']))
    s = e['smoothed_torque']['estimate']
    lines.append(f"  identified, against the smoothed torque: stacked "
                 f"{_number(s['stacked'], '.3f')}; " + _per_joint(s['per_joint']))
    return lines


def _number(value: float | None, spec: str = '.4g') -> str:
    """A JSON number of the document (None: inf or NaN)."""
    return 'inf' if value is None else format(value, spec)


def format_payload_changes(changes: list, warnings: list | None = None) -> str:
    """The payload segments as text: values with stddev, 'not excited' where unknown (with
    the fitted value and its stddev where finite but above payload.tolerance), each change's
    mass step; ``warnings`` first."""
    def show(v, sd, unit, fv=None, fsd=None):
        if v is not None:
            return f'{v:.4g} +- {sd:.2g} {unit}'
        if fv is not None and fsd is not None:
            return f'not excited ({fv:.4g} +- {fsd:.2g} {unit})'
        return 'not excited'
    lines = [f'warning: {w}' for w in warnings or ()]
    lines += [f'payload: {len(changes) - 1} change(s) detected (link frame; inertia about the '
              'centre of mass):']
    for c in changes:
        p = c['payload']
        when = (f"at {c['stamp']:.3f} s" + (f" (detected {c['detected']:.3f} s)"
                                            if c['detected'] is not None else ' (start)'))
        if p is None:
            lines.append(f'  {when}: no fit (too few samples)')
            continue
        sd = p['stddev']
        f = p.get('fitted') or {'mass': None, 'com': [None] * 3, 'inertia': [None] * 6,
                                'stddev': {'mass': None, 'com': [None] * 3,
                                           'inertia': [None] * 6}}
        fsd = f['stddev']
        step = ('' if c.get('mass_change') is None else
                f"; change {c['mass_change']:+.4g} +- {c['mass_change_std']:.2g} kg")
        lines.append(f"  {when}, {p['link']}: mass "
                     f"{show(p['mass'], sd['mass'], 'kg', f['mass'], fsd['mass'])}{step}")
        lines.append('    com ' + ', '.join(show(*a[:2], 'm', *a[2:]) for a in zip(
            p['com'], sd['com'], f['com'], fsd['com'])))
        lines.append('    inertia ' + ', '.join(show(*a[:2], 'kg m^2', *a[2:]) for a in zip(
            p['inertia'], sd['inertia'], f['inertia'], fsd['inertia'])))
    return '\n'.join(lines)


def _per_joint(errors: dict) -> str:
    """Relative errors per joint; n/a where the document has none (null: no torque in the
    rows, as when every equation of the joint was left out)."""
    return ', '.join(f'{j} {"n/a" if e is None else format(e, ".2f")}'
                     for j, e in errors.items())


def paper_table3(fit) -> str:
    """The first paper's Table 3 combinations: identified, model (Table 1) and paper values.
    ``fit``: an Identification (results/identification.py) or an IdentificationPipeline."""
    from identification_node.results.report import paper_table3_rows

    if hasattr(fit, 'rls'):
        theta, cov = fit.rls.theta, fit.covariance
    else:
        theta, cov = fit.theta, fit.covariance
    rows = [(r['combination'], f"{r['identified']:.4f}", f"{r['stddev']:.4f}",
             f"{r['model']:.4f}", f"{r['paper_cad']:.4f}", f"{r['paper_estimate']:.4f}")
            for r in paper_table3_rows(fit.base, theta, cov,
                                       fit.base.to_base(fit.robot.phi_model))]
    return '\n'.join(['', "An, Atkeson, Hollerbach (1986) Table 3 combinations:"] + text_table(
        ('combination', 'identified', 'stddev', 'Table 1', 'paper CAD', 'paper est.'), rows))


ABOUT_ZERO = 3.0     # an estimate within this many stddev of zero has no relative stddev
TEXT_WIDTH = 100    # columns of the text output


def _relative(value: float, stddev: float | None) -> str:
    """stddev / |value| in percent, '-' where the value is about zero (or stddev unknown)."""
    if stddev is None or not np.isfinite(stddev) or abs(value) <= ABOUT_ZERO * stddev:
        return '-'
    return f'{100 * stddev / abs(value):.2f}'


def _spread(n: int, k: int) -> list[int]:
    return sorted({int(round(i)) for i in np.linspace(0, n - 1, min(n, k))}) if n else []


def text_table(header: tuple, rows: list[tuple]) -> list[str]:
    widths = [max(len(str(r[i])) for r in [header] + rows) for i in range(len(header))]
    return ['  ' + '  '.join(f'{str(c):<{w}}' if i == 0 else
                             f'{str(c):>{w}}' for i, (c, w) in enumerate(zip(r, widths))).rstrip()
            for r in [header] + rows]


def format_outputs(doc: dict) -> str:
    """The files --save, --report and --predictions wrote, by name."""
    written = [('--save', doc.get('saved') or []),
               ('--report', list((doc.get('report') or {}).values())),
               ('--predictions', [doc['predictions']] if doc.get('predictions') else [])]
    lines = [f'  {option}: {path}' for option, paths in written for path in paths]
    return '\n'.join(['', 'files written:'] + lines) if lines else ''


def identify_text(doc: dict, ident, gains: list | None = None, arm_table: bool = False,
                  paper_tables: bool = False) -> list[str]:
    """The blocks of identify's text output, in order: the payload changes (when identified;
    the arm's table then only with ``arm_table``), the arm's table, the MIT paper's Table 3
    (``paper_tables``), the drive gains and the files written."""
    blocks = []
    payload = 'payload_changes' in doc
    if payload:   # the payload first; the arm's table when asked
        blocks.append(format_payload_changes(doc['payload_changes'], doc['payload_warnings']))
    if not payload or arm_table:
        blocks.append(('\n' if payload else '') + format_report(doc))
    if paper_tables:
        blocks.append(paper_table3(ident))
    if gains is not None:
        from identification_node.estimation.drive_gains import gains_text
        blocks.append('\n'.join(gains_text(gains)))
    blocks.append(format_outputs(doc))
    return blocks
