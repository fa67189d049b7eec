"""The model corpus (issue 27) with the data's region widened by the smoother's model error.

Per case (bench/corpus.py, defaults as identify runs them): the consistent solve's excess
(the chi-square beyond the data's region its constraints cost; beyond the solver's tolerance,
1e-3 of the region's quantile: no physical arm lies in the region, the data disagree with
one). Where it is, the estimate's sensitivity to the smoother's window, d = (theta(L g) -
theta(L / g)) / 2 from the unconstrained fits at the neighbouring half windows of the
automatic choice L (g = rows.AUTO_GRID), is added to the data's covariance
(ConsistentSolver.solve's ``model_error``, scaled by ``--scale``) and the solve repeated.
Printed per case: excess, whether every link mass is plausible (within 30 % of the truth or
between URDF and truth) and the held-out error ratio to the unconstrained fit, for the
defaults and widened; then the misses of each (a case misses when a mass is not plausible or
the ratio exceeds 1.03). ``--always``: every case widened.

    .venv/bin/python bench/bench_widening.py [--arms ur5,panda] [--rates 100,500]
        [--seeds 3] [--duration 30] [--scale 1] [--always]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from corpus import ARMS, RATES, Case, make_case, plausible_masses  # noqa: E402

from identification_node.estimation.consistency import ConsistentSolver  # noqa: E402
from identification_node.pipeline.rows import AUTO_GRID  # noqa: E402
from identification_node.replay.identify import IdentifyConfig, identify  # noqa: E402
from identification_node.replay.validation import evaluate, evaluation_settings  # noqa: E402
from identification_node.settings import Settings  # noqa: E402

HELD_OUT_RATIO = 1.03
EXCESS_TOLERANCE = 1e-3   # of the region's chi-square quantile: the solver's tolerance


def _settings(arm: str, **more) -> Settings:
    joints = ARMS[arm][1]
    return Settings.from_dict({**({'joints': list(joints)} if joints else {}), **more})


def run_case(case: Case, directory: Path, scale: float, always: bool = False) -> dict:
    """The case identified with the defaults and, where the solve's excess is beyond its
    tolerance (``always``: in any case), widened; a widened solve that fails misses."""
    truth = make_case(case, directory)
    train, heldout = str(truth['dir'] / 'train'), str(truth['dir'] / 'heldout')
    settings = _settings(case.arm)
    done = identify(train, IdentifyConfig(settings, validation_bags=(heldout,)))
    ident, held = done.ident, done.doc['validation'][0]
    unconstrained = held['unconstrained']['stacked']
    ni = ident.robot.n_inertial

    def row(phi: np.ndarray, error: float) -> tuple[bool, float]:
        ok = bool(np.all(plausible_masses(phi[0:ni:10], truth['masses'],
                                          truth['urdf_masses'])))
        return ok, error / unconstrained

    solver = ConsistentSolver.for_robot(ident.robot, ident.base, settings.consistency_options())
    q = solver.region(ident.fit_equations, ident.fit_weights)[2]
    result = {'excess': ident.consistent.excess,
              'default': row(ident.consistent.phi, held['estimate']['stacked'])}
    result['widened'] = result['default']
    if always or ident.consistent.excess > EXCESS_TOLERANCE * q:
        L = ident.details['smoother_half_window']
        fits = [identify(train, IdentifyConfig(_settings(case.arm, **{
            'smoother.half_window': int(round(h))}), physical_consistency=False)).ident.theta
            for h in (L / AUTO_GRID, L * AUTO_GRID)]
        d = scale * (fits[1] - fits[0]) / 2
        widened = solver.solve(ident.fit_equations, ident.fit_weights, d)
        if not widened.ok:
            result['widened'] = (False, np.inf)
            return result
        error = evaluate(heldout, evaluation_settings(settings, ident), ident.robot,
                         ident.base, {'estimate': widened.theta}).errors['estimate'].stacked
        result['widened'] = row(widened.phi, error)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--arms', help=f"comma-separated, of {', '.join(ARMS)} (default all)")
    parser.add_argument('--rates', default='100,250,500,1000', help='comma-separated Hz')
    parser.add_argument('--seeds', type=int, default=3, help='seeds 0..N-1 per arm and rate')
    parser.add_argument('--duration', type=float, default=30.0, help='s per motion')
    parser.add_argument('--scale', type=float, default=1.0, help='k: model error k d')
    parser.add_argument('--always', action='store_true', help='widen every case')
    args = parser.parse_args()
    arms = args.arms.split(',') if args.arms else list(ARMS)
    rates = [float(r) for r in args.rates.split(',')] if args.rates else list(RATES)
    print('case | excess | default: masses ok, held-out ratio | widened: masses ok, ratio')
    misses: dict[str, list[str]] = {'default': [], 'widened': []}
    with tempfile.TemporaryDirectory() as tmp:
        for arm in arms:
            for rate in rates:
                for seed in range(args.seeds):
                    case = Case(arm, rate, args.duration, seed)
                    r = run_case(case, Path(tmp), args.scale, args.always)
                    cells = []
                    for kind in ('default', 'widened'):
                        ok, ratio = r[kind]
                        if not (ok and ratio <= HELD_OUT_RATIO):
                            misses[kind].append(case.name)
                        cells.append(f"{'yes' if ok else 'NO'}, {ratio:.3f}")
                    print(f"{case.name} | {r['excess']:.3g} | {cells[0]} | {cells[1]}",
                          flush=True)
    for kind, names in misses.items():
        print(f"{kind}: {len(names)} case(s) miss a target: {', '.join(names) or 'none'}")
    return 0


if __name__ == '__main__':
    sys.exit(main())
