"""A PointCloud2 crosses two processes over DDS confined to loopback (conftest's profile)."""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
from sensor_msgs.msg import PointCloud2

from msg_adapters.pointcloud2 import read_xyzi

pytestmark = pytest.mark.ros

PUBLISHER = r'''
import sys, time
import numpy as np
import rclpy
from msg_adapters.family import rclpy_family
from msg_adapters.pointcloud2 import create_cloud
rclpy.init()
node = rclpy.create_node('cloud_publisher')
family = rclpy_family()
pub = node.create_publisher(family.cls('sensor_msgs/msg/PointCloud2'), 'points', 5)
points = np.zeros(64 * 128, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                   ('intensity', '<f4')])
points['x'] = np.arange(points.size)
points['y'] = 2.0
points['z'] = -1.5
points['intensity'] = np.arange(points.size) % 255
deadline = time.monotonic() + 30
while time.monotonic() < deadline:
    pub.publish(create_cloud(pub.msg_type,
                             family.header(42, 'lidar'), points, height=64))
    rclpy.spin_once(node, timeout_sec=0.1)
'''


def test_pointcloud2_crosses_processes_on_loopback(ros_env, rclpy_context):
    assert ros_env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    assert ros_env['FASTRTPS_DEFAULT_PROFILES_FILE'].endswith('fastdds_loopback.xml')
    publisher = subprocess.Popen([sys.executable, '-c', PUBLISHER], env=ros_env)
    node = rclpy.create_node('cloud_listener', context=rclpy_context)
    received = []
    node.create_subscription(PointCloud2, 'points', received.append, 5)
    executor = rclpy.executors.SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 30
        while not received and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
    finally:
        publisher.kill()
        publisher.wait()
        node.destroy_node()
    assert received, 'no PointCloud2 arrived from the publisher process within 30 s'
    msg = received[0]
    assert (msg.height, msg.width, msg.header.frame_id) == (64, 128, 'lidar')
    xyz, intensity = read_xyzi(msg)
    # point 0 is (0, 2, -1.5): not a no-return, all 8192 points survive
    assert xyz.shape == (64 * 128, 3)
    np.testing.assert_array_equal(xyz[:, 0], np.arange(64 * 128))
    np.testing.assert_array_equal(intensity, np.arange(64 * 128) % 255)
