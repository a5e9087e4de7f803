"""contrast_rings per return: each return's laser gain looked up, by its ring id or by its
elevation, and the encoded value (intensity_rings.ring_table measures the gains).

Fused and compiled, in float32 exactly as numpy would compute raw * gain / scale, clipped:
the elevation lookup reproduces numpy's searchsorted over the ring edges bit for bit.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from fhld_ros.compiled import compiled

# a ring field with a larger id, a negative, fractional or non-finite one, or the wrong length
# is not a laser index (real sensors have < 256 lasers): the elevation rings are used instead
RING_MAX_ID = 1023


class RingTable(NamedTuple):
    """Gains to look up per return. By ring id (tan_edges None): gain[id], 1 past its end. By
    elevation: gain[k], k = how many of tan_edges (ascending tan(elevation) between the rings)
    lie at or below the return's; gain[0] and gain[-1] are below and above every ring; cells
    is that lookup as edge_cells builds it."""

    gain: np.ndarray
    tan_edges: np.ndarray | None = None
    cells: tuple | None = None


def valid_ring_ids(ring: np.ndarray | None, count: int) -> np.ndarray | None:
    """ring as laser ids for count returns, or None when absent or malformed (see
    RING_MAX_ID): integers 0..RING_MAX_ID, in any numeric dtype."""
    if ring is None:
        return None
    ids = np.asarray(ring).reshape(-1)
    if ids.shape[0] != count or ids.dtype.kind not in 'uif' or count == 0:
        return None
    return ids if _max_id(ids, RING_MAX_ID) >= 0 else None


@compiled
def _max_id(ids: np.ndarray, limit: int) -> int:
    """The largest of ids, or -1 when one is not an integer in 0..limit (NaN included)."""
    top = 0
    for i in range(ids.shape[0]):
        v = ids[i]
        if not (v >= 0 and v <= limit) or np.floor(v) != v:
            return -1
        top = max(top, int(v))
    return top


def encode_with_gains(table: RingTable, xyz_sensor: np.ndarray, raw: np.ndarray,
                      ids: np.ndarray | None, inv_scale: float, clip: bool = True
                      ) -> np.ndarray:
    """(N,) float32: raw * each return's ring gain * inv_scale, in float32, clipped to [0, 1]
    with non-finite values 0 (as intensity.normalize_intensity); unclipped with clip=False.
    ids: the returns' valid ring ids where table is by id."""
    raw = np.asarray(raw).reshape(-1).astype(np.float32, copy=False)
    inv = np.float32(inv_scale)
    if table.tan_edges is None:
        return _encode_by_id(ids, raw, table.gain, inv, clip)
    flat = np.ascontiguousarray(xyz_sensor, dtype=np.float32).reshape(-1)
    return _encode_by_elevation(flat, raw, *table.cells, inv, clip)


@compiled
def edge_cells(tan_edges: np.ndarray, gain: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.float32, np.float32, bool]:
    """The ring lookup of _encode_by_elevation as cells of t = tan(elevation): t's cell is
    int((t - origin) * per_tan) clamped to 0..cells, monotonic in t, so an edge in a lower
    cell than t's is below t and one in a higher cell above it. Cells are made fine enough
    to hold one edge at most; per cell the gain below its edge, the edge (inf: none) and the
    gain at or above it. Cells cells + 1 and + 2: a non-finite t (on the sensor's axis, or
    NaN), below / above every ring. Not separable (False) when no cells up to 1 << 20 keep
    the edges apart: edges closer than 1e-6 of their span, or not increasing (not rings)."""
    edges = tan_edges.shape[0]
    origin = tan_edges[0]
    span = np.float64(tan_edges[edges - 1] - origin)
    cells, per_tan = 4 * edges, np.float32(0.0)
    cell = np.zeros(edges, dtype=np.int64)
    separable = False
    while span > 0 and not separable and cells <= 1 << 20:
        per_tan = np.float32(cells / span)
        for k in range(edges):
            cell[k] = min(int(np.float32((tan_edges[k] - origin) * per_tan)), cells)
        separable = np.all(cell[1:] > cell[:-1])
        cells *= 2
    cells //= 2
    below = np.full(cells + 3, gain[edges], dtype=np.float32)
    above = np.full(cells + 3, gain[edges], dtype=np.float32)
    edge = np.full(cells + 3, np.inf, dtype=np.float32)
    k = 0
    for c in range(cells + 1):
        below[c] = above[c] = gain[k]
        if separable and k < edges and cell[k] == c:
            edge[c], above[c] = tan_edges[k], gain[k + 1]
            k += 1
    below[cells + 1] = above[cells + 1] = gain[0]
    return below, above, edge, origin, per_tan, separable


@compiled
def _scaled(value: np.float32, gain: np.float32, inv_scale: np.float32,
            clip: bool) -> np.float32:
    """np.clip(raw * gain * inv_scale, 0, 1) in float32, NaN -> 0 (-0.0 stays, as in numpy)."""
    out = np.float32(np.float32(value * gain) * inv_scale)
    if not clip:
        return out
    if out > 1:
        return np.float32(1.0)
    if out >= 0:
        return out
    return np.float32(0.0)


@compiled
def _encode_by_id(ids: np.ndarray, raw: np.ndarray, gain: np.ndarray, inv_scale: np.float32,
                  clip: bool) -> np.ndarray:
    out = np.empty(raw.shape[0], dtype=np.float32)
    size = gain.shape[0]
    for i in range(raw.shape[0]):
        k = int(ids[i])
        out[i] = _scaled(raw[i], gain[k] if k < size else np.float32(1.0), inv_scale, clip)
    return out


@compiled
def _encode_by_elevation(flat: np.ndarray, raw: np.ndarray, below: np.ndarray,
                         above: np.ndarray, edge: np.ndarray, origin: np.float32,
                         per_tan: np.float32, inv_scale: np.float32, clip: bool) -> np.ndarray:
    """Each return's gain from its ring: the number of ring edges at or below its
    tan(elevation) t in float32, as the rings were cut (numpy's searchsorted 'right'), looked
    up in edge_cells. flat: x, y, z of each return in turn. Three passes, as each then
    compiles to vector code or to few instructions: t and its cell; the gain; the clip."""
    n = raw.shape[0]
    t = np.empty(n, dtype=np.float32)
    cell = np.empty(n, dtype=np.int32)
    cells = below.shape[0] - 3
    top = np.float32(cells)
    for i in range(n):
        x, y, z = flat[3 * i], flat[3 * i + 1], flat[3 * i + 2]
        h = np.float32(np.sqrt(np.float32(x * x) + np.float32(y * y)))
        t[i] = np.float32(z / h)
        c = np.float32((t[i] - origin) * per_tan)
        c = c if c >= 0 else np.float32(0.0)
        c = c if c <= top else top
        axis = cells + 1 if z < 0 else cells + 2
        cell[i] = np.int32(c) if np.isfinite(t[i]) else axis
    out = np.empty(n, dtype=np.float32)
    for i in range(n):
        c = cell[i]
        out[i] = _scaled(raw[i], above[c] if edge[c] <= t[i] else below[c], inv_scale, False)
    if clip:
        for i in range(n):
            out[i] = _scaled(out[i], np.float32(1.0), np.float32(1.0), True)
    return out
