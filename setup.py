from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'fhld_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=['fhld_ros', 'fhld_ros.*', 'msg_adapters', 'msg_adapters.*']),
    package_data={PACKAGE: ['checkpoints/*.pt']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml') + glob('config/*.xml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='fhld_ros maintainers',
    maintainer_email='fhld-ros@example.com',
    description='FHLD 3D lane detection in LiDAR point clouds for ROS 2 Jazzy',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'lane_detector = fhld_ros.ros.lane_detector:main',
            'camera_lane_detector = fhld_ros.ros.camera_lane_detector:main',
            'fhld = fhld_ros.cli:main',
        ],
    },
)
