"""Thin rclpy adapters around the ROS-free core (one module per executable, plus common helpers)."""
