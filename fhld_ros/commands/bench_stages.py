"""`fhld bench` stage sections, one function each: () -> {name: value}, timings in ms (medians).

Every section runs on synthetic input made here, so the figures compare across machines and
commits: an Ouster-like 64x1024 cloud, a street-canyon sweep, curved lanes, a random raster.
"""
from __future__ import annotations

import functools
import math
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from fhld_ros.bev import BevSpec
from fhld_ros.classical import ClassicalLaneDetector
from fhld_ros.evaluation.metrics import once_counts, once_counts_official, point_counts
from fhld_ros.intensity import CONTRAST
from fhld_ros.model.checkpoint import build_default_detector
from fhld_ros.model.inference import TracedFeatures, serving_features
from fhld_ros.rolling_grid import RollingBevGrid
from fhld_ros.sim.simulator import Simulator
from msg_adapters.family import rosbags_family
from msg_adapters.pointcloud2 import create_cloud, read_xyzi


def time_median(fn: Callable[[], object], repeats: int = 20, warmup: int = 2) -> float:
    """Median wall time of ``fn()`` in milliseconds."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - start) * 1e3)
    return statistics.median(samples)


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
    msg = ouster_like_cloud()
    decode_ms = time_median(lambda: read_xyzi(msg), repeats=50, warmup=5)
    points = msg.height * msg.width
    return {'decode_ms': decode_ms, 'decode_mpoints_per_s': points / decode_ms / 1e3,
            'points_per_sweep': float(points)}


def bench_bev() -> dict[str, float]:
    """`fhld bench bev`: 64x1024 sweeps at 10 Hz, 10 accumulated, ego at 10 m/s turning."""

    rng = np.random.default_rng(0)
    sweeps = [synthetic_sweep(rng) for _ in range(4)]
    # the shipped weights' encoding: each sweep's ground level measured (fhld_ros/intensity.py)
    grid = RollingBevGrid(BevSpec(), accumulate_sec=1.0, max_sweeps=10,
                          intensity_encoding=CONTRAST)
    state = {'k': 0}

    def insert() -> None:
        k = state['k'] = state['k'] + 1
        yaw = 0.02 * k
        pose = np.eye(4)
        pose[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        pose[:2, 3] = [1000.0 + k, 2000.0 + 0.1 * k]
        xyz, inten = sweeps[k % len(sweeps)]
        grid.insert(k * 100_000_000, xyz, inten, pose)

    for _ in range(10):
        insert()
    insert_ms = time_median(insert, repeats=30, warmup=2)
    raster_ms = time_median(grid.window, repeats=20, warmup=2)
    window = grid.window()
    return {'grid_insert_ms': insert_ms, 'raster_ms': raster_ms,
            'raster_points': float(window.points_window.shape[0]),
            'grid_points': float(sum(s.e.shape[0] for s in grid._sweeps))}


def synthetic_sweep(rng: np.random.Generator, beams: int = 64,
                    columns: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """A beams x columns spinning-LiDAR sweep of a street canyon (benchmarks and tests).

    Ground at z = -1.8 m below the sensor, walls at |y| = 7 m, far returns capped at 80 m;
    intensity 0-255 with bright 15 cm lane stripes at y = +-1.75 m.
    """
    elev = np.deg2rad(np.linspace(-25.0, 15.0, beams))[:, None]
    azim = np.linspace(-np.pi, np.pi, columns, endpoint=False)[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim),
                                     np.sin(elev)), axis=-1).reshape(-1, 3)
    with np.errstate(divide='ignore'):
        t_ground = np.where(d[:, 2] < 0, -1.8 / d[:, 2], np.inf)
        t_wall = np.where(d[:, 1] != 0, 7.0 / np.abs(d[:, 1]), np.inf)
    r = np.minimum(np.minimum(t_ground, t_wall), 80.0) + rng.normal(0, 0.01, d.shape[0])
    xyz = (d * r[:, None]).astype(np.float32)
    on_stripe = (np.abs(np.abs(xyz[:, 1]) - 1.75) < 0.075) & (xyz[:, 2] < -1.7)
    intensity = np.where(on_stripe, 180.0, 20.0) + rng.uniform(0, 15, d.shape[0])
    return xyz, intensity.astype(np.float32)


def bench_classical() -> dict[str, float]:
    """`fhld bench classical`: detect on 10 accumulated synthetic 64x1024 sweeps."""
    rng = np.random.default_rng(0)
    grid = RollingBevGrid(accumulate_sec=1.0, max_sweeps=10)
    for k in range(10):
        pose = np.eye(4)
        pose[0, 3] = 1.0 * k  # 10 m/s at 10 Hz
        grid.insert(k * 100_000_000, *synthetic_sweep(rng), pose)
    window = grid.window()
    points, intensity = np.asarray(window.points_window), np.asarray(window.intensity)
    detector = ClassicalLaneDetector()
    return {'classical_detect_ms': time_median(lambda: detector.detect(points, intensity),
                                               repeats=5, warmup=1),
            'classical_points': float(len(points))}


def bench_metrics() -> dict[str, float]:
    """`fhld bench metrics`: per-frame cost of each metric, 4 curved lanes against 4."""

    x = np.linspace(-12.8, 12.8, 65)
    gt = [np.column_stack([x, y + x**2 / 120.0, np.full_like(x, -1.8)])
          for y in (-5.25, -1.75, 1.75, 5.25)]
    pred = [lane + [0.0, 0.06, 0.01] for lane in gt]
    return {
        'metric_point_ms': time_median(lambda: point_counts(pred, gt), repeats=10),
        'metric_once_ms': time_median(lambda: once_counts(pred, gt, 12.8), repeats=10),
        'metric_once_official_ms': time_median(
            lambda: once_counts_official(pred, [1.0] * 4, gt), repeats=10),
    }


def bench_model() -> dict[str, float]:
    """`fhld bench model`: forward + detect post-processing, 640 x 640, batch 1, on the CPU.

    model_ms is the path the node and `fhld replay` serve with (serving_features in
    inference.py: ONNX Runtime when installed, one thread per core as the node's default);
    model_torchscript_ms and model_eager_ms the alternatives, on the caller's torch threads.
    """
    model = build_default_detector().eval()
    cfg = model.cfg
    gen = torch.Generator().manual_seed(0)
    raster = torch.rand(1, cfg.in_channels, cfg.size_px, cfg.size_px, generator=gen)
    raster[:, :, ::3] = 0  # sparse-ish, like a real BEV raster
    with torch.inference_mode():
        prob = model(raster)['logits'].softmax(-1)[0, :, 1]
    # Post-processing cost grows with the lanes found: time it with 8, the most a window holds.
    threshold = float(prob.topk(min(8, len(prob))).values[-1])
    runners = {'model_ms': serving_features(model), 'model_torchscript_ms': TracedFeatures(model),
               'model_eager_ms': None}  # None: detect() runs the plain module

    def detect_with(run) -> None:
        model.detect(raster, threshold, features=None if run is None else run(raster))
    return {name: time_median(functools.partial(detect_with, run), repeats=20, warmup=3)
            for name, run in runners.items()}


def bench_simulator() -> dict[str, float]:
    """`fhld bench simulator`: one 64x1024 sweep (os1-64), median over a moving ego."""

    sim = Simulator(seed=7, sweeps=60, sensor='os1-64', road='urban', speed=12.0)
    state = {'k': 0}

    def one() -> None:
        state['k'] = (state['k'] + 1) % sim.n_sweeps
        sim.sweep(state['k'])

    ms = time_median(one, repeats=20, warmup=2)
    return {'sim_sweep_ms': ms, 'sim_points': float(sim.sweep(0).points.shape[0])}
