"""The node's physically consistent solve, off its processing thread.

:class:`SolverProcess` runs a ConsistentSolver (estimation/consistency.py) in a child process
of its own, so that the node's processing thread never waits for the GIL while it solves.
:class:`ConsistencyWorker` is the node's thread that takes the snapshots of the pipeline in
order (service_requests.Snapshot), hands each to the node's handler (which solves through
``solve`` and publishes) and answers the requests it covers. ROS-free.
"""
from __future__ import annotations

import collections
import multiprocessing
import os
import signal
import threading
import time
import traceback
from typing import Any, Callable, Sequence

import numpy as np

from identification_node.estimation.consistency import (Body, ConsistencyOptions,
                                                        ConsistentEstimate, ConsistentSolver,
                                                        robot_bodies)
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.model.identifiability import BaseParameters

__all__ = ['NICE', 'ConsistencyWorker', 'SolverProcess']

NICE = 5    # the solver process: below the node's processing, yet not starved by a neighbour


class SolverProcess:
    """A ConsistentSolver in a child process of its own (spawned), with ``solve`` as the
    solver's: the node's processing thread never waits for the GIL while it solves. A child
    that dies or overruns ``time_limit`` (+ STARTUP_GRACE for the first solve, which builds the
    problem) is stopped and the solve reported failed; the next one starts a new child.
    ``ready`` tells, without waiting, whether the child has built its problem: on a busy
    machine that takes tens of seconds, which a caller need not wait for."""

    STARTUP_GRACE = 60.0   # s: spawn, imports and the problem's canonicalisation
    GRACE = 10.0           # s over the solver's own time limit

    def __init__(self, base: BaseParameters, phi_prior: np.ndarray, bodies: Sequence[Body],
                 options: ConsistencyOptions | None = None):
        self.options = options or ConsistencyOptions()
        self.options.validate()
        self._args = (base, np.asarray(phi_prior, dtype=float), list(bodies), self.options)
        self._process = self._conn = None
        self._ready = False     # the child has built its problem (its first message)
        # start and close come from different threads (the node's solve worker and its
        # shutdown): a child being started is never terminated half made
        self._lock = threading.Lock()

    @classmethod
    def for_robot(cls, robot, base: BaseParameters,
                  options: ConsistencyOptions | None = None) -> SolverProcess:
        """As ConsistentSolver.for_robot (the bodies are read here, from the robot)."""
        options = options or ConsistencyOptions()
        options.validate(robot.dof)
        from identification_node.estimation.prior import safe_prior

        return cls(base, safe_prior(robot)[0], robot_bodies(robot, options), options)

    def start(self):
        """Start the child (solve does when needed); it builds the problem at once. Returns
        the connection to it."""
        with self._lock:
            if self._process is not None and self._process.is_alive():
                return self._conn
            ctx = multiprocessing.get_context('spawn')
            self._conn, child = ctx.Pipe()
            self._process = ctx.Process(target=_serve, args=(child, *self._args),
                                        daemon=True, name='identification_consistency')
            # Ctrl-C in a terminal signals the whole process group: the child is ended by its
            # parent (close), not by SIGINT mid-import (a traceback). It inherits an ignored
            # SIGINT, which only the main thread can set (a child started by another thread,
            # after a time-out, is spared only once it runs _serve).
            main = threading.current_thread() is threading.main_thread()
            sigint = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
            try:
                self._process.start()
            finally:
                if main:
                    signal.signal(signal.SIGINT, sigint)
            child.close()
            self._ready = False
            return self._conn

    def ready(self) -> bool:
        """Whether the child has built its problem, so that ``solve`` waits for the solve
        only (never blocks; False before ``start``)."""
        with self._lock:
            if not self._ready and self._conn is not None:
                try:
                    if self._conn.poll(0):
                        self._conn.recv()   # ('ready', error): an error is told by solve
                        self._ready = True
                except (EOFError, OSError):
                    self._ready = True      # ended: solve reports it and starts another
            return self._ready

    def solve(self, equations: NormalEquations, weights: np.ndarray | float = 1.0
              ) -> ConsistentEstimate:
        start = time.perf_counter()
        conn = self.start()
        wait = self.options.time_limit + (self.GRACE if self._ready else self.STARTUP_GRACE)
        deadline = time.monotonic() + wait
        try:
            conn.send((equations, weights))
            kind = 'ready'
            while kind == 'ready' and conn.poll(max(deadline - time.monotonic(), 0.0)):
                kind, value = conn.recv()
                self._ready = True
            if kind == 'ok':
                return value
            if kind == 'error':
                status = f'solver_error: {value}'
            else:
                status = 'time_limit'
                self.close()
        except (EOFError, OSError, BrokenPipeError) as exc:
            status = f'solver_error: solver process ended ({exc or type(exc).__name__})'
            self.close()
        b = self._args[0].num_base
        return ConsistentEstimate(status, None, None, np.full(b, np.inf),
                                  time.perf_counter() - start)

    def close(self) -> None:
        """Stop the child."""
        with self._lock:
            if self._process is None:
                return
            self._process.terminate()   # nothing to keep: quick, also mid-solve
            self._process.join(timeout=1.0)
            self._conn.close()
            self._process = self._conn = None


def _serve(conn, base, phi_prior, bodies, options) -> None:
    """The child of SolverProcess: build the solver, say ('ready', error), then answer
    (equations, weights) with ('ok', ConsistentEstimate) or ('error', message) until None or
    the pipe closes. It runs
    at a lower priority (nice +NICE) than the node, whose 1 kHz processing comes first.
    SIGINT is ignored (see SolverProcess.start): the parent ends it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.nice(NICE)
    solver, error = None, ''
    try:
        solver = ConsistentSolver(base, phi_prior, bodies, options)
    except Exception as exc:  # noqa: BLE001 - reported to the parent with every request
        error = f'{type(exc).__name__}: {exc}'
    try:
        conn.send(('ready', error))
    except (EOFError, OSError):
        return
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        if solver is None:
            conn.send(('error', error))
            continue
        try:
            conn.send(('ok', solver.solve(*request)))
        except Exception as exc:  # noqa: BLE001 - the parent keeps the unconstrained estimate
            conn.send(('error', f'{type(exc).__name__}: {exc}'))


class ConsistencyWorker:
    """A daemon thread taking the jobs given to ``submit`` in order: ``handle(job)`` (which
    may call ``solve``) gives the outcome, ``answer(job.seq, outcome)`` sends it. A handler
    that raises is counted in ``errors['estimate']``, logged, and answered with
    ``failure(text)``. The solver process (``options`` None: none) is started here, on the
    caller's thread (the main thread's, so that Ctrl-C spares it: SolverProcess)."""

    def __init__(self, robot, base: BaseParameters, options: ConsistencyOptions | None,
                 handle: Callable[[Any], Any], answer: Callable[[int, Any], None],
                 failure: Callable[[str], Any], errors: collections.Counter, logger: Any):
        self.options = options
        self.consistent: ConsistentEstimate | None = None   # the last solve's result
        self._robot, self._base = robot, base
        self._handle, self._answer, self._failure = handle, answer, failure
        self._errors, self._logger = errors, logger
        self._solver: SolverProcess | None = None
        self._solver_lock = threading.Lock()
        self._solver_failure = ''
        self._solved_for: tuple | None = None   # the equations ``consistent`` solved
        self._jobs: list[Any] = []     # taken in order
        self._job_ready = threading.Condition()
        self._running = True
        if options is not None:
            try:
                self._solver_instance()
            except Exception as exc:  # noqa: BLE001 - reported by the first solve again
                logger.error(f'physical consistency solver: {exc}')
        self._thread = threading.Thread(target=self._run, name='identification_consistency',
                                        daemon=True)
        self._thread.start()

    def submit(self, jobs: list) -> None:
        """Queue ``jobs`` (service_requests.Snapshot), in order; a newer one replaces one not
        yet taken unless that one is to be saved."""
        if not jobs:
            return
        with self._job_ready:
            for job in jobs:
                if self._jobs and not self._jobs[-1].save:
                    self._jobs[-1] = job
                else:
                    self._jobs.append(job)
            self._job_ready.notify()

    def solve(self, equations: tuple, wait: bool = True) -> ConsistentEstimate:
        """The consistent estimate of ``equations`` ((NormalEquations, weights)); a failure
        is logged when it differs from the last one. Unless ``wait``, status 'starting' (the
        unconstrained estimate goes out) while the solver process still builds its problem.
        The same equations as the last successful solve's (a frozen or reset estimate, saved
        again and again) give its result without a trip to the solver process, which a busy
        machine may keep waiting."""
        solver = self._solver_instance()
        with self._solver_lock:
            if (self.consistent is not None and self._solved_for is not None
                    and _same_equations(self._solved_for, equations)):
                return self.consistent
            if not wait and not solver.ready():
                return ConsistentEstimate('starting', None, None,
                                          np.full(self._base.num_base, np.inf), 0.0)
            result = self.consistent = solver.solve(*equations)
            self._solved_for = equations if result.ok else None
        if not result.ok and result.status != self._solver_failure and self._running:
            self._logger.warning(
                f'physically consistent solve: {result.status}; publishing the '
                'unconstrained estimate')
        self._solver_failure = '' if result.ok else result.status
        return result

    def stop(self) -> None:
        """End the thread and the solver process (a job in progress is not waited for)."""
        with self._job_ready:
            self._running = False
            self._job_ready.notify()
        if self._solver is not None:
            self._solver.close()   # not under the solver lock: a solve may be in flight
        self._thread.join(timeout=1.0)

    def _solver_instance(self) -> SolverProcess:
        with self._solver_lock:
            if self._solver is None:
                self._solver = SolverProcess.for_robot(self._robot, self._base, self.options)
                self._solver.start()
            return self._solver

    def _run(self) -> None:
        while True:
            with self._job_ready:
                while not self._jobs and self._running:
                    self._job_ready.wait()
                if not self._running:
                    return
                job = self._jobs.pop(0)
            try:
                outcome = self._handle(job)
            except Exception as exc:  # noqa: BLE001 - the worker must survive and report
                self._errors['estimate'] += 1
                self._logger.error('publishing the estimate failed: ' + ''.join(
                    traceback.format_exception(exc)), throttle_duration_sec=5.0)
                outcome = self._failure(f'estimate failed: {type(exc).__name__}: {exc}')
            self._answer(job.seq, outcome)


def _same_equations(a: tuple, b: tuple) -> bool:
    """Whether two (NormalEquations, weights) hold the same numbers."""
    return (np.array_equal(a[0].augmented, b[0].augmented)
            and np.array_equal(a[0].count, b[0].count) and np.array_equal(a[1], b[1]))
