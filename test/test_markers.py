"""The ``ros`` marker is enforced by conftest: a test using the ``ros`` fixture without it
stops the collection (before ``-m`` could leave it in the ROS-free core), and a test without
it cannot initialise ROS, in its own process or in a child."""
import subprocess
import sys
from pathlib import Path

import pytest

CONFTEST = (Path(__file__).parent / 'conftest.py').read_text()
INI = """
[pytest]
markers =
    ros: starts ROS
    slow: takes seconds
strict_markers = true
"""


@pytest.fixture
def tests(pytester):
    """A pytester directory with this suite's conftest and markers."""
    pytester.makeconftest(CONFTEST)
    pytester.makeini(INI)
    return pytester


def test_ros_fixture_without_the_marker_stops_the_collection(tests):
    tests.makepyfile(test_a="""
        import pytest

        @pytest.fixture
        def node(ros):
            return ros

        def test_plain():
            pass

        @pytest.mark.ros
        def test_marked(ros):
            pass

        def test_direct(ros):
            pass

        def test_through_a_fixture(node):
            pass
        """)
    result = tests.runpytest('-m', 'not ros and not slow', '-p', 'no:cacheprovider')
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    err = result.stderr.str()
    assert 'test_a.py::test_direct' in err and 'test_a.py::test_through_a_fixture' in err
    assert 'test_marked' not in err and 'test_plain' not in err


def test_marked_ros_tests_are_left_out_of_the_core(tests):
    tests.makepyfile(test_b="""
        import pytest

        @pytest.mark.ros
        def test_marked(ros):
            pass

        def test_plain():
            pass
        """)
    result = tests.runpytest('-m', 'not ros and not slow', '-p', 'no:cacheprovider')
    result.assert_outcomes(passed=1, deselected=1)


def test_rclpy_init_without_the_marker_fails(tests):
    pytest.importorskip('rclpy')
    tests.makepyfile(test_c="""
        import rclpy

        def test_init():
            rclpy.init(context=rclpy.Context(), domain_id=7)
        """)
    result = tests.runpytest('-p', 'no:cacheprovider')
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(['*initialises ROS: mark it @pytest.mark.ros*'])


def test_a_child_process_without_the_marker_cannot_start_ros():
    pytest.importorskip('rclpy')
    child = subprocess.run([sys.executable, '-c', 'import rclpy; rclpy.init()'],
                           capture_output=True, text=True, timeout=60)
    assert child.returncode != 0
    assert 'ROS_DOMAIN_ID' in child.stderr
