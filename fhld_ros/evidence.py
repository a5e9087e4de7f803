"""Lanes only where there is evidence: where the sensor looked, and where paint shows.

keep_observed: lane ends far from every observed cell are cut.

The model draws a lane through the whole window once it has found it, also across ground that
no return ever touched: the sector beside and behind a forward-only scanner, the road past a
row of vehicles. A cell is observed when the window's density channel is non-zero; a lane point
is supported when an observed cell lies within `reach_m` of it (a square neighbourhood: cheap
with row prefix sums). Each lane keeps the span from its first to its last supported point,
if that is at least `min_length_m` long. Gaps inside the span stay bridged: splitting a lane
there cost the lane-level (ONCE-3DLanes) matching more than it gained (docs/accuracy.md), and
the ring gaps of a sparse sensor or the blind ring around a single sweep are such gaps.

keep_painted: a lane whose brightest returns do not stand out from the road on both sides of it
is dropped. On real sweeps the model drew confident lanes along a light strip at a curb foot, a
dark seam and a bare curb, where the layout looks like a lane but no paint is (docs/accuracy.md,
"Paint evidence"). Paint is brighter than the road it lies on, whatever the sensor's units, so
the test is a ratio: the 95th percentile of the mean intensities of the observed cells within
PAINT_HALF_WIDTH_M of the lane, against the median of the cells 0.35-1 m to each side that lie
at the lane's height (curbs and sidewalks are not the road). Both sides must fall short of it by
min_contrast. A worn edge line a few decimetres inside a light verge or a concrete edge fails
that test (the verge is brighter than the worn paint) and is a stripe all the same: so a lane
is also kept when it stands out by STRIPE_FACTOR x min_contrast from the road right beside it
(0.2-0.3 m) on both sides, which the false lanes above, edges of a brighter surface, do not. A
lane with too few observed cells on it, or beside it on both sides, is kept: no evidence either
way (the blind ring of a single sweep, a lane at the window's edge).
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fhld_ros.bev import decode_min_height

INTENSITY_CHANNEL, DENSITY_CHANNEL, MIN_HEIGHT_CHANNEL = 0, 1, 3
PAINT_STEP_M = 0.1  # the lane is sampled this often along its length
PAINT_HALF_WIDTH_M = 0.12  # on the lane: paint is 0.1-0.2 m wide, the lane a few cm off it
ROAD_BESIDE_M = (0.35, 1.0)  # the road surface on each side, clear of the paint
RIGHT_BESIDE_M = (0.2, 0.3)  # the road between the paint and a verge or shoulder beyond it
# a stripe against the road right beside it must stand out by this x min_contrast: the false
# lanes on the real sweeps read <= 1.46 there, the worn simulated lines beside a light verge
# that it keeps 2.0-3.4 (validation seeds)
STRIPE_FACTOR = 1.25
LEVEL_M = 0.05  # a cell beside the lane is road when its lowest return is this close in height
PERCENTILE = 95.0  # dashed lines: paint covers a quarter of a lane's length, or less
MIN_CELLS = 10  # fewer observed cells on the lane (or on a side): no evidence either way
# lateral offsets sampled at each point: 7 across the paint, 3 right beside it and 8 on the
# road to each side
_BESIDE = np.concatenate([np.linspace(*RIGHT_BESIDE_M, 3), np.linspace(*ROAD_BESIDE_M, 8)])
_OFFSETS = np.concatenate([np.linspace(-PAINT_HALF_WIDTH_M, PAINT_HALF_WIDTH_M, 7),
                           -_BESIDE, _BESIDE])


def _row_prefix(raster: np.ndarray) -> np.ndarray:
    """(H, W + 1) counts of observed cells left of each column edge, row by row."""
    occupied = raster[DENSITY_CHANNEL] > 0
    prefix = np.zeros((occupied.shape[0], occupied.shape[1] + 1), dtype=np.int32)
    np.cumsum(occupied, axis=1, dtype=np.int32, out=prefix[:, 1:])
    return prefix


def _observed_count(prefix: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                    reach_px: int) -> np.ndarray:
    """Observed cells within reach_px (Chebyshev) of each (row, col), from the row prefix sums:
    the rows of each box are summed at the lane points only, so the window is passed once (a
    full integral image took a second, slower pass over all 640 x 640 cells)."""
    h, w = prefix.shape[0], prefix.shape[1] - 1
    rows, cols = np.asarray(rows).ravel(), np.asarray(cols).ravel()
    c0, c1 = np.clip(cols - reach_px, 0, w)[:, None], np.clip(cols + reach_px + 1, 0, w)[:, None]
    band = rows[:, None] + np.arange(-reach_px, reach_px + 1)  # (N, 2 reach + 1) box rows
    inside = (band >= 0) & (band < h)
    np.clip(band, 0, h - 1, out=band)
    return np.where(inside, prefix[band, c1] - prefix[band, c0], 0).sum(axis=1)


def keep_observed(lanes: list[np.ndarray], confidences: np.ndarray, raster: np.ndarray,
                  resolution_m: float, reach_m: float, min_length_m: float = 2.0
                  ) -> tuple[list[np.ndarray], np.ndarray]:
    """Each (K, 3) window-frame lane from its first to its last supported point, with its
    confidence; lanes with no supported span of min_length_m are dropped.

    reach_m <= 0 returns the lanes unchanged.
    """
    if reach_m <= 0 or not lanes:
        return lanes, confidences
    size = raster.shape[1]
    half = size * resolution_m / 2
    points = np.concatenate(lanes)  # box sums at every lane's points in one call
    col = np.clip(((points[:, 0] + half) / resolution_m).astype(int), 0, size - 1)
    row = np.clip(((points[:, 1] + half) / resolution_m).astype(int), 0, size - 1)
    support = _observed_count(_row_prefix(raster), row, col,
                              int(round(reach_m / resolution_m))) > 0
    ends = np.cumsum([len(lane) for lane in lanes])
    kept, scores = [], []
    for lane, score, lane_support in zip(lanes, np.asarray(confidences),
                                         np.split(support, ends[:-1])):
        supported = np.flatnonzero(lane_support)
        if supported.size < 2:
            continue
        span = lane[supported[0]:supported[-1] + 1]
        if np.linalg.norm(np.diff(span[:, :2], axis=0), axis=1).sum() >= min_length_m:
            kept.append(span)
            scores.append(score)
    return kept, np.asarray(scores, dtype=np.asarray(confidences).dtype)


def _along(lane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) points every PAINT_STEP_M along the lane's xy and the unit normals there."""
    xy = lane[:, :2]
    step = np.diff(xy, axis=0)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(step[:, 0], step[:, 1]))])
    at = np.arange(0.0, arc[-1], PAINT_STEP_M)
    points = np.column_stack([np.interp(at, arc, xy[:, 0]), np.interp(at, arc, xy[:, 1])])
    if len(points) < 2:
        return points, np.zeros_like(points)
    tangent = np.empty_like(points)  # central differences, one-sided at the ends
    tangent[1:-1] = points[2:] - points[:-2]
    tangent[0], tangent[-1] = points[1] - points[0], points[-1] - points[-2]
    tangent /= np.maximum(np.hypot(tangent[:, :1], tangent[:, 1:]), 1e-9)
    return points, np.column_stack([-tangent[:, 1], tangent[:, 0]])


def _cells(raster: np.ndarray, points: np.ndarray, normals: np.ndarray, offsets: np.ndarray,
           resolution_m: float) -> tuple[np.ndarray, ...]:
    """Mean intensity, lowest height (m), lateral offset and point index of the observed cells
    at points + offsets * normals (each offset at each point; outside the window: unobserved)."""
    size = raster.shape[-1]
    scale, centre = 1.0 / resolution_m, size / 2
    col = np.floor((points[:, :1] + offsets * normals[:, :1]) * scale + centre).astype(np.intp)
    row = np.floor((points[:, 1:] + offsets * normals[:, 1:]) * scale + centre).astype(np.intp)
    col, row = col.ravel(), row.ravel()
    inside = np.flatnonzero((np.minimum(col, row) >= 0) & (np.maximum(col, row) < size))
    flat = row.take(inside) * size + col.take(inside)
    cells = raster.reshape(raster.shape[0], -1)
    observed = cells[DENSITY_CHANNEL].take(flat) > 0
    flat, inside = flat[observed], inside[observed]
    point, which = np.divmod(inside, len(offsets))
    return (cells[INTENSITY_CHANNEL].take(flat),
            decode_min_height(cells[MIN_HEIGHT_CHANNEL].take(flat)),
            offsets.take(which), point)


def _quantile(values: np.ndarray, q: float) -> float:
    """np.quantile(values, q) (linear) by one partition: at a few hundred cells numpy's own
    median and percentile cost ~0.1 ms a call in overhead, several times the work."""
    pos = q * (len(values) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(values) - 1)
    part = np.partition(values, (lo, hi))
    return float(part[lo] + (part[hi] - part[lo]) * (pos - lo))


def _contrast(values: np.ndarray, z: np.ndarray, offset: np.ndarray) -> tuple[float, float]:
    """paint_contrasts from one lane's observed cells."""
    on = np.abs(offset) <= PAINT_HALF_WIDTH_M
    if np.count_nonzero(on) < MIN_CELLS:
        return float('nan'), float('nan')
    top = _quantile(values[on], PERCENTILE / 100)
    level = np.abs(z - _quantile(z[on], 0.5)) < LEVEL_M
    right_beside = np.abs(offset) < ROAD_BESIDE_M[0]
    return (_against_sides(top, values, offset, level & ~on & ~right_beside, any),
            _against_sides(top, values, offset, level & ~on & right_beside, all))


def _against_sides(top: float, values: np.ndarray, offset: np.ndarray, road: np.ndarray,
                   need: Callable[[list[bool]], bool]) -> float:
    """top / the brighter side's median of the road cells; NaN unless need() of the two sides
    has MIN_CELLS (any: one side will do; all: both sides must show)."""
    sides = [values[road & (offset < 0)], values[road & (offset > 0)]]
    shown = [side.size >= MIN_CELLS for side in sides]
    if not need(shown):
        return float('nan')
    level = max(_quantile(side, 0.5) for side, ok in zip(sides, shown) if ok)
    return top / level if level > 0 else float('nan')


def paint_contrasts(lanes: list[np.ndarray], raster: np.ndarray,
                    resolution_m: float) -> np.ndarray:
    """(N, 2): per lane, how far its brightest returns stand out (PERCENTILE of the cells on
    it) from the road on its brighter side, 0.35-1 m away (one side will do) and right beside
    it (both sides must be observed); NaN without evidence. One gather for all lanes: the
    per-call overhead, not the samples, is the cost."""
    along = [_along(np.asarray(lane, dtype=np.float64)) for lane in lanes]
    counts = np.array([len(points) for points, _ in along])
    if not counts.sum():
        return np.full((len(lanes), 2), np.nan)
    values, z, offset, point = _cells(raster, np.concatenate([p for p, _ in along]),
                                      np.concatenate([n for _, n in along]), _OFFSETS,
                                      resolution_m)
    bounds = np.searchsorted(point, np.concatenate([[0], np.cumsum(counts)]))
    return np.array([_contrast(values[i:j], z[i:j], offset[i:j]) if n >= 2 else
                     (np.nan, np.nan) for i, j, n in zip(bounds[:-1], bounds[1:], counts)]
                    ).reshape(len(lanes), 2)


def paint_contrast(lane: np.ndarray, raster: np.ndarray, resolution_m: float) -> float:
    """paint_contrasts of one lane against the road 0.35-1 m away."""
    return float(paint_contrasts([lane], raster, resolution_m)[0, 0])


def stripe_contrast(lane: np.ndarray, raster: np.ndarray, resolution_m: float) -> float:
    """paint_contrasts of one lane against the road right beside it."""
    return float(paint_contrasts([lane], raster, resolution_m)[0, 1])


def keep_painted(lanes: list[np.ndarray], confidences: np.ndarray, raster: np.ndarray,
                 resolution_m: float, min_contrast: float) -> tuple[list[np.ndarray], np.ndarray]:
    """The lanes (with their confidences) whose paint_contrast is >= min_contrast or unknown,
    or whose stripe_contrast is >= STRIPE_FACTOR x min_contrast.

    min_contrast <= 0 returns the lanes unchanged.
    """
    if min_contrast <= 0 or not lanes:
        return lanes, confidences
    beside, right_beside = paint_contrasts(lanes, raster, resolution_m).T
    keep = ~(beside < min_contrast) | (right_beside >= STRIPE_FACTOR * min_contrast)  # NaN: kept
    return [lane for lane, k in zip(lanes, keep) if k], np.asarray(confidences)[keep]
