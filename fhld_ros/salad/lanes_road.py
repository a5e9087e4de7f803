"""What an image's decoded lanes say about the road under the camera: the plane they span (the
camera's height over it is the network's read of the mount) and where their image lines meet
(the camera's pitch).

Lines parallel on a level road meet in the image at a point on the horizon, whatever their
heading; a camera pitched down by p sees the horizon at row cy - f tan p. So the near part of
each lane (3-25 m ahead, where a lane is near straight and the road near plane) is projected
back into the virtual image and fitted with a straight line u = a + b v, and each pair of
lanes not near parallel in the image gives a horizon row; their median gives the pitch. Only
the lanes' image positions count, not their depths: the network's depth follows the camera
heights it was trained on (docs/salad.md, "Cameras mounted higher") and a real camera's can be
a third too deep, but its lanes' image lines are where the paint is.

`image_road` uses it where only the mount's height is to be trusted: the depths stay the
network's while the road its lanes span lies within AGREE of that height; otherwise the near
lanes take the road at that height and the image's pitch (decode.py, road_plane.py).
"""
from __future__ import annotations

import numpy as np

from fhld_ros.annotation.footprint import ground_plane
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.virtual_camera import VirtualCamera

# optical frame (x right, y down, z forward) -> the camera's forward-left-up frame
OPTICAL_TO_FLU = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# the lanes span a plane when they spread this far sideways, on this many points at least,
# and the camera lies this high over it, tilted at most this much from the camera's vertical
PLANE_SPREAD_M = 1.5
PLANE_MIN_POINTS = 10
PLANE_HEIGHT_M = (0.3, 10.0)
PLANE_MAX_TILT_DEG = 15.0
NEAR_M = (3.0, 25.0)  # the part of a lane whose image line is fitted, by its depth
LINE_MIN_POINTS = 4
LINE_MIN_ROWS_PX = 5.0  # a lane spanning fewer virtual image rows gives no line
MIN_SLOPE_GAP = 0.2  # lines closer in slope (du / dv) than this meet too far off to trust
# the network's road within this much of the mount's height (log ratio): its depths stand
# (chosen on the validation drives: docs/salad.md, "The pitch from the image")
AGREE = 0.05


def lanes_plane(lanes_flu: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
    """(up normal, point) of the plane the lanes (camera forward-left-up frame) span, None when
    they span none or one a camera on a road would not be over (see PLANE_*)."""
    if not lanes_flu:
        return None
    points = np.concatenate(lanes_flu)
    if len(points) < PLANE_MIN_POINTS or np.ptp(points[:, 1]) < PLANE_SPREAD_M:
        return None
    normal, point = ground_plane(points)
    height = height_over((normal, point))
    tilt = np.degrees(np.arccos(np.clip(normal[2], -1.0, 1.0)))
    if not PLANE_HEIGHT_M[0] <= height <= PLANE_HEIGHT_M[1] or tilt > PLANE_MAX_TILT_DEG:
        return None
    return normal, point


def height_over(plane: tuple[np.ndarray, np.ndarray]) -> float:
    """The camera's height (metres) over a plane (up normal, point) in its own frame."""
    normal, point = plane
    return float(-normal @ point)


def lane_lines(lanes: list[np.ndarray], camera: VirtualCamera) -> np.ndarray:
    """(L, 2) the straight image lines u = a + b v (virtual camera pixels) of the lanes'
    near parts (optical frame, near to far); lanes too short in the image are left out."""
    lines = []
    for lane in lanes:
        near = lane[(lane[:, 2] > NEAR_M[0]) & (lane[:, 2] < NEAR_M[1])]
        if len(near) < LINE_MIN_POINTS:
            continue
        u = camera.focal * near[:, 0] / near[:, 2] + camera.cx
        v = camera.focal * near[:, 1] / near[:, 2] + camera.cy
        if np.ptp(v) >= LINE_MIN_ROWS_PX:
            slope, offset = np.polyfit(v, u, 1)
            lines.append((offset, slope))
    return np.asarray(lines, dtype=np.float64).reshape(-1, 2)


def horizon_row(lines: np.ndarray) -> float | None:
    """The median row (px) where pairs of lines u = a + b v meet; None without such a pair."""
    a, b = lines[:, 0], lines[:, 1]
    i, j = np.triu_indices(len(lines), k=1)
    apart = np.abs(b[i] - b[j]) > MIN_SLOPE_GAP
    if not apart.any():
        return None
    i, j = i[apart], j[apart]
    return float(np.median((a[j] - a[i]) / (b[i] - b[j])))


def lanes_pitch(lanes: list[np.ndarray], camera: VirtualCamera) -> float | None:
    """The camera's pitch down over the road (radians) from its lanes' vanishing point (module
    doc); None when fewer than two lanes give lines that meet."""
    row = horizon_row(lane_lines(lanes, camera))
    return None if row is None else float(np.arctan2(camera.cy - row, camera.focal))


def image_road(mount: RoadPlane, lanes: list[np.ndarray], camera: VirtualCamera
               ) -> RoadPlane | None:
    """The road for the near lanes of an image whose lanes (optical frame, decoded on the
    network's depth) are given, when the mount's height (and roll) is known but not its pitch:
    None where those lanes span no plane, or one within AGREE of that height (the network's
    depths stand); else the mount's road at the image's pitch, or at its own where the lanes
    give none."""
    plane = lanes_plane([lane @ OPTICAL_TO_FLU.T for lane in lanes])
    if plane is None or abs(np.log(height_over(plane) / mount.height_m)) <= AGREE:
        return None
    pitch = lanes_pitch(lanes, camera)
    return mount.with_pitch(mount.pitch_rad if pitch is None else pitch)
