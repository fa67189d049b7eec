"""The README's command for any arm, as a user runs it (issue 18's 'done when'):
``identify TRAIN --urdf ROBOT.urdf --validate HELDOUT`` and nothing else.

Two bags of a third-party 7-joint URDF (test/fixtures/panda_like.urdf) made by the
``simulate`` verb at 1 kHz: joint friction the URDF does not know, an 18-bit encoder,
0.01 rad/s velocity and 0.1 N m torque noise. The independent truths: the parameters the bags
were simulated with (true_parameters.yaml) and the torque noise, which sets the least error
any model can have against the raw torque, read from the bag with rosbags."""
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from identification_node.cli import main
from test_rate_sweep import FRICTION, URDF

TORQUE_STD = 0.1   # N m

pytestmark = pytest.mark.slow


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    path = tmp_path_factory.mktemp('user')
    truth = path / 'friction.yaml'
    truth.write_text(yaml.safe_dump({f'joint{i + 1}.{k}': v[i] for k, v in FRICTION.items()
                                     for i in range(7)}))
    out = {}
    for name, seed, duration in (('train', 1, 30), ('held', 2, 20)):
        out[name] = str(path / name)
        assert main(['simulate', '--urdf', URDF, '--trajectory', 'fourier', '--rate', '1000',
                     '--duration', str(duration), '--encoder-counts', '262144',
                     '--velocity-std', '0.01', '--torque-std', str(TORQUE_STD),
                     '--true-parameters', str(truth), '--seed', str(seed),
                     '--out', out[name]]) == 0
    return out


def raw_torque_norm(bag: str) -> tuple[float, int]:
    """||effort||_2 over all samples and joints of the bag's joint states, and the count."""
    efforts = []
    with AnyReader([Path(bag)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == '/joint_states']
        for conn, _, raw in reader.messages(connections=conns):
            efforts.append(reader.deserialize(raw, conn.msgtype).effort)
    return float(np.linalg.norm(efforts)), len(efforts)


def test_identify_urdf_validate_and_nothing_else_is_accurate_and_honest(bags, capsys):
    assert main(['identify', bags['train'], '--urdf', URDF, '--validate', bags['held'],
                 '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    # Accurate: on the held-out bag's raw torque, near the noise floor 100 sigma sqrt(N n) /
    # ||tau||. Predictions from the smoothed motion and the friction's sign at reversals keep
    # any fit above it: 1.18 x by default.
    (held,) = doc['validation']
    norm, count = raw_torque_norm(bags['held'])
    floor = 100 * TORQUE_STD * np.sqrt(count * 7) / norm
    assert floor < held['estimate']['stacked'] < 1.3 * floor, (held['estimate'], floor)
    # Honest: the errors against the simulated parameters are those of the reported stddev.
    truth = yaml.safe_load((Path(bags['train']) / 'true_parameters.yaml').read_text())
    rows = [b for b in doc['base_parameters'] if b['stddev']]
    z = np.array([(b['unconstrained_estimate'] - truth['base_parameters'][b['name']])
                  / b['stddev'] for b in rows])
    assert len(z) == len(doc['base_parameters']) and np.sqrt(np.mean(z ** 2)) < 1.5
    assert np.all(np.abs(z) < 4.5), dict(zip([b['name'] for b in rows], z.round(1)))
    # Consistent, converged, friction found, nothing to warn about.
    assert doc['physically_consistent'] and doc['converged'] and doc['warnings'] == []
    assert doc['smoother']['source'] == 'automatic'
    fv = {b['name']: b['estimate'] for b in doc['base_parameters']}['joint1.fv']
    assert fv == pytest.approx(FRICTION['fv'][0], rel=0.1)
