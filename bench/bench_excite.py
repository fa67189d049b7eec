"""Excitation design benchmark: example-robot-data's UR5 and Panda, with and without
self-collision, in one process; wall time against a baseline measured in the same run.

Each case runs ``optimize_excitation`` with the shipped defaults (5 harmonics, period 10 s,
100 criterion samples, SLSQP --maxiter 200, limits with 10 % margin), as ``excite --urdf ...``
does: the Panda's 7 arm joints (test/arms.py ARMS) and, with collision, its SRDF and meshes
(package:// resolved in the wheel's share/ folder). The baseline: the UR5 without collision.
Printed per case: wall and CPU time, SLSQP iterations, the criterion (initial -> designed),
the clearance with collision, and wall time / baseline. ``--cases`` also takes
tiago_pro+collision: TIAGo Pro's left arm, an arm outside the suite's tuning (meshes, no SRDF,
so 531 pairs), about 2 minutes.

``--exact`` also times the collision constraints and their Jacobian at the Panda's initial
guess (one SLSQP iteration's collision work) on the exact meshes, as the optimiser did before
the convex hulls, against the hulls: CPU time and ratio, measured in the same run.

BLAS runs single-threaded, as ``excite`` sets it (OPENBLAS_NUM_THREADS=1).

    .venv/bin/python bench/bench_excite.py [--cases ur5,ur5+collision,panda,panda+collision]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

from checkout import ROOT  # noqa: E402  (this checkout's package, here and in subprocesses)

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # before numpy loads OpenBLAS

sys.path.insert(0, str(ROOT / 'test'))

from arms import ARMS, arm_urdf, robots_dir  # noqa: E402

from identification_node.excitation.collision import CollisionChecker  # noqa: E402
from identification_node.excitation.design import optimize_excitation  # noqa: E402
from identification_node.model.robot import load_robot  # noqa: E402

SRDF = {'ur5': 'ur_description/srdf/ur5.srdf', 'panda': 'panda_description/srdf/panda.srdf'}
CASES = ('ur5', 'ur5+collision', 'panda', 'panda+collision')
MORE = ('tiago_pro+collision',)   # on --cases only: TIAGo Pro's left arm, no SRDF, 531 pairs


class _MeshesInOptimiser(CollisionChecker):
    """The checker before convex hulls: the optimiser's constraints on the exact meshes."""

    def hulls(self) -> CollisionChecker:
        return self


def _robot_and_checker(case: str, exact: bool = False):
    name, _, collision = case.partition('+')
    robot = load_robot(str(arm_urdf(name)), ARMS[name][1])
    if not collision:
        return robot, None
    kind = _MeshesInOptimiser if exact else CollisionChecker
    srdf = robots_dir() / SRDF[name] if name in SRDF else None
    return robot, kind(robot, [robots_dir().parent.parent], srdf)


def run(case: str, maxiter: int = 200, exact: bool = False, quiet: bool = True) -> dict:
    robot, checker = _robot_and_checker(case, exact)
    t0, c0 = time.perf_counter(), time.process_time()
    res = optimize_excitation(robot, maxiter=maxiter, checker=checker,
                              progress=None if quiet else print)
    return {'wall': time.perf_counter() - t0, 'cpu': time.process_time() - c0,
            'iterations': res.iterations, 'initial': res.initial_value, 'value': res.value,
            'message': res.message, 'warnings': res.warnings,
            'clearance': None if res.clearance is None else res.clearance['distance']}


def constraint_cpu(exact: bool) -> float:
    """CPU s of the Panda's collision constraints and Jacobian at the initial guess."""
    from identification_node.excitation.criteria import base_of
    from identification_node.excitation.design import MARGIN
    from identification_node.excitation.initial_guess import (DEFAULT_HARMONICS, DEFAULT_PERIOD,
                                                              initial_trajectory, to_x)
    from identification_node.excitation.limits import ExcitationLimits
    from identification_node.excitation.problem import DesignProblem
    from identification_node.excitation.result import DEFAULT_LIMIT_MARGIN

    robot, checker = _robot_and_checker('panda+collision', exact)
    limits = ExcitationLimits.from_robot(robot).with_margin(DEFAULT_LIMIT_MARGIN)
    design = DesignProblem(robot, base_of(robot, None), limits, DEFAULT_HARMONICS,
                           DEFAULT_PERIOD, 100, 'cond', None, MARGIN, None, checker)
    x = to_x(initial_trajectory(robot, None, limits, DEFAULT_HARMONICS, DEFAULT_PERIOD, 0))
    c0 = time.process_time()
    design.collision_ks(x, True)
    return time.process_time() - c0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--cases', default=','.join(CASES),
                        help=f'comma-separated cases of {", ".join(CASES + MORE)} (the first '
                        'is the baseline)')
    parser.add_argument('--exact', action='store_true',
                        help='also time the collision constraints on meshes against hulls')
    parser.add_argument('--progress', action='store_true', help='print the progress lines')
    args = parser.parse_args()
    cases = [c.strip() for c in args.cases.split(',') if c.strip()]
    unknown = set(cases) - set(CASES + MORE)
    if unknown:
        parser.error(f'unknown cases {sorted(unknown)}')
    rows = {}
    for case in cases:
        rows[case] = run(case, quiet=not args.progress)
        r = rows[case]
        print(f'{case}: {r["wall"]:.1f} s', flush=True)
    base = rows[cases[0]]['wall']
    print(f'OPENBLAS_NUM_THREADS={os.environ["OPENBLAS_NUM_THREADS"]}, load average '
          f'{os.getloadavg()[0]:.1f}; baseline {cases[0]} ({base:.1f} s)')
    print(f'{"case":17s}{"wall s":>8s}{"CPU s":>7s}{"/base":>7s}{"iter":>6s}'
          f'{"criterion":>22s}{"clearance m":>13s}  stopped')
    for case, r in rows.items():
        crit = f'{r["initial"]:.4g} -> {r["value"]:.4g}'
        clear = '' if r['clearance'] is None else f'{r["clearance"]:.4f}'
        print(f'{case:17s}{r["wall"]:8.1f}{r["cpu"]:7.1f}{r["wall"] / base:7.2f}'
              f'{r["iterations"]:6d}{crit:>22s}{clear:>13s}  {r["message"]}'
              + ''.join(f'\n{"":17s}warning: {w}' for w in r['warnings']))
    if args.exact:
        hull, mesh = (constraint_cpu(exact) for exact in (False, True))
        print(f'panda+collision, collision constraints and Jacobian at the initial guess: '
              f'meshes {mesh:.2f} s CPU, convex hulls {hull:.2f} s CPU: {mesh / hull:.1f}x')


if __name__ == '__main__':
    main()
