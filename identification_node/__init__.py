"""identification_node: online identification of robot arm inertial parameters.

The numerical core (robot, identifiability, estimators, torque, signals, ...) has no ROS
dependency; ``identification_node.ros`` holds the thin rclpy adapters.
"""
__version__ = '0.1.0'
