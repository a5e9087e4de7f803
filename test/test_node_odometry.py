"""LaneDetectorNode when odometry stops and comes back (issue #17): the poll's clock check lets a
sweep that waits for odometry in when nothing more arrives, the node detects per sweep in the
cloud frame and says so on /diagnostics (WARN), and returns to the odometry frame after."""
from __future__ import annotations

import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import Odometry
from ros_helpers import wait_until
from sensor_msgs.msg import PointCloud2
from test_node import START_NS, running  # noqa: F401  (running: the node fixture)

from msg_adapters.family import rclpy_family
from msg_adapters.lanes import marker_array_to_lanes
from msg_adapters.odometry import euler_to_matrix, make_odometry
from msg_adapters.pointcloud2 import create_cloud

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SWEEP_NS = 100_000_000


def _cloud(stamp_ns: int) -> PointCloud2:
    rng = np.random.default_rng(0)
    points = np.zeros(4000, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                   ('intensity', '<f4')])
    points['x'], points['y'] = rng.uniform(-12, 12, 4000), rng.uniform(-12, 12, 4000)
    points['z'], points['intensity'] = -1.8, rng.uniform(0, 30, 4000)
    return create_cloud(PointCloud2, rclpy_family().header(stamp_ns, 'lidar'), points)


def _odom(stamp_ns: int) -> Odometry:
    pose = euler_to_matrix(2.0 * (stamp_ns - START_NS) * 1e-8, 0, 0, 0, 0, 0)
    return make_odometry(rclpy_family(), rclpy_family().header(stamp_ns, 'odom'), 'lidar', pose)


def test_odometry_that_stops_falls_back_per_sweep_and_comes_back(running):  # noqa: F811
    node, probe = running(detector='classical', size_px=128, resolution_m=0.2,
                          odom_wait_sec=0.3)
    assert wait_until(lambda: probe.points.get_subscription_count() > 0
                      and probe.odom.get_subscription_count() > 0, 10)

    def frame_at(stamp_ns: int) -> str | None:
        for msg in list(probe.lanes):
            if marker_array_to_lanes(msg).stamp_ns == stamp_ns:
                return msg.markers[0].header.frame_id
        return None

    s0, s1, s2 = (START_NS + k * SWEEP_NS for k in range(3))
    probe.odom.publish(_odom(s0))
    probe.points.publish(_cloud(s0))
    assert wait_until(lambda: frame_at(s0) == 'odom', 10)
    # then a sweep whose odometry never comes, and nothing else: the clock check lets it in
    probe.points.publish(_cloud(s1))
    assert wait_until(lambda: frame_at(s1) is not None, 10), probe.diagnostic_values()
    assert frame_at(s1) == 'lidar'
    assert wait_until(lambda: probe.diagnostic_values().get('odometry_stopped') == 'true', 5)
    status = probe.diagnostics[-1].status[0]
    assert (status.level, status.message) == (
        DiagnosticStatus.WARN, 'odometry stopped: detecting per sweep')
    values = probe.diagnostic_values()
    assert (values['clouds_without_odometry'], values['odometry_timeouts']) == ('1', '1')
    assert values.get('bad_clouds', '0') == '0'
    # odometry comes back: the odometry frame again, and the warning clears
    probe.odom.publish(_odom(s2))
    probe.points.publish(_cloud(s2))
    assert wait_until(lambda: frame_at(s2) == 'odom', 10), probe.diagnostic_values()
    assert wait_until(lambda: probe.diagnostic_values().get('odometry_stopped') == 'false', 5)
    assert probe.diagnostics[-1].status[0].level == DiagnosticStatus.OK
    assert node.pipeline.counters['clouds'] == 3


def test_a_sweep_whose_pose_was_lost_goes_in_extrapolated_without_waiting(running):  # noqa: F811
    # issue #34: DDS lost 10-45 % of the poses published just before a 3 MB cloud
    node, probe = running(detector='classical', size_px=128, resolution_m=0.2)
    assert wait_until(lambda: probe.points.get_subscription_count() > 0
                      and probe.odom.get_subscription_count() > 0, 10)

    def lanes_at(stamp_ns: int):
        for msg in list(probe.lanes):
            if marker_array_to_lanes(msg).stamp_ns == stamp_ns:
                return msg
        return None

    stamps = [START_NS + k * SWEEP_NS for k in range(8)]
    for stamp in stamps[:6]:  # poses come before their sweeps: the node learns that
        probe.odom.publish(_odom(stamp))
        assert wait_until(lambda s=stamp: node.pipeline.odometry.newest == s, 5)
        probe.points.publish(_cloud(stamp))
        assert wait_until(lambda s=stamp: lanes_at(s) is not None, 10)
    lost = stamps[6]
    sent = time.monotonic()
    probe.points.publish(_cloud(lost))  # its pose never comes
    assert wait_until(lambda: lanes_at(lost) is not None, 10), probe.diagnostic_values()
    # it went in well before the next pose or odom_wait_sec (1 s) would have let it in
    assert time.monotonic() - sent < 0.5
    assert lanes_at(lost).markers[0].header.frame_id == 'odom'
    window = lanes_at(lost).markers[-1]  # the window outline, centred on the extrapolated pose
    centre = np.mean([[p.x, p.y] for p in window.points[:4]], axis=0)
    np.testing.assert_allclose(centre, [2.0 * 6 * SWEEP_NS * 1e-8, 0.0], atol=1e-3)
    assert (node.pipeline.counters['clouds_extrapolated'],
            node.pipeline.counters['clouds_without_odometry']) == (1, 0)
    probe.odom.publish(_odom(stamps[7]))
    probe.points.publish(_cloud(stamps[7]))
    assert wait_until(lambda: lanes_at(stamps[7]) is not None, 10)
    assert node.pipeline.counters['clouds_extrapolated'] == 1
