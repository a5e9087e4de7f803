"""Training samples straight from the simulator, through the node's own input path.

Each sweep is encoded as a PointCloud2 (msg_adapters.pointcloud2.create_cloud), decoded by the
grid (RollingBevGrid.read_cloud: the ring field too where the encoding tells lasers apart) and
inserted with the /odom pose, exactly as the node does; the window's raster is the sample, and
the GT lines are cut to the window square.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from fhld_ros.bev import BevSpec, yaw_frame
from fhld_ros.intensity import CONTRAST
from fhld_ros.rolling_grid import BevWindow, RollingBevGrid
from fhld_ros.sim.gt_lines import clip_to_square
from fhld_ros.sim.scene import ASPHALT, PAINT
from fhld_ros.sim.simulator import Simulator
from msg_adapters.family import rosbags_family
from msg_adapters.pointcloud2 import INTENSITY_FIELDS, create_cloud


@dataclass
class TrainingSample:
    raster: np.ndarray  # (4, H, W) float32, bev.py channel layout
    lanes: list[np.ndarray]  # (K, 3) polylines in the window frame, inside the window
    window_to_odom: np.ndarray  # (4, 4) window frame in the reported odom frame
    meta: dict = field(default_factory=dict)
    window: BevWindow | None = None  # the node's window (points too), with keep_window=True


def scale_intensity(points: np.ndarray, gain: float) -> np.ndarray:
    """The cloud with its intensity field (intensity, else reflectivity) times gain: what a
    sensor with another gain would send. Integer fields round and saturate at their type's
    range, as a real driver's counts do; float fields are unbounded."""
    name = next((n for n in INTENSITY_FIELDS if n in (points.dtype.names or ())), None)
    if gain == 1.0 or name is None:
        return points
    out = points.copy()
    value = out[name].astype(np.float64) * gain
    kind = out.dtype[name]
    if np.issubdtype(kind, np.integer):
        info = np.iinfo(kind)
        value = np.clip(np.round(value), info.min, info.max)
    out[name] = value
    return out


def paint_contrast(points: np.ndarray, labels: np.ndarray) -> float:
    """Median intensity of paint returns / median of asphalt returns in one sweep (NaN when
    either is missing or the asphalt median is 0): how well paint stands out on this road."""
    name = next((n for n in INTENSITY_FIELDS if n in (points.dtype.names or ())), None)
    if name is None:
        return float('nan')
    value = points[name].astype(np.float64)
    paint, asphalt = value[labels == PAINT], value[labels == ASPHALT]
    if not paint.size or not asphalt.size or np.median(asphalt) <= 0:
        return float('nan')
    return float(np.median(paint) / np.median(asphalt))


def _window_sweeps(n_sweeps: int, n: int | None, per_sample: int, stride: int, start: int
                   ) -> Iterator[tuple[int, bool]]:
    """(sweep index, is the newest sweep of a window) for every sweep some window needs, in
    order: window j ends at start + per_sample - 1 + j * stride; sweeps no window uses are
    never simulated."""
    done = start - 1  # newest sweep handed out so far
    j = 0
    while n is None or j < n:
        end = start + per_sample - 1 + j * stride
        if end >= n_sweeps:
            return
        for k in range(max(done + 1, end - per_sample + 1), end + 1):
            yield k, k == end
        done, j = end, j + 1


def window_ends(n_sweeps: int, per_sample: int, stride: int, start: int = 0) -> list[int]:
    """Index of the newest sweep of every window of a run of n_sweeps (training_samples'
    rule, for sweeps that come from elsewhere, such as a bag)."""
    return [k for k, newest in _window_sweeps(n_sweeps, None, per_sample, stride, start)
            if newest]


def accumulation(sweeps_per_sample: int) -> tuple[float, int]:
    """(accumulate_sec, max_sweeps) of a window of sweeps_per_sample 10 Hz sweeps: the age
    limit lies half a period from the oldest sweep wanted and from the one before it, so stamp
    jitter neither drops the one nor keeps the other."""
    return sweeps_per_sample * 0.1 - 0.05, sweeps_per_sample


def lanes_in_window(lines: list[np.ndarray], window_to_world: np.ndarray, half: float
                    ) -> tuple[list[np.ndarray], list[int]]:
    """World polylines in the window frame (window_to_world: the window's pose), cut to the
    window square |x|, |y| < half; the pieces and their source line index (clip_to_square)."""
    rot, origin = window_to_world[:3, :3], window_to_world[:3, 3]
    return clip_to_square([(line - origin) @ rot for line in lines], half)


def training_samples(sim: Simulator, n: int | None = None, sweeps_per_sample: int = 10,
                     stride: int | None = None, spec: BevSpec | None = None,
                     keep_window: bool = False, intensity_gain: float = 1.0,
                     odometry: bool = True, start: int = 0,
                     intensity_encoding: str = CONTRAST) -> Iterator[TrainingSample]:
    """Up to n samples (default: as many as the run allows), one every `stride` sweeps
    (default sweeps_per_sample), each accumulating the last sweeps_per_sample sweeps (1 s);
    the first window ends at sweep start + sweeps_per_sample - 1.

    GT is placed with the true pose of the newest sweep, so with odometry drift the target
    stays what the newest sweep shows while older sweeps smear as they would on the car.
    keep_window=True also hands over the BevWindow (its accumulated points feed detectors that
    work on points, such as the classical baseline); it keeps the window's sweeps alive.
    intensity_gain multiplies each cloud's intensity field (scale_intensity) before decoding.
    odometry=False is the node without /odom: single sweeps (sweeps_per_sample must be 1)
    in the cloud's own frame, and GT in that frame. intensity_encoding is the grid's (the
    model's, FhldConfig.intensity_encoding). meta['paint_contrast'] is the newest sweep's
    paint_contrast.
    """
    spec = spec or BevSpec()
    stride = stride or sweeps_per_sample
    if sweeps_per_sample < 1 or stride < 1 or start < 0:
        raise ValueError('sweeps_per_sample and stride must be >= 1, start >= 0')
    if not odometry and sweeps_per_sample != 1:
        raise ValueError('without odometry the node detects single sweeps: sweeps_per_sample '
                         'must be 1')
    if not intensity_gain > 0:
        raise ValueError(f'intensity_gain must be > 0, got {intensity_gain}')
    fam = rosbags_family()
    cloud_cls = fam.cls('sensor_msgs/msg/PointCloud2')
    accumulate_sec, max_sweeps = accumulation(sweeps_per_sample)
    grid = RollingBevGrid(spec, accumulate_sec=accumulate_sec, max_sweeps=max_sweeps,
                          intensity_encoding=intensity_encoding)
    for k, newest in _window_sweeps(len(sim), n, sweeps_per_sample, stride, start):
        sweep = sim.sweep(k)
        points = scale_intensity(sweep.points, intensity_gain)
        msg = create_cloud(cloud_cls, fam.header(sweep.stamp_ns, sim.frame_id), points,
                           height=sweep.height)
        xyz, intensity, ring = grid.read_cloud(msg)
        grid.insert(sweep.stamp_ns, xyz, intensity, sweep.odom_pose if odometry else np.eye(4),
                    ring=ring)
        if not newest:
            continue
        window = grid.window()
        # the window frame in the world: the newest sweep's gravity-aligned pose, or without
        # odometry the sensor frame itself (pitch and roll included)
        true_frame = yaw_frame(sweep.sensor_to_odom) if odometry else sweep.sensor_to_odom
        lanes, src = lanes_in_window(sim.scene.lane_lines, true_frame, spec.length_m / 2)
        meta = {'seed': sim.seed, 'sweep': k, 'stamp_ns': sweep.stamp_ns,
                'road_class': sim.scene.road_class, 'sensor': sim.config.sensor,
                'sweeps': len(grid), 'line_ids': src,
                'paint_contrast': paint_contrast(points, sweep.labels)}
        yield TrainingSample(window.raster, lanes, window.window_to_output, meta,
                             window if keep_window else None)
