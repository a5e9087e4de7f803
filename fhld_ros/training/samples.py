"""Training samples straight from the simulator, through the node's own input path.

Each sweep is encoded as a PointCloud2 (msg_adapters.pointcloud2.create_cloud), decoded with
read_xyzi and inserted into a RollingBevGrid with the /odom pose, exactly as the node does;
the window's raster is the sample, and the GT lines are cut to the window square.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from fhld_ros.bev import BevSpec, yaw_frame
from fhld_ros.rolling_grid import BevWindow, RollingBevGrid
from fhld_ros.sim.gt_lines import clip_to_square
from fhld_ros.sim.simulator import Simulator
from msg_adapters.family import rosbags_family
from msg_adapters.pointcloud2 import create_cloud, read_xyzi


@dataclass
class TrainingSample:
    raster: np.ndarray  # (4, H, W) float32, bev.py channel layout
    lanes: list[np.ndarray]  # (K, 3) polylines in the window frame, inside the window
    window_to_odom: np.ndarray  # (4, 4) window frame in the reported odom frame
    meta: dict = field(default_factory=dict)
    window: BevWindow | None = None  # the node's window (points too), with keep_window=True


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
