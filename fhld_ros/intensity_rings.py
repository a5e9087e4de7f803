"""contrast_rings: each laser's own gain, measured on the sweep's ground returns (intensity.py).

Lasers are told apart by a PointCloud2 ``ring`` field where the cloud has a usable one, else
by the elevation angles of the ground returns in the sensor frame. Neighbouring rings are
compared azimuth sector by sector, the steps chained into a profile over the rings, and a
quadratic in elevation taken out of it; the rest is each laser's gain (ring_table).

The loops are compiled; arctan2, log and tan stay numpy's, whose float32 results (SIMD on some
CPUs) differ from libm's in the last bit, which could move a return across a sector or ring
edge and change what a model trained on these values saw.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.compiled import compiled
from fhld_ros.intensity_lookup import RingTable, edge_cells, encode_with_gains, valid_ring_ids

# One laser's returns share one elevation seen from one origin (range noise runs along the
# ray), so its ground returns span well under 0.01 degrees; the closest lasers of common
# sensors are 0.125-0.17 degrees apart (Hesai 64/128, OS2-128), the widest 1.33 (HDL-32E).
# Ground elevations further apart than RING_GAP_DEG start a new ring.
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


# np.degrees of a float32 is x * float32(180) / float32(pi), not x * float32(180 / pi)
_DEGREES = np.float32(np.degrees(np.float32(1.0)))


def ring_table(x: np.ndarray, y: np.ndarray, z: np.ndarray, values: np.ndarray,
               ids: np.ndarray | None = None) -> RingTable | None:
    """The ring gains of a sweep from its ground returns (float32 coordinates, already
    subsampled to about RING_SAMPLE; ids their valid ring ids or None), or None when fewer than
    RING_MIN_RINGS rings have a level: the rings cannot be told apart.

    Rings by elevation: the ground returns' elevation angles, sorted, split at gaps over
    RING_GAP_DEG. By ring id: one ring per id, ordered by its median ground elevation; fewer
    than RING_MIN_RINGS ids among the ground returns, and the elevation rings are used. A
    ring wider than RING_MAX_WIDTH_DEG (elevation rings only) or with fewer than
    RING_MIN_POINTS ground returns, or a RING_MIN_SHARE of the median ring's, keeps gain 1.
    """
    v = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(v)
    if not finite.all():
        x, y, z, v = x[finite], y[finite], z[finite], v[finite]
        ids = None if ids is None else ids[finite]
    if v.size < RING_MIN_POINTS * RING_MIN_RINGS:
        return None
    tilt = np.arctan2(z, np.hypot(x, y))  # radians; degrees as numpy's in the kernels
    azimuth = np.arctan2(y, x)
    if ids is not None:
        table = _table_by_id(ids, tilt, azimuth, v)
        if table is not False:
            return table
    lo, hi, count, member = _elevation_clusters(tilt, _DEGREES, np.float32(RING_GAP_DEG))
    ok = _usable(count) & (hi - lo <= RING_MAX_WIDTH_DEG)
    if ok.sum() < RING_MIN_RINGS:
        return None
    ring_of = np.where(ok, np.cumsum(ok) - 1, -1)  # cluster -> consecutive ring of the kept
    log_gain = _log_gains(ring_of, member, azimuth, v, 0.5 * (lo + hi)[ok])
    if log_gain is None:
        return None
    gain = np.ones(lo.size + 2, dtype=np.float32)  # [below all rings, rings..., above]
    gain[1:-1][ok] = np.clip(np.exp(-log_gain), *RING_GAIN_RANGE)
    tan_edges = _tan_edges(lo, hi)
    *cells, separable = edge_cells(tan_edges, gain)
    return RingTable(gain, tan_edges, tuple(cells)) if separable else None


def elevation_ring_ids(xyz_sensor: np.ndarray) -> np.ndarray:
    """(N,) the ring of each return as ring_table forms rings without a ring field: sorted
    elevation angles split at gaps over RING_GAP_DEG (ids in ascending elevation; -1: not
    finite)."""
    p = np.asarray(xyz_sensor, dtype=np.float32).reshape(-1, 3)
    tilt = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    return _elevation_clusters(tilt, _DEGREES, np.float32(RING_GAP_DEG))[3]


def _usable(count: np.ndarray) -> np.ndarray:
    """Rings with enough ground returns for a level. One with a small share of the others'
    lost its dark ground to range (only paint and bright ground still return): biased."""
    big = count[count >= RING_MIN_POINTS]
    return count >= max(RING_MIN_POINTS, RING_MIN_SHARE * _median(big) if big.size else 0)


@compiled
def _median(values: np.ndarray) -> float:
    """np.median (the same selection and mean of the middle two), without numpy's overhead
    on the few values here."""
    return np.median(values)


def _table_by_id(ids: np.ndarray, tilt: np.ndarray, azimuth: np.ndarray,
                 v: np.ndarray) -> RingTable | None | bool:
    """ring_table by ring id; False when the ids are too few to be lasers."""
    count, median_el = _id_groups(ids, tilt, _DEGREES, int(ids.max()) + 1)
    if np.count_nonzero(count) < RING_MIN_RINGS:
        return False
    kept = np.flatnonzero(_usable(count))
    if kept.size < RING_MIN_RINGS:
        return None
    kept = kept[np.argsort(median_el[kept], kind='stable')]
    ring_of = np.full(count.size, -1, dtype=np.int64)
    ring_of[kept] = np.arange(kept.size)
    log_gain = _log_gains(ring_of, ids, azimuth, v, median_el[kept])
    if log_gain is None:
        return None
    gain = np.ones(count.size, dtype=np.float32)
    gain[kept] = np.clip(np.exp(-log_gain), *RING_GAIN_RANGE)
    return RingTable(gain)


def _log_gains(ring_of: np.ndarray, member: np.ndarray, azimuth: np.ndarray, v: np.ndarray,
               centre: np.ndarray) -> np.ndarray | None:
    """Each kept ring's log gain, ring_of[member[i]] the ring of ground return i (-1: none).

    Each ring against the next one up, azimuth sector by sector: the same stretch of road,
    kerb or verge, so the materials (near rings see road, far ones verges) cancel; the median
    log ratio over the sectors is that pair's gain step. The steps chained up from the lowest
    ring are the profile of the levels: each laser's gain on a smooth darkening with range and
    incidence, which a quadratic in elevation (centre: each ring's) takes out (the simulator,
    and the model trained on it, keep that darkening). None: too few steps measured.
    """
    rings = centre.size
    mean = _sector_means(ring_of, member, azimuth, v, rings, RING_SECTORS)
    with np.errstate(divide='ignore', invalid='ignore'):
        log_mean = np.log(mean)
    profile, matched = _chained_steps(log_mean, RING_MIN_SECTORS)
    if matched < RING_MIN_RINGS - 1:
        return None
    fit = np.ones(rings, dtype=bool)
    for _ in range(2):  # the second pass without the rings furthest off the first fit
        smooth = np.polyval(np.polyfit(centre[fit], profile[fit], 2), centre)
        off = np.abs(profile - smooth)
        fit = off <= max(3.0 * _median(off), 1e-6)
    return profile - smooth


@compiled
def _elevation_clusters(tilt: np.ndarray, degrees: np.float32, gap: np.float32
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The elevations (tilt * degrees, float32) sorted and split where one is more than gap
    above the one below, without sorting: buckets half a gap wide never split inside, so only
    the step from one occupied bucket's highest to the next one's lowest decides. Each
    cluster's lowest and highest elevation (ascending), its size, and each return's cluster
    (-1: not finite)."""
    n = tilt.shape[0]
    el = np.empty(n, dtype=np.float32)
    low, high = np.inf, -np.inf
    for i in range(n):
        el[i] = np.float32(tilt[i] * degrees)
        if np.isfinite(el[i]):
            low, high = min(low, np.float64(el[i])), max(high, np.float64(el[i]))
    per_deg = 2.0 / np.float64(gap)  # buckets half a gap wide
    buckets = int((high - low) * per_deg) + 1 if high >= low else 0
    b_lo = np.full(buckets, np.inf, dtype=np.float32)
    b_hi = np.full(buckets, -np.inf, dtype=np.float32)
    b_count = np.zeros(buckets, dtype=np.int64)
    bucket = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        if np.isfinite(el[i]):
            b = min(int((np.float64(el[i]) - low) * per_deg), buckets - 1)
            bucket[i] = b
            b_lo[b], b_hi[b] = min(b_lo[b], el[i]), max(b_hi[b], el[i])
            b_count[b] += 1
    lo = np.empty(buckets, dtype=np.float32)
    hi = np.empty(buckets, dtype=np.float32)
    count = np.zeros(buckets, dtype=np.int64)
    cluster_of = np.full(buckets, -1, dtype=np.int64)
    c = -1
    for b in range(buckets):
        if b_count[b] == 0:
            continue
        if c < 0 or np.float32(b_lo[b] - hi[c]) > gap:
            c += 1
            lo[c] = b_lo[b]
        hi[c] = b_hi[b]
        count[c] += b_count[b]
        cluster_of[b] = c
    member = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        if bucket[i] >= 0:
            member[i] = cluster_of[bucket[i]]
    return lo[:c + 1], hi[:c + 1], count[:c + 1], member


@compiled
def _id_groups(ids: np.ndarray, tilt: np.ndarray, degrees: np.float32,
               size: int) -> tuple[np.ndarray, np.ndarray]:
    """Ground returns per ring id and the median of their elevations (NaN: none)."""
    count = np.zeros(size, dtype=np.int64)
    for i in range(ids.shape[0]):
        count[int(ids[i])] += 1
    start = np.zeros(size + 1, dtype=np.int64)
    start[1:] = np.cumsum(count)
    fill = start[:-1].copy()
    grouped = np.empty(ids.shape[0], dtype=np.float64)
    for i in range(ids.shape[0]):
        k = int(ids[i])
        grouped[fill[k]] = np.float32(tilt[i] * degrees)
        fill[k] += 1
    median = np.full(size, np.nan)
    for k in range(size):
        if count[k]:
            median[k] = np.median(grouped[start[k]:start[k + 1]])
    return count, median


@compiled
def _sector_means(ring_of: np.ndarray, member: np.ndarray, azimuth: np.ndarray,
                  v: np.ndarray, rings: int, sectors: int) -> np.ndarray:
    """(rings, sectors) mean of v per ring and azimuth sector, NaN under 2 returns. The
    sector's float32 arithmetic is numpy's ((azimuth + pi) * sectors / 2 pi, truncated, the
    sector at +pi the one at -pi)."""
    n = np.zeros((rings, sectors), dtype=np.int64)
    total = np.zeros((rings, sectors), dtype=np.float64)
    half_turn, per_rad = np.float32(np.pi), np.float32(sectors / (2 * np.pi))
    for i in range(member.shape[0]):
        r = ring_of[int(member[i])] if member[i] >= 0 else -1
        if r >= 0 and np.isfinite(azimuth[i]):
            s = int(np.float32(np.float32(azimuth[i] + half_turn) * per_rad))
            s = s - sectors if s >= sectors else s
            n[r, s] += 1
            total[r, s] += v[i]
    mean = np.full((rings, sectors), np.nan)
    for r in range(rings):
        for s in range(sectors):
            if n[r, s] >= 2:
                mean[r, s] = total[r, s] / n[r, s]
    return mean


@compiled
def _chained_steps(log_mean: np.ndarray, min_sectors: int) -> tuple[np.ndarray, int]:
    """The profile (rings,): 0, then each ring's step over the one below (the median over the
    sectors both see of the difference in log level; 0 where under min_sectors do) added up;
    and how many steps were measured."""
    rings, sectors = log_mean.shape
    profile = np.zeros(rings)
    seen = np.empty(sectors)
    matched = 0
    for r in range(rings - 1):
        k = 0
        for s in range(sectors):
            d = log_mean[r + 1, s] - log_mean[r, s]
            if np.isfinite(d):
                seen[k] = d
                k += 1
        step = 0.0
        if k >= min_sectors:
            step = np.median(seen[:k])
            matched += 1
        profile[r + 1] = profile[r] + step
    return profile, matched


def _tan_edges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """tan of the edges between the rings (elevations lo[k]..hi[k], degrees): each ring spans
    from the middle of the gap below it to the middle of the gap above it."""
    gaps = lo[1:] - hi[:-1]
    edges = np.concatenate([[lo[0] - gaps[0] / 2], (lo[1:] + hi[:-1]) / 2,
                            [hi[-1] + gaps[-1] / 2]])  # >= RING_MIN_RINGS rings here
    return np.tan(np.radians(edges)).astype(np.float32)


def ground_subsample(sample: np.ndarray, ground: np.ndarray, every: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every every-th ground return of sample (N, 3): x, y, z (float32) and its index."""
    index = np.flatnonzero(ground)[::every]
    return (*_columns(np.asarray(sample, dtype=np.float32), index), index)


@compiled
def _columns(xyz: np.ndarray, index: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z of the rows index of xyz, each contiguous (numpy's fastest layout)."""
    x = np.empty(index.shape[0], dtype=np.float32)
    y, z = np.empty_like(x), np.empty_like(x)
    for j in range(index.shape[0]):
        x[j], y[j], z[j] = xyz[index[j], 0], xyz[index[j], 1], xyz[index[j], 2]
    return x, y, z


def ring_gains(xyz_sensor: np.ndarray, ground_xyz: np.ndarray, ground_values: np.ndarray,
               ring: np.ndarray | None = None, ground_ring: np.ndarray | None = None
               ) -> np.ndarray | None:
    """(N,) float32 gain per return of xyz_sensor (ring_table, clipped to RING_GAIN_RANGE;
    1 outside every ring), or None where ring_table is.

    ground_xyz, ground_values: the sweep's ground returns (ground_mask), ground_ring their
    ring field where ring is the sweep's; a ring field that is not valid_ring_ids is unused.
    """
    xyz = np.asarray(xyz_sensor).reshape(-1, 3)
    ids = valid_ring_ids(ring, xyz.shape[0])
    ground_ids = valid_ring_ids(ground_ring, len(ground_values)) if ids is not None else None
    every = max(1, len(ground_values) // RING_SAMPLE)
    g = np.asarray(ground_xyz, dtype=np.float32).reshape(-1, 3)[::every]
    table = ring_table(*(np.ascontiguousarray(g[:, k]) for k in range(3)),
                       np.asarray(ground_values).reshape(-1)[::every],
                       None if ground_ids is None else ground_ids[::every])
    if table is None:
        return None
    return encode_with_gains(table, xyz, np.ones(xyz.shape[0], dtype=np.float32), ids, 1.0,
                             clip=False)
