"""``python -m identification_node structure``: output checked against the MIT arm paper."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from identification_node.cli import main

ROOT = Path(__file__).resolve().parents[1]
PANDA = str(ROOT / 'test' / 'fixtures' / 'panda_like.urdf')
LINK_PARAMS = ['m', 'mx', 'my', 'mz', 'Ixx', 'Ixy', 'Ixz', 'Iyy', 'Iyz', 'Izz']
# An, Atkeson, Hollerbach (1986) Table 3 (l2 = 0.45 m): combination, CAD value (the second is
# a typo in the paper: Table 1 gives -0.2735).
TABLE3 = [
    ({'link2.Iyz': 1.0, 'link3.mz': 0.45}, -1.3565),
    ({'link3.Ixx': 1.0, 'link3.Iyy': -1.0}, -0.2735),
    ({'link2.Izz': 1.0, 'link3.Ixx': 1.0}, 0.8632),
    ({'link1.Izz': 1.0, 'link2.Ixx': 1.0, 'link3.Ixx': 1.0, 'link3.m': 0.2025}, 12.8169),
    ({'link2.Ixx': 1.0, 'link2.Iyy': -1.0, 'link3.Ixx': 1.0}, 0.4147),
    ({'link3.mz': 1.0, 'link2.my': -1.0}, -3.0814),
]
KEYS = {'robot', 'joints', 'parameters', 'num_params', 'num_base', 'identifiable',
        'unidentifiable', 'combined', 'base_parameters'}


def run_json(capsys, *argv):
    assert main(['structure', *argv, '--json']) == 0
    out = capsys.readouterr().out
    return json.loads(out)


def check_mit(doc):
    assert set(doc) == KEYS
    assert doc['robot'] == 'mit_dd_arm' and doc['joints'] == ['joint1', 'joint2', 'joint3']
    assert doc['parameters'] == [f'link{i}.{p}' for i in (1, 2, 3) for p in LINK_PARAMS]
    assert (doc['num_params'], doc['num_base']) == (30, 15)
    assert len(doc['base_parameters']) == 15
    assert (len(doc['identifiable']), len(doc['unidentifiable']), len(doc['combined'])) == \
        (9, 11, 10)
    assert set(doc['unidentifiable']) == {f'link1.{p}' for p in LINK_PARAMS[:-1]} | {
        'link2.m', 'link2.mz'}
    # every Table 3 combination is a combination of the printed base parameters, and its
    # value follows from the printed values
    names = doc['parameters']
    K = np.zeros((15, 30))
    for k, b in enumerate(doc['base_parameters']):
        for name, c in b['terms'].items():
            K[k, names.index(name)] = c
    values = np.array([b['value'] for b in doc['base_parameters']])
    for terms, cad in TABLE3:
        c = np.array([terms.get(n, 0.0) for n in names])
        x, *_ = np.linalg.lstsq(K.T, c, rcond=None)
        np.testing.assert_allclose(K.T @ x, c, atol=1e-9)
        assert x @ values == pytest.approx(cad, abs=1e-3), terms
    expressions = {b['expression'] for b in doc['base_parameters']}
    assert {'link2.Iyz + 0.45 link3.mz', 'link3.Ixx - link3.Iyy'} <= expressions


def test_json_in_process(capsys):
    check_mit(run_json(capsys, '--robot', 'mit_dd_arm'))


def test_json_subprocess():
    result = subprocess.run(
        [sys.executable, '-m', 'identification_node', 'structure', '--robot', 'mit_dd_arm',
         '--json'], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    check_mit(json.loads(result.stdout))


def test_table(capsys):
    assert main(['structure', '--robot', 'mit_dd_arm']) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert 'mit_dd_arm' in lines[0]
    assert any(line.startswith('identifiable alone (9)') for line in lines)
    assert any(line.startswith('unidentifiable') and '(11)' in line for line in lines)
    assert any(line.startswith('identifiable only in linear combinations (10)')
               for line in lines)
    rows = [line for line in lines if line.startswith('  ') and line.split()[0].isdigit()]
    assert len(rows) == 15
    table = {r.split()[1]: r.split()[2:] for r in rows}
    assert table['link2.IyzR'] == ['-1.35654', 'kg', 'm^2', 'link2.Iyz', '+', '0.45', 'link3.mz']
    assert table['link3.mx'] == ['0.3108', 'kg', 'm', 'link3.mx']
    assert table['link3.IxxR'][0] == '-0.2735'
    # the value column is right-aligned
    assert len({len(r.split('kg')[0].rstrip()) for r in rows}) == 1


def test_urdf_joints_and_extras(capsys):
    doc = run_json(capsys, '--urdf', PANDA, '--joints', 'joint2,joint1', '--extras', 'fv,Ia')
    assert doc['joints'] == ['joint2', 'joint1']
    assert doc['parameters'][:2] == ['link2.m', 'link2.mx']
    assert doc['parameters'][-4:] == ['joint2.fv', 'joint2.Ia', 'joint1.fv', 'joint1.Ia']
    assert doc['num_params'] == 24
    assert main(['structure', '--robot', 'crs_a465', '--extras', 'fv', '--samples', '80',
                 '--seed', '3']) == 0
    out = capsys.readouterr().out
    assert '60 + 6' not in out and '66 standard parameters, 42 base parameters' in out
    assert 'N m s/rad' in out


def _error(capsys, argv):
    code = main(['structure', *argv])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith('error: ') and 'Traceback' not in err
    return err


def test_user_errors(capsys, tmp_path):
    assert 'nosuch_robot' in _error(capsys, ['--robot', 'nosuch_robot'])
    broken = tmp_path / 'broken.urdf'
    broken.write_text('<robot name="broken"><link name="a"><joint name="j"')
    assert 'does not parse' in _error(capsys, ['--urdf', str(broken)])
    assert 'joint9' in _error(capsys, ['--robot', 'mit_dd_arm', '--joints', 'joint1,joint9'])
    assert '--samples' in _error(capsys, ['--robot', 'mit_dd_arm', '--samples', '0'])
    assert 'more samples' in _error(capsys, ['--robot', 'crs_a465', '--samples', '2'])
