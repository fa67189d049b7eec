"""One bag on several cores (replay/parallel.py, ``identify --workers``): its segments, one per
worker and cut at the 10 s residual grid, streamed in worker processes and merged give the
serial run's estimate and stddev (robust gate off), or say how many samples the segments' gates
held back (gate on)."""
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from identification_node.cli import main
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import load_robot
from identification_node.replay.parallel import parallel_identify, segments
from identification_node.pipeline.rows import RowBuilder
from identification_node.replay.segments import BagSegment, balanced_segments, chosen_smoother
from identification_node.replay.stream import identify_bag, replay_identify
from identification_node.settings import Settings
from test_offline import simulate, write_bag

pytestmark = pytest.mark.slow
EXTRAS = ['fv', 'fc']
LONG = 200.0     # s at 100 Hz: twenty cells of the 10 s residual grid


@pytest.fixture(scope='module')
def robot():
    return load_robot('mit_dd_arm', extras=EXTRAS)


@pytest.fixture(scope='module')
def long_bag(tmp_path_factory, robot):
    t, q, qd, tau = simulate(robot, FourierTrajectory.random(robot, seed=5, period=10.0), LONG,
                             rate=100.0, seed=21)
    return write_bag(tmp_path_factory.mktemp('long') / 'long', robot, t, q, qd, tau)


def test_a_bag_is_split_evenly_wherever_its_log_starts():
    grid = 10 * 10**9
    start = 1_733_000_003_700_000_000           # a log time between grid multiples
    halves = balanced_segments(start, start + 100 * 10**9, 2)
    middle = start - 3_700_000_000 + 5 * grid   # the multiple nearest to 50 s in
    assert [(t.start_ns, t.stop_ns) for t in halves] == [(None, middle), (middle, None)]
    thirds = balanced_segments(start, start + 95 * 10**9, 3)
    lengths = np.diff([start] + [t.stop_ns for t in thirds[:-1]] + [start + 95 * 10**9])
    assert len(thirds) == 3 and lengths.max() - lengths.min() <= grid
    assert len(balanced_segments(start, start + 95 * 10**9, 1)) == 1
    # shorter than the grid between two multiples: one segment, nothing to cut at
    assert balanced_segments(start, start + 5 * 10**9, 4) == [BagSegment(None, None)]


def identify_json(bag, capsys, tmp_path, workers, robust):
    config = tmp_path / f'config_{robust}.yaml'
    config.write_text(yaml.safe_dump({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                                      'robust': {'enabled': robust}}))
    assert main(['identify', str(bag), '--config', str(config), '--workers', str(workers),
                 '--no-physical-consistency', '--json']) == 0
    return json.loads(capsys.readouterr().out)


def test_parallel_identify_equals_the_serial_run_with_the_gate_off(long_bag, robot, tmp_path,
                                                                   capsys):
    grid = 10 * 10**9
    assert [(t.start_ns, t.stop_ns) for t in segments(long_bag, 2)] == [
        (None, 10 * grid), (10 * grid, None)]       # as many segments as workers, equal
    eight = segments(long_bag, 8)    # cut at the multiples nearest to 25, 50, ... 175 s
    cuts = np.array([t.stop_ns for t in eight[:-1]])
    assert len(eight) == 8 and eight[-1].stop_ns is None and not np.any(cuts % grid)
    assert np.abs(cuts - LONG * 1e9 * np.arange(1, 8) / 8).max() <= grid / 2 + 2e7
    assert [t.start_ns for t in eight[1:]] == [t.stop_ns for t in eight[:-1]]
    serial = identify_json(long_bag, capsys, tmp_path, 1, False)
    parallel = identify_json(long_bag, capsys, tmp_path, 2, False)
    for key in ('unconstrained_estimate', 'stddev', 'noise_std'):
        a, b = serial[key], parallel[key]
        a, b = (list(a.values()), list(b.values())) if isinstance(a, dict) else (a, b)
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)
    assert parallel['num_samples'] == serial['num_samples']
    assert parallel['messages'] == serial['messages'] and not parallel['warnings']
    assert parallel['smoother'] == serial['smoother']


def test_the_serial_runs_warnings_come_out_of_the_merge_too(robot, tmp_path, capsys):
    """Torque 50 ms late against the motion and a torque offset the model has no column for:
    the time-offset check (on the stream's first 10 s: the first segment's) and the missing
    model term warn as in the serial run, and the equations left out per joint add up."""
    t, q, qd, tau = simulate(robot, FourierTrajectory.random(robot, seed=6, period=10.0), 60.0,
                             rate=100.0, seed=22)
    lag = 5   # samples at 100 Hz: the torque 0.05 s late
    bag = write_bag(tmp_path / 'late', robot, t[lag:], q[lag:], qd[lag:], tau[:-lag] + 0.5)
    serial = identify_json(bag, capsys, tmp_path, 1, False)
    parallel = identify_json(bag, capsys, tmp_path, 2, False)
    assert any(re.search(r'the torque is 0\.0(4[5-9]|5[0-5]) s late', w)
               for w in serial['warnings']), serial['warnings']
    assert any('torque offset (fo) missing?' in w for w in serial['warnings'])
    assert parallel['warnings'] == serial['warnings']
    assert parallel['excluded_equations'] == serial['excluded_equations']
    assert sum(serial['excluded_equations'].values()) > 0   # Coulomb: reversals left out


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


def test_the_smoother_is_chosen_without_rows_as_the_serial_run(long_bag, robot, monkeypatch):
    """The parent's read for the smoother (segments.chosen_smoother) stops once it is chosen
    and makes no rows of what it read (the estimate and the time-offset check are the
    segments' work), and chooses what the serial run does."""
    settings = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS})
    serial = identify_bag(long_bag, settings, robot).pipeline.smoother
    made = []
    call = RowBuilder.__call__

    def rows(self, *args, **kwargs):
        out = call(self, *args, **kwargs)
        made.append(len(out.t))
        return out
    monkeypatch.setattr(RowBuilder, '__call__', rows)
    choice = chosen_smoother(long_bag, settings, robot)
    assert choice is not None and choice.source == 'automatic'
    assert choice.document() == serial.document()
    assert made and not any(made)


def test_the_merged_counters_are_the_serial_runs(robot, tmp_path):
    """Messages rejected next to a cut (in both segments' margins) and undecodable ones are
    counted once, as the serial run counts them: each segment counts the messages stamped
    inside it, and an undecodable one by its log time."""
    from identification_node.bags.writer import BagWriter
    t, q, qd, tau = simulate(robot, FourierTrajectory.random(robot, seed=7, period=10.0), 40.0,
                             rate=100.0, seed=23)
    q[[500, 1997, 2002]] = np.nan                      # non-finite: far from the cut, next to it
    repeated = {1999, 2003}                            # written twice: a repeated stamp
    garbage = {1000, 1998, 2001}                       # undecodable messages before these
    bag = tmp_path / 'faults'
    with BagWriter(bag) as out:
        out.write_string('/robot_description', 0, robot.description)
        for k in range(len(t)):
            ns = int(round(t[k] * 1e9))
            if k in garbage:
                out.write_raw('/joint_states', ns, b'\x00\x01\x00\x00' + b'\xff' * 9)
            for _ in range(2 if k in repeated else 1):
                out.write_joint_state('/joint_states', ns, ns * 1e-9, robot.joint_names,
                                      q[k], qd[k], tau[k])
    settings = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                                   'robust': {'enabled': False}})
    assert [t.stop_ns for t in segments(bag, 2)] == [20 * 10**9, None]   # cut at 20 s
    serial = identify_bag(bag, settings, robot)
    parallel = parallel_identify(bag, settings, robot, 2)
    counted = {k: v for k, v in serial.pipeline.rejected.items() if v}
    assert counted == {'non_finite': 3, 'repeated_stamp': 2, 'malformed': 3}
    assert {k: v for k, v in parallel.rejected.items() if v} == counted
    assert parallel.messages == serial.messages == len(t) + 5
    assert parallel.pipeline.received == serial.pipeline.received == len(t) + 5
    assert parallel.num_samples == serial.pipeline.rls.num_samples


def test_joint_states_without_currents_next_to_a_cut_are_counted_once(tmp_path):
    """The currents of 60 ms around the cut dropped: the joint states there are rejected
    'no_current' once, as in the serial run, not again in the neighbouring segment's margin."""
    from identification_node.bags.reader import open_bag
    from identification_node.bags.writer import BagWriter
    from identification_node.replay.stream import bag_robot
    from identification_node.settings import read_parameter_file
    config = Path(__file__).resolve().parents[1] / 'config' / 'identification.yaml'
    assert main(['simulate', '--config', str(config), '--duration', '25', '--seed', '3',
                 '--out', str(tmp_path / 'sim')]) == 0
    cut = 10 * 10**9
    with open_bag(tmp_path / 'sim') as reader, BagWriter(tmp_path / 'gap') as out:
        for topic, msgtype in reader.topics.items():
            out.add_topic(topic, msgtype, latched=topic == '/robot_description')
        for topic, _, t_ns, raw in reader.raw_messages():
            if topic != '/motor_currents' or abs(t_ns - cut) > 30_000_000:
                out.write_raw(topic, t_ns, raw)
    settings = Settings.from_dict({**read_parameter_file(config), 'robust.enabled': False})
    robot = bag_robot(tmp_path / 'gap', settings)
    assert [t.stop_ns for t in segments(tmp_path / 'gap', 2)] == [cut, None]
    serial = identify_bag(tmp_path / 'gap', settings, robot).pipeline
    parallel = parallel_identify(tmp_path / 'gap', settings, robot, 2)
    counted = {k: v for k, v in serial.rejected.items() if v}
    assert set(counted) == {'no_current'} and 50 <= counted['no_current'] <= 62
    assert {k: v for k, v in parallel.rejected.items() if v} == counted
    assert parallel.pipeline.received == serial.received == 25001


def test_a_bag_stamped_by_a_simulators_clock_is_cut_in_its_stamps(robot, tmp_path):
    """Header stamps from 0 s (a simulator's clock) logged at wall-clock time: the segments
    are cut in the stamps, where the rows lie, so each worker gets half of them (cut in log
    time, one segment took them all); the merge equals the serial run. Fleet cuts alike."""
    from identification_node.bags.writer import BagWriter
    from identification_node.fleet import fleet
    t, q, qd, tau = simulate(robot, FourierTrajectory.random(robot, seed=8, period=10.0), 60.0,
                             rate=100.0, seed=24)
    wall = 1_733_000_000_123_000_000
    bag = tmp_path / 'sim_time'
    with BagWriter(bag) as out:
        out.write_string('/robot_description', wall, robot.description)
        for k in range(len(t)):
            ns = int(round(t[k] * 1e9))
            out.write_joint_state('/joint_states', wall + ns + 2_000_000, ns * 1e-9,
                                  robot.joint_names, q[k], qd[k], tau[k])
    grid = 10 * 10**9
    assert segments(bag, 2) == [BagSegment(None, 3 * grid), BagSegment(3 * grid, None)]
    settings = Settings.from_dict({'robot': 'mit_dd_arm', 'extras': EXTRAS,
                                   'robust': {'enabled': False}})
    serial = identify_bag(bag, settings, robot).pipeline
    parallel = parallel_identify(bag, settings, robot, 2)
    np.testing.assert_allclose(parallel.theta, serial.rls.theta, rtol=1e-9, atol=1e-12)
    first, whole = (c.num_samples for c in parallel.history)
    assert whole == serial.rls.num_samples and abs(first - whole / 2) < 0.01 * whole
    tasks = fleet.plan_tasks([fleet.FleetEntry(str(bag), 'arm', 'day1')], segment_seconds=20.0)
    assert [(k.start_ns, k.stop_ns) for k in tasks] == [
        (None, 2 * grid), (2 * grid, 4 * grid), (4 * grid, None)]
