"""From SALAD's maps to 3D lanes (paper §4.4): lane cells, moved by their offsets, given depth
by the row shift and scale, back-projected with the virtual camera's intrinsics, grouped into
lanes and fitted.

A lane point stands for its run of cells, so a fitted lane ends at the mean depth of its
topmost cell row; near the horizon one cell row spans tens of metres (45-68 m for a camera
1.5 m up), so each lane is continued on its trend to the far edge of that row, where the image
still shows it (`extend_to_row_edge`).

Grouping happens in 3D, row by row from the bottom of the image up: each row's runs of lane
cells, cut where touching cells lie on different lanes in 3D, are one point each, and a point
joins the lane whose lateral position (x, metres) it continues. Far away lanes converge in
the image and their cells touch, but in 3D they stay metres apart, so grouping there does not
merge them as connected components would.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.salad.config import STRIDE, SaladConfig

MIN_DEPTH_M = 1.0
LINK_M = 0.8  # a point continues a lane within this lateral distance (metres) ...
LINK_FRACTION = 0.04  # ... or this share of its depth, when that is more
DEPTH_JUMP = 0.1  # touching cells whose depths differ by this share can be two lanes
GAP_ROWS = 8  # a lane waits this many rows for its next point (dashes, occlusions)
HEADING_M = 3.0  # a lane's lateral slope is measured over its last this many metres
MIN_POINTS = 4
MIN_LENGTH_M = 2.0
SAMPLE_STEP_M = 0.5  # fitted lanes are sampled every this much depth
MAX_DEGREE = 3
TAIL_M = 10.0  # a lane is continued on its straight-line trend over its last this many metres


def lane_points(prob: np.ndarray, spatial: np.ndarray, cfg: SaladConfig) -> np.ndarray:
    """(P, 5) points (x, y, z, probability, row) in the optical frame, one per piece of a row's
    run of lane cells, bottom rows first (see `_pieces`)."""
    mask = prob > cfg.seg_threshold
    rows, cols = np.nonzero(mask)  # row-major: a row's cells left to right
    if not len(rows):
        return np.zeros((0, 5))
    p = prob[mask]
    cam = cfg.camera
    u = (cols + spatial[0][mask] + 0.5) * STRIDE - 0.5
    v = (rows + spatial[1][mask] + 0.5) * STRIDE - 0.5
    z = np.asarray(cfg.row_shift)[rows] + np.asarray(cfg.row_scale)[rows] * spatial[2][mask]
    # each cell back-projected on its own, then averaged: a cell row near the horizon spans
    # tens of metres of a lane, and the mean of u times the mean of z is not on it
    x, y = (u - cam.cx) * z / cam.focal, (v - cam.cy) * z / cam.focal
    piece = _pieces(rows, cols, x, z)
    count = np.bincount(piece, weights=p)
    cells = np.bincount(piece)

    def mean(values: np.ndarray) -> np.ndarray:
        return np.bincount(piece, weights=values * p) / count

    out = np.column_stack([mean(x), mean(y), mean(z), count / cells,
                           np.bincount(piece, weights=rows) / cells])
    keep = (out[:, 2] > MIN_DEPTH_M) & (out[:, 2] < cfg.max_depth_m)
    out = out[keep]
    return out[np.argsort(-out[:, 4], kind='stable')]


def _pieces(rows: np.ndarray, cols: np.ndarray, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Piece index of each lane cell (row-major order). A piece is a run of touching cells in a
    row, cut where the next cell lies on another lane: its point is laterally farther than the
    link reach and at another depth. The lines of outer lanes, seen from a camera 1-2 m up, lie
    almost along the image rows and touch their neighbours near the horizon, but not in 3D;
    one mean point for such a run lay between the lanes and lost both (on the validation
    images' own targets, F1 at 0.3 m was 65.8 with one point per run, 76.5 with pieces;
    docs/salad.md, "Where the F1 goes")."""
    far = np.maximum(z[1:], z[:-1])
    other_lane = ((np.abs(x[1:] - x[:-1]) > np.maximum(LINK_M, LINK_FRACTION * far))
                  & (np.abs(z[1:] - z[:-1]) > DEPTH_JUMP * far))
    same = (rows[1:] == rows[:-1]) & (cols[1:] == cols[:-1] + 1) & ~other_lane
    return np.cumsum(np.concatenate([[True], ~same])) - 1


def group_points(points: np.ndarray) -> list[np.ndarray]:
    """Indices of the points of each lane (see the module doc). A loop over rows, each with a
    few runs: the cells themselves were reduced to runs without Python loops."""
    lanes: list[list[int]] = []
    last_row: list[float] = []
    for row in np.unique(points[:, 4])[::-1]:
        here = np.flatnonzero(points[:, 4] == row)
        alive = [i for i, r in enumerate(last_row) if r - row <= GAP_ROWS]
        used_points: set[int] = set()
        used_lanes: set[int] = set()
        if alive:
            ends = np.array([_heading(points[lanes[i]]) for i in alive])  # (x, z, dx/dz)
            reach = np.maximum(LINK_M, LINK_FRACTION * points[here, 2])
            ahead = ends[None, :, 0] + ends[None, :, 2] * (points[here, 2][:, None]
                                                          - ends[None, :, 1])
            cost = np.abs(points[here, 0][:, None] - ahead)
            for flat in np.argsort(cost, axis=None):  # greedy, nearest pairs first
                a, b = divmod(int(flat), len(alive))
                if cost[a, b] > reach[a] or a in used_points or b in used_lanes:
                    continue
                lanes[alive[b]].append(int(here[a]))
                last_row[alive[b]] = row
                used_points.add(a)
                used_lanes.add(b)
        for a in range(len(here)):
            if a not in used_points:
                lanes.append([int(here[a])])
                last_row.append(row)
    return [np.array(lane) for lane in lanes]


def _heading(lane: np.ndarray) -> tuple[float, float, float]:
    """A lane's last point (x, z) and its lateral slope dx/dz over the last HEADING_M."""
    x, z = lane[-1, 0], lane[-1, 2]
    back = np.flatnonzero(lane[:, 2] <= z - HEADING_M)
    if not len(back):
        return x, z, 0.0
    i = back[-1]
    return x, z, (x - lane[i, 0]) / (z - lane[i, 2])


def fit_lane(points: np.ndarray) -> np.ndarray | None:
    """x(z) and y(z) polynomials through a lane's points (probability-weighted), sampled
    near to far; None for too few points or too short a lane."""
    z = points[:, 2]
    if len(points) < MIN_POINTS or np.ptp(z) < MIN_LENGTH_M:
        return None
    degree = min(MAX_DEGREE, len(points) // 3)
    weight = np.sqrt(points[:, 3])
    fx = np.polynomial.Polynomial.fit(z, points[:, 0], degree, w=weight)
    fy = np.polynomial.Polynomial.fit(z, points[:, 1], degree, w=weight)
    zs = np.append(np.arange(z.min(), z.max(), SAMPLE_STEP_M), z.max())
    return np.column_stack([fx(zs), fy(zs), zs])


def extend_to_row_edge(lane: np.ndarray, top_row: float, cfg: SaladConfig) -> np.ndarray:
    """The lane (N, 3), near to far, continued on its straight trend over the last TAIL_M until
    it leaves the top edge of its topmost cell row `top_row` in the image, or reaches
    max_depth_m."""
    z = lane[:, 2]
    tail = z >= z[-1] - TAIL_M
    extra = np.arange(z[-1] + SAMPLE_STEP_M, cfg.max_depth_m + 1e-9, SAMPLE_STEP_M)
    if tail.sum() < 2 or not len(extra):
        return lane
    x = np.polyval(np.polyfit(z[tail], lane[tail, 0], 1), extra)
    y = np.polyval(np.polyfit(z[tail], lane[tail, 1], 1), extra)
    cam = cfg.camera
    inside = cam.focal * y / extra + cam.cy >= top_row * STRIDE - 0.5  # image v, top edge
    n = len(inside) if inside.all() else int(np.argmin(inside))
    return np.vstack([lane, np.column_stack([x, y, extra])[:n]])


def decode(prob: np.ndarray, spatial: np.ndarray, cfg: SaladConfig
           ) -> tuple[list[np.ndarray], np.ndarray]:
    """Lanes ((N, 3) optical frame, near to far) and their scores (mean cell probability)
    from one image's maps: prob (h, w) in [0, 1], spatial (3, h, w)."""
    points = lane_points(prob, spatial, cfg)
    lanes, scores = [], []
    for index in group_points(points):
        lane = fit_lane(points[index])
        score = float(points[index, 3].mean())
        if lane is not None and score >= cfg.score_threshold:
            lanes.append(extend_to_row_edge(lane, points[index, 4].min(), cfg))
            scores.append(score)
    return lanes, np.asarray(scores, dtype=np.float64)
