"""What the node watches in itself: callbacks that fail (counted per name for the
diagnostics' ``callback_errors`` and logged in one line, throttled, never raised) and, with
``use_sim_time``, a ROS clock that stands still."""
from __future__ import annotations

import collections
import functools
import traceback
from typing import Any, Callable

from rclpy.node import Node

__all__ = ['CallbackErrors', 'SimClockCheck']

THROTTLE = 5.0   # s between two log lines of one kind of failure


class CallbackErrors:
    """Failures of a node's callbacks, counted per name in ``counts`` and logged by
    ``logger``."""

    def __init__(self, logger: Any):
        self.counts: collections.Counter = collections.Counter()
        self._logger = logger

    def guarded(self, callback: Callable) -> Callable:
        """``callback`` (a timer's) that never raises: a failure is counted under its name
        and logged in one line."""
        name = callback.__name__.lstrip('_')

        @functools.wraps(callback)
        def guarded(*args: Any) -> Any:
            try:
                return callback(*args)
            except Exception as exc:   # noqa: BLE001 - counted and logged, never raised
                self.counts[name] += 1
                text = f'{name} failed: {type(exc).__name__}: {exc}'
                self._logger.error(text, throttle_duration_sec=THROTTLE)
                return None
        return guarded

    def service(self, name: str, exc: BaseException) -> None:
        """Service ``name``'s handler raised ``exc`` (ServiceThread's on_error)."""
        key = 'srv_' + name.lstrip('~/').replace('/', '_')
        self.counts[key] += 1
        self._logger.error(f'{key} failed: {type(exc).__name__}: {exc}',
                           throttle_duration_sec=THROTTLE)

    def processing(self, exc: BaseException) -> None:
        """A processing run raised ``exc``: logged with where."""
        self.counts['processing'] += 1
        where = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
        at = f' (at {where.filename}:{where.lineno})' if where else ''
        self._logger.error(f'processing failed: {type(exc).__name__}: {exc}{at}',
                           throttle_duration_sec=THROTTLE)


class SimClockCheck:
    """Warns once when ``node`` has use_sim_time on but ROS time has not advanced over three
    calls of ``check`` (one a second: nothing on /clock): the node's timers then stand
    still."""

    def __init__(self, node: Node):
        self.node = node
        self._ros_now = (-1, 0)     # (last ROS time seen, checks it stood still)

    def check(self) -> None:
        if not self.node.get_parameter('use_sim_time').value:
            self._ros_now = (-1, 0)
            return
        now = self.node.get_clock().now().nanoseconds
        still = self._ros_now[1] + 1 if now == self._ros_now[0] else 0
        self._ros_now = (now, still)
        if still == 3:
            self.node.get_logger().warning(
                'use_sim_time is true but ROS time has not advanced for 3 s (nothing on '
                '/clock?): the estimate, robot_description and diagnostics timers are stopped '
                'until it does; processing goes on')
