"""The core that the node and `fhld replay` both drive: sweeps and odometry in, lanes out.

    pipeline.add_odometry(msg)        # any time, any order
    pipeline.add_cloud(msg)           # decode + pose + insert into the rolling grid
    out = pipeline.detect()           # None when nothing new arrived since the last call

Lanes come out in the output frame (the odometry's frame, else the cloud's) with stable ids.
"""
from __future__ import annotations

import bisect
import collections
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from scipy.optimize import linear_sum_assignment

from fhld_ros.bev import BevSpec
from fhld_ros.rolling_grid import BevWindow, RollingBevGrid
from fhld_ros.ros.parameters import DetectorParams
from msg_adapters.family import stamp_to_ns
from msg_adapters.odometry import euler_to_matrix, interpolate_pose, odometry_to_matrix
from msg_adapters.pointcloud2 import read_xyzi

ODOM_HISTORY = 400  # ~4 s at 100 Hz
ODOM_HOLD_NS = 200_000_000  # a cloud up to 0.2 s newer than the newest odometry uses it as is
MAX_PENDING = 3  # sweeps that wait for the odometry of their stamp (0.3 s at 10 Hz)


class LaneDetector(Protocol):
    def __call__(self, window: BevWindow) -> tuple[list[np.ndarray], np.ndarray]:
        """Lanes ((K, 3) window frame, ordered) and confidences of one window."""


@dataclass
class LaneOutput:
    """One detection cycle, ready to publish."""

    stamp_ns: int
    frame_id: str
    lanes: list[np.ndarray]  # (K, 3) output frame
    confidences: np.ndarray
    ids: np.ndarray
    outline: np.ndarray  # (5, 3) output frame
    ego_left: np.ndarray | None
    ego_right: np.ndarray | None
    timings_ms: dict[str, float] = field(default_factory=dict)


class PoseBuffer:
    """Recent stamped poses of one frame pair, interpolated at query stamps."""

    def __init__(self, capacity: int = ODOM_HISTORY) -> None:
        self.capacity = capacity
        self.stamps: list[int] = []
        self.poses: list[np.ndarray] = []

    def clear(self) -> None:
        self.stamps.clear()
        self.poses.clear()

    def add(self, stamp_ns: int, pose: np.ndarray) -> None:
        if self.stamps and stamp_ns < self.stamps[-1] - 1_000_000_000:
            self.clear()  # time went back (bag loop): old poses belong to another run
        index = bisect.bisect(self.stamps, stamp_ns)
        self.stamps.insert(index, stamp_ns)
        self.poses.insert(index, pose)
        if len(self.stamps) > self.capacity:
            del self.stamps[0], self.poses[0]

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """Pose at stamp_ns, or None when the stamp is outside the buffered span."""
        if not self.stamps:
            return None
        index = bisect.bisect_left(self.stamps, stamp_ns)
        if index < len(self.stamps) and self.stamps[index] == stamp_ns:
            return self.poses[index]
        if index == 0:
            return None
        if index == len(self.stamps):
            return self.poses[-1] if stamp_ns - self.stamps[-1] <= ODOM_HOLD_NS else None
        return interpolate_pose(stamp_ns, self.stamps[index - 1], self.poses[index - 1],
                                self.stamps[index], self.poses[index])


class LaneIdTracker:
    """Keeps a lane's id from one cycle to the next by matching lanes in the output frame."""

    def __init__(self, max_mean_distance_m: float = 1.0) -> None:
        self.max_distance = max_mean_distance_m
        self.previous: list[np.ndarray] = []
        self.previous_ids: np.ndarray = np.zeros(0, dtype=np.int64)
        self.next_id = 0

    def reset(self) -> None:
        self.previous, self.previous_ids = [], np.zeros(0, dtype=np.int64)

    def assign(self, lanes: list[np.ndarray]) -> np.ndarray:
        ids = np.full(len(lanes), -1, dtype=np.int64)
        if lanes and self.previous:
            cost = np.array([[_mean_distance(a, b) for b in self.previous] for a in lanes])
            # inf (no overlap) would make the assignment infeasible; such pairs fail the test
            rows, cols = linear_sum_assignment(np.minimum(cost, 1e6))
            good = cost[rows, cols] <= self.max_distance
            ids[rows[good]] = self.previous_ids[cols[good]]
        fresh = ids < 0
        ids[fresh] = self.next_id + np.arange(fresh.sum())
        self.next_id += int(fresh.sum())
        self.previous, self.previous_ids = lanes, ids
        return ids


def _mean_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean top-view distance from a's points to b's points, over a's overlap with b."""
    d = np.sqrt(((a[:, None, :2] - b[None, :, :2]) ** 2).sum(-1)).min(axis=1)
    overlap = d < 2.0
    return float(d[overlap].mean()) if overlap.sum() >= 2 else np.inf


def ego_lane_bounds(lanes_window: list[np.ndarray],
                    reach_m: float = 5.0) -> tuple[int | None, int | None]:
    """Indices of the lanes bounding the ego lane: nearest on the left (y > 0) and right.

    A lane's lateral offset is taken at its point nearest to x = 0, if within reach_m.
    """
    left = right = None
    best_left, best_right = np.inf, -np.inf
    for index, lane in enumerate(lanes_window):
        nearest = int(np.argmin(np.abs(lane[:, 0])))
        if abs(lane[nearest, 0]) > reach_m:
            continue
        y = float(lane[nearest, 1])
        if 0 < y < best_left:
            left, best_left = index, y
        elif best_right < y <= 0:
            right, best_right = index, y
    return left, right


class LanePipeline:
    """Odometry + clouds -> rolling BEV grid -> detector -> lanes in the output frame."""

    def __init__(self, params: DetectorParams, detector: LaneDetector,
                 expect_odometry: bool = True) -> None:
        self.params = params
        self.detector = detector
        # False when it is known that no odometry will come (a bag without it): no sweep waits
        self.expect_odometry = expect_odometry
        self.grid = RollingBevGrid(BevSpec(params.size_px, params.resolution_m),
                                   params.accumulate_sec, params.max_sweeps)
        self.odometry = PoseBuffer()
        self.odom_frame: str | None = None
        self.odom_child: str | None = None
        self.lidar_to_base = euler_to_matrix(*params.lidar_to_base)
        self.ids = LaneIdTracker()
        self.output_frame: str | None = None
        self.sweeps_since_detection = 0
        self.pending: collections.deque[tuple] = collections.deque()
        self.counters = {'clouds': 0, 'odometry': 0, 'detections': 0, 'sweeps_skipped': 0,
                         'resets': 0, 'clouds_without_odometry': 0}

    @property
    def uses_odometry(self) -> bool:
        return self.odom_frame is not None

    def add_odometry(self, msg: Any) -> None:
        """Buffer one odometry message. Raises ValueError (naming the problem), changing
        nothing, for an empty frame_id (it would be the output frame) or a non-finite or
        non-unit pose."""
        frame = str(msg.header.frame_id)
        if not frame:
            raise ValueError('odometry has an empty frame_id')
        pose = odometry_to_matrix(msg)  # validates before any state changes
        self.odom_frame, self.odom_child = frame, str(msg.child_frame_id)
        self.odometry.add(stamp_to_ns(msg.header.stamp), pose)
        self.counters['odometry'] += 1
        # sweeps that arrived before the odometry of their stamp go in now, in order
        while self.pending and self.pending[0][0] <= self.odometry.stamps[-1]:
            try:
                self._insert(*self.pending.popleft())
            except ValueError:
                self.counters['clouds_without_odometry'] += 1

    def sensor_pose(self, stamp_ns: int, cloud_frame: str) -> np.ndarray | None:
        """Cloud frame -> output frame at the stamp (identity without odometry)."""
        if not self.uses_odometry:
            return np.eye(4)
        pose = self.odometry.at(stamp_ns)
        if pose is None:
            return None
        return pose if cloud_frame == self.odom_child else pose @ self.lidar_to_base

    def add_cloud(self, msg: Any) -> dict[str, float]:
        """Decode and insert one sweep. Raises ValueError (naming the problem) for bad input:
        a malformed cloud, one over params.max_points, an empty frame_id.

        A sweep newer than the newest odometry waits (up to MAX_PENDING sweeps) for the
        odometry of its stamp, since clouds and odometry arrive on independent topics.
        """
        start = time.perf_counter()
        frame = str(msg.header.frame_id)
        if not frame:  # it would become the output frame without odometry
            raise ValueError('cloud has an empty frame_id')
        xyz, intensity = read_xyzi(msg, max_points=self.params.max_points)
        decoded = time.perf_counter()
        sweep = (stamp_to_ns(msg.header.stamp), frame, xyz, intensity)
        ahead = self.uses_odometry and sweep[0] > self.odometry.stamps[-1]
        first = (self.expect_odometry and not self.uses_odometry
                 and self.counters['clouds'] == 0)  # odometry may be near
        if ahead or first or self.pending:
            self.pending.append(sweep)
            if len(self.pending) <= MAX_PENDING:
                return {'decode_ms': (decoded - start) * 1e3}
            # odometry is late: the oldest goes in on a held pose; with no odometry at all,
            # everything that waited goes in per sweep
            for _ in range(1 if self.uses_odometry else len(self.pending)):
                self._insert(*self.pending.popleft())
        else:
            self._insert(*sweep)
        done = time.perf_counter()
        return {'decode_ms': (decoded - start) * 1e3, 'grid_insert_ms': (done - decoded) * 1e3}

    def insert_waiting(self) -> bool:
        """Insert the oldest sweep still waiting for odometry (at the end of a bag); False when
        none waits. Raises ValueError when no odometry lies around its stamp."""
        if not self.pending:
            return False
        self._insert(*self.pending.popleft())
        return True

    def _insert(self, stamp_ns: int, frame: str, xyz: np.ndarray, intensity: np.ndarray) -> None:
        pose = self.sensor_pose(stamp_ns, frame)
        if pose is None:
            raise ValueError(f'no odometry around cloud stamp {stamp_ns * 1e-9:.3f} s')
        if not self.uses_odometry and len(self.grid):
            self.grid.reset()  # without odometry sweeps cannot be registered: one at a time
        scale = self.params.intensity_scale or None
        if self.grid.insert(stamp_ns, xyz, intensity, pose, scale):
            self.counters['resets'] += 1
            self.ids.reset()
        self.output_frame = self.odom_frame if self.uses_odometry else frame
        self.sweeps_since_detection += 1
        self.counters['clouds'] += 1

    def take_window(self) -> BevWindow | None:
        """The current window, or None if no sweep arrived since the last one was taken.

        Cheap relative to the detector: the node calls it under its lock and runs
        detect_window outside, so incoming sweeps never wait for the model.
        """
        if self.sweeps_since_detection == 0:
            return None
        # sweeps that arrived since the last window but were never the newest one detected on
        self.counters['sweeps_skipped'] += self.sweeps_since_detection - 1
        self.sweeps_since_detection = 0
        return self.grid.window()

    def detect_window(self, window: BevWindow) -> LaneOutput:
        """Run the detector on one window; lanes above score_threshold, in the output frame."""
        start = time.perf_counter()
        lanes_window, confidences = self.detector(window)
        detected = time.perf_counter()
        keep = [i for i, c in enumerate(confidences) if c >= self.params.score_threshold]
        lanes_window = [np.asarray(lanes_window[i], dtype=np.float64) for i in keep]
        confidences = np.asarray(confidences, dtype=np.float64)[keep]
        lanes = [window.to_output(lane) for lane in lanes_window]
        left, right = ego_lane_bounds(lanes_window)
        self.counters['detections'] += 1
        return LaneOutput(
            stamp_ns=window.stamp_ns, frame_id=self.output_frame or '', lanes=lanes,
            confidences=confidences, ids=self.ids.assign(lanes), outline=window.outline,
            ego_left=None if left is None else lanes[left],
            ego_right=None if right is None else lanes[right],
            timings_ms={'model_ms': (detected - start) * 1e3})

    def detect(self) -> LaneOutput | None:
        """take_window + detect_window; None when nothing new arrived."""
        start = time.perf_counter()
        window = self.take_window()
        if window is None:
            return None
        raster_ms = (time.perf_counter() - start) * 1e3
        out = self.detect_window(window)
        out.timings_ms['raster_ms'] = raster_ms
        return out
