"""SALAD's training targets at the output cells (paper §4.2, §4.3), from 3D lanes in the
virtual camera's optical frame.

* seg: cells a lane crosses (its projection densified to a quarter cell, so no cell is
  skipped), widened by one cell left and right: a lane a cell wide is a hard target to hit.
* offsets: (du, dv) from a lane cell's centre to the nearest lane point, in cells.
* depth: the nearest lane point's depth at lane cells, completed to a dense map (paper: depth
  completion of the sparse lane depths, after Ku et al.). Inverse depth is linear along any
  image line on a plane, so it is interpolated: along each row between the lane cells, then
  down each column between the rows that have lanes. Rows above the farthest or below the
  nearest lane row stay unlabelled (no ground known there).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from fhld_ros.geometry import resample_polyline
from fhld_ros.salad.config import STRIDE
from fhld_ros.salad.virtual_camera import VirtualCamera

MIN_DEPTH_M = 1.0  # lane points nearer than this (behind the lens) are not projected
LANE_STEP_M = 0.5  # lanes resampled this finely in 3D before projection
DENSIFY_CELLS = 0.25  # projected segments are cut to pieces at most this long (cells)


@dataclass
class SaladTargets:
    """Maps of one image, (h, w) each (offsets (2, h, w)); depth in metres, 0 where unlabelled."""

    seg: np.ndarray  # float32 {0, 1}
    offsets: np.ndarray  # float32, cells
    depth: np.ndarray  # float32 metres
    depth_mask: np.ndarray  # bool: depth is labelled


def project_lanes(lanes: list[np.ndarray], camera: VirtualCamera) -> np.ndarray:
    """(M, 3) cell coordinates (col, row, depth m) densely along the lanes' projections:
    pixel (u, v) -> cell ((u + 0.5) / STRIDE - 0.5, ...), so cell centres are integers."""
    pieces = []
    k = camera.intrinsics
    for lane in lanes:
        pts = resample_polyline(lane, LANE_STEP_M) if len(lane) > 1 else lane
        pts = pts[pts[:, 2] > MIN_DEPTH_M]
        if len(pts) < 2:
            continue
        inv = 1.0 / pts[:, 2]
        cells = np.column_stack([(k[0, 0] * pts[:, 0] * inv + k[0, 2] + 0.5) / STRIDE - 0.5,
                                 (k[1, 1] * pts[:, 1] * inv + k[1, 2] + 0.5) / STRIDE - 0.5])
        # each segment cut into n pieces; inverse depth is linear along a projected segment
        n = np.maximum(np.ceil(np.linalg.norm(np.diff(cells, axis=0), axis=1)
                               / DENSIFY_CELLS), 1).astype(np.intp)
        seg = np.repeat(np.arange(len(n)), n)
        t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)
        xy = cells[seg] + (cells[seg + 1] - cells[seg]) * t[:, None]
        w = inv[seg] + (inv[seg + 1] - inv[seg]) * t
        pieces.append(np.column_stack([xy, 1.0 / w]))
        pieces.append(np.column_stack([cells[-1:], pts[-1:, 2]]))
    return np.concatenate(pieces) if pieces else np.zeros((0, 3))


def lane_targets(lanes: list[np.ndarray], camera: VirtualCamera) -> SaladTargets:
    w, h = camera.width // STRIDE, camera.height // STRIDE
    seg = np.zeros((h, w), dtype=np.float32)
    offsets = np.zeros((2, h, w), dtype=np.float32)
    depth = np.zeros((h, w), dtype=np.float32)
    points = project_lanes(lanes, camera)
    cells = np.rint(points[:, :2]).astype(np.intp)
    inside = (cells[:, 0] >= 0) & (cells[:, 0] < w) & (cells[:, 1] >= 0) & (cells[:, 1] < h)
    points, cells = points[inside], cells[inside]
    if not len(points):
        return SaladTargets(seg, offsets, depth, np.zeros((h, w), dtype=bool))
    hit = np.zeros((h, w), dtype=bool)
    hit[cells[:, 1], cells[:, 0]] = True
    core = hit.copy()
    hit[:, 1:] |= core[:, :-1]
    hit[:, :-1] |= core[:, 1:]
    rows, cols = np.nonzero(hit)
    _, nearest = cKDTree(points[:, :2]).query(np.column_stack([cols, rows]))
    seg[rows, cols] = 1.0
    offsets[0, rows, cols] = points[nearest, 0] - cols
    offsets[1, rows, cols] = points[nearest, 1] - rows
    sparse = np.zeros((h, w), dtype=np.float32)
    sparse[rows, cols] = points[nearest, 2]
    depth, mask = complete_depth(sparse)
    return SaladTargets(seg, offsets, depth, mask)


def complete_depth(sparse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dense depth, labelled mask) from a sparse depth map (0 = none); see the module doc."""
    h, w = sparse.shape
    has = sparse > 0
    rows = np.flatnonzero(has.any(axis=1))
    dense = np.zeros((h, w), dtype=np.float32)
    if not len(rows):
        return dense, np.zeros((h, w), dtype=bool)
    inv = np.zeros((len(rows), w))
    cols = np.arange(w)
    for i, r in enumerate(rows):  # one interpolation per labelled row (64 at most)
        known = np.flatnonzero(has[r])
        inv[i] = np.interp(cols, known, 1.0 / sparse[r, known])
    span = np.arange(rows[0], rows[-1] + 1)
    j = np.clip(np.searchsorted(rows, span), 1, max(len(rows) - 1, 1))
    if len(rows) == 1:
        filled = inv[:1]
    else:
        a = ((span - rows[j - 1]) / (rows[j] - rows[j - 1]))[:, None]
        filled = inv[j - 1] * (1 - a) + inv[j] * a
    dense[span] = 1.0 / filled
    mask = np.zeros((h, w), dtype=bool)
    mask[span] = True
    return dense, mask


def row_statistics(depths: np.ndarray, masks: np.ndarray, min_scale_m: float = 1.0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Per output row, the mean and spread of labelled depths over a set of images
    ((N, h, w) each): the row shift and scale of paper eq. 3. Rows no image labels take
    their nearest labelled row's values."""
    count = masks.sum(axis=(0, 2))
    total = np.where(masks, depths, 0).sum(axis=(0, 2))
    mean = np.divide(total, count, out=np.zeros(len(count)), where=count > 0)
    square = np.where(masks, depths.astype(np.float64) ** 2, 0).sum(axis=(0, 2))
    var = np.divide(square, count, out=np.zeros(len(count)), where=count > 0) - mean ** 2
    scale = np.maximum(np.sqrt(np.maximum(var, 0)), min_scale_m)
    known = np.flatnonzero(count > 0)
    if not len(known):
        raise ValueError('no labelled depth in any image: no row statistics')
    nearest = known[np.abs(np.arange(len(count))[:, None] - known[None]).argmin(axis=1)]
    return mean[nearest], scale[nearest]
