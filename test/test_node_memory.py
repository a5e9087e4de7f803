"""Overload: a burst of huge clouds costs the node nothing lasting. Each is refused from its
header (max_points), later sweeps are all detected, and the memory DDS took for the burst goes
back (the loopback profile's DYNAMIC history, config/fastdds_loopback.xml)."""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import NodeOutputs, wait_until
from sensor_msgs.msg import PointCloud2, PointField

from msg_adapters.family import rclpy_family
from msg_adapters.pointcloud2 import create_cloud

pytestmark = [pytest.mark.ros, pytest.mark.slow]

HUGE_POINTS = 8_000_000  # 128 MB of x y z intensity: past max_points (2**20) many times over
STAMP0 = 1_700_000_000


def rss_mb(pid: int) -> float:
    with open(f'/proc/{pid}/status') as status:
        return int(status.read().split('VmRSS:')[1].split()[0]) / 1024


def plane_cloud(family, k: int) -> PointCloud2:
    """A 64 x 1024 road plane at the sweep k stamp (10 Hz)."""
    rng = np.random.default_rng(k)
    points = np.zeros(65536, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                    ('intensity', '<f4')])
    points['x'], points['y'] = rng.uniform(-20, 20, (2, 65536))
    points['z'], points['intensity'] = -1.8, rng.uniform(0, 1, 65536)
    return create_cloud(PointCloud2, family.header(STAMP0 * 10**9 + k * 10**8, 'lidar'), points)


def huge_cloud(family, k: int) -> PointCloud2:
    """HUGE_POINTS zero points: the bytes DDS must carry, without building them point by point."""
    fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, n in enumerate(('x', 'y', 'z', 'intensity'))]
    return PointCloud2(header=family.header(STAMP0 * 10**9 + k * 10**8, 'lidar'), height=1,
                       width=HUGE_POINTS, fields=fields, is_bigendian=False, point_step=16,
                       row_step=16 * HUGE_POINTS, data=bytes(16 * HUGE_POINTS), is_dense=True)


def test_a_burst_of_huge_clouds_is_refused_and_its_memory_returned(ros_env, rclpy_context):
    node = subprocess.Popen([sys.executable, '-m', 'fhld_ros.ros.lane_detector', '--ros-args',
                             '-p', 'detector:=classical'], env=ros_env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    outputs = NodeOutputs(rclpy_context, 'burst_listener')
    family = rclpy_family()
    pub_node = rclpy.create_node('burst_publisher', context=rclpy_context)
    pub = pub_node.create_publisher(PointCloud2, 'points',
                                    QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
    try:
        assert wait_until(lambda: pub.get_subscription_count() > 0 and
                          outputs.node.count_publishers('lanes') > 0, 60)
        small = [plane_cloud(family, k) for k in range(3)]

        def send(msg: PointCloud2, k: int) -> None:
            msg.header.stamp.sec, msg.header.stamp.nanosec = STAMP0 + k // 10, k % 10 * 10**8
            pub.publish(msg)
            time.sleep(0.1)
        for k in range(30):
            send(small[k % 3], k)
        assert wait_until(lambda: len(outputs.lanes) >= 10, 30), len(outputs.lanes)
        warm = rss_mb(node.pid)
        huge = huge_cloud(family, 0)
        for k in range(30, 33):
            send(huge, k)
        del huge
        # A reliable keep-last-5 writer drops a sample still unacknowledged once five newer ones
        # are queued, and a 128 MB cloud takes seconds of UDP fragments on a loaded machine: the
        # burst must land before traffic resumes, or DDS, not the node, loses one of it.
        assert wait_until(lambda: outputs.diagnostic_values().get('bad_clouds') == '3', 60), \
            outputs.diagnostic_values()
        before = len(outputs.lanes)
        for k in range(33, 63):
            send(small[k % 3], k)
        assert wait_until(lambda: len(outputs.lanes) - before >= 10, 30)  # detecting on
        assert outputs.diagnostic_values().get('bad_clouds') == '3'
        time.sleep(1.0)
        grown = rss_mb(node.pid) - warm
        # with rmw's preallocated history about one burst cloud stays for good (+134 MB with
        # 96 MB clouds); what remains with DYNAMIC history is the allocator's (30-50 MB)
        assert grown < 0.6 * 16 * HUGE_POINTS / 2**20, f'{grown:.0f} MB kept after the burst'
        assert node.poll() is None
    finally:
        outputs.close()
        pub_node.destroy_node()
        node.terminate()
        node.wait(30)
