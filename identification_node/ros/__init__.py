"""Thin rclpy adapters over the ROS-free core: they copy messages in and publish results."""
