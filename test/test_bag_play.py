"""Every bundled bag through both paths: played over DDS (`play`, its own process) to a running
identification node (another process), and replayed offline; the two final estimates agree,
and both match the bag's true parameters."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from std_srvs.srv import Trigger

from identification_node.estimation.consistency import ConsistentSolver, pipeline_equations
from identification_node.replay.stream import identify_bag
from identification_node.settings import Settings, read_parameter_file
from ros_helpers import wait_for
from test_bags import BAGS, true_base_parameters
from test_node import reliable, remaps, start_node_process, stop_process

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize('bag', sorted(BAGS))
def test_bag_played_to_the_node_agrees_with_offline_replay(ros, bag, tmp_path):
    config = read_parameter_file(REPO / 'config' / BAGS[bag])
    settings = Settings.from_dict(config)
    offline = identify_bag(REPO / 'bags' / bag, settings, settings.load_robot())
    est = offline.pipeline.estimate()
    name = f'play_{bag}'
    # Reliable, and a queue deeper than the bag: a node stalled by a loaded machine must not
    # lose the messages that arrive meanwhile.
    params = dict(config, process_period=0.01, output_directory=str(tmp_path / 'out'),
                  **reliable(name, depth=50000))
    node = start_node_process(ros, name, params, tmp_path, remaps(name))

    def live_estimate():
        return json.loads(ros.call(Trigger, f'/{name}/get_estimate', Trigger.Request()).message)
    try:
        # The player exits only once the node acknowledged every message: a reliable
        # writer's unacknowledged tail dies with its process.
        play = subprocess.run(
            [sys.executable, '-m', 'identification_node', 'play', str(REPO / 'bags' / bag),
             '--rate', '2', '--topics', '/joint_states', '/motor_currents',
             '--wait-for-subscribers', '30', '--wait-for-all-acked', '30', '--ros-args',
             *sum((['-r', r] for r in remaps(name)), [])],
            cwd=REPO, env=ros.env(), capture_output=True, text=True, timeout=120)
        assert play.returncode == 0, play.stderr
        assert 'did not acknowledge' not in play.stderr, play.stderr
        # At the end of a live stream the node still holds the samples its smoother and the
        # current alignment wait for; offline replay flushes them. A node slowed by a loaded
        # machine is still taking its queue: wait for it.
        live = wait_for(lambda: (e := live_estimate())['num_samples'] >= est.num_samples - 5
                        and e['consistency_status'] != 'starting' and e, 90) or live_estimate()
    finally:
        log = stop_process(node)
    assert live['names'] == est.names
    # the node's log names what it rejected or lost, should the counts differ
    assert 0 <= est.num_samples - live['num_samples'] <= 5, log[-4000:]
    values, stddev = np.array(live['values']), np.array(live['stddev'])
    unconstrained = np.array(live['unconstrained_values'])
    # Those few samples aside, both saw the same data through the same pipeline ...
    assert np.all(np.abs(unconstrained - est.values) <= 0.2 * est.stddev), (
        (unconstrained - est.values) / est.stddev).round(3)
    np.testing.assert_allclose(stddev, est.stddev, rtol=0.05)
    # ... and the published, physically consistent estimate is the same solve offline
    assert live['consistency_status'] == 'optimal'
    consistent = ConsistentSolver.for_robot(offline.pipeline.robot, offline.pipeline.base,
                                            settings.consistency_options()).solve(
        *pipeline_equations(offline.pipeline))
    assert np.all(np.abs(values - consistent.theta) <= 0.2 * est.stddev), (
        (values - consistent.theta) / est.stddev).round(3)
    # the stddev is the data's estimate's (the consistent one may lie anywhere in their region)
    true = true_base_parameters(bag, est.names)
    assert np.all(np.abs(unconstrained - true) < 4 * stddev)
