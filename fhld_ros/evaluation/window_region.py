"""The window a /lanes message was searched in, from its bev_window outline, and lanes clipped to
it (docs/design.md §3, §4 `fhld eval`).

The node's outline is a closed square in bev.py's corner order (rear-right, front-right,
front-left, rear-left, back to the first: corner 0 -> 1 is forward, 0 -> 3 is left); lanes are
clipped to it with metrics.clip_polyline_to_square. Any other closed simple polygon (fhld
autolabel: the ground its camera sees) is clipped to as it is, in top view.
"""
from __future__ import annotations

import numpy as np


def window_frame(outline: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(origin (3,), rotation (3, 3) whose columns are the window axes, half size) of an outline.

    Raises ValueError unless the outline is a closed square.
    """
    pts = np.asarray(outline, dtype=np.float64)
    if pts.shape != (5, 3) or not np.isfinite(pts).all():
        raise ValueError(f'outline must be 5 finite points, got shape {pts.shape}')
    forward, left = pts[1] - pts[0], pts[3] - pts[0]
    side = np.linalg.norm(forward)
    tol = 1e-3 * max(side, 1e-9)
    square = (side > 0 and abs(np.linalg.norm(left) - side) <= tol
              and abs(forward @ left) <= tol * side
              and np.linalg.norm(pts[2] - pts[1] - left) <= tol
              and np.linalg.norm(pts[4] - pts[0]) <= tol)
    if not square:
        raise ValueError('outline is not a closed square')
    x_axis = forward / side
    y_axis = left / np.linalg.norm(left)
    rot = np.column_stack([x_axis, y_axis, np.cross(x_axis, y_axis)])
    return pts[:4].mean(axis=0), rot, side / 2


def window_region(outline: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None]:
    """window_frame's (origin, rotation, half size) and the region lanes are clipped to: None
    for a closed square (the node's window: clipped to the square, as ever), else the corners
    (M, 2) of a closed simple polygon in its frame: x the inward normal of the closing edge
    (the rear edge in bev.py's order), y left, z up, origin at the centre of its bounding box
    (whose larger side is twice the half size). Raises ValueError for anything else."""
    try:
        return *window_frame(outline), None
    except ValueError:
        pass
    pts = np.asarray(outline, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4 or not np.isfinite(pts).all():
        raise ValueError(f'outline must be 4 or more finite points, got shape {pts.shape}')
    ring = pts[:-1, :2]
    scale = float(np.ptp(ring, axis=0).max())
    area = _signed_area(ring)
    closed = np.linalg.norm(pts[-1] - pts[0]) <= 1e-3 * scale
    if not closed or abs(area) <= 1e-6 * scale ** 2 or not _is_simple(ring):
        raise ValueError('outline is not a closed square or simple polygon')
    rear = ring[0] - ring[-1]
    x_axis = np.sign(area) * np.array([-rear[1], rear[0]]) / np.linalg.norm(rear)
    axes = np.array([x_axis, [-x_axis[1], x_axis[0]]])  # rows: x, y in top view
    local = (ring - ring[0]) @ axes.T
    lo, hi = local.min(axis=0), local.max(axis=0)
    origin = np.append(ring[0] + (lo + hi) / 2 @ axes, pts[:-1, 2].mean())
    rot = np.eye(3)
    rot[:2, :2] = axes.T
    return origin, rot, float((hi - lo).max() / 2), local - (lo + hi) / 2


def _signed_area(ring: np.ndarray) -> float:
    """Shoelace area of an open ring (M, 2): positive counter-clockwise."""
    x, y = ring[:, 0], ring[:, 1]
    return float(0.5 * (x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _is_simple(ring: np.ndarray) -> bool:
    """No two edges of an open ring (M, 2) meet, apart from neighbours at their shared corner."""
    a, b = ring, np.roll(ring, -1, axis=0)
    m = len(ring)
    p, q = a[:, None], b[:, None]  # edge i against edge j
    r, s = a[None], b[None]
    o1, o2 = _cross(q - p, r - p), _cross(q - p, s - p)
    o3, o4 = _cross(s - r, p - r), _cross(s - r, q - r)
    boxes = (np.minimum(p, q) <= np.maximum(r, s)).all(-1) & \
        (np.minimum(r, s) <= np.maximum(p, q)).all(-1)
    meet = (o1 * o2 <= 0) & (o3 * o4 <= 0) & boxes
    gap = np.abs(np.arange(m)[:, None] - np.arange(m)[None])
    return not (meet & (gap > 1) & (gap < m - 1)).any()


def inside_polygon(xy: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(N,) whether points (N, 2) lie inside a simple polygon (M, 2) (even-odd crossings)."""
    x0, y0 = polygon[:, 0], polygon[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    px, py = xy[:, :1], xy[:, 1:2]
    straddle = (y0 > py) != (y1 > py)  # (N, M): the edge spans the point's height
    with np.errstate(divide='ignore', invalid='ignore'):
        x_at = x0 + (py - y0) * (x1 - x0) / (y1 - y0)
    return (straddle & (px < x_at)).sum(axis=1) % 2 == 1


def clip_polyline_to_polygon(points: np.ndarray, polygon: np.ndarray) -> list[np.ndarray]:
    """The parts of a polyline inside a simple polygon (M, 2) in top view, split where it
    leaves (metrics.clip_polyline_to_square for any window shape). Every segment is cut where
    it crosses an edge, all segments and edges at once; a cut piece is kept when its middle is
    inside; z is interpolated along the cut segments."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 2:
        return [pts.copy()] if len(pts) and inside_polygon(pts[:, :2], polygon)[0] else []
    p0, d = pts[:-1], np.diff(pts, axis=0)
    edge = np.roll(polygon, -1, axis=0) - polygon
    den = _cross(d[:, None, :2], edge[None])  # (S, M)
    rel = polygon[None] - p0[:, None, :2]
    with np.errstate(divide='ignore', invalid='ignore'):
        t, u = _cross(rel, edge[None]) / den, _cross(rel, d[:, None, :2]) / den
    cut = (den != 0) & (t > 0) & (t < 1) & (u >= 0) & (u <= 1)
    n = len(d)
    bounds = np.hstack([np.zeros((n, 1)), np.sort(np.where(cut, t, 1.0), axis=1),
                        np.ones((n, 1))])
    t0, t1 = bounds[:, :-1], bounds[:, 1:]  # (S, M + 1) pieces of every segment, in order
    middle = p0[:, None, :2] + ((t0 + t1) / 2)[..., None] * d[:, None, :2]
    keep = (t1 > t0) & inside_polygon(middle.reshape(-1, 2), polygon).reshape(t0.shape)
    seg, piece_of = np.nonzero(keep)  # in order along the polyline
    t0, t1 = t0[seg, piece_of], t1[seg, piece_of]
    if not len(seg):
        return []
    # a kept piece continues the previous one when it starts where that one ended
    new_piece = np.concatenate([[True], seg[1:] + t0[1:] != seg[:-1] + t1[:-1]])
    starts = p0[seg] + t0[:, None] * d[seg]
    ends = np.where((t1 == 1.0)[:, None], pts[seg + 1], p0[seg] + t1[:, None] * d[seg])
    stacked = np.stack([starts, ends], axis=1).reshape(-1, 3)
    opens = np.stack([new_piece, np.zeros_like(new_piece)], axis=1).reshape(-1)
    use = opens | np.tile([False, True], len(seg))  # a start only where a piece opens
    parts = np.split(stacked[use], np.flatnonzero(opens[use][1:]) + 1)
    return [part for part in parts if np.ptp(part, axis=0).any()]
