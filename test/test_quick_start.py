"""The README's quick start: the node with the shipped config and the simulated arm, started
as the two ``ros2 run`` lines start them (the programs' entry points, real rclpy over DDS),
work together: the node converts the arm's currents and identifies it."""
import re
import subprocess
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray

from identification_node.cli import main
from identification_node.config import PARAMETERS
from ros_helpers import PYTHON, ROOT, Collector, diagnostic_values, wait_for

CONFIG = ROOT / 'config' / 'identification.yaml'
README = ROOT / 'README.md'
INSTALLED = 'install/identification_node/share/identification_node/config/identification.yaml'


def readme_ros2_run_lines():
    """The quick start's ``ros2 run`` commands (continuation lines joined), as argv lists."""
    text = README.read_text().split('## Quick start')[1].split('\n## ')[0]
    text = text.replace('\\\n', ' ')
    return [line.split() for line in text.splitlines() if line.strip().startswith('ros2 run')]


def program(argv, env):
    """``ros2 run identification_node PROGRAM ARGS...`` through the same entry point
    (programs.py); the installed config path replaced by the repository's."""
    _, _, package, name, *args = argv
    assert package == 'identification_node'
    args = [str(CONFIG) if a == INSTALLED else a for a in args]
    code = (f'import sys; from identification_node.programs import {name}; '
            f'sys.exit({name}())')
    return subprocess.Popen([PYTHON, '-c', code, *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.ros
def test_the_readme_quick_start_identifies_the_simulated_arm(ros):
    lines = readme_ros2_run_lines()
    assert [a[3] for a in lines] == ['identification_node', 'simulated_arm']
    diag = Collector(ros, DiagnosticArray, '/diagnostics')
    procs = [program(argv, ros.env()) for argv in lines]
    ros.procs += procs
    try:
        last = [{}]

        def status():
            found = [s for m in diag.snapshot() for s in m.status
                     if s.name.startswith('identification_node:')]
            last[0] = diagnostic_values(found[-1]) if found else {}
            done = (int(last[0].get('samples_used', 0)) >= 2000
                    and last[0].get('converged') == 'true')
            return last[0] if done or any(p.poll() is not None for p in procs) else None
        values = wait_for(status, 90.0, period=0.2)
        for p in procs:
            assert p.poll() is None, p.communicate()[1][-2000:]
        assert values is not None, f'not converged on 2000 samples in 90 s: {last[0]}'
        # nothing refused at the input (the robust gate may flag a few of the noise-free
        # samples once converged: rejected.outlier; on a busy machine, one topic's messages
        # from before the node heard the other's first: rejected.before_*). A message the
        # middleware lost or the node's queue dropped (the README's default QoS, a busy
        # machine) leaves its partner on the other topic alone: as many as the node counted
        # on that topic are allowed.
        lost = {k: int(values.get(f'lost_messages.{k}', 0))
                + int(values.get(f'dropped_messages.{k}', 0))
                for k in ('joint_states', 'motor_currents')}
        allowed = {'rejected.no_current': lost['motor_currents'],
                   'rejected.unmatched_current': lost['joint_states']}
        rejected = {k: v for k, v in values.items() if k.startswith('rejected.') and v != '0'
                    and k not in ('rejected.outlier', 'rejected.before_currents',
                                  'rejected.before_joint_states')
                    and int(v) > allowed.get(k, 0)}
        assert not rejected, (rejected, lost)
        assert int(values.get('rejected.outlier', 0)) < 0.05 * int(values['samples_used']), values
        assert values['converged'] == 'true' and float(values['condition_number']) < 1e8
    finally:
        diag.close()


def test_the_simulated_arms_section_of_the_config_matches_the_nodes():
    """The shipped config's simulated_arm section carries the node's arm, joints and torque
    sources: the currents it publishes are the ones the node converts."""
    import yaml
    doc = yaml.safe_load(CONFIG.read_text())
    node, sim = (doc[k]['ros__parameters'] for k in ('identification_node', 'simulated_arm'))
    shared = set(sim) - {'publish_currents', 'publish_effort'}
    assert shared == {'robot', 'joints', 'torque_source', 'kt', 'gear_ratio', 'pole_pairs',
                      'angle_offset', 'phase_order'}
    assert {k: sim[k] for k in shared} == {k: node[k] for k in shared}
    assert sim['publish_currents'] is True


@pytest.mark.parametrize('verb', ['node', 'sim'])
def test_node_and_sim_help_list_their_parameters(verb, capsys):
    from identification_node.ros.sim_node import SIM_PARAMETERS
    with pytest.raises(SystemExit) as exit_:
        main([verb, '--help'])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    table = PARAMETERS if verb == 'node' else SIM_PARAMETERS
    for name, (default, text) in table.items():
        m = re.search(rf'^  {re.escape(name)} \((.*)\)$\n((?:      .*\n)+)', out, re.M)
        assert m, name
        assert m.group(1) == repr(default)
        assert ' '.join(m.group(2).split()) == ' '.join(text.split())
    assert Path(PYTHON).exists()
