"""Camera lanes only where paint shows: a lane whose pixels do not stand out from the road on
both sides of it is dropped (the camera's counterpart of evidence.keep_painted).

The network draws lanes along edges that look like a lane's place: a kerb's foot, a barrier's,
a sidewalk's edge (docs/salad.md, "Roads without lines along their kerbs"). Paint is brighter
than the road on both of its sides; an edge is brighter on one side only. So each lane's near
points (NEAR_M, where a line is a few pixels wide) are projected into the virtual camera's
image, the same pixels its cells came from whatever their depth; on the lane, the brightest
pixel within PAINT_HALF_WIDTH_M across it (a few centimetres of the network's error), the
lane's PAINT_QUANTILE of them (dashes: most of a dashed lane is the road between them); beside
it, the median of the pixels ROAD_BESIDE_M to each side. Brightness is a pixel's brightest
channel, so yellow paint counts as white does. The lane is kept when its paint is min_contrast
times as bright as the road on each side, or when it has too few pixels beside it on either
side to tell (the image's edge).
"""
from __future__ import annotations

import numpy as np

from fhld_ros.salad.virtual_camera import VirtualCamera

NEAR_M = (3.0, 35.0)  # optical z of the points tested
PAINT_HALF_WIDTH_M = 0.15
ACROSS_M = np.linspace(-PAINT_HALF_WIDTH_M, PAINT_HALF_WIDTH_M, 7)
ROAD_BESIDE_M = np.array([0.4, 0.6, 0.8, 1.0])
PAINT_QUANTILE = 0.8
MIN_POINTS = 8  # fewer tested points on the lane or beside it on a side: no evidence, kept
MIN_CONTRAST = 1.05  # the default (camera node, salad-eval, salad-real): docs/salad.md


def painted(lanes: list[np.ndarray], image: np.ndarray, camera: VirtualCamera,
            min_contrast: float) -> np.ndarray:
    """Which lanes ((N, 3) optical frame, near to far) stand out as paint in the virtual
    camera's image (height, width, 3) uint8: (len(lanes),) bool. min_contrast <= 0: all."""
    keep = np.ones(len(lanes), dtype=bool)
    if min_contrast <= 0 or not lanes:
        return keep
    image = np.asarray(image)
    points, across, lane = near_points(lanes, NEAR_M)
    if not len(points):
        return keep
    paint = across_brightness(points, across, ACROSS_M, image, camera).max(axis=1)
    left, right = (across_brightness(points, across, sign * ROAD_BESIDE_M, image, camera)
                   for sign in (-1.0, 1.0))
    for i in np.unique(lane):
        mine = lane == i
        on, sides = paint[mine], (left[mine], right[mine])
        on, sides = on[on >= 0], [side[side >= 0] for side in sides]
        if min(len(on), *map(len, sides)) < MIN_POINTS:
            continue  # no evidence either way
        road = max(max(float(np.median(side)) for side in sides), 1.0)
        keep[i] = float(np.quantile(on, PAINT_QUANTILE)) >= min_contrast * road
    return keep


def near_points(lanes: list[np.ndarray], near_m: tuple[float, float]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lanes' points within near_m (optical z), the unit vector across each on the road
    (to the right), its lane's index."""
    long = {i: lane for i, lane in enumerate(lanes) if len(lane) >= 2}
    if not long:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=int)
    points = np.concatenate(list(long.values()))
    lane = np.repeat(list(long), [len(p) for p in long.values()])
    across = np.concatenate([across_road(p) for p in long.values()])
    near = (points[:, 2] >= near_m[0]) & (points[:, 2] <= near_m[1])
    return points[near], across[near], lane[near]


def across_road(lane: np.ndarray) -> np.ndarray:
    """(N, 3): the unit vector across a lane (N >= 2 points, optical frame) on the road at each
    of its points, to the right."""
    tangent = np.gradient(lane, axis=0)
    across = np.stack([tangent[:, 2], np.zeros(len(lane)), -tangent[:, 0]], axis=1)
    return across / np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-9)


def across_brightness(points: np.ndarray, across: np.ndarray, offsets_m: np.ndarray,
                      image: np.ndarray, camera: VirtualCamera) -> np.ndarray:
    """(P, len(offsets_m)): brightness (as _brightness()) offsets_m along each point's across
    vector on the road."""
    return _brightness(points[:, None] + offsets_m[:, None] * across[:, None], image, camera)


def _brightness(points: np.ndarray, image: np.ndarray, camera: VirtualCamera) -> np.ndarray:
    """The brightest channel of the image's pixels at the projections of points (..., 3), -1
    outside the image or behind it."""
    z = points[..., 2]
    front = z > 0.5
    safe = np.where(front, z, 1.0)
    u = np.round(camera.focal * points[..., 0] / safe + camera.cx)
    v = np.round(camera.focal * points[..., 1] / safe + camera.cy)
    h, w = image.shape[:2]
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.full(z.shape, -1, dtype=np.int16)
    out[inside] = image[v[inside].astype(int), u[inside].astype(int)].max(axis=-1)
    return out
