"""The bundled bags, offline identification from bags, and bad bags."""
import json
import shutil
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from identification_node.bags.writer import BagWriter
from identification_node.cli import main
from identification_node.estimation.consistency import ConsistentSolver, pipeline_equations
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.replay.stream import identify_bag
from identification_node.settings import Settings, read_parameter_file
from identification_node.wire.cdr import JOINT_STATE

REPO = Path(__file__).resolve().parents[1]
BAGS = {  # bag: config
    'mit_paper_moves': 'identification.yaml',
    'mit_exciting': 'identification.yaml',
    'mit_paper_moves_sqlite3': 'identification.yaml',
    'crs_a465_fourier': 'crs_a465.yaml',
}


def settings(config):
    return Settings.from_dict(read_parameter_file(REPO / 'config' / config))


def true_base_parameters(bag, names):
    """The base parameters ``names`` the bundled bag was simulated with."""
    truth = yaml.safe_load((REPO / 'bags' / bag / 'true_parameters.yaml').read_text())
    return np.array([truth['base_parameters'][n] for n in names])


@pytest.mark.parametrize('bag', sorted(BAGS))
def test_bundled_bag_identifies_its_true_parameters(bag):
    s = settings(BAGS[bag])
    result = identify_bag(REPO / 'bags' / bag, s, s.load_robot())
    p = result.pipeline
    est = p.estimate()
    true = true_base_parameters(bag, est.names)
    z = (est.values - true) / est.stddev
    # 15 to 48 parameters: 4 sigma each keeps the family-wise false alarm rate below 0.5 %.
    assert np.all(np.abs(z) < 4), dict(zip(est.names, z.round(2)))
    assert np.sqrt(np.mean(z ** 2)) < 2.0
    assert sum(p.rejected.values()) == 0
    assert est.converged
    assert len(result.history) >= 2 and result.history[-1].num_samples == est.num_samples


@pytest.mark.parametrize('bag', sorted(BAGS))
def test_bundled_bags_read_by_other_readers(bag):
    path = REPO / 'bags' / bag
    meta = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    counts = {t['topic_metadata']['name']: t['message_count']
              for t in meta['topics_with_message_count']}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == '/joint_states']
        n = 0
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            n += 1
        assert n == counts['/joint_states'] and len(msg.position) == len(msg.name)
    if meta['storage_identifier'] == 'mcap':
        with open(next(path.glob('*.mcap')), 'rb') as f:
            topics = [channel.topic for _, channel, _ in make_reader(f).iter_messages()]
        assert topics.count('/joint_states') == counts['/joint_states']


def test_identify_cli_json_matches_the_replay(capsys):
    bag = REPO / 'bags' / 'mit_paper_moves'
    assert main(['identify', str(bag), '--config', str(REPO / 'config' / 'identification.yaml'),
                 '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    s = settings('identification.yaml')
    pipeline = identify_bag(bag, s, s.load_robot()).pipeline
    est = pipeline.estimate()
    assert doc['joints'] == ['joint1', 'joint2', 'joint3']
    assert doc['num_samples'] == est.num_samples
    assert [b['name'] for b in doc['base_parameters']] == est.names
    np.testing.assert_allclose([b['unconstrained_estimate'] for b in doc['base_parameters']],
                               est.values)
    # the published estimate is the consistent solve's, solved here again on the replay's
    # equations (the prior chooses inside the data's confidence region, so it is not the
    # unconstrained estimate even where that is consistent)
    consistent = np.array([b['estimate'] for b in doc['base_parameters']])
    solved = ConsistentSolver.for_robot(pipeline.robot, pipeline.base,
                                        s.consistency_options()).solve(
        *pipeline_equations(pipeline))
    assert np.all(np.abs(consistent - solved.theta) < 1e-3 * est.stddev)
    for key in ('expression', 'terms', 'estimate', 'stddev'):
        assert key in doc['base_parameters'][0]
    assert set(doc['relative_error']) == set(doc['joints'])
    assert doc['condition_number'] > 1


def test_robot_comes_from_the_bag_when_not_given(capsys):
    # crs_a465_fourier carries /robot_description; the joint torque is measured (default).
    assert main(['identify', str(REPO / 'bags' / 'crs_a465_fourier'), '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['robot'] == 'crs_a465' and len(doc['joints']) == 6   # its <robot name>


def _write_bag(path, samples, storage='mcap', topic='/joint_states'):
    robot = load_robot('mit_dd_arm')
    t = np.arange(samples) / 1000.0
    sim = simulate_kinematic(robot, None, FourierTrajectory.random(robot, seed=1), t,
                             SensorNoise(torque_std=0.5), seed=1)
    with BagWriter(path, storage) as bag:
        bag.add_topic(topic, JOINT_STATE)
        for k in range(samples):
            ns = k * 1_000_000
            bag.write_joint_state(topic, ns, ns * 1e-9, robot.joint_names, sim.q_meas[k],
                                  sim.qd_meas[k], sim.tau_meas[k])
    return path


@pytest.mark.slow
def test_replay_memory_does_not_grow_with_the_bag(tmp_path):
    s = Settings.from_dict({'robot': 'mit_dd_arm'})
    robot = s.load_robot()
    peaks = []
    for samples in (10000, 40000):
        bag = _write_bag(tmp_path / f'b{samples}', samples)
        identify_bag(bag, s, robot)            # warm caches first
        tracemalloc.start()
        identify_bag(bag, s, robot)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    assert peaks[1] < 1.5 * peaks[0], peaks


def run_cli(*args):
    return subprocess.run([sys.executable, '-m', 'identification_node', *args],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.slow
def test_bad_bags_give_clear_errors(tmp_path):
    good = _write_bag(tmp_path / 'good', 2000)
    truncated = tmp_path / 'truncated'
    shutil.copytree(good, truncated)
    storage = next(truncated.glob('*.mcap'))
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    corrupt = tmp_path / 'corrupt'
    shutil.copytree(good, corrupt)
    next(corrupt.glob('*.mcap')).write_bytes(b'\x00garbage' * 100)
    empty = tmp_path / 'empty'
    empty.mkdir()
    other_topic = _write_bag(tmp_path / 'other', 100, topic='/arm/joint_states')
    wrong_type = tmp_path / 'wrong_type'
    with BagWriter(wrong_type) as bag:
        bag.write_string('/joint_states', 0, 'not a joint state')
    cases = {truncated: '', corrupt: '', empty: '', tmp_path / 'missing': '',
             other_topic: '/joint_states', wrong_type: 'JointState'}
    for bag, words in cases.items():
        out = run_cli('identify', str(bag), '--robot', 'mit_dd_arm')
        assert out.returncode == 2, (bag, out.stderr)
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith('error: '), out.stderr
        assert words in lines[0] and 'Traceback' not in out.stderr
    # The configuration wants motor currents the bag does not have.
    out = run_cli('identify', str(good), '--config', str(REPO / 'config' / 'identification.yaml'))
    assert out.returncode == 2 and "'/motor_currents' is not in bag" in out.stderr
    # Joint states without the measured torque: every sample rejected, and said so.
    no_effort = tmp_path / 'no_effort'
    with BagWriter(no_effort) as bag:
        for k in range(100):
            bag.write_joint_state('/joint_states', k * 10 ** 6, k * 1e-3,
                                  ['joint1', 'joint2', 'joint3'], [0.0, 0.1, 0.2])
    out = run_cli('identify', str(no_effort), '--robot', 'mit_dd_arm')
    assert out.returncode == 2 and 'no usable samples' in out.stderr
    assert 'missing_effort' in out.stderr
