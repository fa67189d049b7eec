"""The node's consistency worker (ros/solver_worker.py, ROS-free) with a stand-in solver
process that counts its solves."""
import collections
import logging
import types

import numpy as np
import pytest

from identification_node.estimation.consistency import ConsistencyOptions, ConsistentEstimate
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.ros import solver_worker


class CountingSolver:
    """A solver process whose solve is a closed form (theta = the weighted first row), counted;
    ``fail`` makes the next solves fail as a time-out would."""

    def __init__(self) -> None:
        self.solves = 0
        self.fail = False

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def ready(self) -> bool:
        return True

    def solve(self, equations: NormalEquations, weights=1.0) -> ConsistentEstimate:
        self.solves += 1
        theta = equations.augmented[0, 0, :-1] * weights
        if self.fail:
            return ConsistentEstimate('time_limit', None, None, np.full(theta.size, np.inf),
                                      0.0)
        return ConsistentEstimate('optimal', theta, theta, np.ones(theta.size), 0.0)


@pytest.fixture
def solver(monkeypatch):
    counting = CountingSolver()
    monkeypatch.setattr(solver_worker, 'SolverProcess',
                        types.SimpleNamespace(for_robot=lambda *_args: counting))
    return counting


@pytest.fixture
def worker(solver):
    base = types.SimpleNamespace(num_base=3)
    w = solver_worker.ConsistencyWorker(None, base, ConsistencyOptions(), handle=lambda job: job,
                                        answer=lambda seq, outcome: None,
                                        failure=lambda text: text,
                                        errors=collections.Counter(),
                                        logger=logging.getLogger('test'))
    yield w
    w.stop()


def equations(scale: float) -> NormalEquations:
    ne = NormalEquations.zeros(3, 2)
    ne.augmented[:] = scale * np.arange(16.0).reshape(4, 4)
    return ne


def test_unchanged_equations_reuse_the_last_solve(worker, solver):
    """A frozen or reset estimate saved again and again: one trip to the solver process; any
    change in the equations or the weight solves again."""
    first = worker.solve((equations(1.0), 2.0))
    assert solver.solves == 1 and first.ok
    again = worker.solve((equations(1.0), 2.0))      # equal numbers, other arrays
    assert solver.solves == 1 and again is first
    changed = worker.solve((equations(1.5), 2.0))
    assert solver.solves == 2
    np.testing.assert_array_equal(changed.theta, 1.5 * first.theta)
    worker.solve((equations(1.5), 3.0))
    assert solver.solves == 3
    zero = (NormalEquations.zeros(3, 2), 1.0)        # a reset estimate
    worker.solve(zero)
    worker.solve((NormalEquations.zeros(3, 2), 1.0))
    assert solver.solves == 4


def test_a_failed_solve_is_tried_again(worker, solver):
    """A time-out is not kept: the same equations go to the solver process again."""
    solver.fail = True
    assert not worker.solve((equations(1.0), 1.0)).ok
    solver.fail = False
    assert worker.solve((equations(1.0), 1.0)).ok
    assert solver.solves == 2
