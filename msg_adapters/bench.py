"""`fhld bench adapters`: PointCloud2 decode speed for an Ouster-like 64x1024 cloud."""
from __future__ import annotations

import numpy as np

from msg_adapters.family import rosbags_family
from msg_adapters.pointcloud2 import create_cloud, read_xyzi

# Ouster OS-1 legacy layout: 48-byte points with padding after z and between fields.
OUSTER_LEGACY = np.dtype({
    'names': ['x', 'y', 'z', 'intensity', 't', 'reflectivity', 'ring', 'ambient', 'range'],
    'formats': ['<f4', '<f4', '<f4', '<f4', '<u4', '<u2', '<u2', '<u2', '<u4'],
    'offsets': [0, 4, 8, 16, 20, 24, 26, 28, 32], 'itemsize': 48})


def ouster_like_cloud(rows: int = 64, cols: int = 1024, seed: int = 0) -> object:
    """A rosbags PointCloud2 with random returns and ~10 % zero no-returns."""
    rng = np.random.default_rng(seed)
    points = np.zeros(rows * cols, dtype=OUSTER_LEGACY)
    returned = rng.random(points.size) > 0.1
    for axis in 'xyz':
        points[axis][returned] = rng.uniform(-50, 50, returned.sum())
    points['reflectivity'] = rng.integers(0, 255, points.size)
    family = rosbags_family()
    return create_cloud(family.cls('sensor_msgs/msg/PointCloud2'), family.header(0, 'os_lidar'),
                        points, height=rows)


def bench_decode() -> dict[str, float]:
    from fhld_ros.bench import time_median
    msg = ouster_like_cloud()
    decode_ms = time_median(lambda: read_xyzi(msg), repeats=50, warmup=5)
    points = msg.height * msg.width
    return {'decode_ms': decode_ms, 'decode_mpoints_per_s': points / decode_ms / 1e3,
            'points_per_sweep': float(points)}
