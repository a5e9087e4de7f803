"""Lanes only where the sensor looked: lane ends far from every observed cell are cut.

The model draws a lane through the whole window once it has found it, also across ground that
no return ever touched: the sector beside and behind a forward-only scanner, the road past a
row of vehicles. A cell is observed when the window's density channel is non-zero; a lane point
is supported when an observed cell lies within `reach_m` of it (a square neighbourhood: cheap
with an integral image). Each lane keeps the span from its first to its last supported point,
if that is at least `min_length_m` long. Gaps inside the span stay bridged: splitting a lane
there cost the lane-level (ONCE-3DLanes) matching more than it gained (docs/accuracy.md), and
the ring gaps of a sparse sensor or the blind ring around a single sweep are such gaps.
"""
from __future__ import annotations

import numpy as np

DENSITY_CHANNEL = 1


def _integral(raster: np.ndarray) -> np.ndarray:
    """(H + 1, W + 1) counts of observed cells above and left of each corner."""
    counts = (raster[DENSITY_CHANNEL] > 0).astype(np.int32)
    integral = np.zeros((counts.shape[0] + 1, counts.shape[1] + 1), dtype=np.int32)
    np.add.accumulate(counts, axis=0, out=counts)  # in place: no third 640 x 640 array
    np.add.accumulate(counts, axis=1, out=integral[1:, 1:])
    return integral


def _observed_count(integral: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                    reach_px: int) -> np.ndarray:
    """Observed cells within reach_px (Chebyshev) of each (row, col), from the integral."""
    h, w = integral.shape[0] - 1, integral.shape[1] - 1
    r0, r1 = np.clip(rows - reach_px, 0, h), np.clip(rows + reach_px + 1, 0, h)
    c0, c1 = np.clip(cols - reach_px, 0, w), np.clip(cols + reach_px + 1, 0, w)
    return integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]


def keep_observed(lanes: list[np.ndarray], confidences: np.ndarray, raster: np.ndarray,
                  resolution_m: float, reach_m: float, min_length_m: float = 2.0
                  ) -> tuple[list[np.ndarray], np.ndarray]:
    """Each (K, 3) window-frame lane from its first to its last supported point, with its
    confidence; lanes with no supported span of min_length_m are dropped.

    reach_m <= 0 returns the lanes unchanged.
    """
    if reach_m <= 0 or not lanes:
        return lanes, confidences
    integral = _integral(raster)  # box sums at the lane points only: no full-window mask
    reach_px = int(round(reach_m / resolution_m))
    size = raster.shape[1]
    half = size * resolution_m / 2
    kept, scores = [], []
    for lane, score in zip(lanes, np.asarray(confidences)):
        col = np.clip(((lane[:, 0] + half) / resolution_m).astype(int), 0, size - 1)
        row = np.clip(((lane[:, 1] + half) / resolution_m).astype(int), 0, size - 1)
        supported = np.flatnonzero(_observed_count(integral, row, col, reach_px))
        if supported.size < 2:
            continue
        span = lane[supported[0]:supported[-1] + 1]
        if np.linalg.norm(np.diff(span[:, :2], axis=0), axis=1).sum() >= min_length_m:
            kept.append(span)
            scores.append(score)
    return kept, np.asarray(scores, dtype=np.asarray(confidences).dtype)
