"""The consistent solve's link masses with and without its L1 mass term (consistency.py,
``mass_weight``), on the suite's two fixture arms (six_dof_arm, panda_like) with friction
columns: truth = each URDF body scaled by 1 +- 30 % (corpus.truth), 20 s of Fourier motion
at 200 Hz, white torque noise, the model exact (no Stribeck bump, unlike bench_models.py's
corpus). Per case and weight: how many link masses are plausible (within 30 % of the truth or
between the URDF and the truth, 1 % slack) and the masses over the truth.

    .venv/bin/python bench/bench_mass_term.py [--seeds 3] [--weights 0,30]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from corpus import plausible_masses, truth  # noqa: E402

from identification_node.estimation.consistency import (ConsistencyOptions,  # noqa: E402
                                                        ConsistentSolver)
from identification_node.estimation.normal_equations import NormalEquations  # noqa: E402
from identification_node.excitation.trajectories import FourierTrajectory  # noqa: E402
from identification_node.model.identifiability import BaseParameters  # noqa: E402
from identification_node.model.robot import load_robot  # noqa: E402

FIXTURES = Path(__file__).resolve().parents[1] / 'test' / 'fixtures'
ARMS = ('six_dof_arm', 'panda_like')
RATE, DURATION = 200.0, 20.0


def case(robot, base, seed: int, sigma: float) -> tuple[np.ndarray, NormalEquations]:
    """(true parameters, normal equations of 20 s of noisy torque) for one seed: the bodies
    as bench_models.py's corpus perturbs them, friction drawn in [0.1, 0.5]."""
    rng = np.random.default_rng(seed)
    phi = truth(robot, seed)[0]
    for k, name in enumerate(robot.param_names[robot.n_inertial:], robot.n_inertial):
        phi[k] = rng.uniform(0.1, 0.5) if name.endswith(('.fv', '.fc')) else 0.05
    t = np.arange(0.0, DURATION, 1.0 / RATE)
    q, qd, qdd = FourierTrajectory.random(robot, harmonics=5, period=DURATION, seed=seed,
                                          margin=0.8).sample(t)
    Y = robot.regressor(q, qd, qdd)
    tau = Y @ phi + sigma * rng.standard_normal((len(t), robot.dof))
    return phi, NormalEquations.from_rows(base.base_regressor(Y), tau)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, default=3)
    parser.add_argument('--weights', default='0,30', help='comma-separated mass_weight values')
    args = parser.parse_args()
    weights = [float(w) for w in args.weights.split(',')]
    totals = dict.fromkeys(weights, 0)
    count = 0
    print('arm | seed | noise N m | ' + ' | '.join(f'w={w:g}: plausible, masses/truth'
                                                   for w in weights))
    for arm in ARMS:
        robot = load_robot(str(FIXTURES / f'{arm}.urdf'), extras=['fv', 'fc', 'Ia'])
        base = BaseParameters.from_robot(robot)
        urdf = robot.phi_model[0:robot.n_inertial:10]
        for seed in range(args.seeds):
            for sigma in (0.05, 0.5):
                phi, ne = case(robot, base, seed, sigma)
                true = phi[0:robot.n_inertial:10]
                cells = []
                for w in weights:
                    solver = ConsistentSolver.for_robot(robot, base,
                                                        ConsistencyOptions(mass_weight=w))
                    m = solver.solve(ne, sigma ** -2).phi[0:robot.n_inertial:10]
                    ok = plausible_masses(m, true, urdf)
                    totals[w] += int(ok.sum())
                    cells.append(f"{ok.sum()}/{len(ok)}, {' '.join(f'{r:.2f}' for r in m / true)}")
                count += robot.dof
                print(f"{arm} | {seed} | {sigma:g} | {' | '.join(cells)}", flush=True)
    print('plausible masses: ' + ', '.join(f'w={w:g} {totals[w]} of {count}' for w in weights))


if __name__ == '__main__':
    main()
