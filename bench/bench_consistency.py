"""Physically consistent solve time (consistency.py), as the node runs it at every refresh.

For a 6-DOF (CRS A465) and a 7-DOF (Panda-like) arm with viscous and Coulomb friction, the RLS
is fed a simulated excitation in blocks of 1 s (1 kHz rows); after each block the constrained
problem is solved on its normal equations: 'cold' is the first solve of a new solver (cvxpy's
canonicalisation included), 'warm' every later one (the parametrised problem re-used; Clarabel
itself starts afresh, SCS from the previous solution). Wall and thread CPU time per solve, with
the unconstrained solve of the same normal equations as the baseline measured in the same run.

    .venv/bin/python bench/bench_consistency.py [--refreshes 20] [--solver CLARABEL|SCS]
"""
from __future__ import annotations

import argparse
import os
import time

from checkout import ROOT  # noqa: E402  (this checkout's package, here and in subprocesses)

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # as the node's entry point, before numpy

import numpy as np  # noqa: E402

from identification_node.estimation.consistency import (ConsistencyOptions,  # noqa: E402
                                                        ConsistentSolver)
from identification_node.estimation.rls import RecursiveLeastSquares  # noqa: E402
from identification_node.excitation.trajectories import FourierTrajectory  # noqa: E402
from identification_node.model.identifiability import BaseParameters  # noqa: E402
from identification_node.model.robot import load_robot  # noqa: E402

ARMS = {'6-DOF crs_a465': 'crs_a465',
        '7-DOF panda_like': str(ROOT / 'test' / 'fixtures' / 'panda_like.urdf')}


def timed(fn):
    wall, cpu = time.perf_counter(), time.thread_time()
    out = fn()
    return out, time.perf_counter() - wall, time.thread_time() - cpu


def run(label: str, source: str, refreshes: int, solver: str) -> None:
    robot = load_robot(source, extras=['fv', 'fc'])
    base = BaseParameters.from_robot(robot)
    traj = FourierTrajectory.random(robot, harmonics=5, period=10.0, seed=1, margin=0.7)
    rng = np.random.default_rng(2)
    phi = robot.phi_model.copy()
    phi[robot.n_inertial:] = 0.3
    rls = RecursiveLeastSquares(base.num_base)
    options = ConsistencyOptions(solver=solver)
    solver_, build, _ = timed(lambda: ConsistentSolver.for_robot(robot, base, options))
    walls, cpus, plain, failed = [], [], [], []
    for k in range(refreshes + 1):
        t = k + np.arange(0.0, 1.0, 1e-3)
        q, qd, qdd = traj.sample(t)
        Y = robot.regressor(q, qd, qdd)
        rls.update(base.base_regressor(Y), Y @ phi + 0.1 * rng.standard_normal(q.shape))
        ne = rls.normal_equations()
        result, wall, cpu = timed(lambda: solver_.solve(ne, 100.0))
        if not result.ok:
            failed.append(result.status)
        walls.append(wall)
        cpus.append(cpu)
        G, g, _ = ne.combined(100.0)
        plain.append(timed(lambda: np.linalg.solve(G, g))[1])
    warm, warm_cpu, baseline = (np.median(x[1:]) for x in (walls, cpus, plain))
    print(f'{label}: {robot.num_params} standard / {base.num_base} base parameters; '
          f'solver {solver}')
    print(f'  build {1e3 * build:.0f} ms; cold solve {1e3 * walls[0]:.0f} ms '
          f'(cpu {1e3 * cpus[0]:.0f} ms)')
    print(f'  warm solve median {1e3 * warm:.1f} ms (range {1e3 * min(walls[1:]):.1f}-'
          f'{1e3 * max(walls[1:]):.1f}), cpu {1e3 * warm_cpu:.1f} ms; over {refreshes} '
          f'refreshes')
    print(f'  ratio to the unconstrained solve ({1e6 * baseline:.0f} us): warm '
          f'{warm / baseline:.0f}x, cold {walls[0] / baseline:.0f}x; warm / cold '
          f'{warm / walls[0]:.2f}')
    if failed:
        print(f'  {len(failed)} of {refreshes + 1} solves failed: {sorted(set(failed))[:3]}')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--refreshes', type=int, default=20)
    parser.add_argument('--solver', default='CLARABEL', choices=('CLARABEL', 'SCS'))
    args = parser.parse_args()
    for label, source in ARMS.items():
        run(label, source, args.refreshes, args.solver)


if __name__ == '__main__':
    main()
