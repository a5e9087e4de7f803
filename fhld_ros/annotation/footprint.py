"""The ground a camera sees up to a depth: its image's field of view on the local ground plane,
as the closed 4-corner outline /lanes carries in ns bev_window (docs/design.md §3: 5 points).

In normalised image coordinates (x, y, 1) a ray meets the plane n.p = n.p0 at depth h / g,
where h is the camera's height over the plane and g = -n.(R (x, y, 1)) is linear in (x, y).
Depth <= reach is then the half plane g >= h / reach of the image: the image rectangle cut by
one line parallel to the horizon (a ray above the horizon is cut at the range), a convex
polygon of 3 to 5 corners that the plane maps to a convex polygon on the ground, whatever the
pitch. With lens distortion the image's border is curved in normalised coordinates; the
rectangle is then the largest box inside it (calibration.seen_box), which claims no ground the
image does not show.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.camera.calibration import CameraCalibration, seen_box

MIN_HEIGHT_M = 0.1  # a camera this close to (or below) the ground plane sees no footprint
MIN_AREA_M2 = 1.0  # smaller footprints are degenerate: no outline
PLANE_POINTS = 20_000  # the ground plane is fitted to about this many returns at most


def ground_plane(ground_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit up normal (3,), a point (3,)) of the least-squares plane z = a x + b y + c."""
    pts = ground_xyz[::max(1, len(ground_xyz) // PLANE_POINTS)]
    centre = pts.mean(axis=0)
    a = np.column_stack([pts[:, :2] - centre[:2], np.ones(len(pts))])
    (gx, gy, c), *_ = np.linalg.lstsq(a, pts[:, 2], rcond=None)
    normal = np.array([-gx, -gy, 1.0])
    return normal / np.linalg.norm(normal), np.array([centre[0], centre[1], c])


def camera_footprint(calib: CameraCalibration, T_out_camera: np.ndarray, normal: np.ndarray,
                     point: np.ndarray, reach_m: float) -> np.ndarray | None:
    """(5, 3) closed outline of the ground plane (normal, point) that the camera sees at depths
    up to reach_m, counter-clockwise from above and starting at the right end of the edge
    nearest the camera (bev.py's order for a camera looking ahead: near-right, far-right,
    far-left, near-left, near-right); None when it sees too little of the plane."""
    origin, R = T_out_camera[:3, 3], T_out_camera[:3, :3]
    height = float(normal @ (origin - point))
    if height < MIN_HEIGHT_M or reach_m <= 0:
        return None
    w, h = calib.width, calib.height
    # the seen box's corners (optical frame, z = 1), counter-clockwise on the ground ahead
    (x0, y0), (x1, y1) = seen_box(w, h, calib.K, calib.lens)
    xy1 = np.array([[x1, y1, 1.0], [x1, y0, 1.0], [x0, y0, 1.0], [x0, y1, 1.0]])
    coef = -(normal @ R)  # g(x, y) = coef . (x, y, 1)
    xy1 = _clip_half_plane(xy1, coef, height / reach_m)
    if len(xy1) < 3:
        return None
    ground = origin + (height / (xy1 @ coef))[:, None] * (xy1 @ R.T)
    ground = _four_corners(ground)
    area = _signed_area(ground[:, :2])
    if abs(area) < MIN_AREA_M2:
        return None
    if area < 0:  # a camera upside down: its image turns the other way
        ground = ground[::-1]
    mid = (ground + np.roll(ground, -1, axis=0)) / 2  # mid[i]: edge i -> i + 1
    near = int(np.argmin(np.linalg.norm(mid[:, :2] - origin[:2], axis=1)))
    ground = np.roll(ground, -(near + 1), axis=0)  # the near edge closes the outline
    return np.vstack([ground, ground[:1]])


def _clip_half_plane(poly: np.ndarray, coef: np.ndarray, threshold: float) -> np.ndarray:
    """The convex polygon (M, 3) cut to coef . p >= threshold (Sutherland-Hodgman, one edge):
    each corner kept if inside, then where its edge crosses the line."""
    s = poly @ coef - threshold
    s_next, nxt = np.roll(s, -1), np.roll(poly, -1, axis=0)
    crosses = (s >= 0) != (s_next >= 0)
    with np.errstate(divide='ignore', invalid='ignore'):
        t = np.where(crosses, s / (s - s_next), 0.0)
    hits = poly + t[:, None] * (nxt - poly)
    keep = np.column_stack([s >= 0, crosses]).ravel()
    return np.stack([poly, hits], axis=1).reshape(-1, 3)[keep]


def _four_corners(poly: np.ndarray) -> np.ndarray:
    """A convex 3..5-gon as 4 corners (the contract's 5-point outline): a triangle gains its
    longest edge's midpoint (the same region); a pentagon loses the corner whose triangle is
    smallest (a region inside the footprint: never claims what the camera does not see)."""
    if len(poly) == 3:
        edge = np.linalg.norm(np.roll(poly, -1, axis=0) - poly, axis=1)
        k = int(np.argmax(edge))
        return np.insert(poly, k + 1, (poly[k] + poly[(k + 1) % 3]) / 2, axis=0)
    if len(poly) == 5:
        prev, nxt = np.roll(poly, 1, axis=0), np.roll(poly, -1, axis=0)
        a, b = (prev - poly)[:, :2], (nxt - poly)[:, :2]
        lost = np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
        return np.delete(poly, int(np.argmin(lost)), axis=0)
    return poly


def _signed_area(ring: np.ndarray) -> float:
    """Shoelace area of an open ring (M, 2): positive counter-clockwise."""
    x, y = ring[:, 0], ring[:, 1]
    return float(0.5 * (x @ np.roll(y, -1) - y @ np.roll(x, -1)))
