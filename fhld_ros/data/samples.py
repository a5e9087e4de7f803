"""Training samples straight from the simulator, through the node's own input path.

Each sweep is encoded as a PointCloud2 (msg_adapters.pointcloud2.create_cloud), decoded with
read_xyzi and inserted into fhld_ros.bev.RollingBevGrid with the /odom pose, exactly as the
node does; the window's raster is the sample, and the GT lines are cut to the window square.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from fhld_ros.bev import BevSpec, BevWindow
    from fhld_ros.data.simulator import Simulator


@dataclass
class TrainingSample:
    raster: np.ndarray  # (4, H, W) float32, bev.py channel layout
    lanes: list[np.ndarray]  # (K, 3) polylines in the window frame, inside the window
    window_to_odom: np.ndarray  # (4, 4) window frame in the reported odom frame
    meta: dict = field(default_factory=dict)
    window: BevWindow | None = None  # the node's window (points too), with keep_window=True


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def clip_to_square(lines: list[np.ndarray], half: float, min_length: float = 0.2
                   ) -> tuple[list[np.ndarray], list[int]]:
    """Parts of (K, 3) polylines inside the square |x|, |y| < half (window frame).

    Each segment is clipped exactly (Liang-Barsky); consecutive inside segments are joined and a
    line that leaves and re-enters gives several pieces. Returns pieces and their source index.
    """
    out, src = [], []
    for index, line in enumerate(lines):
        if line.shape[0] < 2:
            continue
        p0, p1 = line[:-1], line[1:]
        delta = p1 - p0
        lo = np.zeros(len(p0))
        hi = np.ones(len(p0))
        for axis in (0, 1):
            for sign in (-1.0, 1.0):  # boundary sign * x <= half
                num = half - sign * p0[:, axis]
                den = sign * delta[:, axis]
                with np.errstate(divide='ignore', invalid='ignore'):
                    t = num / den
                lo = np.where(den < 0, np.maximum(lo, t), lo)
                hi = np.where(den > 0, np.minimum(hi, t), hi)
                lo = np.where((den == 0) & (num < 0), 2.0, lo)  # parallel and outside
        seg = np.flatnonzero(lo < hi)
        if seg.size == 0:
            continue
        start = p0[seg] + lo[seg, None] * delta[seg]
        end = p0[seg] + hi[seg, None] * delta[seg]
        # a piece continues while segments follow each other through full vertices
        joined = (np.diff(seg) == 1) & (hi[seg[:-1]] >= 1.0 - 1e-12) & (lo[seg[1:]] <= 1e-12)
        for part in np.split(np.arange(seg.size), np.flatnonzero(~joined) + 1):
            piece = np.vstack([start[part[:1]], end[part]])
            steps = np.linalg.norm(np.diff(piece[:, :2], axis=0), axis=1)
            piece = piece[np.concatenate([[True], steps > 1e-9])]
            if piece.shape[0] >= 2 and steps.sum() >= min_length:
                out.append(piece)
                src.append(index)
    return out, src


def crop_to_disc(lines: list[np.ndarray], centre: np.ndarray, radius: float
                 ) -> tuple[list[np.ndarray], list[int]]:
    """Vertex runs of polylines within radius of centre (xy); keeps each run's line index."""
    out, src = [], []
    for index, line in enumerate(lines):
        inside = np.hypot(line[:, 0] - centre[0], line[:, 1] - centre[1]) <= radius
        for a, b in _runs(inside):
            if b - a >= 2:
                out.append(line[a:b])
                src.append(index)
    return out, src


def training_samples(sim: Simulator, n: int | None = None, sweeps_per_sample: int = 10,
                     stride: int | None = None, spec: BevSpec | None = None,
                     keep_window: bool = False) -> Iterator[TrainingSample]:
    """Up to n samples (default: as many as the run allows), one every `stride` sweeps
    (default sweeps_per_sample), each accumulating the last sweeps_per_sample sweeps (1 s).

    GT is placed with the true pose of the newest sweep, so with odometry drift the target
    stays what the newest sweep shows while older sweeps smear as they would on the car.
    keep_window=True also hands over the BevWindow (its accumulated points feed detectors that
    work on points, such as the classical baseline); it keeps the window's sweeps alive.
    """
    from fhld_ros.bev import BevSpec, RollingBevGrid, yaw_frame
    from msg_adapters.family import rosbags_family
    from msg_adapters.pointcloud2 import create_cloud, read_xyzi

    spec = spec or BevSpec()
    stride = stride or sweeps_per_sample
    if sweeps_per_sample < 1 or stride < 1:
        raise ValueError('sweeps_per_sample and stride must be >= 1')
    fam = rosbags_family()
    cloud_cls = fam.cls('sensor_msgs/msg/PointCloud2')
    grid = RollingBevGrid(spec, accumulate_sec=sweeps_per_sample * 0.1 - 0.05,
                          max_sweeps=sweeps_per_sample)
    made = 0
    for sweep in sim.sweeps():
        msg = create_cloud(cloud_cls, fam.header(sweep.stamp_ns, sim.frame_id), sweep.points,
                           height=sweep.height)
        xyz, intensity = read_xyzi(msg)
        grid.insert(sweep.stamp_ns, xyz, intensity, sweep.odom_pose)
        k = sweep.index
        if k + 1 < sweeps_per_sample or (k + 1 - sweeps_per_sample) % stride:
            continue
        window = grid.window()
        true_frame = yaw_frame(sweep.sensor_to_odom)
        local = [(line - true_frame[:3, 3]) @ true_frame[:3, :3] for line in sim.scene.lane_lines]
        lanes, src = clip_to_square(local, spec.length_m / 2)
        meta = {'seed': sim.seed, 'sweep': k, 'stamp_ns': sweep.stamp_ns,
                'road_class': sim.scene.road_class, 'sensor': sim.config.sensor,
                'sweeps': len(grid), 'line_ids': src}
        yield TrainingSample(window.raster, lanes, window.window_to_output, meta,
                             window if keep_window else None)
        made += 1
        if n is not None and made >= n:
            return
