"""Adaptive lane blending (ONCE-3DLanes section 3.2): a 2D lane label broadened into a region
whose width follows the distance, and the projected ground returns that fall inside it.

A label is a polyline in pixels; its region holds the pixels within
max(MIN_HALF_PX, f * HALF_WIDTH_M * cos(slant) / depth) of it, where depth is that of the return
being tested and slant the label's angle from the image vertical (a sideways offset on the road
shows as a horizontal shift of f / depth pixels per metre, of which the distance across a
slanted label is the cos part). So the region is about 2 * HALF_WIDTH_M wide across the line
on the road at every distance: wide enough for the paint plus a few pixels of labelling error,
narrow enough to stay off the next line.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

HALF_WIDTH_M = 0.3
MIN_HALF_PX = 1.5
END_SLACK_PX = 2.0  # returns this far past a label's ends still count
SAMPLE_PX = 0.5  # the label is resampled this finely: distances are exact to a quarter pixel


@dataclass
class LaneMembers:
    """The returns inside one label's region."""

    index: np.ndarray  # (M,) into the projected returns
    t: np.ndarray  # (M,) pixel arc length along the label of each return's foot point
    offset_px: np.ndarray  # (M,) signed distance from the label (left of its direction < 0)


def _samples(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points every SAMPLE_PX along the polyline, extended END_SLACK_PX past both ends, with
    their arc length and the unit direction of their segment."""
    seg = np.diff(poly, axis=0)
    length = np.linalg.norm(seg, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(length)])
    t = np.arange(-END_SLACK_PX, arc[-1] + END_SLACK_PX + SAMPLE_PX / 2, SAMPLE_PX)
    k = np.clip(np.searchsorted(arc, t, side='right') - 1, 0, len(seg) - 1)
    unit = seg[k] / length[k, None]
    return poly[k] + (t - arc[k])[:, None] * unit, np.clip(t, 0.0, arc[-1]), unit


def lane_members(uv: np.ndarray, depth: np.ndarray, label_uv: np.ndarray, focal_px: float,
                 half_width_m: float = HALF_WIDTH_M) -> LaneMembers:
    """Returns (projected to uv with their depth) inside the broadened label polyline."""
    poly = np.asarray(label_uv, dtype=np.float64)
    keep = np.concatenate([[True], np.any(np.diff(poly, axis=0) != 0, axis=1)])
    poly = poly[keep]
    if poly.shape[0] < 2 or uv.shape[0] == 0:
        empty = np.zeros(0)
        return LaneMembers(np.zeros(0, dtype=np.intp), empty, empty)
    half = np.maximum(MIN_HALF_PX, focal_px * half_width_m / np.maximum(depth, 1e-3))
    reach = float(half.max()) + END_SLACK_PX  # before the slant: an upper bound
    lo, hi = poly.min(axis=0) - reach, poly.max(axis=0) + reach
    near = np.flatnonzero(np.all((uv >= lo) & (uv <= hi), axis=1))
    samples, t, unit = _samples(poly)
    dist, nearest = cKDTree(samples).query(uv[near], distance_upper_bound=reach)
    found = np.isfinite(dist)
    near, dist, nearest = near[found], dist[found], nearest[found]
    direction = unit[nearest]
    rel = uv[near] - samples[nearest]
    cross = direction[:, 0] * rel[:, 1] - direction[:, 1] * rel[:, 0]
    cos_slant = np.abs(direction[:, 1])
    inside = dist <= np.maximum(MIN_HALF_PX, half[near] * cos_slant)
    return LaneMembers(near[inside], t[nearest[inside]], np.sign(cross[inside]) * dist[inside])
