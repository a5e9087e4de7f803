"""What one detection cycle publishes: the lanes in the output frame with ids kept from cycle
to cycle, the window outline and the ego lane's bounds, and their CDR-serialised messages on
the lanes topic and its ego_left / ego_right Paths (docs/design.md §3). The node and `fhld
replay` both publish lane_messages, so what they write cannot differ."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from msg_adapters.lanes import lane_to_path_cdr, lanes_to_marker_array_cdr

# topic suffix (after the lanes topic) -> message type
LANE_TOPICS = {'': 'visualization_msgs/msg/MarkerArray', '/ego_left': 'nav_msgs/msg/Path',
               '/ego_right': 'nav_msgs/msg/Path'}


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


def lane_messages(out: LaneOutput) -> dict[str, bytes]:
    """The CDR messages of one cycle, keyed by their LANE_TOPICS suffix. Written from the arrays
    (~10x faster than building rclpy messages)."""
    return {'': lanes_to_marker_array_cdr(out.stamp_ns, out.frame_id, out.lanes,
                                          out.confidences, out.ids, out.outline),
            '/ego_left': lane_to_path_cdr(out.stamp_ns, out.frame_id, out.ego_left),
            '/ego_right': lane_to_path_cdr(out.stamp_ns, out.frame_id, out.ego_right)}
