"""Intensity encodings: a sweep's raw intensity field -> the [0, 1] values the BEV raster averages.

Sensors disagree on what intensity means: 0-1 floats, 0-255 counts, uint16 reflectivity, and
any gain from one unit to the next. Three encodings (docs/design.md §3); a checkpoint records the
one its model was trained with (FhldConfig.intensity_encoding):

* ``absolute``: raw / full scale, the full scale inferred per sweep (1, 255 or 65535) unless
  given. The model then learns one simulator's brightness: a gain of x2 changes its lanes.
* ``contrast``: raw / the sweep's own ground level * GROUND_LEVEL. Paint is read by how much
  brighter it is than the road around it, so units and gain cancel (up to quantisation and
  saturation of the sensor's own counts).
* ``contrast_rings``: ``contrast`` after each laser's own gain is taken out: every return is
  scaled by its laser's gain measured on the ground (intensity_rings.py), the lasers told
  apart by the cloud's ring field, else by elevation angle in the sensor frame, so
  uncalibrated multi-laser sensors (whole bright rings on an HDL-64E) read like calibrated
  ones. Without separable rings (a pre-accumulated or non-spinning cloud) it is ``contrast``.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.compiled import compiled
from fhld_ros.intensity_lookup import RingTable, encode_with_gains, valid_ring_ids
from fhld_ros.intensity_rings import RING_SAMPLE, ground_subsample, ring_table

ABSOLUTE, CONTRAST, CONTRAST_RINGS = 'absolute', 'contrast', 'contrast_rings'
INTENSITY_ENCODINGS = (ABSOLUTE, CONTRAST, CONTRAST_RINGS)
INTENSITY_FULL_SCALES = (1.0, 255.0, 65535.0)  # 0-1 float, 8-bit / Velodyne, 16-bit sensors
INTENSITY_PERCENTILE = 99.9  # robust "max" of a sweep when picking its full scale
# contrast: the ground level maps here, so paint up to 1 / GROUND_LEVEL = 20x the road stays
# below saturation (fresh simulated paint is 15-20x; the asphalt sits at 0.02-0.07 in the
# absolute encoding)
GROUND_LEVEL = 0.05
GROUND_RANGE_M = (2.5, 20.0)  # horizontal range of the returns the ground level is taken from
GROUND_CELL_M = 2.0  # a return is ground within GROUND_BAND_M of the lowest one of its cell
GROUND_BAND_M = 0.15
GROUND_BELOW_SENSOR_M = 0.5  # and at least this far below the sensor (not roofs, not walls)
GROUND_QUANTILE = 75.0  # level = mean of the ground values up to this percentile (no paint)
GROUND_MIN_POINTS = 200  # fewer ground returns: the previous sweep's level is kept
GROUND_SAMPLE = 65536  # the level is taken from at most about this many returns (every k-th)


def normalize_intensity(raw: np.ndarray, scale: float | None = None) -> np.ndarray:
    """The absolute encoding: raw intensity of one sweep -> float32 in [0, 1].

    With ``scale=None`` the full scale is the smallest of INTENSITY_FULL_SCALES (1, 255, 65535)
    that is >= the sweep's 99.9th percentile (the largest one if none is): 0-1 float sensors
    -> 1; Velodyne-style 0-255 floats and Ouster calibrated reflectivity (uint16 holding 0-255)
    -> 255; raw 16-bit signal -> 65535. The percentile ignores a few retro-reflector outliers,
    which are then clipped to 1. Pass ``scale`` to fix it for a sensor (e.g. from a parameter)
    so a dim sweep cannot switch scales. Non-finite values become 0.
    """
    values = np.asarray(raw, dtype=np.float32).reshape(-1)
    if scale is None:
        finite = values[np.isfinite(values)]
        robust_max = float(np.percentile(finite, INTENSITY_PERCENTILE)) if finite.size else 0.0
        scale = next((s for s in INTENSITY_FULL_SCALES if s >= robust_max),
                     INTENSITY_FULL_SCALES[-1])
    elif not scale > 0:
        raise ValueError(f'intensity scale must be > 0, got {scale}')
    out = values * np.float32(1.0 / scale)
    np.clip(out, 0.0, 1.0, out=out)
    out[~np.isfinite(out)] = 0.0  # clip keeps NaN
    return out


def ground_mask(xyz_sensor: np.ndarray) -> np.ndarray:
    """(N,) bool: returns that lie on the ground near the sensor (sensor-frame points).

    Local, so neither the mount height nor a few degrees of pitch or roll matter: a return is
    ground when it lies within GROUND_BAND_M of the lowest return of its GROUND_CELL_M square
    cell, GROUND_RANGE_M away horizontally and GROUND_BELOW_SENSOR_M below the sensor.
    """
    x, y, z = np.asarray(xyz_sensor, dtype=np.float32).reshape(-1, 3).T
    f32 = np.float32
    lo, hi = GROUND_RANGE_M
    return _ground_mask(x, y, z, f32(lo * lo), f32(hi * hi), f32(-GROUND_BELOW_SENSOR_M),
                        f32(hi), f32(GROUND_CELL_M), int(np.ceil(2 * hi / GROUND_CELL_M)),
                        f32(GROUND_BAND_M))


@compiled
def _ground_mask(x: np.ndarray, y: np.ndarray, z: np.ndarray, lo2: np.float32,
                 hi2: np.float32, below: np.float32, hi: np.float32, cell_m: np.float32,
                 side: int, band: np.float32) -> np.ndarray:
    """ground_mask's two passes: the lowest return of each cell, then the returns near it."""
    n = x.shape[0]
    cell = np.full(n, -1, dtype=np.int64)  # -1: not in the ground range
    lowest = np.full(side * side, np.inf, dtype=np.float32)
    for j in range(n):
        r2 = x[j] * x[j] + y[j] * y[j]
        if r2 >= lo2 and r2 <= hi2 and z[j] < below:
            ix = min(max(int((x[j] + hi) / cell_m), 0), side - 1)
            iy = min(max(int((y[j] + hi) / cell_m), 0), side - 1)
            cell[j] = ix * side + iy
            lowest[cell[j]] = min(lowest[cell[j]], z[j])
    mask = np.zeros(n, dtype=np.bool_)
    for j in range(n):
        if cell[j] >= 0:
            mask[j] = z[j] - lowest[cell[j]] < band
    return mask


def ground_level(values: np.ndarray) -> float | None:
    """Typical raw intensity of ground returns: the mean of those up to their GROUND_QUANTILE
    percentile, so paint (a few % of the ground) stays out while a mean, unlike a median, keeps
    some resolution in coarse integer counts. None with too few returns or an all-zero road."""
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
    if values.size < GROUND_MIN_POINTS:
        return None
    typical = values[values <= np.percentile(values, GROUND_QUANTILE)]
    level = float(typical.mean()) if typical.size else 0.0
    if level <= 0:  # road quantised to 0 counts, paint not: the mean of all is still a level
        level = float(values.mean())
    return level if level > 0 else None


class IntensityEncoder:
    """Per-sweep encoding of raw intensity, remembering the last ground level (contrast).

    A sweep with too few ground returns (a cloud of only walls, a tiny test cloud) is encoded
    with the previous sweep's level, or with its own robust mean when it is the first.
    """

    def __init__(self, encoding: str = ABSOLUTE) -> None:
        if encoding not in INTENSITY_ENCODINGS:
            raise ValueError(f'unknown intensity encoding {encoding!r} (choose from '
                             f'{", ".join(INTENSITY_ENCODINGS)})')
        self.encoding = encoding
        self.level: float | None = None
        self.rings_found = False  # contrast_rings: whether the last sweep's rings were used

    def __call__(self, xyz_sensor: np.ndarray, raw: np.ndarray, scale: float | None = None,
                 ring: np.ndarray | None = None) -> np.ndarray:
        """(N,) float32 in [0, 1]; scale is the absolute encoding's fixed full scale, ring the
        cloud's ring field (contrast_rings: its lasers, see intensity_rings.valid_ring_ids)."""
        if self.encoding == ABSOLUTE:
            return normalize_intensity(raw, scale)
        raw = np.asarray(raw).reshape(-1)
        step = max(1, raw.shape[0] // GROUND_SAMPLE)  # a 128 x 2048 sweep: a quarter is plenty
        xyz = np.asarray(xyz_sensor).reshape(-1, 3)
        sample = xyz[::step]
        ground = ground_mask(sample)
        ground_values = raw[::step][ground]
        level = ground_level(ground_values)
        table = ids = None
        if level is None:
            level = self.level if self.level is not None else ground_level(raw)
        else:
            self.level = level
            if self.encoding == CONTRAST_RINGS:
                ids = valid_ring_ids(ring, raw.shape[0])
                table = self._ring_table(sample, ground, ground_values, step, ids)
        self.rings_found = table is not None
        if level is None:  # no intensity at all: nothing stands out
            return np.zeros(raw.shape[0], dtype=np.float32)
        if table is not None:
            return encode_with_gains(table, xyz, raw, ids, 1.0 / (level / GROUND_LEVEL))
        return normalize_intensity(raw, level / GROUND_LEVEL)

    @staticmethod
    def _ring_table(sample: np.ndarray, ground: np.ndarray, ground_values: np.ndarray,
                    step: int, ids: np.ndarray | None) -> RingTable | None:
        """ring_table from every k-th ground return of the sample (every step-th return)."""
        every = max(1, ground_values.size // RING_SAMPLE)
        x, y, z, index = ground_subsample(sample, ground, every)
        return ring_table(x, y, z, ground_values[::every],
                          None if ids is None else ids[index * step])
