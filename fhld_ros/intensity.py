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
  scaled by the ground level of the rings around its ring / its ring's own (ring_gains), the
  rings told apart by elevation angle in the sensor frame, so uncalibrated multi-laser sensors
  (whole bright rings on an HDL-64E) read like calibrated ones. Without separable rings (a
  pre-accumulated or non-spinning cloud) it is ``contrast``.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.compiled import compiled

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
# contrast_rings. One laser's returns share one elevation seen from one origin (range noise
# runs along the ray), so its ground returns span well under 0.01 degrees; the closest lasers
# of common sensors are 0.125-0.17 degrees apart (Hesai 64/128, OS2-128), the widest 1.33
# (HDL-32E). Ground elevations further apart than RING_GAP_DEG start a new ring.
RING_GAP_DEG = 0.05
# wider: not one laser (a cloud accumulated while driving smears each laser over degrees; a
# laser origin 0.2 m off the sensor's, as on the HDL-64E, spreads a ring over ~0.1 degrees)
RING_MAX_WIDTH_DEG = 0.25
RING_SAMPLE = 16384  # rings and their levels from at most about this many ground returns
RING_MIN_POINTS = 50  # ground returns a ring needs for its own level (else its gain stays 1)
RING_MIN_SHARE = 0.25  # and at least this share of the median ring's
RING_SECTORS = 180  # azimuth sectors in which neighbouring rings are compared
RING_MIN_SECTORS = 10  # sectors two rings must share for their gain step to be measured
RING_MIN_RINGS = 4  # fewer rings: not a multi-laser sweep, the sweep's level alone is used
# uncalibrated lasers differ by up to ~x2 (simulated: log-normal sigma <= 0.3); a ring beyond
# this is more likely a different material (a far ring on grass) than a different gain
RING_GAIN_RANGE = (0.5, 2.0)


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


def ring_gains(xyz_sensor: np.ndarray, ground_xyz: np.ndarray,
               ground_values: np.ndarray) -> np.ndarray | None:
    """(N,) float32 gain per return of xyz_sensor: the median ground level of the RING_TREND
    rings around its laser's ring / that ring's own, clipped to RING_GAIN_RANGE.

    ground_xyz, ground_values: the sweep's ground returns (ground_mask; a subsample is fine).
    Rings: the ground returns' elevation angles, sorted, split at gaps over RING_GAP_DEG; a
    cluster wider than RING_MAX_WIDTH_DEG or with fewer than RING_MIN_POINTS ground returns
    keeps gain 1, and so does every return outside all rings (lasers that see no ground in
    GROUND_RANGE_M). None when fewer than RING_MIN_RINGS rings have a level: the rings cannot
    be told apart, the caller uses the sweep's level alone.
    """
    v = np.asarray(ground_values, dtype=np.float64).reshape(-1)
    step = max(1, v.size // RING_SAMPLE)
    g = np.asarray(ground_xyz, dtype=np.float32).reshape(-1, 3)[::step]
    v = v[::step]
    g, v = g[np.isfinite(v)], v[np.isfinite(v)]
    if v.size < RING_MIN_POINTS * RING_MIN_RINGS:
        return None
    el = np.degrees(np.arctan2(g[:, 2], np.hypot(g[:, 0], g[:, 1])))
    order = np.argsort(el)
    el, v, g = el[order], v[order], g[order]
    split = np.flatnonzero(np.diff(el) > RING_GAP_DEG) + 1
    starts = np.concatenate([[0], split])
    ends = np.concatenate([split, [el.size]])
    count = ends - starts
    big = count[count >= RING_MIN_POINTS]
    # a ring with a small share of the ground returns of the others lost its dark ground to
    # range (only paint and bright ground still return): its level is biased
    ok = ((count >= max(RING_MIN_POINTS, RING_MIN_SHARE * np.median(big) if big.size else 0))
          & (el[ends - 1] - el[starts] <= RING_MAX_WIDTH_DEG))
    if ok.sum() < RING_MIN_RINGS:
        return None
    # Each ring against the next one up, azimuth sector by sector: the same stretch of road,
    # kerb or verge, so the materials (near rings see road, far ones verges) cancel; the
    # median log ratio over the sectors is that pair's gain step.
    index = np.cumsum(ok) - 1  # cluster -> consecutive ring of the kept ones
    rings = int(ok.sum())
    member = np.repeat(np.where(ok, index, -1), count)
    keep = member >= 0
    azimuth = np.arctan2(g[keep, 1], g[keep, 0])
    sector = ((azimuth + np.pi) * (RING_SECTORS / (2 * np.pi))).astype(np.int64) % RING_SECTORS
    cell = member[keep] * RING_SECTORS + sector
    n = np.bincount(cell, minlength=rings * RING_SECTORS)
    total = np.bincount(cell, v[keep], rings * RING_SECTORS)
    with np.errstate(divide='ignore', invalid='ignore'):
        log_mean = np.log(total / n).reshape(rings, RING_SECTORS)
    log_mean[(n < 2).reshape(rings, RING_SECTORS) | ~np.isfinite(log_mean)] = np.nan
    ratio = log_mean[1:] - log_mean[:-1]
    seen = np.isfinite(ratio)
    matched = seen.sum(axis=1) >= RING_MIN_SECTORS
    if matched.sum() < RING_MIN_RINGS - 1:
        return None
    ratio[~seen] = np.inf  # sorted last: the median of the seen sectors only
    ratio.sort(axis=1)
    counts = seen.sum(axis=1)
    rows = np.arange(rings - 1)
    lo_mid, hi_mid = np.maximum(counts - 1, 0) // 2, counts // 2
    step = 0.5 * (ratio[rows, lo_mid] + ratio[rows, np.minimum(hi_mid, RING_SECTORS - 1)])
    # the profile of the kept rings' levels, chained up from the lowest: each laser's gain
    # on a smooth darkening with range and incidence, which a quadratic in elevation takes
    # out (the simulator, and the model trained on it, keep that darkening)
    profile = np.concatenate([[0.0], np.cumsum(np.where(matched, step, 0.0))])
    centre = 0.5 * (el[starts] + el[ends - 1])[ok]
    fit = np.ones(rings, dtype=bool)
    for _ in range(2):  # the second pass without the rings furthest off the first fit
        smooth = np.polyval(np.polyfit(centre[fit], profile[fit], 2), centre)
        off = np.abs(profile - smooth)
        fit = off <= max(3.0 * np.median(off), 1e-6)
    log_gain = profile - smooth
    gain = np.ones(starts.size + 2, dtype=np.float32)  # [below all rings, rings..., above]
    gain[1:-1][ok] = np.clip(np.exp(-log_gain), *RING_GAIN_RANGE)
    return _per_return(gain, el[starts], el[ends - 1], xyz_sensor)


def _per_return(gain: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                xyz_sensor: np.ndarray) -> np.ndarray:
    """Each return's ring gain: ring k (elevations lo[k]..hi[k], degrees) spans from the
    middle of the gap below it to the middle of the gap above it; gain[0] and gain[-1] are
    for returns below and above every ring."""
    gaps = lo[1:] - hi[:-1]
    edges = np.concatenate([[lo[0] - gaps[0] / 2], (lo[1:] + hi[:-1]) / 2,
                            [hi[-1] + gaps[-1] / 2]])  # >= RING_MIN_RINGS rings here
    # tan(elevation) of every return against tan(edges): no arctan over the whole sweep
    x, y, z = np.asarray(xyz_sensor, dtype=np.float32).reshape(-1, 3).T
    return _gain_per_return(x, y, z, np.tan(np.radians(edges)).astype(np.float32),
                            np.asarray(gain, dtype=np.float32))


@compiled
def _gain_per_return(x: np.ndarray, y: np.ndarray, z: np.ndarray, tan_edges: np.ndarray,
                     gain: np.ndarray) -> np.ndarray:
    """gain[k] for each return, k its ring: tan(elevation) searched among tan_edges (numpy's
    searchsorted 'right'; a return on the sensor's axis, or NaN, is above every ring)."""
    out = np.empty(x.shape[0], dtype=np.float32)
    edges = tan_edges.shape[0]
    for i in range(x.shape[0]):
        h = np.float32(np.sqrt(np.float32(x[i] * x[i]) + np.float32(y[i] * y[i])))
        if h == 0 or not np.isfinite(z[i] / h):
            out[i] = gain[edges] if not z[i] < 0 else gain[0]
            continue
        t = np.float32(z[i] / h)
        lo, hi = 0, edges
        while lo < hi:  # first edge above t
            mid = (lo + hi) // 2
            if tan_edges[mid] <= t:
                lo = mid + 1
            else:
                hi = mid
        out[i] = gain[lo]
    return out


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

    def __call__(self, xyz_sensor: np.ndarray, raw: np.ndarray,
                 scale: float | None = None) -> np.ndarray:
        """(N,) float32 in [0, 1]; scale is the absolute encoding's fixed full scale."""
        if self.encoding == ABSOLUTE:
            return normalize_intensity(raw, scale)
        raw = np.asarray(raw).reshape(-1)
        step = max(1, raw.shape[0] // GROUND_SAMPLE)  # a 128 x 2048 sweep: a quarter is plenty
        xyz = np.asarray(xyz_sensor).reshape(-1, 3)
        sample = xyz[::step]
        ground = ground_mask(sample)
        ground_values = raw[::step][ground]
        level = ground_level(ground_values)
        gains = None
        if level is None:
            level = self.level if self.level is not None else ground_level(raw)
        else:
            self.level = level
            if self.encoding == CONTRAST_RINGS:
                gains = ring_gains(xyz, sample[ground], ground_values)
        self.rings_found = gains is not None
        if level is None:  # no intensity at all: nothing stands out
            return np.zeros(raw.shape[0], dtype=np.float32)
        if gains is not None:
            raw = raw.astype(np.float32) * gains
        return normalize_intensity(raw, level / GROUND_LEVEL)
