"""ament_python package setup for identification_node."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'identification_node'


setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench']),
    package_data={PACKAGE: ['robots/*.urdf']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
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
        'rosbags>=0.11,<1',
        'mcap>=1.2,<2',
        'matplotlib>=3.6,<4',
        'dask[distributed]>=2024.1',   # the fleet verb's cluster (fleet.py)
        'cvxpy>=1.5,<2',
        'clarabel>=0.9,<1',
    ],
    extras_require={
        'ros': [
            'ros-jazzy-rclpy[fastrtps]>=7.1,<7.2',
            'ros-jazzy-common-interfaces>=5.3,<5.4',
        ],
        'test': [
            'pytest>=7,<10',
            'flake8>=6,<8',
            'mypy>=1.10,<3',   # `python -m mypy` (setup.cfg [mypy])
            'colcon-common-extensions>=0.3,<0.4',
            'example-robot-data>=6,<7',   # URDFs of real arms (test/arms.py)
        ],
    },
    zip_safe=False,
    maintainer='identification_node developers',
    maintainer_email='dev@identification-node.invalid',
    description='Online identification of robot arm inertial parameters for ROS 2.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'identification_node = identification_node.programs:identification_node',
            'simulated_arm = identification_node.programs:simulated_arm',
            'payload_forwarder = identification_node.programs:payload_forwarder',
            'parameter_forwarder = identification_node.programs:parameter_forwarder',
            'identification_cli = identification_node.programs:identification_cli',
        ],
    },
)
