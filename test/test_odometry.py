"""msg_adapters.odometry: pose <-> matrix, odometry messages, interpolation."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msg_adapters.family import rclpy_family, rosbags_family
from msg_adapters.odometry import (
    euler_to_matrix,
    interpolate_pose,
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
