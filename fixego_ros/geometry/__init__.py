"""ROS-free geometry: rotations and rigid motions, the rig model (cameras, pan/tilt, calibration file)."""
