"""Geometry shared across the package: polylines resampled by arc length, and stamped rigid
poses interpolated, extrapolated and looked up. Pure numpy (scipy for rotation vectors)."""
from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np

from msg_adapters.odometry import matrix_to_quaternion, quaternion_to_matrix


def resample_polyline(points: np.ndarray, step: float) -> np.ndarray:
    """Points at equal arc length along a polyline ((K, D), any D), spacing <= step, both ends
    kept."""
    pts = np.asarray(points, dtype=np.float64)
    pts = pts.reshape(-1, pts.shape[-1])
    if len(pts) < 2:
        return pts.copy()
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    pts = pts[np.concatenate([[True], seg > 0])]  # np.interp needs increasing arc length
    seg = seg[seg > 0]
    if len(pts) < 2:
        return pts.copy()
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, arc[-1], int(np.ceil(arc[-1] / step)) + 1)
    return np.stack([np.interp(t, arc, pts[:, k]) for k in range(pts.shape[1])], axis=1)


def resample_to_count(xyz: np.ndarray, count: int) -> np.ndarray | None:
    """count points equally spaced in 3D arc length; None for a degenerate lane."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if len(xyz) < 2:
        return None
    step = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    keep = np.concatenate([[True], step > 1e-9])  # repeated points break the interpolation
    xyz, arc = xyz[keep], np.concatenate([[0.0], np.cumsum(step[step > 1e-9])])
    if arc[-1] <= 1e-6:
        return None
    s = np.linspace(0.0, arc[-1], count)
    return np.stack([np.interp(s, arc, xyz[:, k]) for k in range(3)], axis=1)


def slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    """Shortest-arc spherical interpolation of unit quaternions (x, y, z, w)."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly parallel: lerp is exact enough and avoids 0/0
        q = q0 + fraction * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - fraction) * theta) * q0 + np.sin(fraction * theta) * q1) / np.sin(theta)


def interpolate_pose(t: float, t0: float, pose0: np.ndarray, t1: float,
                     pose1: np.ndarray) -> np.ndarray:
    """Pose at time t between two stamped 4x4 poses (linear translation, slerp rotation).

    Outside [t0, t1] the fraction is clamped: a small extrapolation is safer as a hold.
    """
    fraction = 0.0 if t1 == t0 else float(np.clip((t - t0) / (t1 - t0), 0.0, 1.0))
    transform = np.eye(4)
    q = slerp(matrix_to_quaternion(pose0[:3, :3]), matrix_to_quaternion(pose1[:3, :3]), fraction)
    transform[:3, :3] = quaternion_to_matrix(q)
    transform[:3, 3] = (1 - fraction) * pose0[:3, 3] + fraction * pose1[:3, 3]
    return transform


def _left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian V: exp of a twist (rotvec, u) moves by V u."""
    theta = float(np.linalg.norm(rotvec))
    k = np.array([[0, -rotvec[2], rotvec[1]], [rotvec[2], 0, -rotvec[0]],
                  [-rotvec[1], rotvec[0], 0]])
    if theta < 1e-9:
        return np.eye(3) + 0.5 * k
    return (np.eye(3) + (1 - np.cos(theta)) / theta ** 2 * k
            + (theta - np.sin(theta)) / theta ** 3 * k @ k)


def extrapolate_pose(t: float, t0: float, pose0: np.ndarray, t1: float,
                     pose1: np.ndarray) -> np.ndarray:
    """Pose at time t >= t1, continuing the motion from pose0 (t0) to pose1 (t1 > t0) at the
    same body-frame twist: exact for constant speed and turn rate (a screw motion)."""
    from scipy.spatial.transform import Rotation

    step = np.linalg.solve(pose0, pose1)  # pose0^-1 pose1: the motion in pose0's frame
    rotvec = Rotation.from_matrix(step[:3, :3]).as_rotvec()
    u = np.linalg.solve(_left_jacobian(rotvec), step[:3, 3])
    k = (t - t1) / (t1 - t0)
    ahead = np.eye(4)
    ahead[:3, :3] = Rotation.from_rotvec(rotvec * k).as_matrix()
    ahead[:3, 3] = _left_jacobian(rotvec * k) @ (u * k)
    return pose1 @ ahead


def pose_at(stamps: Sequence[int], poses: Sequence[np.ndarray], stamp_ns: int,
            max_gap_ns: int | None) -> np.ndarray | None:
    """The pose at stamp_ns from sorted stamped poses: the one at exactly that stamp, else
    interpolated between the two around it (None outside them, or when they lie more than
    max_gap_ns apart)."""
    index = bisect.bisect_left(stamps, stamp_ns)
    if index < len(stamps) and stamps[index] == stamp_ns:
        return poses[index]
    if index == 0 or index == len(stamps):
        return None
    t0, t1 = int(stamps[index - 1]), int(stamps[index])
    if max_gap_ns is not None and t1 - t0 > max_gap_ns:
        return None
    return interpolate_pose(stamp_ns, t0, poses[index - 1], t1, poses[index])
