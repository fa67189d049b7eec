"""The console scripts as ``ros2 run`` starts them: ``--help`` prints help (and starts no
node), other arguments go to ROS; Ctrl-C (SIGINT to the whole process group, as a terminal
sends it) ends the node and its solver child without a traceback or a solver warning."""
import importlib
import os
import signal
import subprocess
import threading

import pytest

from ros_helpers import PYTHON, ROOT, Collector, wait_for
from test_package import console_scripts


@pytest.mark.parametrize('script', sorted(console_scripts()))
def test_help_prints_help_and_starts_nothing(script, capsys, monkeypatch):
    import rclpy
    monkeypatch.setattr(rclpy, 'init', lambda *a, **k: pytest.fail('--help started ROS'))
    module, func = console_scripts()[script].split(':')
    with pytest.raises(SystemExit) as exit_:
        getattr(importlib.import_module(module), func)(['--help'])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith('usage: ')
    if script != 'identification_cli':
        assert out.startswith(f'usage: ros2 run identification_node {script}')


def test_node_help_lists_its_parameters(capsys):
    from identification_node.programs import identification_node
    from identification_node.config import PARAMETERS
    with pytest.raises(SystemExit):
        identification_node(['--help'])
    out = capsys.readouterr().out
    assert all(f'  {name} (' in out for name in PARAMETERS)


def test_ros_arguments_reach_the_node(monkeypatch):
    """What follows the script name goes to rclpy unchanged (launch_ros's --ros-args)."""
    import identification_node.ros.node as node
    seen = []
    monkeypatch.setattr(node, 'main', lambda args: seen.append(args) or 0)
    from identification_node.programs import identification_node
    ros = ['--ros-args', '-r', '__node:=arm_id', '--params-file', 'f.yaml', '-p', 'a:=1']
    assert identification_node(ros) == 0
    assert seen == [['identification_node', *ros]]


def _interrupt(tmp_path, ros, ready) -> subprocess.CompletedProcess:
    """Start the node on the bundled arm in a process group of its own, wait for ``ready``,
    and send SIGINT to the group."""
    proc = subprocess.Popen(
        [PYTHON, '-m', 'identification_node', 'node', '--ros-args', '--params-file',
         str(ROOT / 'config' / 'identification.yaml')], cwd=tmp_path, env=ros.env(),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    try:
        assert wait_for(lambda: ready(lines) or proc.poll() is not None, 120), ''.join(lines)
        assert proc.poll() is None, ''.join(lines)
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    reader.join(10)
    with pytest.raises(ProcessLookupError):   # the solver child is gone too
        wait_for(lambda: os.killpg(proc.pid, 0), 10)
        os.killpg(proc.pid, 0)
    return subprocess.CompletedProcess(proc.args, proc.returncode, '', ''.join(lines))


@pytest.mark.ros
def test_ctrl_c_while_the_solver_starts(ros, tmp_path):
    """SIGINT right after start-up, while the solver child imports cvxpy."""
    done = _interrupt(tmp_path, ros, lambda lines: any('identifying' in s for s in lines))
    assert done.returncode == 0, done.stderr
    assert 'Traceback' not in done.stderr and 'solver process ended' not in done.stderr
    assert 'KeyboardInterrupt' not in done.stderr


@pytest.mark.ros
def test_ctrl_c_with_the_solver_running(ros, tmp_path):
    """SIGINT once the node has published a solved estimate."""
    from std_msgs.msg import Float64MultiArray
    params = Collector(ros, Float64MultiArray, '/identification_node/base_parameters')
    done = _interrupt(tmp_path, ros, lambda lines: len(params) > 0)
    params.close()
    assert done.returncode == 0, done.stderr
    assert 'Traceback' not in done.stderr and 'solver process ended' not in done.stderr
    assert 'KeyboardInterrupt' not in done.stderr
