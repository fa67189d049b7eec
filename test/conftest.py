"""Shared test configuration and fixtures.

Markers (setup.cfg): ``ros`` tests start ROS 2 nodes or processes, ``slow`` ones take seconds
of CPU; ``pytest -m "not ros and not slow"`` runs the ROS-free core, ``make test`` everything.
"""
import os

import pytest

# single-threaded BLAS (threads only spin on a 2-core machine); before numpy loads
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')


@pytest.fixture(scope='module')
def ros(request):
    """A RosHarness (context, client node, spinning executors) on the test module's own ROS
    domain, shut down after the module."""
    from ros_helpers import RosHarness, domain_id
    harness = RosHarness(domain_id(request.module.__name__))
    yield harness
    harness.shutdown()


@pytest.fixture(scope='module')
def mit():
    """The bundled MIT arm and its base parameters (modules wanting other MIT data override
    this fixture with their own)."""
    from identification_node.model.identifiability import BaseParameters
    from identification_node.model.robot import load_robot
    robot = load_robot('mit_dd_arm')
    return robot, BaseParameters.from_robot(robot)
