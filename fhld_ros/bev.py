"""Bird's-eye-view encoding: sweeps -> rolling point buffer -> 4-channel raster (FHLD input).

One code path for training samples, bag replay and the live node, so there is no
training/serving skew. Conventions (fixed, docs/design.md §3):

* Window frame: origin at the newest sweep's sensor position, x forward along its heading
  (yaw only, gravity aligned), y left, z up; heights are relative to the sensor.
* The window is the half-open square [-L/2, L/2)^2, L = size_px * resolution_m. Cell
  (row iy, col ix) = (floor((y + L/2)/res), floor((x + L/2)/res)); raster layout (C, H, W).
* Channels (FHLD "Problem Definition"), all float32 in [0, 1], formulas below:
  0 mean intensity  mean of the per-sweep encoded intensity (intensity.py: absolute or contrast)
  1 density         log1p(count) / log1p(DENSITY_REF_COUNT), clipped
  2 height var.     population variance of z (m^2) / HEIGHT_VAR_REF_M2, clipped
  3 min height      (min z - MIN_HEIGHT_LOW_M) / (MIN_HEIGHT_HIGH_M - MIN_HEIGHT_LOW_M), clipped
  Empty cells: channels 0-2 are 0 and min height is EMPTY_MIN_HEIGHT; density == 0 is the
  unambiguous "no points" marker.
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache

import numpy as np

from fhld_ros.raster_kernels import encode_cells, scatter_points

# --- normalisation constants of the channel formulas (RasterAccumulator.encode) ---
DENSITY_REF_COUNT = 16  # points per cell that saturate the density channel
HEIGHT_VAR_REF_M2 = 0.1  # variance (m^2) that saturates the height-variance channel
MIN_HEIGHT_LOW_M = -3.0  # min height mapped to 0 (road is about -1.5..-2 m below the sensor)
MIN_HEIGHT_HIGH_M = 1.0  # min height mapped to 1
EMPTY_MIN_HEIGHT = 1.0  # min-height channel of an empty cell: min of no points = +inf, clipped
HEIGHT_SHIFT_M = -1.8  # nominal road height: heights are summed relative to it (float32 sums)
Z_REBASE_M = 2.0  # the grid re-bases its height reference when the road moves this much
MAX_RASTER_THREADS = 4  # a raster is memory-bound: more threads than this gain nothing
CHANNELS = ('mean_intensity', 'density', 'height_variance', 'min_height')


@dataclass(frozen=True)
class BevSpec:
    """Geometry of the BEV window: size_px x size_px square cells of resolution_m metres."""

    size_px: int = 640
    resolution_m: float = 0.04

    def __post_init__(self) -> None:
        if self.size_px <= 0 or not self.resolution_m > 0:
            raise ValueError(f'BevSpec needs size_px > 0 and resolution_m > 0, got {self}')

    @property
    def length_m(self) -> float:
        """Side of the square window in metres."""
        return self.size_px * self.resolution_m

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """Window-frame metres (..., >=2) x, y[, z] -> continuous pixel coords (..., 2) col, row.

        Cell (row, col) covers [row, row + 1) x [col, col + 1); pixel centres are at k + 0.5.
        float32 input stays float32.
        """
        xy = np.asarray(xy)[..., :2]
        dtype = xy.dtype if xy.dtype == np.float32 else np.dtype(np.float64)
        return xy.astype(dtype, copy=False) * dtype.type(1.0 / self.resolution_m) \
            + dtype.type(self.size_px / 2)

    def pixel_to_world(self, colrow: np.ndarray) -> np.ndarray:
        """Continuous pixel coords (..., 2) (col, row) -> window-frame metres (..., 2) (x, y)."""
        colrow = np.asarray(colrow, dtype=np.float64)
        return (colrow - self.size_px / 2) * self.resolution_m


def decode_min_height(channel: np.ndarray) -> np.ndarray:
    """Min-height channel values (any shape) -> metres: the inverse of the encoding inside its
    clip range (heights outside [MIN_HEIGHT_LOW_M, MIN_HEIGHT_HIGH_M] come back clipped)."""
    return channel * (MIN_HEIGHT_HIGH_M - MIN_HEIGHT_LOW_M) + MIN_HEIGHT_LOW_M


def min_height_m(raster: np.ndarray) -> np.ndarray:
    """(..., 4, H, W) raster -> (..., H, W) per-cell minimum height in metres, NaN where empty."""
    raster = np.asarray(raster)
    return np.where(raster[..., 1, :, :] > 0, decode_min_height(raster[..., 3, :, :]), np.nan)


def window_affine(cos: float, sin: float, offset: np.ndarray, spec: BevSpec) -> np.ndarray:
    """(2, 3) float32 map [x, y, 1] -> bordered pixel coordinates (col + 1, row + 1).

    For points rotated by the window yaw (cos, sin), then shifted by offset (window metres).
    The accumulators have a one-cell border, hence the + 1.
    """
    inv, base = 1.0 / spec.resolution_m, spec.size_px / 2 + 1
    return np.array([[cos * inv, sin * inv, offset[0] * inv + base],
                     [-sin * inv, cos * inv, offset[1] * inv + base]], dtype=np.float32)


def pixel_coords(xy: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """affine @ [x; y; 1] for xy (2, N) float32 -> (2, N) float32, with the float32 operations
    of raster_kernels.scatter_points in their order, so a point maps to the cell it was
    rasterised into. Elementwise, not a matmul: BLAS may fuse multiply-adds (other roundings),
    and its threads stalled for milliseconds now and then on this busy 2-core machine."""
    x, y = xy
    out = np.empty_like(xy)
    for k in range(2):
        out[k] = x * affine[k, 0]
        out[k] += y * affine[k, 1]
        out[k] += affine[k, 2]
    return out


# density depends only on the count and saturates at DENSITY_REF_COUNT: a lookup table
_DENSITY_LUT = (np.log1p(np.arange(DENSITY_REF_COUNT + 1)) / math.log1p(DENSITY_REF_COUNT)
                ).astype(np.float32)


class RasterAccumulator:
    """Per-cell statistics of one window, in arrays reused across windows.

    The arrays have a one-cell border: points outside the window are clipped into it instead of
    being compacted away. Per cell: float32 sums of 1, intensity, e and e^2 (heights e relative
    to a reference near the road: variance is shift-invariant, and small e keeps E[e^2] -
    E[e]^2 accurate) and the minimum e. The loops are compiled (raster_kernels.py); with
    threads=2 each of two threads takes half of the rows, so every cell still sums its points
    in the order they were added.
    """

    def __init__(self, spec: BevSpec, threads: int = 2) -> None:
        if not 1 <= threads <= MAX_RASTER_THREADS:
            raise ValueError(f'RasterAccumulator threads must be 1..{MAX_RASTER_THREADS}, '
                             f'got {threads}')
        self.spec = spec
        side = spec.size_px + 2
        self.sums = np.zeros((side * side, 4), dtype=np.float32)
        self.e_min = np.full(side * side, np.inf, dtype=np.float32)
        self._bands = _row_bands(side, threads)  # bordered rows, for the points
        self._cell_bands = _row_bands(spec.size_px, threads)  # window rows, for the cells
        _load_kernels()

    def clear(self) -> None:
        self.sums.fill(0)
        self.e_min.fill(np.inf)

    def add(self, xy: np.ndarray, affine: np.ndarray, intensity01: np.ndarray,
            e: np.ndarray) -> None:
        """Add points: xy (2, N) float32 mapped to pixels by affine (2, 3); intensity01 and
        e = z - z_ref (N,) float32."""
        self.add_all([(xy, affine, intensity01, e)])

    def add_all(self, sources: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
                ) -> None:
        """add() for each (xy, affine, intensity01, e) in order, one hand-off per thread."""
        side = self.spec.size_px + 2

        def band(rows: tuple[int, int]) -> None:
            for xy, affine, intensity01, e in sources:
                scatter_points(self.sums, self.e_min, side, *rows, xy, affine, intensity01, e)
        self._in_bands(band, self._bands)

    def encode(self, z_ref: float) -> np.ndarray:
        """The (4, H, W) float32 raster of the points added since clear(); z = e + z_ref.

        Formulas per cell with n points: mean intensity = sum(i) / n; density =
        min(log1p(n) / log1p(DENSITY_REF_COUNT), 1); height variance = clip((sum(e^2) / n -
        (sum(e) / n)^2) / HEIGHT_VAR_REF_M2, 0, 1); min height = clip((min z - LOW) / (HIGH -
        LOW), 0, 1). For n = 0 the sums are 0 (channels 0-2 are 0) and min z is +inf, so the
        min height saturates at 1 (EMPTY_MIN_HEIGHT).
        """
        size, f32 = self.spec.size_px, np.float32
        raster = np.empty((4, size, size), dtype=f32)
        scale = 1.0 / (MIN_HEIGHT_HIGH_M - MIN_HEIGHT_LOW_M)
        constants = (_DENSITY_LUT, f32(1.0 / HEIGHT_VAR_REF_M2), f32(scale),
                     f32((z_ref - MIN_HEIGHT_LOW_M) * scale), raster)

        def band(rows: tuple[int, int]) -> None:
            encode_cells(self.sums, self.e_min, size + 2, *rows, *constants)
        self._in_bands(band, self._cell_bands)
        return raster

    def _in_bands(self, band: Callable[[tuple[int, int]], None],
                  bands: list[tuple[int, int]]) -> None:
        """band(rows) for every band: the first in this thread, the others in the pool."""
        others = [_band_pool().submit(band, rows) for rows in bands[1:]]
        band(bands[0])
        for other in others:
            other.result()


@cache
def _load_kernels() -> None:
    """Compile the loops (or load them from numba's cache) once per process, with the argument
    types of every later call, so that a node's first sweep does not wait for it."""
    f32, side = np.float32, 3
    sums, e_min, none = np.zeros((side * side, 4), f32), np.zeros(side * side, f32), f32([])
    scatter_points(sums, e_min, side, 0, side, none.reshape(2, 0), np.zeros((2, 3), f32), none,
                   none)
    encode_cells(sums, e_min, side, 0, 1, _DENSITY_LUT, f32(1), f32(1), f32(0),
                 np.zeros((4, 1, 1), f32))


@cache
def _band_pool() -> ThreadPoolExecutor:
    """The threads that take the other bands, shared by every accumulator of the process."""
    return ThreadPoolExecutor(MAX_RASTER_THREADS - 1, thread_name_prefix='raster')


# a forked child has none of its parent's threads: it starts a pool of its own
os.register_at_fork(after_in_child=_band_pool.cache_clear)


def _row_bands(rows: int, threads: int) -> list[tuple[int, int]]:
    """[lo, hi) row ranges that split rows into threads near-equal bands."""
    edges = np.linspace(0, rows, threads + 1).round().astype(int)
    return [(int(lo), int(hi)) for lo, hi in zip(edges[:-1], edges[1:])]


def rasterize(xyz_window: np.ndarray, intensity01: np.ndarray,
              spec: BevSpec = BevSpec()) -> np.ndarray:
    """Points (N, 3) in the window frame + intensities in [0, 1] -> float32 raster (4, H, W).

    Points outside the window or with a non-finite coordinate/intensity are ignored.
    """
    xyz = np.asarray(xyz_window, dtype=np.float32).reshape(-1, 3)
    inten = np.asarray(intensity01, dtype=np.float32).reshape(-1)
    if inten.shape[0] != xyz.shape[0]:
        raise ValueError(f'{xyz.shape[0]} points but {inten.shape[0]} intensities')
    keep = np.isfinite(xyz).all(axis=1) & np.isfinite(inten)
    xyz, inten = xyz[keep], inten[keep]
    e = xyz[:, 2] - np.float32(HEIGHT_SHIFT_M)
    acc = RasterAccumulator(spec, threads=1)
    acc.add(np.ascontiguousarray(xyz[:, :2].T), window_affine(1.0, 0.0, np.zeros(3), spec),
            inten, e)
    return acc.encode(HEIGHT_SHIFT_M)


def yaw_frame(sensor_to_output: np.ndarray) -> np.ndarray:
    """Gravity-aligned pose: sensor position, yaw of its x axis, roll/pitch dropped."""
    yaw = math.atan2(sensor_to_output[1, 0], sensor_to_output[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    frame = np.eye(4)
    frame[:2, :2] = [[c, -s], [s, c]]
    frame[:3, 3] = sensor_to_output[:3, 3]
    return frame
