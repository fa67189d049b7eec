"""The suite's ROS domains: two suites on one machine never share one (test/ros_helpers)."""
import os
import subprocess
import sys
from pathlib import Path

import ros_helpers

CHILD = """
import os, sys
sys.path.insert(0, {test!r})
os.getpid = lambda: 0
import ros_helpers
print(ros_helpers.domain_id('same_module'), flush=True)
sys.stdin.read()
"""


def test_a_domain_held_by_another_process_is_not_taken(monkeypatch):
    child = subprocess.Popen(
        [sys.executable, '-c', CHILD.format(test=str(Path(__file__).parent))],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        theirs = int(child.stdout.readline())
        monkeypatch.setattr(os, 'getpid', lambda: 0)   # the same first choice as the child's
        ours = ros_helpers.domain_id('same_module')
        try:
            assert 1 <= ours <= 100 and ours != theirs
        finally:
            ros_helpers.release_domain(ours)
    finally:
        child.kill()
        child.wait()
