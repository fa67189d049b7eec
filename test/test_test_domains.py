"""The suite's ROS domains: two suites on one machine never share one (test/ros_helpers)."""
import subprocess
import sys
from pathlib import Path

import ros_helpers

CHILD = """
import sys
sys.path.insert(0, {test!r})
import ros_helpers
print(ros_helpers.domain_id('same_module'), flush=True)
sys.stdin.read()
"""


def start_child():
    """A process holding a domain of its own; (process, its domain)."""
    child = subprocess.Popen(
        [sys.executable, '-c', CHILD.format(test=str(Path(__file__).parent))],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    return child, int(child.stdout.readline())


def test_a_domain_held_by_another_process_is_not_taken():
    child, theirs = start_child()
    try:
        ours = ros_helpers.domain_id('same_module', first=theirs)
        ros_helpers.release_domain(ours)
        assert 1 <= ours <= 100 and ours != theirs
    finally:
        child.kill()
        child.wait()


def test_the_domain_of_a_process_that_ended_is_taken_over():
    child, theirs = start_child()
    child.kill()     # no release: its claim stays behind, naming a process that ended
    child.wait()
    assert (ros_helpers.DOMAIN_LOCKS / f'{theirs}.pid').exists()
    ours = ros_helpers.domain_id('same_module', first=theirs)
    ros_helpers.release_domain(ours)
    assert ours == theirs
    assert not (ros_helpers.DOMAIN_LOCKS / f'{theirs}.pid').exists()
