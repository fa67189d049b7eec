"""Settings, identified URDF export with consistency checks, saved results, atomic files."""
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from identification_node.errors import IdentificationError
from identification_node.fileio import atomic_write_text
from identification_node.model.robot import load_robot
from identification_node.model.urdf_export import (consistency_problems, identified_urdf,
                                                   link_inertia)
from identification_node.results.documents import save_results
from identification_node.settings import Settings, read_parameter_file

REPO = Path(__file__).resolve().parents[1]
SIX_DOF = str(REPO / 'test' / 'fixtures' / 'six_dof_arm.urdf')


# -- identified URDF ---------------------------------------------------------------------------
@pytest.mark.parametrize('robot_name', ['mit_dd_arm', 'crs_a465', SIX_DOF])
def test_identified_urdf_round_trips_the_parameters(robot_name):
    robot = load_robot(robot_name)
    rng = np.random.default_rng(3)
    phi = robot.phi_model * (1 + 0.05 * rng.standard_normal(robot.num_params))
    back = load_robot(identified_urdf(robot, phi, note='test'), robot.joint_names)
    np.testing.assert_allclose(back.phi_model, phi, rtol=1e-7, atol=1e-9)


def test_identified_urdf_carries_friction():
    """fv and fc in each joint's <dynamics damping friction>, read back by pinocchio's URDF
    parser (urdfdom); fo and Ia, which a URDF cannot hold, named in a comment."""
    import pinocchio as pin
    robot = load_robot('crs_a465', extras=['fv', 'fc', 'fo', 'Ia'])
    phi = robot.phi_model.copy()
    values = np.arange(1.0, 1.0 + 4 * robot.dof).reshape(robot.dof, 4) / 10   # fv fc fo Ia
    phi[robot.n_inertial:] = values.ravel()
    xml = identified_urdf(robot, phi, note='test')
    model = pin.buildModelFromXML(xml)
    ids = [model.getJointId(j) for j in robot.joint_names]
    v = [model.joints[i].idx_v for i in ids]
    np.testing.assert_allclose(np.asarray(model.damping)[v], values[:, 0], rtol=1e-8)
    np.testing.assert_allclose(np.asarray(model.friction)[v], values[:, 1], rtol=1e-8)
    comment = xml.split('<!--')[1].split('-->')[0]
    assert 'test' in comment and 'fo' in comment and 'Ia' in comment
    # without friction columns the description's own <dynamics> stays
    plain = load_robot('crs_a465')
    assert identified_urdf(plain, plain.phi_model).count('damping=') == \
        plain.description.count('damping=')


@pytest.mark.slow
def test_identify_save_writes_the_identified_friction(tmp_path, capsys):
    """identify --save on the bundled CRS bag: the exported URDF's joint damping and friction
    are the friction the bag was simulated with (bags/crs_a465_friction.yaml)."""
    import pinocchio as pin
    from identification_node.cli import main
    assert main(['identify', str(REPO / 'bags' / 'crs_a465_fourier'), '--config',
                 str(REPO / 'config' / 'crs_a465.yaml'), '--save', str(tmp_path)]) == 0
    truth = yaml.safe_load((REPO / 'bags' / 'crs_a465_friction.yaml').read_text())
    model = pin.buildModelFromUrdf(str(tmp_path / 'identified.urdf'))
    for j in range(1, 7):
        k = model.joints[model.getJointId(f'joint{j}')].idx_v
        assert model.damping[k] == pytest.approx(truth[f'joint{j}.fv'], rel=0.2, abs=0.01)
        assert model.friction[k] == pytest.approx(truth[f'joint{j}.fc'], rel=0.2, abs=0.01)


def test_merged_bodies_lose_their_own_inertials():
    # The fixture hangs links on fixed joints; pinocchio merges them into the moving links,
    # so writing the merged values back must not count them twice.
    robot = load_robot(SIX_DOF)
    xml = identified_urdf(robot, robot.phi_model)
    assert load_robot(xml).phi_model == pytest.approx(robot.phi_model, rel=1e-8, abs=1e-10)
    assert xml.count('<inertial>') <= robot.dof + 1


def test_link_inertia_is_the_parallel_axis_theorem():
    m, c = 2.0, np.array([0.1, -0.2, 0.3])
    Ic = np.array([[0.5, 0.01, 0.02], [0.01, 0.4, 0.03], [0.02, 0.03, 0.3]])
    Io = Ic + m * (c @ c * np.eye(3) - np.outer(c, c))
    phi = np.array([m, *(m * c), Io[0, 0], Io[0, 1], Io[0, 2], Io[1, 1], Io[1, 2], Io[2, 2]])
    m2, c2, Ic2 = link_inertia(phi)
    assert m2 == m
    np.testing.assert_allclose(c2, c)
    np.testing.assert_allclose(Ic2, Ic, atol=1e-12)


def test_consistency_problems():
    mit = load_robot('mit_dd_arm')
    # Table 1's link 1 violates the triangle inequality (principal moments 0.62, 1.33, 3.98).
    problems = consistency_problems(mit, mit.phi_model)
    assert len(problems) == 1 and 'link1' in problems[0] and 'triangle' in problems[0]
    # plain text, as the node's diagnostics carry it (no numpy brackets)
    assert 'principal moments 0.6239, 1.328, 3.979 kg m^2' in problems[0], problems
    crs = load_robot('crs_a465', extras=('fv', 'Ia'))
    assert consistency_problems(crs, crs.phi_model) == []
    phi = crs.phi_model.copy()
    phi[crs.param_index('link2.m')] = -1.0
    phi[crs.param_index('link3.Izz')] = -5.0
    phi[crs.param_index('joint4.fv')] = -0.1
    text = ' '.join(consistency_problems(crs, phi))
    assert 'link2: mass' in text and 'link3' in text and 'joint4.fv' in text


# -- settings ----------------------------------------------------------------------------------
def test_bundled_configs_build_pipelines():
    for name, dof, needs_currents in (('identification.yaml', 3, True),
                                      ('crs_a465.yaml', 6, False)):
        settings = Settings.from_dict(read_parameter_file(REPO / 'config' / name))
        pipeline = settings.build()
        assert pipeline.robot.dof == dof
        assert pipeline.converter.needs_currents == needs_currents


def test_per_joint_values_broadcast_and_lengths_are_checked():
    s = Settings.from_dict({'torque_source': 'three_phase', 'kt': [1.0, 2.0, 3.0]})
    cfgs = s.torque_configs(['a', 'b', 'c'])
    assert [c.kt for c in cfgs.values()] == [1.0, 2.0, 3.0]
    assert {c.source for c in cfgs.values()} == {'three_phase'}
    with pytest.raises(IdentificationError, match='kt has 2 values'):
        Settings.from_dict({'kt': [1.0, 2.0]}).torque_configs(['a', 'b', 'c'])


@pytest.mark.parametrize('values, name', [
    ({'forgetting_factor': 'high'}, 'forgetting_factor'),
    ({'smoother': {'half_window': 2.5}}, 'smoother.half_window'),
    ({'publish': {'estimate_rate': 0.0}}, 'publish.estimate_rate'),
    ({'kt': [float('inf')]}, r'kt\[0\]'),
    ({'no_such_parameter': 1}, 'no_such_parameter'),
    ({'joints': ['joint1', 'elbow']}, 'elbow'),
    ({'torque_source': ['magic']}, 'magic'),
    ({'forgetting_factor': 0.5}, 'forgetting'),
    ({'robot': 'no_such_robot'}, 'no_such_robot'),
])
def test_bad_settings_name_the_parameter(values, name):
    with pytest.raises(IdentificationError, match=name):
        Settings.from_dict(values).build()


def test_parameter_file_layouts(tmp_path):
    ros = tmp_path / 'ros.yaml'
    ros.write_text('any_node:\n  ros__parameters:\n    smoother:\n      order: 2\n')
    plain = tmp_path / 'plain.yaml'
    plain.write_text('smoother.order: 2\n')
    assert read_parameter_file(ros) == read_parameter_file(plain) == {'smoother.order': 2}
    bad = tmp_path / 'bad.yaml'
    bad.write_text('[1, 2')
    with pytest.raises(IdentificationError, match='parameter file .* is not valid YAML'):
        read_parameter_file(bad)


# -- results and atomic files ------------------------------------------------------------------
def test_save_results_writes_yaml_and_urdf(tmp_path):
    settings = Settings.from_dict({'robot': 'mit_dd_arm'})
    pipeline = settings.build()
    # before any data the unconstrained estimate (zero base) has no physical bodies: refused
    with pytest.raises(IdentificationError, match='not physically consistent'):
        save_results(pipeline, tmp_path / 'out')
    assert not (tmp_path / 'out').exists()
    paths = save_results(pipeline, tmp_path / 'out', inconsistent=True)
    assert sorted(p.name for p in paths) == ['estimate.yaml', 'identified.urdf']
    doc = yaml.safe_load(paths[0].read_text())
    assert doc['robot'] == 'mit_dd_arm' and doc['num_samples'] == 0
    assert [b['name'] for b in doc['base_parameters']] == pipeline.base.names
    # Before any data the estimate is the model's own parameters' closest point: zero base.
    assert len(doc['covariance']) == pipeline.base.num_base
    assert load_robot(paths[1].read_text()).dof == 3
    assert sorted(os.listdir(tmp_path / 'out')) == ['estimate.yaml', 'identified.urdf']


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path, monkeypatch):
    target = tmp_path / 'f.txt'
    atomic_write_text(target, 'old')

    def fail(*_):
        raise OSError('disk full')
    monkeypatch.setattr(os, 'replace', fail)
    with pytest.raises(OSError):
        atomic_write_text(target, 'new')
    assert target.read_text() == 'old'
    assert os.listdir(tmp_path) == ['f.txt']
