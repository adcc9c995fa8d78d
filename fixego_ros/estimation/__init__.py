"""ROS-free estimation core: two-frame coplanarity solve, local bundle adjustment, incremental estimator."""
