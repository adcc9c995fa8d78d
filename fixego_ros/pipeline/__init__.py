"""ROS-free pipeline from camera samples to estimator observations (front end, synchronisation, wire format)."""
