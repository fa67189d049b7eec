"""The model corpus (issue 27): every arm x rate identified with the defaults, one table.

Per case (bench/corpus.py: truth = URDF bodies x (1 +- 30 %), viscous, Coulomb and Stribeck
friction, encoder/velocity/torque noise; held out = another Fourier motion): physically
consistent or not and the solver path, held-out torque error of the estimate and of the
unconstrained fit (percent, raw torque) and their ratio, link masses against the truth and
the URDF, whether every mass is within +-30 % of the truth or between the URDF and the truth,
and the RMS of (estimate - truth) / stddev over the base parameters. Per arm first: the
links whose mass alone the joint torques determine (corpus.masses_in_data). ``--recordings``:
the real TX40 and Kinova Gen3 runs of ../shared/data instead (bench/recordings.py), masses
against the URDF only.

    .venv/bin/python bench/bench_models.py [--arms ur5,panda] [--rates 100,500]
        [--duration 60] [--seeds 1] [--recordings] [--config FILE]

``--config``: a parameter YAML passed to every ``identify`` (e.g. other ``consistency.*``).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from corpus import ARMS, RATES, Case, case_robot, identify_case, masses_in_data  # noqa: E402


def _masses(ratios) -> str:
    return ' '.join(f'{r:.2f}' for r in ratios)


def _config(args) -> list[str]:
    return ['--config', args.config] if args.config else []


def simulated(args) -> int:
    arms = args.arms.split(',') if args.arms else list(ARMS)
    rates = [float(r) for r in args.rates.split(',')] if args.rates else list(RATES)
    print('case | consistent | path | held-out % (unconstr.) | ratio | masses/truth | '
          'masses/URDF | masses ok | z RMS | s')
    failures = 0
    with tempfile.TemporaryDirectory() as tmp:
        for arm in arms:
            alone = masses_in_data(case_robot(arm))
            print(f"{arm}: link masses the torques determine alone: {', '.join(alone) or 'none'}"
                  ' (the others only in combinations: the prior and physical consistency '
                  'split them)')
            for rate, seed in ((r, k) for r in rates for k in range(args.seeds)):
                case = Case(arm, rate, args.duration, seed)
                start = time.perf_counter()
                r = identify_case(case, Path(tmp), _config(args))
                ok = (r['consistent'] and not r['errors'] and r['heldout_ratio'] <= 1.03
                      and r['masses_ok'])
                failures += not ok
                print(f"{case.name} | {'yes' if r['consistent'] else 'NO'} | {r['path']} | "
                      f"{r['heldout']:.3f} ({r['heldout_unconstrained']:.3f}) | "
                      f"{r['heldout_ratio']:.3f} | {_masses(r['truth_ratio'])} | "
                      f"{_masses(r['urdf_ratio'])} | {'yes' if r['masses_ok'] else 'NO'} | "
                      f"{r['z_rms']:.2f} | {time.perf_counter() - start:.0f}", flush=True)
                for note in r['notes']:
                    print(f'    note: {note}')
    print(f'{failures} case(s) miss a target')
    return 0


def recordings(args) -> int:
    from recordings import RECORDINGS, identify_recording

    print('recording | consistent | path | held-out % (unconstr.) | ratio | masses/URDF | '
          'masses kg')
    with tempfile.TemporaryDirectory() as tmp:
        for name in RECORDINGS:
            try:
                r = identify_recording(name, Path(tmp), _config(args))
            except RuntimeError as exc:   # identify's own error line is above
                print(f'{name} | not identified: {exc}', flush=True)
                continue
            print(f"{name} | {'yes' if r['consistent'] else 'NO'} | {r['path']} | "
                  f"{r['heldout']:.2f} ({r['heldout_unconstrained']:.2f}) | "
                  f"{r['heldout_ratio']:.3f} | {_masses(r['urdf_ratio'])} | "
                  f"{_masses(r['masses'])}", flush=True)
            for note in r['notes']:
                print(f'    note: {note}')
            print(f"    URDF total {np.sum(r['urdf_masses']):.2f} kg, estimate "
                  f"{np.sum(r['masses']):.2f} kg")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--arms', help=f"comma-separated, of {', '.join(ARMS)} (default all)")
    parser.add_argument('--rates', help='comma-separated Hz (default 100,250,500,1000,2000)')
    parser.add_argument('--duration', type=float, default=60.0, help='s per motion')
    parser.add_argument('--seeds', type=int, default=1,
                        help='cases per arm and rate (truth perturbation, motions, noise)')
    parser.add_argument('--recordings', action='store_true',
                        help='the real recordings of ../shared/data instead')
    parser.add_argument('--config', help='parameter YAML given to every identify')
    args = parser.parse_args()
    return recordings(args) if args.recordings else simulated(args)


if __name__ == '__main__':
    sys.exit(main())
