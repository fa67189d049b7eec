"""The consistent solve's link masses with and without its L1 mass term (consistency.py,
``mass_weight``), on the suite's two fixture arms (six_dof_arm, panda_like) with friction
columns: truth = each URDF body scaled by 1 +- 30 % (random signs), 20 s of Fourier motion at
200 Hz, white torque noise, the model exact (no Stribeck bump, unlike bench_models.py's
corpus). Per case and weight: how many link masses are plausible (within 30 % of the truth or
between the URDF and the truth, 1 % slack) and the masses over the truth.

    .venv/bin/python bench/bench_mass_term.py [--seeds 3] [--weights 0,30]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from identification_node.estimation.consistency import ConsistencyOptions, ConsistentSolver
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import load_robot

FIXTURES = Path(__file__).resolve().parents[1] / 'test' / 'fixtures'
ARMS = ('six_dof_arm', 'panda_like')
RATE, DURATION, PERTURBATION, SLACK = 200.0, 20.0, 0.3, 0.01


def case(robot, base, seed: int, sigma: float) -> tuple[np.ndarray, NormalEquations]:
    """(true parameters, normal equations of 20 s of noisy torque) for one seed."""
    rng = np.random.default_rng(seed)
    factors = 1.0 + PERTURBATION * rng.choice([-1.0, 1.0], robot.dof)
    phi = robot.phi_model.copy()
    for i, f in enumerate(factors):
        phi[10 * i:10 * i + 10] *= f
    for k, name in enumerate(robot.param_names[robot.n_inertial:], robot.n_inertial):
        phi[k] = rng.uniform(0.1, 0.5) if name.endswith(('.fv', '.fc')) else 0.05
    t = np.arange(0.0, DURATION, 1.0 / RATE)
    q, qd, qdd = FourierTrajectory.random(robot, harmonics=5, period=DURATION, seed=seed,
                                          margin=0.8).sample(t)
    Y = robot.regressor(q, qd, qdd)
    tau = Y @ phi + sigma * rng.standard_normal((len(t), robot.dof))
    return phi, NormalEquations.from_rows(base.base_regressor(Y), tau)


def plausible(masses: np.ndarray, true: np.ndarray, urdf: np.ndarray) -> np.ndarray:
    lo, hi = np.minimum(true, urdf), np.maximum(true, urdf)
    return ((np.abs(masses / true - 1) <= PERTURBATION + SLACK)
            | ((masses >= lo * (1 - SLACK)) & (masses <= hi * (1 + SLACK))))


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
                    ok = plausible(m, true, urdf)
                    totals[w] += int(ok.sum())
                    cells.append(f"{ok.sum()}/{len(ok)}, {' '.join(f'{r:.2f}' for r in m / true)}")
                count += robot.dof
                print(f"{arm} | {seed} | {sigma:g} | {' | '.join(cells)}", flush=True)
    print('plausible masses: ' + ', '.join(f'w={w:g} {totals[w]} of {count}' for w in weights))


if __name__ == '__main__':
    main()
