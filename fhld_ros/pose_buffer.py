"""PoseBuffer: recent stamped poses of one frame pair, interpolated (and, for the live node,
extrapolated) at the stamps of the sweeps. The pipeline keeps one for the odometry."""
from __future__ import annotations

import bisect

import numpy as np

from fhld_ros.geometry import extrapolate_pose, pose_at

ODOM_HISTORY = 4000  # poses kept at most (20 s at 200 Hz) ...
ODOM_HISTORY_NS = 5_000_000_000  # ... and no older than this behind the newest
# Poses further apart than this are not interpolated between: odometry stopped in between.
# As long as the longest wait for odometry (odom_wait_sec's default): a burst of poses lost in
# DDS (measured: up to 5 in a row of 10 Hz poses) leaves gaps over 0.5 s, and a sweep in one
# going in alone would reset the grid.
ODOM_MAX_GAP_NS = 1_000_000_000
# Extrapolation continues the motion between the newest pose and one at least this much older
# (two poses 5 ms apart at 200 Hz would scale their jitter 20-fold over 100 ms)
EXTRAPOLATION_BASE_NS = 50_000_000
# a stamp this far behind the oldest pose kept (the pipeline: the newest stamp seen): time went
# back (bag loop)
TIME_BACK_NS = 1_000_000_000


class PoseBuffer:
    """Recent stamped poses of one frame pair, interpolated at query stamps."""

    def __init__(self, capacity: int = ODOM_HISTORY) -> None:
        self.capacity = capacity
        self.stamps: list[int] = []
        self.poses: list[np.ndarray] = []

    def clear(self) -> None:
        self.stamps.clear()
        self.poses.clear()

    @property
    def oldest(self) -> int | None:
        return self.stamps[0] if self.stamps else None

    @property
    def newest(self) -> int | None:
        return self.stamps[-1] if self.stamps else None

    def add(self, stamp_ns: int, pose: np.ndarray) -> bool:
        """Keep a pose; False (nothing changes) when one of that stamp is kept already."""
        if self.stamps and stamp_ns < self.stamps[0] - TIME_BACK_NS:
            # time went back (bag loop): old poses belong to another run. A pose inside the
            # kept span is a late one (a reliable writer resends what DDS lost seconds later)
            self.clear()
        index = bisect.bisect(self.stamps, stamp_ns)
        if index and self.stamps[index - 1] == stamp_ns:
            return False
        self.stamps.insert(index, stamp_ns)
        self.poses.insert(index, pose)
        old = bisect.bisect_left(self.stamps, self.stamps[-1] - ODOM_HISTORY_NS)
        old = max(old, len(self.stamps) - self.capacity)
        if old > 0:
            del self.stamps[:old], self.poses[:old]
        return True

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """Pose at stamp_ns, or None when no two poses at most ODOM_MAX_GAP_NS apart (or one
        at exactly stamp_ns) surround it: no extrapolation, no hold."""
        return pose_at(self.stamps, self.poses, stamp_ns, ODOM_MAX_GAP_NS)

    def extrapolated(self, stamp_ns: int, reach_ns: int) -> np.ndarray | None:
        """Pose at a stamp at most reach_ns after the newest pose before it (past the newest,
        or inside a gap too wide to interpolate): the motion from a pose EXTRAPOLATION_BASE_NS
        or more before that one (at most ODOM_MAX_GAP_NS) continued. None when the stamp is
        not in that reach or no such older pose is kept."""
        last = bisect.bisect_left(self.stamps, stamp_ns) - 1
        if last < 0 or not 0 < stamp_ns - self.stamps[last] <= reach_ns:
            return None
        base = bisect.bisect_right(self.stamps, self.stamps[last] - EXTRAPOLATION_BASE_NS) - 1
        if base < 0 or self.stamps[last] - self.stamps[base] > ODOM_MAX_GAP_NS:
            return None
        return extrapolate_pose(stamp_ns, self.stamps[base], self.poses[base],
                                self.stamps[last], self.poses[last])
