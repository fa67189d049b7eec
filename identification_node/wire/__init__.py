"""The input record, as copied from the wire (sensor_msgs/JointState)."""
