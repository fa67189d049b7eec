"""ament_python package setup for identification_node."""
import os
import sys
from glob import glob

from setuptools import Extension, find_packages, setup

PACKAGE = 'identification_node'


def kernel_extension() -> list:
    """The compiled per-run step (identification_node/_kernel.cpp, C++17 with pybind11 only),
    optional: without pybind11, or when it fails to compile, the package installs without it
    and the pipeline runs its Python path (identification_node.compiled).
    IDENTIFICATION_NODE_COMPILED=0 leaves it out."""
    if os.environ.get('IDENTIFICATION_NODE_COMPILED') == '0':
        return []
    try:
        import pybind11
    except ImportError:
        print('identification_node: pybind11 not found, building without the compiled step',
              file=sys.stderr)
        return []
    return [Extension(f'{PACKAGE}._kernel', [f'{PACKAGE}/_kernel.cpp'],
                      include_dirs=[pybind11.get_include()], language='c++', optional=True,
                      extra_compile_args=['-std=c++17', '-O2', '-fvisibility=hidden'])]


setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench']),
    ext_modules=kernel_extension(),
    package_data={PACKAGE: ['robots/*.urdf']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/robots', glob(PACKAGE + '/robots/*.urdf')),
    ],
    python_requires='>=3.10',
    # The ROS client libraries come from the ROS installation on a ROS machine; the PyPI wheels
    # of ROS 2 Jazzy stand in for them on a machine without ROS (extra 'ros').
    install_requires=[
        'numpy>=1.24,<3',
        'scipy>=1.10,<2',
        'pin>=3.3,<5',
        'PyYAML>=6,<7',
        'rosbags>=0.11,<0.12',
        'mcap>=1.2,<2',
        'matplotlib>=3.6,<4',
    ],
    extras_require={
        'ros': [
            'ros-jazzy-rclpy[fastrtps]>=7.1,<7.2',
            'ros-jazzy-common-interfaces>=5.3,<5.4',
        ],
        'test': [
            'pytest>=7,<10',
            'flake8>=6,<8',
            'colcon-common-extensions>=0.3,<0.4',
        ],
    },
    zip_safe=False,
    maintainer='identification_node developers',
    maintainer_email='dev@identification-node.invalid',
    description='Online identification of robot arm inertial parameters for ROS 2.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'identification_node = identification_node.ros.node:main',
            'simulated_arm = identification_node.ros.sim_node:main',
            'identification_cli = identification_node.cli:main',
        ],
    },
)
