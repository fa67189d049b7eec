"""Running a node in its own process: executor choice, SIGINT/SIGTERM, exit codes, and a
periodic thread for work that should not wait on the executor.

rclpy's own signal handlers do not stop the EventsExecutor of this rclpy (waking it from
another thread deadlocks, and its ``spin()`` starves timers), so processes here install their
own handlers and spin on the main thread in 0.1 s slices of ``spin_until_future_complete``
(many events per call: about half the per-message cost of ``spin_once``), checking for a
signal between slices.
"""
from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time
from typing import Any, Callable, Iterator

from ..errors import IdentificationError


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


class PeriodicThread:
    """Calls ``func()`` every ``period`` seconds of wall-clock time on a daemon thread of its
    own, on a fixed schedule (a late call moves the schedule instead of bursting to catch up),
    until ``stop()`` or until ``alive()`` turns false. An exception from ``func`` goes to
    ``on_error`` and the schedule goes on.

    For periodic work that would otherwise be an executor timer: with the EventsExecutor every
    timer tick wakes two threads (its timer thread, then the executor), here one.
    """

    def __init__(self, period: float, func: Callable[[], None], name: str,
                 on_error: Callable[[BaseException], None],
                 alive: Callable[[], bool] = lambda: True) -> None:
        self.period, self._func, self._on_error, self._alive = period, func, on_error, alive
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        due = time.monotonic()
        while True:
            due += self.period
            wait = due - time.monotonic()
            if wait < 0:
                due, wait = time.monotonic(), 0.0
            if self._stop.wait(wait) or not self._alive():
                return
            try:
                self._func()
            except Exception as exc:   # noqa: BLE001 - reported, and the schedule goes on
                self._on_error(exc)

    def stop(self) -> None:
        """Stop the schedule and wait for a call in progress to finish."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()


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
    2 when the factory refuses its parameters (IdentificationError, printed as one line)."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from rclpy.task import Future

    with stop_signals() as signals:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        try:
            node = factory()
        except IdentificationError as exc:
            print(f'{name}: error: {exc}', file=sys.stderr)
            rclpy.try_shutdown()
            return 2
        executor = make_executor(polled)
        executor.add_node(node)
        never = Future()
        try:
            while not signals.received and rclpy.ok() and not (done and done(node)):
                executor.spin_until_future_complete(never, timeout_sec=0.1)
            end = time.monotonic() + linger
            while not signals.received and rclpy.ok() and time.monotonic() < end:
                executor.spin_until_future_complete(never, timeout_sec=0.05)
        finally:
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown()
    return 0
