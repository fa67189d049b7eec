"""The fleet report: per robot, the estimate over the periods with standard deviations
(fleet.md), figures of each joint's friction and of the main inertial combinations over the
periods (PNG, matplotlib Agg), the flags and the failed bags. Files written atomically."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from identification_node.fileio import atomic_write_text, save_figure
from identification_node.results.report import markdown_table, number_text

__all__ = ['FRICTION', 'MAIN_INERTIAL', 'trend_data', 'plot_trend', 'write_fleet_report']

FRICTION = ('.fv', '.fc', '.fo', '.Ia')
MAIN_INERTIAL = 6          # inertial combinations plotted per robot: the best determined


def trend_data(periods: dict[str, dict]) -> dict:
    """periods -> identify document, in time order: names, estimate and stddev (P, b), and
    which base parameters are friction / rotor terms and which the main inertial ones (the
    largest median |estimate| / stddev)."""
    first = next(iter(periods.values()))
    names = [p['name'] for p in first['base_parameters']]
    est = np.array([[p['estimate'] for p in d['base_parameters']] for d in periods.values()])
    sd = np.array([[np.inf if p['stddev'] is None else p['stddev']
                    for p in d['base_parameters']] for d in periods.values()])
    friction = [i for i, n in enumerate(names) if n.endswith(FRICTION)]
    with np.errstate(divide='ignore', invalid='ignore'):
        significance = np.median(np.abs(est) / sd, axis=0)
    inertial = [i for i in np.argsort(-significance) if i not in friction][:MAIN_INERTIAL]
    return {'periods': list(periods), 'names': names, 'estimate': est, 'stddev': sd,
            'friction': friction, 'inertial': sorted(int(i) for i in inertial)}


def plot_trend(data: dict, columns: list[int], path: str | os.PathLike, title: str) -> Path:
    """One panel per base parameter: estimate +- stddev over the periods."""
    from matplotlib.figure import Figure

    k = max(len(columns), 1)
    fig = Figure(figsize=(9, 1.0 + 1.8 * k))
    axes = fig.subplots(k, 1, sharex=True, squeeze=False)[:, 0]
    x = np.arange(len(data['periods']))
    for ax, i in zip(axes, columns):
        sd = np.where(np.isfinite(data['stddev'][:, i]), data['stddev'][:, i], np.nan)
        ax.errorbar(x, data['estimate'][:, i], yerr=sd, marker='o', ms=4, capsize=3, lw=1.0)
        ax.set_ylabel(data['names'][i], fontsize='small')
        ax.grid(alpha=0.3)
    axes[-1].set_xticks(x, data['periods'], rotation=30, fontsize='small')
    axes[-1].set_xlabel('period')
    axes[0].set_title(title)
    fig.tight_layout()
    return save_figure(fig, Path(path))


def write_fleet_report(directory: str | os.PathLike, doc: dict) -> dict[str, Path]:
    """fleet.md and per robot <robot>_friction.png, <robot>_inertial.png from the
    ``fleet --json`` document; returns name -> path ('report' for fleet.md)."""
    out = Path(directory)
    files: dict[str, Path] = {}
    lines = ['# Fleet identification', '',
             f"{len(doc['robots'])} robot(s); flags at {doc['sigma']:g} standard deviations.",
             '']
    for robot, periods in doc['robots'].items():
        data = trend_data(periods)
        safe = ''.join(c if c.isalnum() or c in '-_.' else '_' for c in robot)
        lines += [f'## {robot}', '']
        rows = [['samples'] + [str(d['num_samples']) for d in periods.values()]] + [
            [name] + [f'{number_text(e, 6)} ± {number_text(s, 2)}'
                      for e, s in zip(data['estimate'][:, i], data['stddev'][:, i])]
            for i, name in enumerate(data['names'])]
        lines += markdown_table(['parameter (SI)'] + data['periods'], rows, text=1) + ['']
        for kind, columns in (('friction', data['friction']), ('inertial', data['inertial'])):
            if not columns:
                continue
            title = (f'{robot}: joint friction and rotor terms' if kind == 'friction'
                     else f'{robot}: main inertial combinations')
            path = plot_trend(data, columns, out / f'{safe}_{kind}.png', title)
            files[f'{robot}_{kind}'] = path
            lines += [f'![{title}]({path.name})', '']
    lines += ['## Flags', '']
    if doc['flags']:
        lines += markdown_table(['robot', 'kind', 'period', 'parameter', 'change (sigma)'], [
            [f['robot'], f['kind'], str(f['period'] or '-'), f['parameter'],
             f"{f['change_sigma']:.1f}"] for f in doc['flags']], text=4)
    else:
        lines.append('none')
    lines += ['', '## Failed bags', '']
    lines += [f"- `{f['bag']}`: {f['error']}" for f in doc['failed']] or ['none']
    files['report'] = atomic_write_text(out / 'fleet.md', '\n'.join(lines) + '\n')
    return files
