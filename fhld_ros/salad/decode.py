"""From SALAD's maps to 3D lanes (paper §4.4): lane cells, moved by their offsets, given depth
by the row shift and scale, back-projected with the virtual camera's intrinsics, grouped into
lanes and fitted.

Grouping happens in 3D, slice by slice of depth from near to far: every lane cell is
back-projected on its own, the cells of a depth slice (8 % of its depth deep) are cut into
points where they lie laterally farther apart than the link reach, and a point joins the lane
whose lateral position (x, metres) it continues. Far away lanes converge in the image and
their cells touch, but in 3D they stay metres apart. Slices, not image rows: the lines of
outer lanes and of curves, seen from a camera 1-2 m up, run almost along the image rows near
the horizon, one cell row holding tens of metres of them and touching the next lane's, and one
point per row lost them (docs/salad.md, "Where the F1 goes").

A fitted lane ends at its farthest point; near the horizon one cell row spans tens of metres
(45-68 m for a camera 1.5 m up), so each lane is continued on its trend to the far edge of its
topmost cell row, where the image still shows it (`extend_to_row_edge`).
"""
from __future__ import annotations

from bisect import bisect_right

import numpy as np

from fhld_ros.salad.config import STRIDE, SaladConfig
from fhld_ros.salad.lanes_road import image_road
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.road_profile import shared_row_depth

MIN_DEPTH_M = 1.0
LINK_M = 0.8  # a point continues a lane within this lateral distance (metres) ...
LINK_FRACTION = 0.04  # ... or this share of its depth, when that is more
SLICE_FRACTION = 0.08  # a depth slice is this share of its depth deep
GAP_SLICES = 5  # a lane waits this many slices (~47 % more depth) for its next point
HEADING_M = 3.0  # a lane's lateral slope is measured over its last this many metres
MIN_POINTS = 6
MIN_LENGTH_M = 2.0
SAMPLE_STEP_M = 0.5  # fitted lanes are sampled every this much depth
MAX_DEGREE = 3
TAIL_M = 10.0  # a lane is continued on its straight-line trend over its last this many metres
X, Y, Z, PROB, TOP_ROW, SLICE = range(6)  # the columns of lane_points


def link_reach(z: np.ndarray) -> np.ndarray:
    """How far (metres, laterally) a point at depth z may lie from a lane and still be on it."""
    return np.maximum(LINK_M, LINK_FRACTION * z)


def lane_points(prob: np.ndarray, spatial: np.ndarray, cfg: SaladConfig,
                road: RoadPlane | None = None, road_profile: bool = True) -> np.ndarray:
    """(P, 6) points (x, y, z, probability, top cell row, depth slice) in the optical frame,
    near slices first, each the probability-weighted mean of a slice's lane cells that lie
    within the link reach of each other laterally. road_profile: the cells' depths pulled
    towards the one depth per image row they share (road_profile.py); with a road plane, the
    near cells then take their depth from it (road_plane.py)."""
    mask = prob > cfg.seg_threshold
    rows, cols = np.nonzero(mask)
    cam = cfg.camera
    u = (cols + spatial[0][mask] + 0.5) * STRIDE - 0.5
    v = (rows + spatial[1][mask] + 0.5) * STRIDE - 0.5
    z = cfg.depth(rows, spatial[2][mask])
    if road_profile:
        z = shared_row_depth(z, u, v, prob[mask], cam)
    if road is not None:
        z = road.blend(z, u, v, cam)
    # each cell back-projected on its own: a cell row near the horizon spans tens of metres of
    # a lane, and the mean of u times the mean of z is not on it
    x, y = (u - cam.cx) * z / cam.focal, (v - cam.cy) * z / cam.focal
    keep = (z > MIN_DEPTH_M) & (z < cfg.max_depth_m)
    if not keep.any():
        return np.zeros((0, 6))
    x, y, z, p, rows = x[keep], y[keep], z[keep], prob[mask][keep], rows[keep]
    depth_slice = np.floor(np.log(z / MIN_DEPTH_M) / np.log1p(SLICE_FRACTION)).astype(int)
    order = np.lexsort((x, depth_slice))
    x, y, z, p, rows, depth_slice = (a[order] for a in (x, y, z, p, rows, depth_slice))
    cut = (np.diff(depth_slice) != 0) | (np.diff(x) > link_reach(z[1:]))
    first = np.concatenate([[True], cut])
    piece = np.cumsum(first) - 1
    weight = np.bincount(piece, weights=p)
    top_row = np.full(piece[-1] + 1, np.inf)
    np.minimum.at(top_row, piece, rows)

    def mean(values: np.ndarray) -> np.ndarray:
        return np.bincount(piece, weights=values * p) / weight

    return np.column_stack([mean(x), mean(y), mean(z), weight / np.bincount(piece), top_row,
                            depth_slice[first]])


def group_points(points: np.ndarray) -> list[np.ndarray]:
    """Indices of the points of each lane (see the module doc). A loop over depth slices, each
    with a few points, in plain Python floats: the cells themselves were reduced to points
    without Python loops, and numpy's cost per call on arrays of a few elements was most of
    the decoding's time. A lane takes at most one point a slice, so its depth grows point by
    point, and its heading (its end and lateral slope, `_Lane.add`) changes only when it takes
    one."""
    order = np.argsort(points[:, SLICE], kind='stable').tolist()
    x, z, depth_slice = (points[order, column].tolist() for column in (X, Z, SLICE))
    reach = link_reach(points[order, Z]).tolist()
    lanes: list[_Lane] = []
    first = 0
    while first < len(order):
        here = range(first, bisect_right(depth_slice, depth_slice[first], first))
        first = here.stop
        alive = [lane for lane in lanes if depth_slice[here[0]] - lane.slice <= GAP_SLICES]
        # greedy, nearest pairs first, within reach
        pairs = sorted((abs(x[a] - lane.ahead(z[a])), a, b) for a in here
                       for b, lane in enumerate(alive))
        used: set[int] = set()
        taken: set[int] = set()
        for cost, a, b in pairs:
            if a in used or b in taken or cost > reach[a]:
                continue
            alive[b].add(order[a], x[a], z[a], depth_slice[a])
            used.add(a)
            taken.add(b)
        for a in here:
            if a not in used:
                lanes.append(_Lane())
                lanes[-1].add(order[a], x[a], z[a], depth_slice[a])
    return [np.array(lane.indices) for lane in lanes]


class _Lane:
    """The points of one lane so far, near to far: indices, x and z; its end, lateral slope
    dx/dz over the last HEADING_M (0 over less) and depth slice."""

    def __init__(self) -> None:
        self.indices: list[int] = []
        self.x: list[float] = []
        self.z: list[float] = []
        self.slope = 0.0
        self.slice = 0.0

    def ahead(self, z: float) -> float:
        """The lane's lateral position x at depth z, on its heading."""
        return self.x[-1] + self.slope * (z - self.z[-1])

    def add(self, index: int, x: float, z: float, depth_slice: float) -> None:
        back = bisect_right(self.z, z - HEADING_M) - 1  # depth grows: the last point that far
        self.indices.append(index)
        self.x.append(x)
        self.z.append(z)
        self.slice = depth_slice
        self.slope = 0.0 if back < 0 else (x - self.x[back]) / (z - self.z[back])


def fit_lane(points: np.ndarray) -> np.ndarray | None:
    """x(z) and y(z) polynomials through a lane's points (probability-weighted), sampled
    near to far; None for too few points or too short a lane. Both in one solve, over z mapped
    to [-1, 1] and the columns scaled to unit norm (as numpy's Polynomial.fit does: the powers
    of metres stay well conditioned), without its checks, which cost more than the solve."""
    z = points[:, Z]
    z_min, z_max = z.min(), z.max()
    if len(points) < MIN_POINTS or z_max - z_min < MIN_LENGTH_M:
        return None
    degree = min(MAX_DEGREE, len(points) // 3)
    half, mid = (z_max - z_min) / 2, (z_max + z_min) / 2
    w = np.sqrt(points[:, PROB])[:, None]
    design = np.vander((z - mid) / half, degree + 1, increasing=True) * w
    norm = np.sqrt(np.square(design).sum(0))
    coef = np.linalg.lstsq(design / norm, points[:, [X, Y]] * w, rcond=None)[0] / norm[:, None]
    zs = np.append(np.arange(z_min, z_max, SAMPLE_STEP_M), z_max)
    return np.column_stack([np.vander((zs - mid) / half, degree + 1, increasing=True) @ coef,
                            zs])


def extend_to_row_edge(lane: np.ndarray, top_row: float, cfg: SaladConfig) -> np.ndarray:
    """The lane (N, 3), near to far, continued on its straight trend over the last TAIL_M until
    it leaves the top edge of its topmost cell row `top_row` in the image, or reaches
    max_depth_m."""
    z = lane[:, 2]
    tail = z >= z[-1] - TAIL_M
    extra = np.arange(z[-1] + SAMPLE_STEP_M, cfg.max_depth_m + 1e-9, SAMPLE_STEP_M)
    if tail.sum() < 2 or not len(extra):
        return lane
    # the least-squares line through the tail, x and y against z
    dz = z[tail] - z[tail].mean()
    centre = lane[tail, :2].mean(0)
    slope = dz @ (lane[tail, :2] - centre) / (dz @ dz)
    x, y = centre[:, None] + slope[:, None] * (extra - z[tail].mean())
    cam = cfg.camera
    inside = cam.focal * y / extra + cam.cy >= top_row * STRIDE - 0.5  # image v, top edge
    n = len(inside) if inside.all() else int(np.argmin(inside))
    return np.vstack([lane, np.column_stack([x, y, extra])[:n]])


def decode(prob: np.ndarray, spatial: np.ndarray, cfg: SaladConfig,
           road: RoadPlane | None = None, road_profile: bool = True
           ) -> tuple[list[np.ndarray], np.ndarray]:
    """Lanes ((N, 3) optical frame, near to far) and their scores (mean cell probability)
    from one image's maps: prob (h, w) in [0, 1], spatial (3, h, w); depths pulled towards
    the image's road profile (road_profile.py), the near lanes' from the road plane where the
    camera's mount gives one (with road.pitch_from_image only where the lanes decoded without
    it put the road off the mount's height, and at their own pitch: lanes_road.image_road)."""
    if road is not None and road.pitch_from_image:
        plain = decode(prob, spatial, cfg, None, road_profile)
        road = image_road(road, plain[0], cfg.camera)
        if road is None:
            return plain
    points = lane_points(prob, spatial, cfg, road, road_profile)
    lanes, scores = [], []
    for index in group_points(points):
        score = float(points[index, PROB].mean())
        lane = fit_lane(points[index]) if score >= cfg.score_threshold else None
        if lane is not None:
            lanes.append(extend_to_row_edge(lane, points[index, TOP_ROW].min(), cfg))
            scores.append(score)
    return lanes, np.asarray(scores, dtype=np.float64)
