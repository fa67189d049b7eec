"""Start-up and offline checks (issue 16): degenerate URDFs, missing or broken parameter files,
a bag of an arm at rest, mimic joints, corrupt mcap chunks, poisoned samples in a bag. Each
gets a clear one-line error or a warning and a finite result, never a traceback."""
import json
import re
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from identification_node.bags.mcap_check import mcap_chunks, verify_chunks
from identification_node.bags.writer import BagWriter
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.estimation.prior import safe_prior
from identification_node.excitation.trajectories import FourierTrajectory
from identification_node.model.robot import BUNDLED_DIR, load_robot
from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
from identification_node.model.urdf_export import (consistency_problems, identified_urdf,
                                                   link_inertia)
from identification_node.pipeline import IdentificationPipeline, PipelineConfig

MIT_XML = (BUNDLED_DIR / 'mit_dd_arm.urdf').read_text()
ROBOT = load_robot('mit_dd_arm')


def run_cli(*args):
    return subprocess.run([sys.executable, '-m', 'identification_node', *args],
                          capture_output=True, text=True, timeout=300)


def one_line_error(out, code=2):
    lines = out.stderr.strip().splitlines()
    assert out.returncode == code, out.stderr
    assert 'Traceback' not in out.stderr and len(lines) == 1, out.stderr
    return lines[0]


def with_inertial(link, mass=None, inertia=None):
    """The MIT arm's URDF with ``link``'s mass and/or inertia replaced."""
    root = ET.fromstring(MIT_XML)
    el = next(x for x in root.iter('link') if x.get('name') == link).find('inertial')
    if mass is not None:
        el.find('mass').set('value', str(mass))
    if inertia is not None:
        el.find('inertia').attrib.update({k: str(v) for k, v in inertia.items()})
    return ET.tostring(root, encoding='unicode')


def write_bag(path, sim, robot=ROBOT, stamps=None):
    N = len(sim.t)
    stamps = 10**9 + np.arange(N) * 10**6 if stamps is None else stamps
    with BagWriter(path) as bag:
        bag.write_string('/robot_description', 0, robot.description)
        for k in range(N):
            bag.write_joint_state('/joint_states', int(stamps[k]), stamps[k] * 1e-9,
                                  robot.joint_names, sim.q_meas[k], sim.qd_meas[k],
                                  sim.tau_meas[k])
    return path


def simulate(duration=12.0, seed=3):
    traj = FourierTrajectory.random(ROBOT, harmonics=4, period=6.0, seed=seed)
    t = np.arange(int(duration * 1000)) / 1000.0
    return simulate_kinematic(ROBOT, None, traj, t, SensorNoise(torque_std=0.3), seed=seed)


@pytest.fixture(scope='module')
def good_bag(tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp('good') / 'bag', simulate())


# -- degenerate URDF priors ----------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize('mass, inertia, words', [
    (0.0, None, 'mass 0 kg is not positive'),
    (-2.0, None, 'mass -2 kg is not positive'),
    (float('nan'), None, 'not positive'),
    (None, {'ixx': 1.0, 'iyy': 1.0, 'izz': -3.0}, 'not positive definite'),
])
def test_degenerate_urdf_prior_warns_and_falls_back(good_bag, tmp_path, mass, inertia, words):
    xml = with_inertial('link2', mass, inertia)
    robot = load_robot(xml)
    phi, notes = safe_prior(robot)
    assert len(notes) == 1 and 'link2' in notes[0] and words in notes[0], notes
    assert not [p for p in consistency_problems(robot, phi) if 'triangle' not in p]
    assert np.isfinite(phi).all()
    m, c, Ic = link_inertia(phi[10:20])
    assert m > 0 and np.all(np.linalg.eigvalsh(Ic) > 0)
    if inertia is not None:    # the URDF's mass and centre of mass were fine: kept
        m0, c0, _ = link_inertia(robot.phi_model[10:20])
        assert m == m0 and np.allclose(c, c0) and np.any(c0), (m, c, m0, c0)
        assert 'kg at its centre of mass' in notes[0]
    np.testing.assert_array_equal(phi[:10], robot.phi_model[:10])   # good links kept
    # a pipeline on the good arm's data: the exported URDF is finite, masses plausible
    p = IdentificationPipeline(robot, PipelineConfig())
    assert p.prior_notes == notes
    sim = simulate(duration=8.0)
    from identification_node.wire.records import JointStateRecord
    stamps = 10**9 + np.arange(len(sim.t)) * 10**6
    p.add_joint_states(JointStateRecord(stamps, tuple(robot.joint_names), sim.q_meas,
                                        sim.qd_meas, sim.tau_meas))
    p.process(flush=True)
    out = identified_urdf(robot, p.standard_parameters())
    masses = [float(x.get('value')) for x in ET.fromstring(out.split('?>', 1)[1]).iter('mass')]
    assert all(np.isfinite(masses)) and max(abs(v) for v in masses) < 1e3, masses
    # identify says so on stderr, once, and still succeeds
    urdf = tmp_path / 'bad.urdf'
    urdf.write_text(xml)
    res = run_cli('identify', str(good_bag), '--urdf', str(urdf), '--json')
    assert res.returncode == 0, res.stderr
    assert re.search(r'^warning: degenerate model inertial.*link2', res.stderr, re.M)
    doc = json.loads(res.stdout)
    assert all(b['estimate'] is None or np.isfinite(b['estimate'])
               for b in doc['base_parameters'])


def test_bundled_robots_need_no_fallback():
    for name in ('mit_dd_arm', 'crs_a465'):
        assert safe_prior(load_robot(name))[1] == []


def test_urdf_without_movable_joints_is_refused(tmp_path):
    urdf = tmp_path / 'statue.urdf'
    urdf.write_text('<robot name="statue"><link name="base"/><link name="top"/>'
                    '<joint name="weld" type="fixed"><parent link="base"/>'
                    '<child link="top"/></joint></robot>')
    with pytest.raises(IdentificationError, match='no movable joints'):
        load_robot(str(urdf))
    line = one_line_error(run_cli('structure', '--urdf', str(urdf)))
    assert 'no movable joints' in line and str(urdf) in line


def test_mimic_joints_are_locked_by_default_and_refused_when_asked_for(tmp_path):
    root = ET.fromstring(MIT_XML)
    j3 = next(j for j in root.iter('joint') if j.get('name') == 'joint3')
    ET.SubElement(j3, 'mimic', joint='joint2', multiplier='1.0')
    xml = ET.tostring(root, encoding='unicode')
    # by default the mimic joint and the joint it follows are locked together
    assert load_robot(xml).joint_names == ['joint1']
    with pytest.raises(IdentificationError,
                       match=r"joint 'joint3' mimics 'joint2'.*\(joint2, joint3 asked for\).*"
                       r"joints: \[joint1\]"):
        load_robot(xml, ['joint1', 'joint2', 'joint3'])
    with pytest.raises(IdentificationError, match=r'joint2 asked for.*joints: \[joint1\]'):
        load_robot(xml, ['joint1', 'joint2'])


def test_training_bag_of_another_robot_is_refused(tmp_path, capsys):
    """identify UR5_BAG --urdf ur10.urdf: the bag's /robot_description is a UR5 (the same joint
    names, other kinematics), so it is refused as a validation bag of another robot is."""
    from arms import arm_urdf
    bag = str(tmp_path / 'ur5')
    assert main(['simulate', '--urdf', str(arm_urdf('ur5')), '--rate', '100', '--duration',
                 '3', '--out', bag]) == 0
    assert main(['identify', bag, '--urdf', str(arm_urdf('ur10'))]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f'error: training bag {bag}'), err
    assert 'another robot' in err and '(ur5)' in err and 'ur10' in err, err
    assert main(['identify', bag, '--urdf', str(arm_urdf('ur5')), '--json']) == 0


# -- parameter files -----------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize('content, words', [
    (None, 'cannot read parameter file'),
    ('identification_node:\n  ros__parameters:\n    robot: [1, {a: 2}\n', 'not valid YAML'),
    ('- just\n- a list\n', 'mapping'),
])
def test_bad_parameter_files_exit_2_naming_the_file(tmp_path, content, words):
    path = tmp_path / 'params.yaml'
    if content is not None:
        path.write_text(content)
    for args in (['node', '--ros-args', '--params-file', str(path)],
                 ['identify', 'nowhere', '--config', str(path)]):
        line = one_line_error(run_cli(*args))
        assert str(path) in line, line
        if args[0] == 'node':
            assert words in line, line


# -- an arm at rest ------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_bag_at_rest_is_reported_not_excited(tmp_path):
    N = 3000
    q = np.tile([0.3, -0.5, 0.8], (N, 1))
    tau = ROBOT.inverse_dynamics(q, 0 * q, 0 * q) + 0.1 * np.random.default_rng(0).normal(
        size=(N, 3))
    sim = type('Sim', (), {'t': np.arange(N) / 1e3, 'q_meas': q, 'qd_meas': 0 * q,
                           'tau_meas': tau})
    bag = write_bag(tmp_path / 'rest', sim)
    # no friction: at rest it is not determined (and with Coulomb friction every equation is
    # near a velocity reversal)
    text = run_cli('identify', str(bag), '--robot', 'mit_dd_arm', '--extras', 'none')
    assert text.returncode == 0 and 'Traceback' not in text.stderr, text.stderr
    assert 'not excited' in text.stdout and 'link1.IzzR' in text.stdout
    doc = json.loads(run_cli('identify', str(bag), '--robot', 'mit_dd_arm', '--extras', 'none',
                             '--json').stdout)
    assert doc['excited'] is False and doc['converged'] is False
    assert 'link1.IzzR' in doc['unexcited_directions']
    by_name = {b['name']: b for b in doc['base_parameters']}
    # no estimate where the data say nothing; gravity terms are excited at rest
    assert by_name['link1.IzzR']['estimate'] is None and not by_name['link1.IzzR']['excited']
    model = {b['name']: b['model'] for b in doc['base_parameters']}
    for name, b in by_name.items():
        if b['estimate'] is not None:
            assert abs(b['estimate']) < 10 * max(abs(model[name]), 1.0), (name, b)


# -- corrupt bags and poisoned samples ----------------------------------------------------------
@pytest.mark.slow
def test_bit_flips_in_mcap_chunks_are_errors_naming_it(good_bag, tmp_path):
    storage = next(good_bag.glob('*.mcap'))
    assert verify_chunks(storage) == 0           # our bags carry chunk CRCs
    data = storage.read_bytes()
    with open(storage, 'rb') as f:
        chunk = mcap_chunks(f)[0]
    rng = np.random.default_rng(5)
    start = chunk.chunk_start_offset + 80
    for trial in range(6):
        flipped = bytearray(data)
        at = int(rng.integers(start, chunk.chunk_start_offset + chunk.chunk_length))
        flipped[at] ^= 1 << int(rng.integers(8))
        bag = tmp_path / f'flip{trial}'
        bag.mkdir()
        (bag / 'metadata.yaml').write_bytes((good_bag / 'metadata.yaml').read_bytes())
        (bag / storage.name).write_bytes(bytes(flipped))
        line = one_line_error(run_cli('identify', str(bag), '--robot', 'mit_dd_arm'))
        assert re.search(r'chunk 0 \(at byte \d+.*\) is corrupt', line), line


@pytest.mark.slow
@pytest.mark.parametrize('value', [1e5, 1e100])
def test_one_absurd_sample_in_a_bag_changes_nothing(good_bag, tmp_path, value):
    sim = simulate()
    sim.qd_meas = sim.qd_meas.copy()
    sim.qd_meas[7000, 1] = value
    bag = write_bag(tmp_path / 'poisoned', sim)
    clean = json.loads(run_cli('identify', str(good_bag), '--json').stdout)
    res = run_cli('identify', str(bag), '--json')
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc['rejected'].get('implausible', 0) >= 1
    for a, b in zip(doc['base_parameters'], clean['base_parameters']):
        assert abs(a['estimate'] - b['estimate']) < 0.2 * b['stddev'], (a, b)


def test_a_numerical_failure_in_a_verb_is_one_line(monkeypatch, capsys, good_bag):
    import identification_node.cli.identify as identify

    def broken(args):
        raise np.linalg.LinAlgError('Eigenvalues did not converge')
    monkeypatch.setattr(identify, 'run', broken)
    assert main(['identify', str(good_bag)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'LinAlgError: Eigenvalues did not converge' in err[0]


def test_consistency_problems_on_non_finite_and_absurd_parameters():
    phi = ROBOT.phi_model.copy()
    phi[3], phi[14] = np.nan, 1e300
    problems = consistency_problems(ROBOT, phi)
    assert any('link1' in p and 'not finite' in p for p in problems)
    assert any(p.startswith('link2') for p in problems)
    phi = np.full(ROBOT.num_params, 1e308)
    assert len(consistency_problems(ROBOT, phi)) == 3


@pytest.mark.slow
def test_a_bag_without_chunk_crcs_is_read_with_a_warning(good_bag, tmp_path):
    import shutil
    import struct
    bag = tmp_path / 'no_crc'
    shutil.copytree(good_bag, bag)
    storage = next(bag.glob('*.mcap'))
    with open(storage, 'r+b') as f:
        chunks = mcap_chunks(f)
        for chunk in chunks:     # as the rosbags writer leaves them: 0, "not computed"
            f.seek(chunk.chunk_start_offset + 1 + 8 + 24)
            f.write(struct.pack('<I', 0))
    assert verify_chunks(storage) == len(chunks)
    out = run_cli('identify', str(bag), '--robot', 'mit_dd_arm', '--json')
    assert out.returncode == 0, out.stderr
    assert re.search(rf'warning: bag .*no_crc: {len(chunks)} mcap chunk\(s\) carry no CRC',
                     out.stderr)


class _Named:
    """The two name accessors of an rclpy node that given_parameter_names reads."""

    def __init__(self, name, namespace='/'):
        self.name, self.fqn = name, namespace.rstrip('/') + '/' + name

    def get_name(self):
        return self.name

    def get_fully_qualified_name(self):
        return self.fqn


def test_given_parameter_names_read_the_ros_arguments_as_rcl_does(tmp_path):
    """The node's sections of each --params-file (its name, its fully qualified name, /**) and
    the -p overrides after --ros-args; another node's section and program arguments are not
    the node's (a name left out could only hide a warning, never raise a false one)."""
    from identification_node.ros.spin import given_parameter_names
    f = tmp_path / 'params.yaml'
    f.write_text('/**:\n  ros__parameters: {use_sim_time: false}\n'
                 'arm/typo:\n  ros__parameters: {smoother: {cutof: 2.0}, robot: x}\n'
                 'other:\n  ros__parameters: {not_ours: 1}\n')
    args = ['prog', '-p', 'program_flag:=1', '--ros-args', '--params-file', str(f),
            '-p', 'forgeting_factor:=0.9', '--param', 'typo:kt:=[1.0]', '-r', '__node:=typo',
            '--', '-p', 'after:=1']
    names = given_parameter_names(args, _Named('typo', '/arm'))
    assert names == {'use_sim_time', 'smoother.cutof', 'robot', 'forgeting_factor', 'kt'}
    assert given_parameter_names(['prog'], _Named('typo')) == set()
