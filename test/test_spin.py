"""PeriodicThread and BudgetPeriod: the node's processing schedule (no ROS needed)."""
import threading
import time

import pytest

from identification_node.ros.spin import BudgetPeriod, PeriodicThread
from ros_helpers import wait_for


def test_periodic_calls_until_stopped_then_none():
    calls = []
    thread = PeriodicThread(0.002, lambda: calls.append(1), 'test', on_error=print)
    assert wait_for(lambda: len(calls) >= 20, 10)
    thread.stop()
    stopped_at = len(calls)
    time.sleep(0.05)
    assert len(calls) == stopped_at


def test_errors_are_reported_and_the_schedule_goes_on():
    calls, errors = [], []

    def work():
        calls.append(1)
        if len(calls) % 2:
            raise ValueError(len(calls))
    thread = PeriodicThread(0.002, work, 'test', on_error=errors.append)
    assert wait_for(lambda: len(calls) >= 10, 10)
    thread.stop()
    assert errors and all(isinstance(e, ValueError) for e in errors)
    assert len(errors) in (len(calls) // 2, (len(calls) + 1) // 2)


def test_ends_by_itself_when_no_longer_alive():
    alive, calls = [True], []
    names = {t.name for t in threading.enumerate()}
    thread = PeriodicThread(0.002, lambda: calls.append(1), 'periodic-alive', on_error=print,
                            alive=lambda: alive[0])
    assert 'periodic-alive' not in names
    assert wait_for(lambda: len(calls) >= 3, 10)
    alive[0] = False
    assert wait_for(lambda: 'periodic-alive' not in {t.name for t in threading.enumerate()}, 10)
    thread.stop()    # no-op once ended


def test_wakes_at_once_and_follows_a_period_function():
    period, calls = [3600.0], []
    thread = PeriodicThread(lambda: period[0], lambda: calls.append(1), 'periodic-follow',
                            on_error=print)
    time.sleep(0.05)
    assert calls == [] and thread.period == 3600.0   # its first call is an hour away
    thread.wake()
    assert wait_for(lambda: len(calls) == 1, 10)
    time.sleep(0.05)
    assert len(calls) == 1                             # and the next one again
    period[0] = 0.002
    thread.wake()
    assert wait_for(lambda: len(calls) >= 10, 10)      # the new period followed
    period[0] = 3600.0
    thread.stop(10)   # at once, whatever its wait
    assert 'periodic-follow' not in {t.name for t in threading.enumerate()}


def test_a_failing_period_function_is_reported_and_the_last_period_kept():
    asked, calls, errors = [], [], []

    def period():
        asked.append(1)
        if len(asked) > 1:
            raise RuntimeError('publisher gone')
        return 0.002
    thread = PeriodicThread(period, lambda: calls.append(1), 'periodic-failing',
                            on_error=errors.append)
    assert wait_for(lambda: len(calls) >= 5, 10)
    thread.stop(10)
    assert errors and all(str(e) == 'publisher gone' for e in errors)


def test_budget_period_leaves_room_for_the_recent_runs():
    """Each run (lateness l, duration d, after an interval I) allows P + l + d max(1, P / I)
    + transport <= budget; the period is the least bound within [shortest, longest], the
    shortest until a run is known."""
    budget = BudgetPeriod(0.02, shortest=0.005, longest=0.1, transport=0.002, runs=4)
    assert budget.period == 0.005
    budget.add(0.001, 0.002, 0.01)       # room 0.017: P + 0.002 P / 0.01 = 0.017
    p = 0.017 / 1.2
    assert budget.period == pytest.approx(p)
    assert p + 0.001 + 0.002 * p / 0.01 + 0.002 == pytest.approx(0.02)
    budget.add(0.0, 0.012, 0.01)          # beyond its interval's room: P + 0.012 <= 0.018
    assert budget.period == pytest.approx(0.006)
    budget.add(0.0, 0.016, 0.01)          # no room at all: the shortest period
    assert budget.period == 0.005
    for _ in range(3):
        budget.add(0.001, 0.002, 0.01)
    assert budget.period == 0.005         # the long run is still among the last 4
    budget.add(0.001, 0.002, 0.01)
    assert budget.period == pytest.approx(p)
    wide = BudgetPeriod(1.0, shortest=0.01, longest=0.1)
    wide.add(0.0, 0.001, 0.01)
    assert wide.period == 0.1
