"""Point cloud recovery (ONCE-3DLanes section 3.2): one label's lane returns -> a 3D lane.

As in the paper, the lane returns of each beam are clustered into a centre point: within each
sweep, returns ordered along the line split into crossings wherever consecutive ones lie more
than CROSSING_GAP_M apart (a beam's ring crosses the region in one run of returns; neighbouring
rings of a dense sensor may merge, which keeps the runs whole). A crossing's centre is the mean
of its returns, weighted by how much brighter than the road each return is when the crossing
holds paint (so a label a few pixels off still gives the paint's centre), unweighted when it
does not; a whole crossing is centred on the line, a crossing cut in two would not be. "Along
the line" is the chord from the label's near end to its far end: a line turning less than 180
degrees advances monotonically along it, while the label's own pixel order does not resolve
distance far away. Crossing centres of all sweeps are averaged in BIN_M bins along the chord,
smoothed over neighbouring bins and resampled every step_m.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.geometry import resample_polyline

BIN_M = 0.5
CROSSING_GAP_M = 0.25
END_SHARE = 0.1  # the chord joins the medians of the nearest and farthest tenth (label order)
PAINT_CONTRAST = 1.8  # a crossing holds paint when a return is this many times the road level
MAX_GAP_M = 4.0  # without rays, a lane is cut where its bins are further apart than this
FILL_GAP_M = 1.5  # with rays, gaps longer than this are filled from the image
RAY_REACH_M = 200.0
RAY_STEPS = 30
END_FIT = 4  # an end centre is checked against the line through this many next ones ...
END_BEND_M = 0.08  # ... and dropped when further from it than this


def _chord(xyz: np.ndarray, t: np.ndarray) -> np.ndarray | None:
    """Unit direction from the label's near end to its far end on the ground, or None."""
    order = np.argsort(t, kind='stable')
    end = max(1, int(END_SHARE * order.size))
    chord = np.median(xyz[order[-end:], :2], axis=0) - np.median(xyz[order[:end], :2], axis=0)
    norm = np.linalg.norm(chord)
    return chord / norm if norm >= BIN_M else None


def crossing_centres(xyz: np.ndarray, s: np.ndarray, sweep: np.ndarray, contrast: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(C, 3) centres of the beam crossings and their positions along the chord."""
    order = np.lexsort((s, sweep))
    xyz, s, sweep, contrast = xyz[order], s[order], sweep[order], contrast[order]
    start = np.concatenate([[True], (np.diff(sweep) != 0) | (np.diff(s) > CROSSING_GAP_M)])
    cluster = np.cumsum(start) - 1
    n = int(cluster[-1]) + 1
    brightest = np.zeros(n)
    np.maximum.at(brightest, cluster, contrast)
    painted = brightest[cluster] >= PAINT_CONTRAST
    weight = np.where(painted, np.clip(contrast - 1.0, 0.0, None) ** 2, 1.0)
    w_sum = np.maximum(np.bincount(cluster, weight, n), 1e-12)
    count = np.bincount(cluster, minlength=n)
    centres = np.column_stack(
        [np.bincount(cluster, weight * xyz[:, k], n) / w_sum for k in (0, 1)]
        + [np.bincount(cluster, xyz[:, 2], n) / count])  # heights unweighted: paint is road
    return centres, np.bincount(cluster, weight * s, n) / w_sum


def recover_lane(xyz: np.ndarray, t: np.ndarray, contrast: np.ndarray, sweep: np.ndarray,
                 rays: tuple[np.ndarray, np.ndarray] | None = None,
                 ground_hits: np.ndarray | None = None, step_m: float = 0.5
                 ) -> list[np.ndarray]:
    """(K, 3) lane pieces from the returns of one label region (xyz in a z-up frame, t their
    position along the label, contrast their intensity over the road's, sweep their sweep).

    rays (origin (3,), unit directions (M, 3) of points along the label, same frame) fill the
    gaps between crossings longer than FILL_GAP_M (a sparse sensor's far rings): each ray meets
    the lane's height profile interpolated between the crossings around it, so the image gives
    the shape where the LiDAR has none.

    ground_hits ((M, 3) where the same rays meet the ground surface of all ground returns,
    ground.GroundSurface; only those with returns near them) extend the lane past its first
    and last crossing, e.g. where a truck shades the line from the LiDAR but not the camera."""
    if xyz.shape[0] < 4:
        return []
    chord = _chord(xyz, t)
    if chord is None:
        return []
    centres, s = crossing_centres(xyz, xyz[:, :2] @ chord, sweep, contrast)
    bins = np.floor((s - s.min()) / BIN_M).astype(np.intp)
    n_bins = int(bins.max()) + 1
    count = np.bincount(bins, minlength=n_bins)
    index = np.flatnonzero(count)
    if index.size < 2:
        return []
    points = _trim_ends(np.column_stack(
        [np.bincount(bins, centres[:, k], n_bins)[index] / count[index] for k in range(3)]))
    if points.shape[0] < 2:
        return []
    if rays is not None:
        points = _fill_gaps(points, chord, *rays)
    if ground_hits is not None and len(ground_hits):
        along = points[:, :2] @ chord
        s_hit = ground_hits[:, :2] @ chord
        beyond = (s_hit < along[0] - BIN_M) | (s_hit > along[-1] + BIN_M)
        points = np.vstack([points, ground_hits[beyond]])
        points = points[np.argsort(points[:, :2] @ chord, kind='stable')]
    along = points[:, :2] @ chord
    pieces = []
    for part in np.split(np.arange(along.size), np.flatnonzero(np.diff(along) > MAX_GAP_M) + 1):
        if part.size >= 2:
            piece = points[part]
            pieces.append(resample_polyline(np.column_stack([_smooth(piece[:, :2]),
                                                     _smooth(piece[:, 2])]), step_m))
    return pieces


def _fill_gaps(points: np.ndarray, chord: np.ndarray, origin: np.ndarray, dirs: np.ndarray
               ) -> np.ndarray:
    """Centres (sorted along the chord) plus the ray hits that fall in their long gaps."""
    along = points[:, :2] @ chord
    if dirs.shape[0] == 0 or not np.any(np.diff(along) > FILL_GAP_M):
        return points

    def below(t: np.ndarray) -> np.ndarray:  # ray under the lane's height profile
        p = origin + t[:, None] * dirs
        return p[:, 2] < np.interp(p[:, :2] @ chord, along, points[:, 2])

    lo, hi = np.full(dirs.shape[0], 0.5), np.full(dirs.shape[0], RAY_REACH_M)
    hits = below(hi) & ~below(lo)
    lo, hi = lo[hits], hi[hits]
    dirs = dirs[hits]
    for _ in range(RAY_STEPS):  # bisection: the first crossing is bracketed
        mid = (lo + hi) / 2
        p = origin + mid[:, None] * dirs
        under = p[:, 2] < np.interp(p[:, :2] @ chord, along, points[:, 2])
        hi, lo = np.where(under, mid, hi), np.where(under, lo, mid)
    hit = origin + ((lo + hi) / 2)[:, None] * dirs
    s_hit = hit[:, :2] @ chord
    k = np.searchsorted(along, s_hit)
    inside = (k > 0) & (k < along.size)
    k = np.clip(k, 1, along.size - 1)
    in_gap = inside & (along[k] - along[k - 1] > FILL_GAP_M) & \
        (s_hit - along[k - 1] > BIN_M) & (along[k] - s_hit > BIN_M)
    merged = np.vstack([points, hit[in_gap]])
    return merged[np.argsort(merged[:, :2] @ chord, kind='stable')]


def _trim_ends(points: np.ndarray) -> np.ndarray:
    """Drop end centres that bend off the line through the next END_FIT centres by more than
    END_BEND_M: at a label's cut end (image border, occluder) its region is one-sided and the
    centre of the returns in it is pulled sideways."""
    for _ in range(2):  # the near end, then (reversed) the far end
        while points.shape[0] > END_FIT + 1:
            a, b = points[1, :2], points[END_FIT, :2]
            direction = (b - a) / max(np.linalg.norm(b - a), 1e-9)
            rel = points[0, :2] - a
            if abs(direction[0] * rel[1] - direction[1] * rel[0]) <= END_BEND_M:
                break
            points = points[1:]
        points = points[::-1]
    return points


def _smooth(values: np.ndarray) -> np.ndarray:
    """Weights 1-2-1 over neighbouring bins (the ends keep their own value)."""
    if values.shape[0] < 3:
        return values
    out = values.copy()
    out[1:-1] = (values[:-2] + 2 * values[1:-1] + values[2:]) / 4
    return out
