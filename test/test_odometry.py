"""msg_adapters.odometry: pose <-> matrix, odometry messages, interpolation."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fhld_ros.geometry import extrapolate_pose, interpolate_pose
from msg_adapters.family import rclpy_family, rosbags_family
from msg_adapters.odometry import (
    euler_to_matrix,
    make_odometry,
    matrix_to_quaternion,
    odometry_to_matrix,
    quaternion_to_matrix,
)

angles = st.floats(-np.pi, np.pi)


@settings(max_examples=100, deadline=None)
@given(angles, st.floats(-1.5, 1.5), angles)
def test_quaternion_matrix_round_trip(roll, pitch, yaw):
    rotation = euler_to_matrix(0, 0, 0, roll, pitch, yaw)[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(rotation)), rotation,
                               atol=1e-9)


def test_euler_matches_ros_convention():
    # yaw 90 deg turns x into y; roll 90 deg turns y into z
    np.testing.assert_allclose(euler_to_matrix(0, 0, 0, 0, 0, np.pi / 2)[:3, 0], [0, 1, 0],
                               atol=1e-12)
    np.testing.assert_allclose(euler_to_matrix(0, 0, 0, np.pi / 2, 0, 0)[:3, 1], [0, 0, 1],
                               atol=1e-12)


@pytest.mark.parametrize('family', [rosbags_family(), rclpy_family()], ids=lambda f: f.name)
def test_odometry_message_round_trip(family):
    transform = euler_to_matrix(1.0, -2.0, 0.5, 0.01, -0.02, 2.5)
    odom = make_odometry(family, family.header(5, 'odom'), 'lidar', transform,
                         linear=(10.0, 0.0, 0.0))
    assert odom.child_frame_id == 'lidar' and odom.header.frame_id == 'odom'
    assert odom.twist.twist.linear.x == 10.0
    np.testing.assert_allclose(odometry_to_matrix(odom), transform, atol=1e-12)


def test_interpolation_is_linear_in_translation_and_slerps_rotation():
    pose0 = euler_to_matrix(0, 0, 0, 0, 0, 0.2)
    pose1 = euler_to_matrix(10, 4, 1, 0, 0, 0.6)
    mid = interpolate_pose(1.25, 1.0, pose0, 1.5, pose1)
    np.testing.assert_allclose(mid, euler_to_matrix(5, 2, 0.5, 0, 0, 0.4), atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(1.0, 1.0, pose0, 1.5, pose1), pose0, atol=1e-12)
    # outside the interval the pose is held, not extrapolated
    np.testing.assert_allclose(interpolate_pose(9.0, 1.0, pose0, 1.5, pose1), pose1, atol=1e-12)


def test_slerp_takes_the_short_way_round():
    pose0 = euler_to_matrix(0, 0, 0, 0, 0, np.pi - 0.1)
    pose1 = euler_to_matrix(0, 0, 0, 0, 0, -np.pi + 0.1)
    mid = interpolate_pose(0.5, 0.0, pose0, 1.0, pose1)
    np.testing.assert_allclose(mid[:3, 0], [-1, 0, 0], atol=1e-9)


def _odometry_with(family, q=None, t=None):
    odom = make_odometry(family, family.header(5, 'odom'), 'lidar', np.eye(4))
    o, p = odom.pose.pose.orientation, odom.pose.pose.position
    if q is not None:
        o.x, o.y, o.z, o.w = map(float, q)
    if t is not None:
        p.x, p.y, p.z = map(float, t)
    return odom


@pytest.mark.parametrize('family', [rosbags_family(), rclpy_family()], ids=lambda f: f.name)
@pytest.mark.parametrize('q,t,message', [
    ((np.nan, 0, 0, 1), None, r'orientation \(x, y, z, w\) = \(nan, 0.0, 0.0, 1.0\) is not '
     'finite'),
    ((0, 0, 0, np.inf), None, 'orientation .* is not finite'),
    ((0, 0, 0, 0), None, 'has norm 0, not 1'),  # "no orientation" from some drivers
    ((0, 0, 0, 2), None, 'has norm 2, not 1'),
    ((0, 0, 0.6, 0.802), None, 'has norm 1.0016, not 1'),
    (None, (1, np.nan, 0), r'position \(x, y, z\) = \(1.0, nan, 0.0\) is not finite'),
    (None, (-np.inf, 0, 0), 'position .* is not finite'),
])
def test_non_finite_or_non_unit_poses_are_refused(family, q, t, message):
    with pytest.raises(ValueError, match=message):
        odometry_to_matrix(_odometry_with(family, q, t))


def test_quaternions_within_rounding_of_unit_norm_are_accepted():
    # float32-rounded or slightly denormalised quaternions from real drivers still pass
    q = np.array([0.0, 0.0, 0.6, 0.8]) * (1 + 9e-4)
    matrix = odometry_to_matrix(_odometry_with(rosbags_family(), q, (1, 2, 3)))
    np.testing.assert_allclose(matrix[:3, :3].T @ matrix[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(matrix[:3, 3], [1, 2, 3])


def test_extrapolation_continues_a_constant_turn_exactly():
    # a car on a circle of radius 50 m at 10 m/s: poses at 0 and 0.1 s, predicted at 0.3 s
    def on_circle(t):
        yaw = 10.0 * t / 50.0
        return euler_to_matrix(50 * np.sin(yaw), 50 * (1 - np.cos(yaw)), 0, 0, 0, yaw)
    predicted = extrapolate_pose(0.3, 0.0, on_circle(0.0), 0.1, on_circle(0.1))
    np.testing.assert_allclose(predicted, on_circle(0.3), atol=1e-9)
    straight = extrapolate_pose(0.3, 0.0, np.eye(4), 0.1, euler_to_matrix(1, 0, 0, 0, 0, 0))
    np.testing.assert_allclose(straight, euler_to_matrix(3, 0, 0, 0, 0, 0), atol=1e-12)
