"""The ROS 2 package contract: package.xml / setup.cfg as ament_python needs them, and a real
colcon build whose install tree serves `ros2 run identification_node <script>`, ament_index
look-ups, the installed config and bundled robots, and a working installed CLI."""
import ast
import configparser
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = 'identification_node'
COLCON = (str(Path(sys.executable).with_name('colcon'))
          if Path(sys.executable).with_name('colcon').exists() else shutil.which('colcon'))

# Root entries that are not part of the package source (colcon would otherwise crawl .venv).
NOT_SOURCE = {'.venv', '.git', 'build', 'install', 'log', 'test', 'bench', 'bags', '.ci',
              '.pytest_cache', '__pycache__', f'{PACKAGE}.egg-info'}
EXEC_DEPENDS = {'rclpy', 'sensor_msgs', 'std_msgs', 'std_srvs', 'geometry_msgs',
                'diagnostic_msgs', 'launch', 'launch_ros'}


def setup_keywords() -> dict:
    """The literal keyword arguments of the setup() call in setup.py (no execution)."""
    tree = ast.parse((ROOT / 'setup.py').read_text())
    call = next(node for node in ast.walk(tree) if isinstance(node, ast.Call)
                and getattr(node.func, 'id', None) == 'setup')
    out = {}
    for kw in call.keywords:
        try:
            out[kw.arg] = ast.literal_eval(kw.value)
        except ValueError:
            pass  # computed values (glob, find_packages, names)
    return out


def console_scripts() -> dict[str, str]:
    entries = setup_keywords()['entry_points']['console_scripts']
    scripts = dict(e.replace(' ', '').split('=', 1) for e in entries)
    assert scripts, 'setup.py declares no console_scripts'
    return scripts


# -- static contract ---------------------------------------------------------------------------
def test_package_xml_is_format3_ament_python():
    root = ET.parse(ROOT / 'package.xml').getroot()
    assert root.tag == 'package' and root.get('format') == '3'
    assert root.findtext('name') == PACKAGE
    assert root.findtext('export/build_type') == 'ament_python'
    exec_depends = {e.text.strip() for e in root.findall('exec_depend')}
    assert EXEC_DEPENDS <= exec_depends, f'missing exec_depend {EXEC_DEPENDS - exec_depends}'
    assert root.findtext('license') and root.find('maintainer').get('email')
    from identification_node import __version__
    assert root.findtext('version') == setup_keywords()['version'] == __version__


def test_setup_cfg_installs_scripts_for_ros2_run():
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / 'setup.cfg')
    assert cfg.get('develop', 'script_dir') == f'$base/lib/{PACKAGE}'
    assert cfg.get('install', 'install_scripts') == f'$base/lib/{PACKAGE}'
    assert (ROOT / 'resource' / PACKAGE).is_file()


def test_console_scripts_point_at_callables():
    import importlib
    for script, target in console_scripts().items():
        module, func = target.split(':')
        assert callable(getattr(importlib.import_module(module), func)), script


# -- colcon build --------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def install(tmp_path_factory) -> Path:
    """colcon build of a copy of the package source; returns install/<package>. The tests
    that need it are skipped where colcon is not installed."""
    if COLCON is None:
        pytest.skip('colcon is not installed')
    tmp = tmp_path_factory.mktemp('colcon')
    shutil.copytree(ROOT, tmp / 'src' / PACKAGE,
                    ignore=lambda d, names: [n for n in names if Path(d) == ROOT
                                             and n in NOT_SOURCE]
                    + ['__pycache__'] + [n for n in names if n.endswith('.so')])
    env = {k: v for k, v in os.environ.items()
           if k not in ('AMENT_PREFIX_PATH', 'COLCON_PREFIX_PATH', 'PYTHONPATH')}
    env['COLCON_HOME'] = str(tmp / 'colcon_home')
    cmd = [COLCON, '--log-base', str(tmp / 'log'), 'build', '--base-paths', str(tmp / 'src'),
           '--build-base', str(tmp / 'build'), '--install-base', str(tmp / 'install')]
    proc = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f'colcon build failed:\n{proc.stdout}\n{proc.stderr}'
    assert '1 package finished' in proc.stdout, proc.stdout
    return tmp / 'install' / PACKAGE


@pytest.fixture(scope='module')
def site_packages(install) -> Path:
    found = list(install.glob('lib/python3*/site-packages'))
    assert len(found) == 1, found
    return found[0]


def installed_env(site_packages: Path, install: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(site_packages), AMENT_PREFIX_PATH=str(install))
    env.pop('PYTHONHOME', None)
    return env


def test_console_scripts_installed_executable(install, site_packages):
    entry_points = next(site_packages.glob(f'{PACKAGE}-*.egg-info/entry_points.txt')).read_text()
    for script, target in console_scripts().items():
        path = install / 'lib' / PACKAGE / script
        assert path.is_file(), f'{script} not installed where ros2 run looks ({path})'
        assert os.access(path, os.X_OK), f'{path} is not executable'
        assert f'{script} = {target}' in entry_points


def test_ament_index_finds_package(install, monkeypatch):
    from ament_index_python.packages import (get_package_prefix, get_package_share_directory,
                                             get_packages_with_prefixes)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(install))
    assert Path(get_package_prefix(PACKAGE)) == install
    share = Path(get_package_share_directory(PACKAGE))
    assert share == install / 'share' / PACKAGE
    assert Path(get_packages_with_prefixes()[PACKAGE]) == install
    assert (share / 'package.xml').read_text() == (ROOT / 'package.xml').read_text()


def test_config_and_robots_installed(install, site_packages):
    share = install / 'share' / PACKAGE
    configs = sorted(p.name for p in (ROOT / 'config').glob('*.yaml'))
    assert sorted(p.name for p in share.glob('config/*.yaml')) == configs
    for name in configs:
        assert (share / 'config' / name).read_bytes() == (ROOT / 'config' / name).read_bytes()
    robots = sorted(p.name for p in (ROOT / PACKAGE / 'robots').glob('*.urdf'))
    assert 'mit_dd_arm.urdf' in robots
    assert sorted(p.name for p in share.glob('robots/*.urdf')) == robots
    # package_data: load_robot('<name>') reads the copy inside the installed Python package.
    assert sorted(p.name for p in (site_packages / PACKAGE / 'robots').glob('*.urdf')) == robots


def test_launch_files_installed(install):
    launch = sorted(p.name for p in (ROOT / 'launch').glob('*.launch.py'))
    assert 'identification.launch.py' in launch
    share = install / 'share' / PACKAGE / 'launch'
    assert sorted(p.name for p in share.glob('*.launch.py')) == launch
    for name in launch:
        assert (share / name).read_bytes() == (ROOT / 'launch' / name).read_bytes()


def test_installed_python_package_is_used(install, site_packages, tmp_path):
    code = ('import identification_node.model.robot as r; print(r.__file__); '
            "print(','.join(r.bundled_robots())); print(r.load_robot('mit_dd_arm').dof)")
    proc = subprocess.run([sys.executable, '-c', code], cwd=tmp_path, capture_output=True,
                          text=True, env=installed_env(site_packages, install), timeout=120)
    assert proc.returncode == 0, proc.stderr
    module, robots, dof = proc.stdout.split()
    assert Path(module).is_relative_to(site_packages)
    assert robots.split(',') == sorted(p.stem for p in (ROOT / PACKAGE / 'robots').glob('*.urdf'))
    assert dof == '3'


def test_installed_cli_help_lists_verbs(install, site_packages, tmp_path):
    from identification_node.cli import VERBS
    script = install / 'lib' / PACKAGE / 'identification_cli'
    proc = subprocess.run([str(script), '--help'], cwd=tmp_path, capture_output=True, text=True,
                          env=installed_env(site_packages, install), timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert 'usage:' in proc.stdout
    listed = ' '.join(proc.stdout.split())  # argparse wraps long help lines
    for verb, (_, text) in VERBS.items():
        assert verb in listed and ' '.join(text.split()) in listed, f'{verb} missing from --help'
    bad = subprocess.run([str(script), 'no-such-verb'], cwd=tmp_path, capture_output=True,
                         text=True, env=installed_env(site_packages, install), timeout=120)
    assert bad.returncode == 2 and 'invalid choice' in bad.stderr


def test_installed_scripts_print_help(install, site_packages, tmp_path):
    """``ros2 run identification_node SCRIPT --help`` runs lib/<package>/SCRIPT --help."""
    for script in console_scripts():
        proc = subprocess.run([str(install / 'lib' / PACKAGE / script), '--help'], cwd=tmp_path,
                              capture_output=True, text=True, timeout=120,
                              env=installed_env(site_packages, install))
        assert proc.returncode == 0, f'{script}: {proc.stderr}'
        assert proc.stdout.startswith('usage: '), script
        assert script == 'identification_cli' or f'ros2 run {PACKAGE} {script}' in proc.stdout


def test_importing_the_package_leaves_the_process_environment_alone(tmp_path):
    """A controller importing controller_client (and so the package) keeps its environment;
    the package's programs set theirs in their entry points (programs.py)."""
    code = ('import os, controller_client, identification_node.pipeline; '
            "print(os.environ.get('OPENBLAS_NUM_THREADS'))")
    env = {k: v for k, v in os.environ.items() if k != 'OPENBLAS_NUM_THREADS'}
    env['PYTHONPATH'] = os.pathsep.join([str(ROOT), str(ROOT / 'examples')])
    proc = subprocess.run([sys.executable, '-c', code], cwd=tmp_path, capture_output=True,
                          text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ['None']
