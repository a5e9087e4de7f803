"""Ground segmentation of an accumulated cloud, coarse to fine (ONCE-3DLanes section 3.2).

Coarse: each sweep keeps only returns well below its sensor (`below_sensor`), which removes
roofs, walls and most of every vehicle whatever the mount. Fine: the accumulated returns are
binned in CELL_M cells of a gravity-aligned frame, each cell's ground height is its lowest
return, and the ground is the region grown from a seed cell ahead of the vehicle across
neighbouring cells whose heights differ by less than STEP_M (the road, its kerbs and sidewalks;
not vehicle sides or barriers). A return is ground when it lies within BAND_M of its cell.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

CELL_M = 1.0
BAND_M = 0.12  # paint and asphalt texture stay inside; a bumper 0.3 m up does not
STEP_M = 0.2  # height change between neighbouring ground cells (kerbs ~0.15 m)
MIN_BELOW_SENSOR_M = 0.5  # coarse: ground lies at least this far below the sensor
MAX_BELOW_SENSOR_M = 5.0  # ... and not deeper (multipath, reflections in puddles)
MIN_CELL_POINTS = 2
PLANE_POINTS = 16  # the surface at a point: a plane through this many nearest ground returns
RAY_NEAR_M, RAY_FAR_M = 0.5, 100.0  # a ray meets the surface within these distances ...
RAY_STEPS = 30  # ... found by this many bisection steps


def below_sensor(xyz_sensor: np.ndarray) -> np.ndarray:
    """Coarse step on one sweep in its sensor frame: (N,) bool."""
    z = xyz_sensor[:, 2]
    return (z < -MIN_BELOW_SENSOR_M) & (z > -MAX_BELOW_SENSOR_M)


def segment_ground(xyz: np.ndarray, seed_xy: np.ndarray) -> np.ndarray:
    """(N,) bool: ground returns of (N, 3) points in a z-up frame, grown from seed_xy."""
    n = xyz.shape[0]
    mask = np.zeros(n, dtype=bool)
    if n == 0:
        return mask
    ij = np.floor(xyz[:, :2] / CELL_M).astype(np.int64)
    lo = ij.min(axis=0)
    ij -= lo
    shape = ij.max(axis=0) + 1
    cell = ij[:, 0] * shape[1] + ij[:, 1]
    lowest = np.full(shape[0] * shape[1], np.inf)
    np.minimum.at(lowest, cell, xyz[:, 2])
    count = np.bincount(cell, minlength=lowest.size)
    valid = count >= MIN_CELL_POINTS
    height = np.where(valid, lowest, np.nan).reshape(shape)

    # cells joined to their right and upper neighbours where both are valid and the step small
    index = np.arange(height.size).reshape(shape)
    pairs = ((index[:-1], index[1:]), (index[:, :-1], index[:, 1:]))
    flat_height = height.ravel()
    rows, cols = [], []
    for ia, ib in pairs:
        ok = np.abs(flat_height[ia] - flat_height[ib]) < STEP_M  # NaN compares False
        rows.append(ia[ok])
        cols.append(ib[ok])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(height.size,) * 2)
    _, component = connected_components(graph, directed=False)

    # seed: the valid cell nearest seed_xy (the road just ahead of the vehicle)
    centres = (np.argwhere(np.isfinite(height)) + lo + 0.5) * CELL_M
    if centres.size == 0:
        return mask
    flat = np.flatnonzero(np.isfinite(height).ravel())
    seed = flat[np.argmin(np.sum((centres - seed_xy[:2]) ** 2, axis=1))]
    ground_cell = component == component[seed]
    mask = ground_cell[cell] & (xyz[:, 2] - lowest[cell] < BAND_M)
    return mask


class GroundSurface:
    """The ground between returns: at (x, y) the plane through the PLANE_POINTS nearest ground
    returns (it follows crossfall and grade), and how far the nearest of them lies."""

    def __init__(self, ground_xyz: np.ndarray) -> None:
        self.xyz = np.asarray(ground_xyz, dtype=np.float64)
        self.tree = cKDTree(self.xyz[:, :2])

    def height(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) surface heights and (N,) distances to the nearest ground return."""
        k = min(PLANE_POINTS, self.xyz.shape[0])
        dist, index = self.tree.query(xy, k=k)
        dist, index = dist.reshape(len(xy), k), index.reshape(len(xy), k)
        near = self.xyz[index]  # (N, k, 3)
        a = np.concatenate([np.ones((*index.shape, 1)), near[..., :2] - xy[:, None, :]], axis=2)
        ata = np.einsum('nki,nkj->nij', a, a) + 1e-6 * np.eye(3)
        atz = np.einsum('nki,nk->ni', a, near[..., 2])
        return np.linalg.solve(ata, atz[..., None])[:, 0, 0], dist[:, 0]

    def cast(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where rays from origin first go below the surface: (M, 3) points and (M,) the
        distance of the nearest ground return to each (inf: the ray never meets it)."""
        def below(t: np.ndarray, d: np.ndarray) -> np.ndarray:
            p = origin + t[:, None] * d
            return p[:, 2] < self.height(p[:, :2])[0]

        lo, hi = np.full(len(dirs), RAY_NEAR_M), np.full(len(dirs), RAY_FAR_M)
        ok = below(hi, dirs) & ~below(lo, dirs)
        lo, hi, d = lo[ok], hi[ok], dirs[ok]
        for _ in range(RAY_STEPS):
            mid = (lo + hi) / 2
            under = below(mid, d)
            hi, lo = np.where(under, mid, hi), np.where(under, lo, mid)
        hits = np.full((len(dirs), 3), np.nan)
        support = np.full(len(dirs), np.inf)
        hits[ok] = origin + ((lo + hi) / 2)[:, None] * d
        if ok.any():
            support[ok] = self.height(hits[ok, :2])[1]
        return hits, support
