"""nav_msgs/Odometry and geometry_msgs/Pose <-> 4x4 homogeneous matrices."""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from msg_adapters.family import MessageFamily

# |q| may differ from 1 by float32 rounding or a driver's own normalisation, not by more: a
# zero or scaled quaternion is a broken message, not a rotation to guess.
QUATERNION_NORM_TOLERANCE = 1e-3


def quaternion_to_matrix(q: Sequence[float]) -> np.ndarray:
    """(x, y, z, w) -> 3x3 rotation; the quaternion need not be normalised."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """3x3 rotation -> (x, y, z, w) with w >= 0 (Shepperd's method, stable for all angles)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(m)
    candidates = np.array([trace, m[0, 0], m[1, 1], m[2, 2]])
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    return q if q[3] >= 0 else -q


def euler_to_matrix(x: float, y: float, z: float, roll: float, pitch: float,
                    yaw: float) -> np.ndarray:
    """[x, y, z, roll, pitch, yaw] (ROS fixed-axis RPY, radians) -> 4x4."""
    cr, sr, cp, sp, cy, sy = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch),
                              np.cos(yaw), np.sin(yaw))
    transform = np.eye(4)
    transform[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                         [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                         [-sp, cp * sr, cp * cr]]
    transform[:3, 3] = (x, y, z)
    return transform


def rigid_matrix(position: Any, orientation: Any, what: tuple[str, str]) -> np.ndarray:
    """A message's point/vector (x, y, z) and quaternion (x, y, z, w) -> 4x4.

    ValueError, naming them by `what` (e.g. ('pose position', 'pose orientation')), for a
    non-finite position or a quaternion that is not finite or not of unit norm (within
    QUATERNION_NORM_TOLERANCE).
    """
    q = np.array((orientation.x, orientation.y, orientation.z, orientation.w), dtype=np.float64)
    t = np.array((position.x, position.y, position.z), dtype=np.float64)
    if not np.isfinite(t).all():
        raise ValueError(f'{what[0]} (x, y, z) = {tuple(t.tolist())} is not finite')
    if not np.isfinite(q).all():
        raise ValueError(f'{what[1]} (x, y, z, w) = {tuple(q.tolist())} is not finite')
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise ValueError(f'{what[1]} (x, y, z, w) = {tuple(q.tolist())} has norm '
                         f'{norm:.6g}, not 1 (tolerance {QUATERNION_NORM_TOLERANCE:g})')
    transform = np.eye(4)
    transform[:3, :3] = quaternion_to_matrix(q)
    transform[:3, 3] = t
    return transform


def pose_to_matrix(pose: Any) -> np.ndarray:
    """geometry_msgs/Pose (any family) -> 4x4; ValueError as rigid_matrix."""
    return rigid_matrix(pose.position, pose.orientation, ('pose position', 'pose orientation'))


def odometry_to_matrix(odom: Any) -> np.ndarray:
    """Pose of odom.child_frame_id in odom.header.frame_id as a 4x4; ValueError for a
    non-finite or non-unit pose (see pose_to_matrix)."""
    return pose_to_matrix(odom.pose.pose)


def rigid_message(family: MessageFamily, transform: np.ndarray, msgtype: str,
                  fields: tuple[str, str], vector_type: str) -> Any:
    """4x4 -> a message of a vector and a quaternion (Pose: position/orientation as a Point;
    Transform: translation/rotation as a Vector3)."""
    transform = np.asarray(transform, dtype=np.float64)
    q = matrix_to_quaternion(transform[:3, :3])
    t = transform[:3, 3]
    return family.new(msgtype, **{
        fields[0]: family.new(vector_type, x=float(t[0]), y=float(t[1]), z=float(t[2])),
        fields[1]: family.new('geometry_msgs/msg/Quaternion', x=float(q[0]), y=float(q[1]),
                              z=float(q[2]), w=float(q[3]))})


def matrix_to_pose(family: MessageFamily, transform: np.ndarray) -> Any:
    return rigid_message(family, transform, 'geometry_msgs/msg/Pose',
                         ('position', 'orientation'), 'geometry_msgs/msg/Point')


def make_odometry(family: MessageFamily, header: Any, child_frame_id: str, transform: np.ndarray,
                  linear: Sequence[float] = (0.0, 0.0, 0.0),
                  angular: Sequence[float] = (0.0, 0.0, 0.0)) -> Any:
    """nav_msgs/Odometry with the pose of `child_frame_id` and a twist in the child frame."""
    vec = 'geometry_msgs/msg/Vector3'
    twist = family.new('geometry_msgs/msg/Twist',
                       linear=family.new(vec, **dict(zip('xyz', map(float, linear)))),
                       angular=family.new(vec, **dict(zip('xyz', map(float, angular)))))
    return family.new(
        'nav_msgs/msg/Odometry', header=header, child_frame_id=child_frame_id,
        pose=family.new('geometry_msgs/msg/PoseWithCovariance',
                        pose=matrix_to_pose(family, transform)),
        twist=family.new('geometry_msgs/msg/TwistWithCovariance', twist=twist))
