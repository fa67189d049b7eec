"""config.py: the one source of every default. The ROS parameter table, the subsystems' option
dataclasses and config/identification.yaml agree with the dataclass tree."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest

from identification_node import config
from identification_node.config import (EMPTY_LISTS, FLOAT_LISTS, PARAMETERS, PER_JOINT,
                                        RANGES, BatchConfig, Config)
from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import ConsistencyOptions
from identification_node.estimation.robust import RobustSettings
from identification_node.model.plausibility import PlausibilitySettings
from identification_node.model.torque import JointTorqueConfig
from identification_node.batch.rows import BatchOptions
from identification_node.payload.fit import DEFAULT_TOLERANCE
from identification_node.payload.monitor import MonitorConfig
from identification_node.pipeline import PipelineConfig
from identification_node.pipeline.config import CONFIG_FIELD_PARAMETERS
from identification_node.settings import Settings, read_parameter_file

REPO = Path(__file__).resolve().parents[1]
# The values config/identification.yaml sets for the MIT arm's bags; every other is a default.
ARM_SPECIFIC = {'joints', 'extras', 'torque_source', 'kt', 'pole_pairs', 'smoother.half_window'}


def tree_leaves(obj, prefix=''):
    """Dotted name: value of every leaf of a Config (sections walked)."""
    out = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out.update(tree_leaves(value, f'{prefix}{f.name}.'))
        else:
            out[prefix + f.name] = value
    return out


def same(a, b):
    """Equal and of the same type (1 is not 1.0 for a ROS parameter's type)."""
    return a == b and type(a) is type(b)


def test_the_ros_parameter_table_is_the_dataclass_defaults():
    leaves = tree_leaves(Config())
    assert list(leaves) == list(PARAMETERS)
    for name, value in leaves.items():
        default, text = PARAMETERS[name]
        assert same(value, default), name
        if isinstance(value, list):
            assert all(same(a, b) for a, b in zip(value, default)), name
        assert text == config.metadata(name)['description'] and text, name
    assert set(RANGES) <= set(PARAMETERS)
    for name, (lo, hi) in RANGES.items():
        assert lo <= PARAMETERS[name][0] <= hi, name
    assert set(FLOAT_LISTS) == {n for n, (d, _) in PARAMETERS.items()
                                if d == [] and n not in ('joints',)}
    assert EMPTY_LISTS == ('extras',)
    assert PER_JOINT == ('torque_source', 'kt', 'gear_ratio', 'pole_pairs', 'angle_offset',
                         'phase_order')


def test_defaults_are_copies():
    a, b = Config(), Config()
    a.extras.append('Ia')
    assert b.extras == ['fv', 'fc', 'fo'] == PARAMETERS['extras'][0]
    config.default('extras').append('Ia')
    assert PARAMETERS['extras'][0] == ['fv', 'fc', 'fo']


def test_validated_values_make_the_tree():
    values = config.validated({})
    assert values == {name: default for name, (default, _) in PARAMETERS.items()}
    assert Config.from_values(values) == Config()
    tree = Config.from_values(config.validated({'robust': {'k': 4}, 'payload.min_z': 6}))
    assert tree.robust.k == 4.0 and type(tree.robust.k) is float
    assert tree.payload.min_z == 6.0
    assert Settings.from_dict({'smoother.order': 2}).config.smoother.order == 2


@pytest.mark.parametrize('given, message', [
    ({'nope': 1}, "unknown parameter(s) ['nope']"),
    ({'forgetting_factor': 0.5}, 'parameter forgetting_factor = 0.5 must be in [0.9, 1.0]'),
    ({'watchdog_timeout': -1.0}, 'parameter watchdog_timeout must be >= 0'),
    ({'process_period': 0.0}, 'parameter process_period = 0.0 must be > 0'),
    ({'output_directory': ' '}, 'parameter output_directory must not be empty'),
    ({'kt': ['a']}, "parameter kt[0] = 'a' must be a number"),
    ({'robust.enabled': 1}, 'parameter robust.enabled = 1 must be true or false'),
])
def test_validation_names_the_parameter(given, message):
    with pytest.raises(IdentificationError) as error:
        config.validated(given)
    assert message in str(error.value)


def _fields(obj) -> dict:
    """Fields of a dataclass instance, lists as tuples."""
    return {f.name: tuple(v) if isinstance(v := getattr(obj, f.name), list) else v
            for f in dataclasses.fields(obj)}


def test_subsystem_options_default_to_the_tree():
    tree = Config()
    assert RobustSettings() == RobustSettings(**dataclasses.asdict(tree.robust))
    assert _fields(PlausibilitySettings()) == _fields(tree.plausibility)
    assert _fields(ConsistencyOptions()) == _fields(tree.consistency)
    assert ConsistencyOptions() == Settings.from_dict({}).consistency_options()
    monitor = MonitorConfig()
    for name in ('fit_time', 'settle', 'refresh', 'window', 'threshold', 'min_change', 'min_z',
                 'confirm', 'cutoff'):
        assert same(getattr(monitor, name), getattr(tree.payload, name)), name
    assert monitor.max_gap == tree.smoother.max_gap
    assert DEFAULT_TOLERANCE == dataclasses.asdict(tree.payload.tolerance)
    torque = JointTorqueConfig()
    for field, name in [('source', 'torque_source'), ('kt', 'kt'),
                        ('gear_ratio', 'gear_ratio'), ('pole_pairs', 'pole_pairs'),
                        ('angle_offset', 'angle_offset'), ('phase_order', 'phase_order')]:
        assert [getattr(torque, field)] == PARAMETERS[name][0], name
    pipeline = PipelineConfig()
    built = Settings.from_dict({}).pipeline_config([])
    assert _fields(pipeline) == _fields(built)
    for f in dataclasses.fields(PipelineConfig):
        name = CONFIG_FIELD_PARAMETERS.get(f.name, f.name)
        if name in PARAMETERS:
            default = PARAMETERS[name][0]
            assert getattr(pipeline, f.name) == (tuple(default) if isinstance(default, list)
                                                 else default), name
    batch = BatchOptions()
    assert (batch.min_harmonics, batch.order) == (BatchConfig.min_harmonics, BatchConfig.order)


def test_identification_yaml_holds_every_parameter_at_its_default():
    """config/identification.yaml, the node's documented parameter file, names every parameter
    and gives its default but for the MIT arm's own (ARM_SPECIFIC)."""
    given = read_parameter_file(REPO / 'config' / 'identification.yaml')
    assert set(given) == set(PARAMETERS)
    values = config.validated(given)
    differ = {name for name, (default, _) in PARAMETERS.items() if values[name] != default}
    assert differ == ARM_SPECIFIC
    for name, value in given.items():   # written with the default's type (1.0, not 1)
        default = PARAMETERS[name][0]
        if isinstance(default, float):
            assert isinstance(value, float) or math.isinf(default), name


def test_descriptors_are_typed_and_ranged_from_the_tree():
    """What the node's rclpy descriptors say (ros/node.py parameter_descriptor)."""
    for name, (default, text) in PARAMETERS.items():
        d = config.descriptor(name, default, text)
        assert d.description == text
        if isinstance(default, list):
            assert d.array == bool(default and name not in EMPTY_LISTS), name
            assert d.type is (config.element_type(name, default) if d.array else None), name
            continue
        assert d.type is type(default) and not d.array, name
        assert d.range == RANGES.get(name), name
        if d.range is not None:
            assert all(type(b) is (int if type(default) is int else float)
                       for b in d.range), name
    assert config.descriptor('kt', [1.0], '').type is float
    assert config.descriptor('smoother.order', 3, '').range == (2, 4)
    assert config.descriptor('coulomb_velocity', 0.0, '').range == (0.0, math.inf)


# plain scalars of a parameter file, and what rcl_yaml_param_parser makes of them
RCL_SCALARS = {'1e-3': 1e-3, '-2.5E+2': -250.0, '.5': 0.5, '5.': 5.0, 'inf': math.inf,
               '-.inf': -math.inf, '.NaN': math.nan, '0x1.8p1': 3.0, 'y': True, 'N': False,
               'off': False, 'Yes': True, '010': 8, '0x1F': 31, '+5': 5, '-0': 0,
               '~': '~', 'null': 'null', '1_000': '1_000', '1e999': '1e999', 'abc': 'abc',
               "'1e-3'": '1e-3', '"y"': 'y', '9223372036854775808': 9.223372036854775808e18,
               '-0o7': '-0o7', '1' * 5000: '1' * 5000, '2' * 300: float('2' * 300),
               '0' * 30 + '17': 15, '0x' + '0' * 30 + 'fF': 255}


def _scalar_file(directory: Path) -> Path:
    path = directory / 'scalars.yaml'
    path.write_text('/**:\n  ros__parameters:\n'
                    + ''.join(f'    p{k}: {text}\n' for k, text in enumerate(RCL_SCALARS))
                    + '    doubles: [1e-3, 2.0, -.inf]\n    on: 1\n')
    return path


def _same(a, b) -> bool:
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(map(_same, a, b))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return type(a) is type(b) and a == b


def test_parameter_files_are_read_as_rcl_reads_them(tmp_path):
    """`identify --config FILE` takes FILE as `ros2 run --params-file FILE` does: 1e-3 a
    number (PyYAML: a string), y a bool, ~ and 1_000 strings, names strings ('on')."""
    given = read_parameter_file(_scalar_file(tmp_path))
    expected = {f'p{k}': v for k, v in enumerate(RCL_SCALARS.values())}
    expected.update({'doubles': [1e-3, 2.0, -math.inf], 'on': 1})
    assert set(given) == set(expected)
    assert [n for n in expected if not _same(given[n], expected[n])] == []
    text = 'consistency:\n  weight: 1e-2\n  total_mass: [1e1, 2e1]\n'
    (tmp_path / 'plain.yaml').write_text(text)
    settings = Settings.from_dict(read_parameter_file(tmp_path / 'plain.yaml'))
    assert settings['consistency.weight'] == 0.01
    assert settings['consistency.total_mass'] == [10.0, 20.0]


@pytest.mark.ros
def test_rcl_reads_the_scalar_table_so(tmp_path, monkeypatch):
    """The table above is rcl's: the same file through rclpy's --params-file."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.node import Node
    from ros_helpers import domain_id, release_domain

    path = _scalar_file(tmp_path)
    domain = domain_id(__name__)
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    context = rclpy.Context()
    try:
        rclpy.init(args=['--ros-args', '--params-file', str(path)], context=context,
                   domain_id=domain)
        node = Node('rcl_scalars', context=context,
                    automatically_declare_parameters_from_overrides=True)
        names = [n for n in node.list_parameters([], 10).names if n != 'use_sim_time']
        got = {p.name: p.value for p in node.get_parameters(names)}
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
        release_domain(domain)
    got = {n: list(v) if isinstance(v, (list, tuple)) or hasattr(v, 'tolist') else v
           for n, v in got.items()}
    assert [n for n, v in read_parameter_file(path).items() if not _same(v, got.get(n))] == []
