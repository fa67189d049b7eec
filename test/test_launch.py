"""launch/identification.launch.py without the `launch` package: it is run against stand-ins
for the launch_ros API it uses, each with the signature the launch and launch_ros
documentation gives (an argument they do not take fails), and every executable, file,
launch argument and parameter it names is checked against the package."""
import ast
import runpy
import sys
import types
from pathlib import Path

import pytest
import yaml

from test_package import ROOT, console_scripts

PACKAGE = 'identification_node'
LAUNCH = ROOT / 'launch' / 'identification.launch.py'
# ExecuteProcess / Action keyword arguments a launch_ros Node passes on
PROCESS_KWARGS = {'output', 'emulate_tty', 'condition', 'respawn', 'respawn_delay',
                  'additional_env', 'sigterm_timeout', 'sigkill_timeout'}


class Recorded:
    def __init__(self, kind: str, *args, **kwargs):
        self.kind, self.args, self.kwargs = kind, args, kwargs

    def __repr__(self):
        return f'{self.kind}{self.args}'


def _api(log: list) -> dict[str, types.ModuleType]:
    """Modules launch, launch.actions, ... with stand-ins of the documented signatures."""
    def record(kind):
        def make(*args, **kwargs):
            r = Recorded(kind, *args, **kwargs)
            log.append(r)
            return r
        return make

    def LaunchDescription(initial_entities=None, *, deprecated_reason=None):
        return record('LaunchDescription')(list(initial_entities or []))

    def DeclareLaunchArgument(name, *, default_value=None, description=None, choices=None):
        return record('DeclareLaunchArgument')(name, default_value=default_value,
                                               description=description, choices=choices)

    def LaunchConfiguration(variable_name, *, default=None):
        return record('LaunchConfiguration')(variable_name)

    def PathJoinSubstitution(substitutions):
        return record('PathJoinSubstitution')(list(substitutions))

    def IfCondition(predicate_expression):
        return record('IfCondition')(predicate_expression)

    def UnlessCondition(predicate_expression):
        return record('UnlessCondition')(predicate_expression)

    def Node(*, executable, package=None, name=None, namespace=None, exec_name=None,
             parameters=None, remappings=None, ros_arguments=None, arguments=None, **kwargs):
        unknown = set(kwargs) - PROCESS_KWARGS
        assert not unknown, f'Node does not take {unknown}'
        return record('Node')(executable=executable, package=package, name=name,
                              parameters=parameters or [], remappings=remappings or [],
                              **kwargs)

    def ParameterValue(value, *, value_type=None):
        return record('ParameterValue')(value, value_type=value_type)

    def FindPackageShare(package):
        return record('FindPackageShare')(package)

    modules = {
        'launch': {'LaunchDescription': LaunchDescription},
        'launch.actions': {'DeclareLaunchArgument': DeclareLaunchArgument},
        'launch.conditions': {'IfCondition': IfCondition, 'UnlessCondition': UnlessCondition},
        'launch.substitutions': {'LaunchConfiguration': LaunchConfiguration,
                                 'PathJoinSubstitution': PathJoinSubstitution},
        'launch_ros': {},
        'launch_ros.actions': {'Node': Node},
        'launch_ros.parameter_descriptions': {'ParameterValue': ParameterValue},
        'launch_ros.substitutions': {'FindPackageShare': FindPackageShare},
    }
    out = {}
    for name, attrs in modules.items():
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        out[name] = module
    return out


@pytest.fixture(scope='module')
def launched():
    """(the LaunchDescription, every recorded call) of generate_launch_description()."""
    log: list = []
    saved = {k: sys.modules.get(k) for k in _api([])}
    sys.modules.update(_api(log))
    try:
        description = runpy.run_path(str(LAUNCH))['generate_launch_description']()
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module
    assert description.kind == 'LaunchDescription'
    return description, log


def entities(launched, kind):
    return [e for e in launched[0].args[0] if e.kind == kind]


def installed_path(sub) -> Path:
    """A PathJoinSubstitution [FindPackageShare(pkg), parts...] as the source file that
    setup.py installs there (share/<pkg>/config/* from config/*)."""
    parts = []
    for part in sub.args[0]:
        if isinstance(part, Recorded) and part.kind == 'FindPackageShare':
            assert part.args == (PACKAGE,)
        elif isinstance(part, Recorded) and part.kind == 'PathJoinSubstitution':
            parts += installed_path(part).relative_to(ROOT).parts
        else:
            parts.append(part)
    return ROOT.joinpath(*parts)


def test_parses_and_imports_only_launch_and_launch_ros():
    tree = ast.parse(LAUNCH.read_text())
    modules = {n.module.split('.')[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    modules |= {a.name.split('.')[0] for n in ast.walk(tree) if isinstance(n, ast.Import)
                for a in n.names}
    assert modules == {'launch', 'launch_ros'}


def test_executables_are_console_scripts_of_this_package(launched):
    nodes = entities(launched, 'Node')
    scripts = console_scripts()
    assert {n.kwargs['executable'] for n in nodes} == {
        'identification_node', 'simulated_arm', 'payload_forwarder'}
    for n in nodes:
        assert n.kwargs['package'] == PACKAGE and n.kwargs['executable'] in scripts


def test_every_launch_configuration_is_declared(launched):
    declared = {d.args[0]: d for d in entities(launched, 'DeclareLaunchArgument')}
    assert set(declared) == {'params_file', 'use_sim_time', 'simulated_arm',
                             'payload_forwarder', 'payload_preset'}
    used = {r.args[0] for r in launched[1] if r.kind == 'LaunchConfiguration'}
    assert used == set(declared)
    for d in declared.values():
        assert d.kwargs['description']
        choices = d.kwargs['choices']
        assert choices is None or d.kwargs['default_value'] in choices
    from identification_node.payload.delivery import PRESETS
    assert set(declared['payload_preset'].kwargs['choices']) == set(PRESETS)


def test_default_params_file_is_installed_and_has_both_nodes(launched):
    default = next(d for d in entities(launched, 'DeclareLaunchArgument')
                   if d.args[0] == 'params_file').kwargs['default_value']
    path = installed_path(default)
    assert path.is_file() and path.parent == ROOT / 'config'
    assert "glob('config/*.yaml')" in (ROOT / 'setup.py').read_text()   # installed there
    sections = yaml.safe_load(path.read_text())
    names = {n.kwargs['name'] for n in entities(launched, 'Node')
             if any(getattr(p, 'kind', '') == 'LaunchConfiguration' and p.args[0] ==
                    'params_file' for p in n.kwargs['parameters'])}
    assert names == {'identification_node', 'simulated_arm'}
    assert names <= set(sections)


def _forwarder_parameters() -> set[str]:
    """The names the payload forwarder declares (read from its source)."""
    tree = ast.parse((ROOT / PACKAGE / 'ros' / 'payload_forwarder.py').read_text())
    names = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.Call) and getattr(n.func, 'attr', '') == 'declare_parameter':
            if isinstance(n.args[0], ast.Constant):
                names.add(n.args[0].value)
        if isinstance(n, ast.comprehension) and isinstance(n.iter, ast.Tuple):
            names |= {e.value for e in n.iter.elts if isinstance(e, ast.Constant)}
    return names


def test_every_parameter_named_exists(launched):
    from identification_node.ros.sim_node import SIM_PARAMETERS
    from identification_node.config import PARAMETERS
    known = {'identification_node': set(PARAMETERS), 'simulated_arm': set(SIM_PARAMETERS),
             'payload_forwarder': _forwarder_parameters()}
    assert {'preset', 'service', 'fields'} <= known['payload_forwarder']
    for node in entities(launched, 'Node'):
        for entry in node.kwargs['parameters']:
            if isinstance(entry, dict):
                unknown = set(entry) - known[node.kwargs['executable']] - {'use_sim_time'}
                assert not unknown, f'{node.kwargs["executable"]}: {unknown}'
    flags = [v['payload.enabled'] for n in entities(launched, 'Node')
             for v in n.kwargs['parameters'] if isinstance(v, dict) and 'payload.enabled' in v]
    assert flags == [True]


def test_forwarder_and_payload_identification_go_together(launched):
    """The node runs once: without payload identification unless the forwarder is on, with
    it when the forwarder is on, and the forwarder listens to its ~/payload."""
    nodes = [n for n in entities(launched, 'Node')
             if n.kwargs['executable'] == 'identification_node']
    kinds = sorted(n.kwargs['condition'].kind for n in nodes)
    assert kinds == ['IfCondition', 'UnlessCondition']
    assert {n.kwargs['condition'].args[0].args[0] for n in nodes} == {'payload_forwarder'}
    forwarder = next(n for n in entities(launched, 'Node')
                     if n.kwargs['executable'] == 'payload_forwarder')
    assert forwarder.kwargs['condition'].args[0].args[0] == 'payload_forwarder'
    name = nodes[0].kwargs['name']
    assert forwarder.kwargs['remappings'] == [('payload', f'/{name}/payload')]
    assert "'~/payload'" in (ROOT / PACKAGE / 'ros' / 'payload_outputs.py').read_text()
