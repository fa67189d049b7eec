"""identification_node: online identification of robot arm inertial parameters.

The numerical core (robot, identifiability, estimators, torque, signals, ...) has no ROS
dependency; ``identification_node.ros`` holds the thin rclpy adapters.
"""
import os

# The matrices here are small (tens of columns): threaded BLAS only spins on the few cores
# a robot computer shares with its controllers. Set before numpy loads; a user's choice wins.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

__version__ = '0.1.0'
