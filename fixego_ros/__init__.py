"""fixego_ros: ego-motion from binocular independent fixation control (ROS 2 Jazzy)."""

__version__ = '0.1.0'
