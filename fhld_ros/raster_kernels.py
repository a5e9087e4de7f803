"""Compiled loops of the BEV raster (bev.RasterAccumulator): one pass over a sweep's points
and one over the window's cells.

numpy needed a pass per operation and three ufunc.at scatters per sweep (~13 ns a point); one
compiled pass does the pixel mapping, the four sums and the minimum of a point together, and
releases the GIL, so two threads can each take half of the window's rows. Every float32
operation is the one numpy did, in the same order (no fast-math, no fused multiply-add), so
the rasters are bit for bit those the shipped weights were trained on.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.compiled import compiled

# sums columns of RasterAccumulator: count, intensity, e, e^2
COUNT, INTENSITY, E, E2 = range(4)


@compiled
def _bordered_index(pixel: np.float32, side: int) -> int:
    """floor(pixel) clipped to [0, side - 1]: outside the window lands in the border cells,
    and so does NaN (a bare int() of NaN would index far outside the arrays)."""
    if pixel >= side - 1:
        return side - 1
    if pixel > 0:
        return int(pixel)  # positive: trunc == floor
    return 0


@compiled
def scatter_points(sums: np.ndarray, e_min: np.ndarray, side: int, row_lo: int, row_hi: int,
                   xy: np.ndarray, affine: np.ndarray, intensity: np.ndarray,
                   e: np.ndarray) -> None:
    """Add the points whose bordered row is in [row_lo, row_hi) to sums (side*side, 4) and
    e_min (side*side,). xy (2, N) float32 maps to bordered pixels (col, row) by affine (2, 3);
    points outside the window are clipped into the border cells."""
    a00, a01, a02 = affine[0, 0], affine[0, 1], affine[0, 2]
    a10, a11, a12 = affine[1, 0], affine[1, 1], affine[1, 2]
    for j in range(xy.shape[1]):
        x, y = xy[0, j], xy[1, j]
        row = x * a10
        row += y * a11
        row += a12
        r = _bordered_index(row, side)
        if r < row_lo or r >= row_hi:
            continue
        col = x * a00
        col += y * a01
        col += a02
        cell = r * side + _bordered_index(col, side)
        ej = e[j]
        sums[cell, COUNT] += np.float32(1.0)
        sums[cell, INTENSITY] += intensity[j]
        sums[cell, E] += ej
        sums[cell, E2] += ej * ej
        if ej < e_min[cell]:
            e_min[cell] = ej


@compiled
def encode_cells(sums: np.ndarray, e_min: np.ndarray, side: int, row_lo: int, row_hi: int,
                 density_lut: np.ndarray, var_scale: np.float32, z_scale: np.float32,
                 z_offset: np.float32, raster: np.ndarray) -> None:
    """Channels of window rows [row_lo, row_hi) into raster (4, side - 2, side - 2); the
    formulas are bev.RasterAccumulator.encode's."""
    zero, one, tiny = np.float32(0.0), np.float32(1.0), np.float32(1e-30)
    top = density_lut.shape[0] - 1
    for r in range(row_lo, row_hi):
        for c in range(side - 2):
            cell = (r + 1) * side + c + 1
            n = sums[cell, COUNT]
            inv_n = one / (n + tiny)  # 1e30 for empty cells, whose sums are 0
            raster[0, r, c] = sums[cell, INTENSITY] * inv_n
            raster[1, r, c] = density_lut[min(int(n), top)]
            mean = sums[cell, E] * inv_n
            var = sums[cell, E2] * inv_n
            var -= mean * mean
            var *= var_scale
            raster[2, r, c] = min(max(var, zero), one)
            z = e_min[cell] * z_scale
            z += z_offset
            raster[3, r, c] = min(max(z, zero), one)  # empty: +inf -> 1
