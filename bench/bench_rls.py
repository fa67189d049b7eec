"""Update cost per sample of the recursive and batch estimators (batches of 1000 samples).

p = 15: the MIT arm's base regressor (3 joints); p = 50: a random 6-joint regressor. Prints the
median wall time per sample. BLAS threading hurts these small matrices on a busy machine:
compare with OPENBLAS_NUM_THREADS=1.
"""
import time

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

import numpy as np
import scipy.linalg as sl

from identification_node.estimation.batch import LeastSquares
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.model.robot import load_robot

BATCH = 1000


def mit_base_rows(rng: np.random.Generator) -> np.ndarray:
    """Base regressor rows (BATCH, 3, 15) of the MIT arm at random states."""
    robot = load_robot('mit_dd_arm')
    Y = robot.regressor(*(rng.uniform(-3, 3, size=(BATCH, 3)) for _ in range(3)))
    R, piv = sl.qr(Y.reshape(-1, robot.num_params), mode='r', pivoting=True)
    d = np.abs(np.diag(R))
    return Y[..., np.sort(piv[:int(np.sum(d > 1e-9 * d[0]))])]


def per_sample_us(step, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    return 1e6 * float(np.median(times)) / BATCH


def main() -> None:
    rng = np.random.default_rng(0)
    cases = {'p=15 (MIT arm base, n=3)': mit_base_rows(rng),
             'p=50 (random, n=6)': rng.normal(size=(BATCH, 6, 50))}
    for label, Y in cases.items():
        n, p = Y.shape[1:]
        tau = Y @ rng.normal(size=p) + 0.1 * rng.normal(size=(BATCH, n))
        rls = RecursiveLeastSquares(p, 0.999)
        rls1 = RecursiveLeastSquares(p, 1.0)
        ls = LeastSquares(p, n)
        repeats = 200 if p < 30 else 50
        for name, step in (('RLS update, forgetting 0.999', lambda: rls.update(Y, tau)),
                           ('RLS update, forgetting 1.0', lambda: rls1.update(Y, tau)),
                           ('LeastSquares.add', lambda: ls.add(Y, tau))):
            step()  # warm up
            print(f'{label:26s} {name:29s} {per_sample_us(step, repeats):7.2f} us/sample')
        call = BATCH * per_sample_us(rls.estimate, repeats)
        print(f'{label:26s} {"RLS estimate()":29s} {call:7.1f} us/call')


if __name__ == '__main__':
    main()
