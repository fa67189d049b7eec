"""The identification node, optionally with the simulated arm and the payload forwarder.

    ros2 launch identification_node identification.launch.py
    ros2 launch identification_node identification.launch.py simulated_arm:=true
    ros2 launch identification_node identification.launch.py params_file:=/path/arm.yaml \
        payload_forwarder:=true payload_preset:=ur

Arguments (``ros2 launch ... --show-args``): params_file (its sections identification_node
and simulated_arm), use_sim_time, simulated_arm, payload_forwarder, payload_preset. With the
payload forwarder on, the node identifies the payload (``payload.enabled: true``) and the
forwarder hands each one to the preset's controller service. With the simulated arm on and
use_sim_time true, the arm publishes /clock.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = 'identification_node'


def generate_launch_description() -> LaunchDescription:
    config = PathJoinSubstitution([FindPackageShare(PACKAGE), 'config'])
    use_sim_time = ParameterValue(LaunchConfiguration('use_sim_time'), value_type=bool)
    forwarder = LaunchConfiguration('payload_forwarder')
    node_parameters = [LaunchConfiguration('params_file'), {'use_sim_time': use_sim_time}]
    node = {'package': PACKAGE, 'executable': 'identification_node',
            'name': 'identification_node', 'output': 'screen', 'emulate_tty': True}
    return LaunchDescription([
        DeclareLaunchArgument(
            'params_file', default_value=PathJoinSubstitution([config, 'identification.yaml']),
            description='parameter file (sections identification_node and, for the '
                        'simulated arm, simulated_arm)'),
        DeclareLaunchArgument('use_sim_time', default_value='false', choices=['true', 'false'],
                              description='use /clock (the simulated arm publishes it)'),
        DeclareLaunchArgument('simulated_arm', default_value='false',
                              choices=['true', 'false'],
                              description='start the simulated arm (joint_states, '
                                          'motor_currents)'),
        DeclareLaunchArgument('payload_forwarder', default_value='false',
                              choices=['true', 'false'],
                              description='identify the payload and forward it to a controller'),
        DeclareLaunchArgument('payload_preset', default_value='ur', choices=['ur', 'franka'],
                              description='the controller service the payload goes to'),
        Node(**node, parameters=node_parameters, condition=UnlessCondition(forwarder)),
        Node(**node, parameters=[*node_parameters, {'payload.enabled': True}],
             condition=IfCondition(forwarder)),
        Node(package=PACKAGE, executable='simulated_arm', name='simulated_arm', output='screen',
             emulate_tty=True,
             parameters=[LaunchConfiguration('params_file'),
                         {'use_sim_time': use_sim_time, 'publish_clock': use_sim_time}],
             condition=IfCondition(LaunchConfiguration('simulated_arm'))),
        Node(package=PACKAGE, executable='payload_forwarder', name='payload_forwarder',
             output='screen', emulate_tty=True,
             parameters=[{'preset': LaunchConfiguration('payload_preset'),
                          'use_sim_time': use_sim_time}],
             remappings=[('payload', '/identification_node/payload')],
             condition=IfCondition(forwarder)),
    ])
