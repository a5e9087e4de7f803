"""fhld_ros: FHLD 3D lane-line detection in LiDAR point clouds for ROS 2 Jazzy."""

__version__ = '0.1.0'
