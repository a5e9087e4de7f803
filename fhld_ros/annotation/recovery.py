"""Point cloud recovery (ONCE-3DLanes section 3.2): one label's lane returns -> a 3D lane.

The paper clusters the lane returns of each beam into a centre point. Accumulated sweeps have
many beams crossing a line at every distance, so the returns are clustered by where they lie
along the line instead: BIN_M bins along the chord from the label's near end to its far end (a
line turning less than 180 degrees advances monotonically along it; the label's own pixel order
does not resolve distance far away). A bin's centre is the mean of its returns, weighted by how
much brighter than the road each return is when the bin holds paint (so a label a few pixels
off still gives the paint's centre), unweighted when it does not. Centres are smoothed over
neighbouring bins and resampled every step_m.
"""
from __future__ import annotations

import numpy as np

BIN_M = 0.5
END_SHARE = 0.1  # the chord joins the medians of the nearest and farthest tenth (label order)
PAINT_CONTRAST = 1.8  # a bin holds paint when a return is this many times the road level
MIN_BIN_POINTS = 2
MAX_GAP_M = 4.0  # a lane is cut where its bins are further apart than this
END_FIT = 4  # an end centre is checked against the line through this many next ones ...
END_BEND_M = 0.08  # ... and dropped when further from it than this


def recover_lane(xyz: np.ndarray, t: np.ndarray, contrast: np.ndarray,
                 step_m: float = 0.5) -> list[np.ndarray]:
    """(K, 3) lane pieces from the returns of one label region (xyz in a z-up frame, t their
    position along the label, contrast their intensity over the road's)."""
    if xyz.shape[0] < 2 * MIN_BIN_POINTS:
        return []
    order = np.argsort(t, kind='stable')
    xyz, contrast = xyz[order], contrast[order]
    end = max(1, int(END_SHARE * xyz.shape[0]))
    chord = np.median(xyz[-end:, :2], axis=0) - np.median(xyz[:end, :2], axis=0)
    if np.linalg.norm(chord) < BIN_M:
        return []
    s = xyz[:, :2] @ (chord / np.linalg.norm(chord))
    bins = np.floor((s - s.min()) / BIN_M).astype(np.intp)
    n_bins = int(bins.max()) + 1
    count = np.bincount(bins, minlength=n_bins)
    brightest = np.zeros(n_bins)
    np.maximum.at(brightest, bins, contrast)
    painted = brightest[bins] >= PAINT_CONTRAST
    weight = np.where(painted, np.clip(contrast - 1.0, 0.0, None) ** 2, 1.0)
    w_sum = np.bincount(bins, weight, n_bins)
    good = (count >= MIN_BIN_POINTS) & (w_sum > 0)
    if good.sum() < 2:
        return []
    safe = np.where(good, w_sum, 1.0)
    centre = np.column_stack([np.bincount(bins, weight * xyz[:, k], n_bins) / safe
                              for k in (0, 1)])
    # heights unweighted: paint sits on the road
    centre_z = np.bincount(bins, xyz[:, 2], n_bins) / np.maximum(count, 1)
    index = np.flatnonzero(good)
    pieces = []
    for part in np.split(index, np.flatnonzero(np.diff(index) * BIN_M > MAX_GAP_M) + 1):
        if part.size < 2:
            continue
        points = _trim_ends(np.column_stack([centre[part], centre_z[part]]))
        if points.shape[0] < 2:
            continue
        points = np.column_stack([_smooth(points[:, :2]), _smooth(points[:, 2])])
        pieces.append(_resample(points, step_m))
    return pieces


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


def _resample(points: np.ndarray, step_m: float) -> np.ndarray:
    """A polyline resampled every step_m of its horizontal arc length (both ends kept)."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points[:, :2], axis=0),
                                                          axis=1))])
    samples = np.append(np.arange(0.0, arc[-1], step_m), arc[-1])
    samples = samples[np.concatenate([[True], np.diff(samples) > 1e-6])]
    return np.column_stack([np.interp(samples, arc, points[:, k]) for k in range(3)])
