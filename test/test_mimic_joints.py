"""URDF <mimic> joints (issue 27): locked with the joint they follow, so that example-robot-data's
Panda with its hand identifies from nothing but its URDF and a bag of panda_joint1..7.

Independent truths: the same arm without the <mimic> tag, locked explicitly where the mimic
relation puts it; the parameters the bags were simulated with; the torque noise."""
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml

from arms import ARMS, arm_urdf
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.model.identifiability import sample_motion
from identification_node.model.robot import BUNDLED_DIR, load_robot
from test_user_command import raw_torque_norm

MIT_XML = (BUNDLED_DIR / 'mit_dd_arm.urdf').read_text()
PANDA_ARM = ARMS['panda'][1]
TORQUE_STD = 0.1    # N m


def with_mimic(multiplier: float, offset: float) -> str:
    root = ET.fromstring(MIT_XML)
    j3 = next(j for j in root.iter('joint') if j.get('name') == 'joint3')
    ET.SubElement(j3, 'mimic', joint='joint2', multiplier=str(multiplier), offset=str(offset))
    return ET.tostring(root, encoding='unicode')


def test_a_mimic_joint_is_locked_where_its_leader_puts_it():
    robot = load_robot(with_mimic(-2.0, 0.3), ['joint1'], locked_positions={'joint2': 0.4})
    plain = load_robot(MIT_XML, ['joint1'], locked_positions={'joint2': 0.4, 'joint3': -0.5})
    q, qd, qdd = sample_motion(robot, 30, seed=2)
    np.testing.assert_allclose(robot.inverse_dynamics(q, qd, qdd),
                               plain.inverse_dynamics(q, qd, qdd), rtol=1e-12, atol=1e-12)
    elsewhere = load_robot(MIT_XML, ['joint1'], locked_positions={'joint2': 0.4})
    assert not np.allclose(robot.inverse_dynamics(q, qd, qdd),
                           elsewhere.inverse_dynamics(q, qd, qdd))
    with pytest.raises(IdentificationError, match='mimic joints.*joint3'):
        load_robot(with_mimic(1.0, 0.0), ['joint1'], locked_positions={'joint3': 0.2})


def test_the_panda_with_its_hand_identifies_its_arm_joints_by_default():
    robot = load_robot(arm_urdf('panda'))
    assert robot.joint_names == PANDA_ARM
    assert robot.mimic_locked == ['panda_finger_joint1', 'panda_finger_joint2']
    with pytest.raises(IdentificationError) as err:
        load_robot(arm_urdf('panda'), PANDA_ARM + ['panda_finger_joint1'])
    suggested = str(err.value).split('joints: [')[1].split(']')[0].split(', ')
    assert suggested == PANDA_ARM


@pytest.fixture(scope='module')
def panda_bags(tmp_path_factory):
    """Training and held-out bags of the Panda with its hand (joints 1..7 only), simulated with
    its links 20 % off the URDF's and joint friction, 18-bit encoders and torque noise."""
    path = tmp_path_factory.mktemp('panda')
    robot = load_robot(arm_urdf('panda'), extras=['fv', 'fc', 'fo'])
    phi = robot.phi_model.copy()
    for i in range(robot.dof):     # a whole link scaled stays physically consistent
        phi[10 * i:10 * i + 10] *= (1.2, 0.8)[i % 2]
    truth = {name: float(v) for name, v in zip(robot.param_names, phi)}
    for i, joint in enumerate(robot.joint_names):
        truth[f'{joint}.fv'], truth[f'{joint}.fc'] = 0.3 - 0.03 * i, 0.4 - 0.04 * i
    (path / 'truth.yaml').write_text(yaml.safe_dump(truth))
    bags = {}
    for name, seed, duration in (('train', 1, 20), ('held', 2, 15)):
        bags[name] = str(path / name)
        assert main(['simulate', '--urdf', str(arm_urdf('panda')), '--joints',
                     ','.join(PANDA_ARM), '--duration', str(duration),
                     '--encoder-counts', '262144', '--velocity-std', '0.01',
                     '--torque-std', str(TORQUE_STD), '--true-parameters',
                     str(path / 'truth.yaml'), '--seed', str(seed), '--out', bags[name]]) == 0
    return bags


@pytest.mark.slow
def test_panda_with_hand_identifies_out_of_the_box(panda_bags, capsys):
    urdf = str(arm_urdf('panda'))
    assert main(['identify', panda_bags['train'], '--urdf', urdf,
                 '--validate', panda_bags['held'], '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['joints'] == PANDA_ARM and doc['physically_consistent']
    # Accurate on a different motion, against the raw torque: near the noise floor, far below
    # the URDF's own parameters.
    (held,) = doc['validation']
    norm, count = raw_torque_norm(panda_bags['held'])
    floor = 100 * TORQUE_STD * np.sqrt(count * 7) / norm
    assert held['estimate']['stacked'] < 1.3 * floor < 0.5 * held['model']['stacked'], (
        held['estimate']['stacked'], floor, held['model']['stacked'])
    # the bag lacks the fingers: locked with their leader, nothing to warn about
    assert not any('finger' in w for w in doc['warnings'])
    # asking for a finger names a joint list that the bag carries
    assert main(['identify', panda_bags['train'], '--urdf', urdf, '--joints',
                 ','.join(PANDA_ARM + ['panda_finger_joint1'])]) == 2
    line = capsys.readouterr().err.strip()
    assert 'mimic' in line and f"joints: [{', '.join(PANDA_ARM)}]" in line, line


def test_fingers_in_the_bag_are_named_as_locked(tmp_path):
    from identification_node.bags.writer import BagWriter
    from identification_node.replay.stream import mimic_warning
    from identification_node.wire.cdr import JOINT_STATE
    robot = load_robot(arm_urdf('panda'))
    for n in (7, 9):
        names = (PANDA_ARM + ['panda_finger_joint1', 'panda_finger_joint2'])[:n]
        with BagWriter(tmp_path / str(n), 'mcap') as bag:
            bag.add_topic('/joint_states', JOINT_STATE)
            bag.write_joint_state('/joint_states', 1, 1e-9, names, [0.0] * n, [0.0] * n,
                                  [0.0] * n)
    assert mimic_warning(robot, tmp_path / '7') is None
    text = mimic_warning(robot, tmp_path / '9')
    assert 'panda_finger_joint1, panda_finger_joint2' in text and 'locked' in text
