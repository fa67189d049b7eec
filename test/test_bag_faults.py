"""Faulty bags and robot descriptions (issue 31): a truncated sqlite3 bag and garbage
metadata.yaml are one line each, one corrupt message in a good bag is counted and skipped, a
description of another robot is reported, zero joint axes and degenerate frames are refused."""
import json
import shutil
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from identification_node.bags.reader import open_bag
from identification_node.bags.writer import BagWriter
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.model.robot import load_robot

ROOT = Path(__file__).resolve().parents[1]
SQLITE = ROOT / 'bags' / 'mit_paper_moves_sqlite3'
MCAP = ROOT / 'bags' / 'mit_paper_moves'
SIX = ROOT / 'test' / 'fixtures' / 'six_dof_arm.urdf'


def one_line(capsys, argv, *words):
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and 'Traceback' not in err, err
    for word in words:
        assert word in err, err
    return err


def rewrite(src: Path, dst: Path, insert: dict[int, bytes] = (),
            description: str | None = None):
    """A copy of bag ``src`` (mcap) with raw /joint_states messages ``insert``ed before the
    k-th one (k -> CDR bytes, same log time) and another /robot_description if given."""
    insert = dict(insert)
    with open_bag(src) as reader, BagWriter(dst) as out:
        for topic, msgtype in reader.topics.items():
            out.add_topic(topic, msgtype, latched=topic == '/robot_description')
        k = 0
        for topic, msgtype, t_ns, raw in reader.raw_messages():
            if topic == '/robot_description' and description is not None:
                out.write_string(topic, t_ns, description)
                continue
            if topic == '/joint_states':
                if k in insert:
                    out.write_raw(topic, t_ns, insert[k])
                k += 1
            out.write_raw(topic, t_ns, raw)
    return dst


# -- storage and metadata -----------------------------------------------------------------------
@pytest.mark.parametrize('fraction', [0.0, 0.02, 0.5, 0.999])
def test_a_truncated_sqlite3_bag_is_reported_as_sqlite3(tmp_path, capsys, fraction):
    bag = tmp_path / 'bag'
    shutil.copytree(SQLITE, bag)
    storage = next(bag.glob('*.db3'))
    data = storage.read_bytes()
    storage.write_bytes(data[:int(len(data) * fraction)])
    err = one_line(capsys, ['identify', bag, '--robot', 'mit_dd_arm'], str(bag))
    assert 'sqlite3' in err and 'mcap' not in err, err


@pytest.mark.parametrize('content, words', [
    (b'rosbag2_bagfile_information:\n  version: [9\n  x: }{\n', 'not valid YAML'),
    (bytes(range(256)) * 8, 'not UTF-8'),
    (b'- a list\n', 'no rosbag2_bagfile_information'),
    (b'rosbag2_bagfile_information: 3\n', 'no rosbag2_bagfile_information'),
    (b'rosbag2_bagfile_information:\n  starting_time: 2001-13-45\n', 'not valid YAML: month'),
    (b'rosbag2_bagfile_information:\n  version: ' + b'9' * 5000 + b'\n', 'not valid YAML')])
def test_garbage_metadata_is_one_line(tmp_path, capsys, content, words):
    bag = tmp_path / 'bag'
    shutil.copytree(MCAP, bag)
    (bag / 'metadata.yaml').write_bytes(content)
    one_line(capsys, ['identify', bag, '--robot', 'mit_dd_arm'], "bag '", 'metadata.yaml', words)


# -- one corrupt message ------------------------------------------------------------------------
@pytest.fixture(scope='module')
def measured_bag(tmp_path_factory):
    """4 s of the MIT arm with measured joint torque (no currents)."""
    out = tmp_path_factory.mktemp('faults') / 'clean'
    assert main(['simulate', '--robot', 'mit_dd_arm', '--duration', '4', '--torque-std', '0.05',
                 '--encoder-counts', '65536', '--seed', '5', '--out', str(out)]) == 0
    return out


def identify_json(capsys, bag, *more):
    code = main(['identify', str(bag), '--json', *map(str, more)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return json.loads(captured.out), captured.err


@pytest.mark.slow
def test_one_corrupt_message_is_counted_and_skipped(tmp_path, capsys, measured_bag):
    with open_bag(measured_bag) as reader:
        good = next(raw for topic, _, _, raw in reader.raw_messages(['/joint_states']))
    names_at = 20   # encapsulation 4, stamp 8, frame_id '' (length 4, 1 byte, pad 3)
    huge = good[:names_at] + struct.pack('<I', 2 ** 31) + good[names_at + 4:]
    bad = rewrite(measured_bag, tmp_path / 'bad', {1000: good[:len(good) // 2], 2500: huge})
    clean, _ = identify_json(capsys, measured_bag)
    doc, _ = identify_json(capsys, bad)
    assert doc['rejected'].get('malformed') == 2
    assert doc['num_samples'] == clean['num_samples']
    est, ref = (np.array(d['estimate'], dtype=float) for d in (doc, clean))
    sd = np.array(clean['stddev'], dtype=float)   # None (nan): not excited
    known = np.isfinite(sd)
    assert known.sum() >= len(sd) // 2
    assert np.all(np.abs(est - ref)[known] < 0.1 * sd[known] + 1e-12), (est - ref) / sd
    # the batch method reads the same way
    from identification_node.batch.samples import read_samples
    from identification_node.settings import Settings
    settings = Settings.from_dict({'robot': 'mit_dd_arm'})
    samples = read_samples(bad, settings, settings.load_robot())
    assert samples.rejected.get('malformed') == 2
    assert samples.num_samples == read_samples(measured_bag, settings,
                                               settings.load_robot()).num_samples


# -- a description of another robot --------------------------------------------------------------
@pytest.mark.slow
def test_a_description_of_another_robot_is_reported(tmp_path, capsys):
    six = tmp_path / 'six'
    assert main(['simulate', '--urdf', str(SIX), '--duration', '2', '--torque-std', '0.05',
                 '--out', str(six)]) == 0
    capsys.readouterr()
    bag = rewrite(six, tmp_path / 'mixed', description=load_robot('mit_dd_arm').description)
    code = main(['identify', str(bag), '--json'])
    out = capsys.readouterr()
    assert "carries 6 joints, 3 of them not in the description of mit_dd_arm" in out.err
    assert 'joint4, joint5, joint6' in out.err and 'another robot' in out.err
    if code == 0:
        assert any('another robot' in w for w in json.loads(out.out)['warnings'])
    # the bag's own description: nothing to say
    code = main(['identify', str(six), '--json'])
    assert 'another robot' not in capsys.readouterr().err


# -- joint axes and frames ----------------------------------------------------------------------
def _urdf(axis='0 0 1', xyz='0 0 0.1', rpy='0 0 0') -> str:
    return f'''<robot name="r"><link name="base"/>
<link name="l1"><inertial><mass value="1"/><origin xyz="0.1 0 0"/>
<inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
<link name="l2"><inertial><mass value="1"/><origin xyz="0.1 0 0"/>
<inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
<joint name="shoulder" type="revolute"><parent link="base"/><child link="l1"/>
<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
<joint name="elbow" type="revolute"><parent link="l1"/><child link="l2"/>
<origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{axis}"/>
<limit lower="-1" upper="1" effort="10" velocity="1"/></joint></robot>'''


@pytest.mark.parametrize('joint_type', ['revolute', 'prismatic'])
def test_a_zero_joint_axis_is_refused_naming_the_joint(joint_type):
    xml = _urdf(axis='0 0 0').replace('"elbow" type="revolute"', f'"elbow" type="{joint_type}"')
    with pytest.raises(IdentificationError, match="joint 'elbow' has a zero axis"):
        load_robot(xml)
    assert load_robot(_urdf(axis='0 0 2')).joint_names == ['shoulder', 'elbow']


@pytest.mark.parametrize('xyz', ['1e9 0 0', '0 0 -1e300'])
def test_a_degenerate_joint_frame_is_refused_naming_it(xyz, capsys, tmp_path):
    with pytest.raises(IdentificationError, match="frame of 'elbow' is degenerate"):
        load_robot(_urdf(xyz=xyz))
    path = tmp_path / 'r.urdf'
    path.write_text(_urdf(xyz=xyz))
    one_line(capsys, ['structure', '--urdf', path], "'elbow'", 'degenerate')


def test_the_arms_of_the_suite_pass_the_frame_checks():
    sys.path.insert(0, str(ROOT / 'test'))
    from arms import ARMS, arm_urdf
    for name, (_, joints) in ARMS.items():
        assert load_robot(arm_urdf(name), joints).dof >= 5
