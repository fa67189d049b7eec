"""Running a node in its own process: executor choice, SIGINT/SIGTERM, exit codes, and a
periodic thread for work that should not wait on the executor.

rclpy's own signal handlers do not stop the EventsExecutor of this rclpy (waking it from
another thread deadlocks, and its ``spin()`` starves timers), so processes here install their
own handlers and spin on the main thread in 0.1 s slices of ``spin_until_future_complete``
(many events per call: about half the per-message cost of ``spin_once``), checking for a
signal between slices.

A watchdog thread (:class:`Watchdog`) makes two promises a supervisor can rely on: SIGINT and
SIGTERM end the process within ``STOP_GRACE`` s whatever state it is in (even with the main
thread stuck in the middleware, where no Python signal handler runs: it learns of the signal
through ``signal.set_wakeup_fd``), and a node whose executor or processing thread stops making
progress for ``watchdog_timeout`` s logs it and exits with status 3 instead of hanging.
"""
from __future__ import annotations

import collections
import contextlib
import os
import re
import select
import signal
import socket
import sys
import threading
import time
from typing import Any, Callable, Iterable, Iterator

from identification_node.errors import IdentificationError


class StopSignals:
    """SIGINT/SIGTERM handler calling ``callback`` instead of raising KeyboardInterrupt; a
    signal that came before the callback was set calls it as soon as it is set."""

    def __init__(self) -> None:
        self.received = False
        self._callback: Callable[[], None] | None = None

    @property
    def callback(self) -> Callable[[], None] | None:
        return self._callback

    @callback.setter
    def callback(self, func: Callable[[], None] | None) -> None:
        self._callback = func
        if func is not None and self.received:
            func()

    def __call__(self, _sig: int, _frame: Any) -> None:
        self.received = True
        if self._callback is not None:
            self._callback()


@contextlib.contextmanager
def stop_signals() -> Iterator[StopSignals]:
    """StopSignals installed for SIGINT and SIGTERM while the block runs."""
    signals = StopSignals()
    handlers = {sig: signal.signal(sig, signals) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield signals
    finally:
        for sig, old in handlers.items():
            signal.signal(sig, old)


STOP_GRACE = 1.5     # s from SIGINT/SIGTERM to a forced exit when the shutdown hangs
STALLED_EXIT = 3     # exit status of a stalled node (the watchdog's)


class Watchdog:
    """A daemon thread watching ``beats`` (name: callable returning the monotonic time of
    that part's last progress): one older than ``timeout`` s (0: never) is a stall, logged
    by ``log`` and ended by ``os._exit(STALLED_EXIT)``. Once SIGINT/SIGTERM has come (told
    through the wakeup fd, which the C-level handler writes even while the main thread is
    blocked), the process is ended by ``os._exit(1)`` if it is still there ``grace`` s later.
    Create and ``close`` it on the main thread."""

    def __init__(self, timeout: float, beats: dict[str, Callable[[], float]],
                 log: Callable[[str], None], grace: float = STOP_GRACE) -> None:
        self.timeout, self.beats, self._log, self.grace = timeout, dict(beats), log, grace
        self.watching = True        # stall checks on (off for the shutdown)
        self._signalled: float | None = None
        self._stop = threading.Event()
        self._read, self._write = socket.socketpair()
        for sock in (self._read, self._write):
            sock.setblocking(False)
        self._old_fd = signal.set_wakeup_fd(self._write.fileno(), warn_on_full_buffer=False)
        self._thread = threading.Thread(target=self._run, name='watchdog', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._read], [], [], 0.1)
            now = time.monotonic()
            if ready:
                with contextlib.suppress(OSError):
                    self._read.recv(64)
                if self._signalled is None:
                    self._signalled = now
            if self._signalled is not None and now - self._signalled > self.grace:
                self._exit(1, f'shutdown did not finish within {self.grace} s of the signal; '
                           'exiting')
            if self.watching and self.timeout > 0 and self._signalled is None:
                for name, beat in self.beats.items():
                    idle = now - beat()
                    if idle > self.timeout:
                        self._exit(STALLED_EXIT, f'{name} made no progress for {idle:.1f} s '
                                   f'(watchdog_timeout {self.timeout} s): exiting with status '
                                   f'{STALLED_EXIT} so that a supervisor can restart the node')

    def _exit(self, code: int, text: str) -> None:
        with contextlib.suppress(Exception):
            print(f'[watchdog] {text}', file=sys.stderr, flush=True)
            self._log(text)
        os._exit(code)

    def close(self) -> None:
        """Stop watching (main thread; a pending forced exit after a signal stays armed until
        here)."""
        self._stop.set()
        self._thread.join()
        signal.set_wakeup_fd(self._old_fd)
        self._read.close()
        self._write.close()


def check_parameter_files(args: list[str] | None) -> None:
    """IdentificationError naming the file when a ``--params-file`` of the ROS arguments is
    missing, unreadable or not a YAML mapping (rcl's own message is a multi-line trace)."""
    from identification_node.safe_yaml import read_yaml
    args = list(args or [])
    for flag, path in zip(args, args[1:]):
        if flag != '--params-file':
            continue
        data = read_yaml(path, f'parameter file {path}', ros=True)
        if not isinstance(data, dict):
            raise IdentificationError(f'parameter file {path} does not hold a mapping of '
                                      'node names to ros__parameters')
        for node, section in data.items():
            if isinstance(section, dict) and not isinstance(
                    section.get('ros__parameters', {}), dict):
                raise IdentificationError(f'parameter file {path}: {node}.ros__parameters '
                                          'is not a mapping of parameter names to values')


def given_parameter_names(args: list[str] | None, node: Any) -> set[str]:
    """Names of the parameters the ROS arguments (``sys.argv`` when None) give ``node``:
    ``-p``/``--param NAME:=VALUE`` and, of each ``--params-file``, the sections for ``/**``,
    the node's name or its fully qualified name (other wildcard patterns are not read)."""
    from rclpy.parameter import parameter_dict_from_yaml_file

    from identification_node.safe_yaml import read_yaml
    args = list(sys.argv if args is None else args)
    keys = {'/**', node.get_name(), node.get_fully_qualified_name(),
            node.get_fully_qualified_name().lstrip('/')}
    names: set[str] = set()
    ros = False
    for flag, value in zip(args, args[1:] + ['']):
        ros = (flag == '--ros-args') or (ros and flag != '--')
        if not ros:
            continue
        if flag in ('-p', '--param') and ':=' in value:
            names.add(value.split(':=', 1)[0].rpartition(':')[2])
        elif flag == '--params-file':
            sections = [k for k in read_yaml(value, ros=True) if k in keys]
            for key in sections:
                names |= set(parameter_dict_from_yaml_file(value, target_nodes=[key]))
    return names


def warn_unknown_parameters(node: Any, given: Iterable[str]) -> list[str]:
    """Log a warning naming the parameters ``given`` to ``node`` (spin.given_parameter_names)
    that it never declared, typically misspelt ones, which rclpy otherwise drops silently;
    returns their names. Call once every parameter is declared."""
    unknown = sorted(name for name in set(given) if not node.has_parameter(name))
    if unknown:
        node.get_logger().warning('ignoring parameters this node does not have: '
                                  + ', '.join(unknown))
    return unknown


def _one_line(exc: BaseException) -> str:
    """An rcl error as one line (without its C source locations)."""
    text = ' '.join(str(exc).split())
    return re.sub(r',? at /\S+:\d+', '', text)


class PeriodicThread:
    """Calls ``func()`` every ``period`` seconds of wall-clock time on a daemon thread of its
    own, on a fixed schedule (a late call moves the schedule instead of bursting to catch up),
    until ``stop()`` or until ``alive()`` turns false. ``period`` may be a function, asked
    before each wait (a schedule that follows the node's state); ``wake()`` runs the next
    call at once. An exception from ``func`` goes to ``on_error`` and the schedule goes on.

    For periodic work that would otherwise be an executor timer: with the EventsExecutor every
    timer tick wakes two threads (its timer thread, then the executor), here one.
    """

    def __init__(self, period: float | Callable[[], float], func: Callable[[], None],
                 name: str, on_error: Callable[[BaseException], None],
                 alive: Callable[[], bool] = lambda: True) -> None:
        self._period = period if callable(period) else (lambda: float(period))
        self._func, self._on_error, self._alive = func, on_error, alive
        self._stop = False
        self._wake = threading.Event()
        self.beat = time.monotonic()    # last progress (monotonic s), for a Watchdog
        self.late = 0.0     # s the last call started after its time (0 when woken)
        self.started = time.monotonic()   # when the last call started (monotonic s)
        self.interval = 0.0   # s between the last two calls' starts
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def period(self) -> float:
        """The period the schedule follows now (s)."""
        return self._period()

    def wake(self) -> None:
        """Run the next call now instead of at its time (the schedule restarts from it)."""
        self._wake.set()

    def _run(self) -> None:
        due, period = time.monotonic(), 1.0   # 1 s while the period function fails at once
        while not self._stop:   # checked before the period, which may ask what stop tears down
            self.beat = time.monotonic()
            try:
                period = self._period()
            except Exception as exc:   # noqa: BLE001 - reported; the last period kept
                self._on_error(exc)
            due += period
            wait = due - time.monotonic()
            if wait < 0:
                due, wait = time.monotonic(), 0.0
            if self._wake.wait(wait):
                self._wake.clear()
                due = time.monotonic()
            if self._stop or not self._alive():
                return
            now = time.monotonic()
            self.late, self.interval, self.started = max(0.0, now - due), now - self.started, now
            try:
                self._func()
            except Exception as exc:   # noqa: BLE001 - reported, and the schedule goes on
                self._on_error(exc)

    def stop(self, timeout: float | None = None) -> bool:
        """Stop the schedule and wait for a call in progress to finish (``timeout``: at most
        that many s); whether it did."""
        self._stop = True
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)
        return not self._thread.is_alive() or self._thread is threading.current_thread()


class BudgetPeriod:
    """The longest processing period (s) that still publishes each output within ``budget``
    s of the moment it could first be computed, within [``shortest``, ``longest``]
    (``shortest`` until a run is known).

    A sample's output can be computed once the sample a smoother delay later has come in;
    that happens anywhere within a period, so its output waits up to one period P, the run's
    lateness to wake and its duration, and ``transport`` s on its way out. A run's duration
    grows with the messages it takes: for a period longer than the interval a run came
    after, taken as growing in proportion (its fixed cost scaled too: on the safe side). So
    each of the last ``runs`` runs (lateness l, duration d, after an interval I) allows
    P + l + d max(1, P / I) + transport <= budget; the period is the least of those bounds
    (budget 0: always ``shortest``).
    """

    def __init__(self, budget: float, shortest: float, longest: float,
                 transport: float = 2e-3, runs: int = 32) -> None:
        self.budget, self.shortest, self.longest = budget, shortest, max(shortest, longest)
        self.transport = transport
        self._bounds: collections.deque[float] = collections.deque(maxlen=runs)

    def add(self, late: float, duration: float, interval: float) -> None:
        """A processing run: s it started after its time, s it took, s since the run
        before it started (what it took in came in over that interval)."""
        room = self.budget - late - self.transport
        if interval > 0 and room >= interval + duration:
            self._bounds.append(room * interval / (interval + duration))
        else:
            self._bounds.append(room - duration)

    @property
    def period(self) -> float:
        """The period to wait now (s)."""
        if not self._bounds:
            return self.shortest
        return min(self.longest, max(self.shortest, min(self._bounds)))


def make_executor(polled: bool = False):
    """The EventsExecutor (about a third of the per-message cost), else the default one.
    ``polled``: for a node with PolledSubscriptions, rclpy's SingleThreadedExecutor, which
    honours callback groups (the EventsExecutor does not: it would dispatch them)."""
    import rclpy.executors
    if polled:
        return rclpy.executors.SingleThreadedExecutor()
    try:
        from rclpy.experimental import EventsExecutor
        return EventsExecutor()
    except ImportError:  # older rclpy
        return rclpy.executors.SingleThreadedExecutor()


def run_node(factory: Callable[[], Any], name: str, args: list[str] | None = None,
             done: Callable[[Any], bool] | None = None, linger: float = 0.0,
             polled: bool = False) -> int:
    """Create the node with ``factory`` and spin it until SIGINT/SIGTERM or ``done(node)``,
    then ``linger`` seconds more (``polled``: see make_executor). Returns the exit code: 0, or
    2 when the parameter files or the factory refuse (printed as one line). The node may
    offer ``watchdog_timeout`` (s) and ``heartbeats()`` (name: callable, see Watchdog)
    besides the executor's own."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from rclpy.task import Future

    with stop_signals() as signals:
        try:
            check_parameter_files(args)
            rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        except (IdentificationError, RuntimeError) as exc:
            print(f'{name}: error: {_one_line(exc)}', file=sys.stderr)
            return 2
        try:
            node = factory()
        except Exception as exc:   # noqa: BLE001 - one line, never a traceback
            from identification_node.error_lines import error_line
            print(f'{name}: error: {error_line(exc) or _one_line(exc)}', file=sys.stderr)
            rclpy.try_shutdown()
            return 2
        warn_unknown_parameters(node, given_parameter_names(args, node))
        executor = make_executor(polled)
        executor.add_node(node)
        never = Future()
        spun = [time.monotonic()]
        beats = {'the executor': lambda: spun[0]}
        beats.update(getattr(node, 'heartbeats', dict)())
        watchdog = Watchdog(float(getattr(node, 'watchdog_timeout', 0.0)), beats,
                            node.get_logger().fatal)
        try:
            while not signals.received and rclpy.ok() and not (done and done(node)):
                executor.spin_until_future_complete(never, timeout_sec=0.1)
                spun[0] = time.monotonic()
            end = time.monotonic() + linger
            while not signals.received and rclpy.ok() and time.monotonic() < end:
                executor.spin_until_future_complete(never, timeout_sec=0.05)
                spun[0] = time.monotonic()
        finally:
            watchdog.watching = False
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown()
            watchdog.close()
    return 0
