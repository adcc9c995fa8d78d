"""ament_python package setup; also installs with plain pip into a venv (ROS from the ros-jazzy wheels)."""

from glob import glob

from setuptools import find_packages, setup

package_name = 'fixego_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    package_data={package_name: ['data/*']},
    python_requires='>=3.11',
    install_requires=[
        'setuptools',
        'numpy',
        'scipy',
        'opencv-python-headless',
        'pyserial',
        'pyyaml',
        'rosbags',
        'mcap',
        'evo',
        'matplotlib',
        'gtsam',
        'threadpoolctl',
    ],
    extras_require={
        # ROS 2 Jazzy from PyPI wheels; on a full ROS install these come from the distro instead.
        'ros': ['ros-jazzy-rclpy[fastrtps]', 'ros-jazzy-common-interfaces'],
        'test': ['pytest', 'hypothesis', 'ruff', 'colcon-common-extensions', 'visca-over-ip'],
    },
    zip_safe=True,
    maintainer='fixego_ros maintainers',
    maintainer_email='fixego@example.com',
    description='Binocular independent fixation ego-motion estimation for ROS 2 Jazzy.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'fixego = fixego_ros.cli:main',
            'sim_rig_node = fixego_ros.nodes.sim_rig_node:main',
            'camera_node = fixego_ros.nodes.camera_node:main',
            'flow_node = fixego_ros.nodes.flow_node:main',
            'estimator_node = fixego_ros.nodes.estimator_node:main',
            'bag_player = fixego_ros.nodes.bag_player:main',
            'bag_recorder = fixego_ros.nodes.bag_recorder:main',
        ],
    },
)
