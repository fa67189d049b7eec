"""package.xml against what the package imports: every module imported anywhere in the package
(and its launch files), at module level or inside a function, is provided by an exec_depend
named by its rosdep key; every exec_depend is needed; the PyPI-only ones (rosdep's pip-rule
names, python3-NAME-pip) are in setup.py's install_requires too."""
import ast
import re
import sys
import xml.etree.ElementTree as ET

from test_package import ROOT, setup_keywords

PACKAGE = 'identification_node'
# import name -> rosdep key (ROS packages keep their name; the rest as the ROS distribution
# names them, or by the pip rule where it has none)
ROSDEP_KEYS = {
    'rclpy': 'rclpy', 'rcl_interfaces': 'rcl_interfaces',
    'builtin_interfaces': 'builtin_interfaces', 'sensor_msgs': 'sensor_msgs',
    'std_msgs': 'std_msgs', 'std_srvs': 'std_srvs', 'geometry_msgs': 'geometry_msgs',
    'diagnostic_msgs': 'diagnostic_msgs', 'rosgraph_msgs': 'rosgraph_msgs',
    'launch': 'launch', 'launch_ros': 'launch_ros',
    'pinocchio': 'pinocchio', 'coal': 'coal',
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'distributed': 'python3-distributed',
    'cvxpy': 'python3-cvxpy-pip', 'rosbags': 'python3-rosbags-pip', 'mcap': 'python3-mcap-pip',
}
# Needed without an import statement of ours: the solver cvxpy loads by the name the
# consistency.solver parameter gives (CLARABEL, the default).
NOT_IMPORTED = {'python3-clarabel-pip': 'cvxpy loads it as the CLARABEL solver'}


def imported_modules() -> dict[str, set[str]]:
    """Top-level name of every absolute import -> the files importing it."""
    files = list((ROOT / PACKAGE).rglob('*.py')) + list((ROOT / 'launch').glob('*.py'))
    found: dict[str, set[str]] = {}
    for path in files:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split('.')[0]
                if top != PACKAGE and top not in sys.stdlib_module_names and top != '__future__':
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def exec_depends() -> set[str]:
    root = ET.parse(ROOT / 'package.xml').getroot()
    return {e.text.strip() for e in root.findall('exec_depend')}


def test_walk_finds_imports_inside_functions_and_launch_files():
    found = imported_modules()
    assert 'coal' in found        # imported inside a function (excitation/collision.py)
    assert 'launch_ros' in found  # the launch file
    assert 'os' not in found and PACKAGE not in found


def test_every_import_is_an_exec_depend():
    found, declared = imported_modules(), exec_depends()
    unmapped = {m: sorted(f) for m, f in found.items() if m not in ROSDEP_KEYS}
    assert not unmapped, f'imports without a rosdep key in ROSDEP_KEYS: {unmapped}'
    missing = {ROSDEP_KEYS[m]: sorted(f) for m, f in found.items()
               if ROSDEP_KEYS[m] not in declared}
    assert not missing, f'package.xml lacks exec_depend for {missing}'


def test_every_exec_depend_is_used():
    used = {ROSDEP_KEYS[m] for m in imported_modules()} | set(NOT_IMPORTED)
    unused = exec_depends() - used
    assert not unused, f'package.xml exec_depends nothing imports: {sorted(unused)}'


def test_pip_rule_keys_are_install_requires():
    requires = {re.split(r'[<>=\[ ]', r)[0].lower()
                for r in setup_keywords()['install_requires']}
    for key in exec_depends():
        match = re.fullmatch(r'python3-(.+)-pip', key)
        if match:
            assert match.group(1) in requires, f'{key}: {match.group(1)} not in install_requires'
