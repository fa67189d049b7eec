"""One bag on several cores (replay/parallel.py, ``identify --workers``): its 60 s segments
streamed in worker processes and merged give the serial run's estimate and stddev (robust gate
off), or say how many samples the segments' gates held back (gate on)."""
import json

import numpy as np
import pytest
import yaml

from identification_node.cli import main
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import load_robot
from identification_node.replay.parallel import parallel_identify, segments
from identification_node.replay.stream import replay_identify
from identification_node.settings import Settings
from test_offline import simulate, write_bag

pytestmark = pytest.mark.slow
EXTRAS = ['fv', 'fc']
LONG = 200.0     # s at 100 Hz: four cells of the 60 s residual grid


@pytest.fixture(scope='module')
def robot():
    return load_robot('mit_dd_arm', extras=EXTRAS)


@pytest.fixture(scope='module')
def long_bag(tmp_path_factory, robot):
    t, q, qd, tau = simulate(robot, FourierTrajectory.random(robot, seed=5, period=10.0), LONG,
                             rate=100.0, seed=21)
    return write_bag(tmp_path_factory.mktemp('long') / 'long', robot, t, q, qd, tau)


def identify_json(bag, capsys, tmp_path, workers, robust):
    config = tmp_path / f'config_{robust}.yaml'
    config.write_text(yaml.safe_dump({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                                      'robust': {'enabled': robust}}))
    assert main(['identify', str(bag), '--config', str(config), '--workers', str(workers),
                 '--no-physical-consistency', '--json']) == 0
    return json.loads(capsys.readouterr().out)


def test_parallel_identify_equals_the_serial_run_with_the_gate_off(long_bag, robot, tmp_path,
                                                                   capsys):
    grid = 60 * 10**9
    assert [(t.start_ns, t.stop_ns) for t in segments(long_bag, 2)] == [
        (None, 2 * grid), (2 * grid, None)]       # as many segments as workers
    assert [(t.start_ns, t.stop_ns) for t in segments(long_bag, 8)] == [
        (None, grid), (grid, 2 * grid), (2 * grid, 3 * grid), (3 * grid, None)]
    serial = identify_json(long_bag, capsys, tmp_path, 1, False)
    parallel = identify_json(long_bag, capsys, tmp_path, 2, False)
    for key in ('unconstrained_estimate', 'stddev', 'noise_std'):
        a, b = serial[key], parallel[key]
        a, b = (list(a.values()), list(b.values())) if isinstance(a, dict) else (a, b)
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)
    assert parallel['num_samples'] == serial['num_samples']
    assert parallel['messages'] == serial['messages'] and not parallel['warnings']
    assert parallel['smoother'] == serial['smoother']


def test_the_gate_of_each_segment_is_reported(long_bag, robot):
    settings = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS})
    ident = parallel_identify(long_bag, settings, robot, 2)
    serial = replay_identify(long_bag, settings, robot)
    held = ident.rejected.get('outlier', 0)
    assert (held == 0) == (not ident.warnings)
    if held:
        assert f'held back {held} sample(s)' in ident.warnings[-1]
    # the segments' gates hold back a few samples of thousands: within a fraction of a sigma
    z = (ident.theta - serial.theta) / serial.stddev
    assert np.abs(z).max() < 0.5
    assert len(ident.history) == 2 and ident.history[-1].num_samples == ident.num_samples
    # one segment or forgetting: the serial run is needed
    assert parallel_identify(long_bag, settings, robot, 1) is None
    forgetting = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                                     'forgetting_factor': 0.999})
    assert parallel_identify(long_bag, forgetting, robot, 2) is None
