"""Shared test configuration and fixtures.

Markers (setup.cfg): ``ros`` tests start ROS 2 nodes or processes, ``slow`` ones take over a
second of CPU; ``pytest -m "not ros and not slow"`` runs the ROS-free core, ``make test``
everything.

The ``ros`` marker is enforced: a test that uses the ``ros`` fixture (directly or through
another fixture) without the marker stops the collection, and a test without the marker that
initialises ROS anyway (rclpy in this process, or a node in a child process) fails.
"""
import os

import pytest

pytest_plugins = ('pytester',)   # test_markers runs pytest on small test files

# single-threaded BLAS (threads only spin on a 2-core machine); before numpy loads
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

# what a test without the ros marker sees as ROS_DOMAIN_ID: rcl refuses to initialise with it
NOT_A_DOMAIN = 'no-ros-marker'


def unmarked_ros_tests(items: list) -> list:
    """The node ids of the items that use the ``ros`` fixture but lack the ``ros`` marker."""
    return [item.nodeid for item in items
            if 'ros' in getattr(item, 'fixturenames', ())
            and item.get_closest_marker('ros') is None]


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Before ``-m`` deselects anything: refuse tests that use ROS without saying so."""
    unmarked = unmarked_ros_tests(items)
    if unmarked:
        raise pytest.UsageError(
            'tests using the ros fixture must carry @pytest.mark.ros (so that '
            '-m "not ros" leaves them out):\n  ' + '\n  '.join(unmarked))


def _refuse_ros(*args, **kwargs):
    pytest.fail('this test initialises ROS: mark it @pytest.mark.ros', pytrace=False)


@pytest.fixture(autouse=True)
def _ros_only_with_the_marker(request, monkeypatch):
    """Without the ``ros`` marker: rclpy contexts refuse to initialise, and child processes get
    a ROS_DOMAIN_ID that rcl refuses (a node started by the test exits with an error)."""
    if request.node.get_closest_marker('ros') is not None:
        yield
        return
    monkeypatch.setenv('ROS_DOMAIN_ID', NOT_A_DOMAIN)
    try:
        from rclpy.context import Context
    except ImportError:   # ROS not installed: nothing can start it
        pass
    else:
        monkeypatch.setattr(Context, 'init', _refuse_ros)
    yield


@pytest.fixture(scope='module')
def ros(request):
    """A RosHarness (context, client node, spinning executors) on the test module's own ROS
    domain, shut down after the module, which then fails if a callback raised."""
    from ros_helpers import RosHarness, domain_id
    harness = RosHarness(domain_id(request.module.__name__))
    yield harness
    harness.shutdown()
    harness.check()


@pytest.fixture(scope='module')
def mit():
    """The bundled MIT arm and its base parameters (modules wanting other MIT data override
    this fixture with their own)."""
    from identification_node.model.identifiability import BaseParameters
    from identification_node.model.robot import load_robot
    robot = load_robot('mit_dd_arm')
    return robot, BaseParameters.from_robot(robot)
