"""KITTI files: velodyne `.bin` sweeps, odometry poses, times and the LiDAR-camera calibration.

A sweep is float32 x, y, z, reflectance per point (16 bytes, little-endian), in the sensor
frame (x forward, y left, z up). Poses are one 3x4 row-major transform per line; times one
number of seconds per line (KITTI's times.txt, relative to the sequence start).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fhld_ros.errors import ConfigError
from fhld_ros.importing.pcd import XYZI_DTYPE


class KittiError(ConfigError, ValueError):
    """A KITTI file cannot be read; the message names the file and the problem."""


def read_bin(path: str | Path) -> np.ndarray:
    """A velodyne sweep as a structured float32 x, y, z, intensity array."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise KittiError(f'cannot read {path}: {exc.strerror or exc}') from None
    if len(raw) % XYZI_DTYPE.itemsize:
        raise KittiError(f'{path}: {len(raw)} bytes is not a multiple of 16 (float32 x, y, z, '
                         'intensity per point): not a KITTI .bin sweep, or truncated')
    return np.frombuffer(raw, dtype=XYZI_DTYPE).copy()


def _numeric_rows(path: Path, what: str, count: int, needs: str
                  ) -> list[tuple[int, list[float]]]:
    """(line number, numbers) of every non-blank line of a text file, each `count` numbers
    (KittiError naming the line otherwise; `needs` says what the numbers are)."""
    try:
        text = path.read_text(encoding='ascii')
    except (OSError, UnicodeDecodeError) as exc:
        raise KittiError(f'cannot read {what} file {path}: {exc}') from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            rows.append((number, [float(v) for v in line.split()]))
        except ValueError:
            raise KittiError(f'{what} file {path}, line {number}: not numbers: '
                             f'{line.strip()[:60]!r}') from None
        if len(rows[-1][1]) != count:
            raise KittiError(f'{what} file {path}, line {number}: {len(rows[-1][1])} numbers, '
                             f'{needs}')
    return rows


def read_poses(path: str | Path) -> np.ndarray:
    """(N, 4, 4) transforms from a KITTI odometry poses file (12 numbers a line)."""
    path = Path(path)
    rows = _numeric_rows(path, 'poses', 12, 'a 3x4 row-major transform needs 12')
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    if rows:
        poses[:, :3, :] = np.array([v for _, v in rows]).reshape(-1, 3, 4)
    if not np.all(np.isfinite(poses)):
        raise KittiError(f'poses file {path} has non-finite values')
    # a rotation must be orthonormal with det +1 (tolerant of 6-digit files)
    gram = np.einsum('nij,nkj->nik', poses[:, :3, :3], poses[:, :3, :3])
    bad = np.flatnonzero((np.abs(gram - np.eye(3)).max(axis=(1, 2)) > 1e-3)
                         | (np.linalg.det(poses[:, :3, :3]) < 0))
    if bad.size:
        raise KittiError(f'poses file {path}, line {rows[bad[0]][0]}: the 3x3 part is not a '
                         'rotation')
    return poses


def read_times(path: str | Path) -> np.ndarray:
    """(N,) seconds from a KITTI times file (one number a line), strictly increasing."""
    path = Path(path)
    rows = _numeric_rows(path, 'times', 1, 'expected one time in seconds')
    times = np.array([v[0] for _, v in rows], dtype=np.float64)
    if not np.all(np.isfinite(times)):
        raise KittiError(f'times file {path} has non-finite values')
    back = np.flatnonzero(np.diff(times) <= 0)
    if back.size:
        k = back[0] + 1
        raise KittiError(f'times file {path}, line {rows[k][0]}: {times[k]:g} s does not '
                         f'follow {times[k - 1]:g} s (times must increase)')
    return times


def read_velo_to_cam(path: str | Path) -> np.ndarray:
    """4x4 velodyne -> camera-0 transform from a KITTI calib file (`Tr:` as in the odometry
    benchmark's calib.txt, or `Tr_velo_to_cam:` as in the object benchmark's)."""
    path = Path(path)
    try:
        lines = path.read_text(encoding='ascii').splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise KittiError(f'cannot read calib file {path}: {exc}') from None
    for line in lines:
        key, _, rest = line.partition(':')
        if key.strip() in ('Tr', 'Tr_velo_to_cam'):
            try:
                values = [float(v) for v in rest.split()]
            except ValueError:
                values = []
            if len(values) != 12:
                raise KittiError(f'calib file {path}: {key.strip()} needs 12 numbers')
            transform = np.eye(4)
            transform[:3, :] = np.reshape(values, (3, 4))
            return transform
    raise KittiError(f'calib file {path} has no Tr: or Tr_velo_to_cam: line')


def camera_poses_to_lidar(poses: np.ndarray, velo_to_cam: np.ndarray) -> np.ndarray:
    """KITTI ground-truth poses (camera 0 in the first camera frame) as LiDAR poses in the
    first LiDAR frame: Tr^-1 P Tr, so the odometry frame has z up like the sensor."""
    return np.linalg.inv(velo_to_cam) @ poses @ velo_to_cam
