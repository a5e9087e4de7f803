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

HALF_WIDTH_M = 0.3
MIN_HALF_PX = 1.5
END_SLACK_PX = 2.0  # returns this far past a label's ends still count
CHUNK = 1 << 22  # point x segment pairs evaluated at once (memory bound)


@dataclass
class LaneMembers:
    """The returns inside one label's region."""

    index: np.ndarray  # (M,) into the projected returns
    t: np.ndarray  # (M,) pixel arc length along the label of each return's foot point
    offset_px: np.ndarray  # (M,) signed distance from the label (left of its direction < 0)


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
    a, b = poly[:-1], poly[1:]
    seg = b - a
    length = np.linalg.norm(seg, axis=1)
    cos_slant = np.abs(seg[:, 1]) / length
    start_t = np.concatenate([[0.0], np.cumsum(length)[:-1]])
    best = np.full(near.size, np.inf)
    best_cos = np.ones(near.size)
    best_t = np.zeros(near.size)
    best_off = np.zeros(near.size)
    step = max(1, CHUNK // max(1, len(a)))
    for s in range(0, near.size, step):  # chunks of points, every segment at once
        p = uv[near[s:s + step]]
        rel = p[:, None, :] - a[None]
        along = np.einsum('psk,sk->ps', rel, seg) / length
        clamped = np.clip(along, -END_SLACK_PX, length + END_SLACK_PX)
        foot = a[None] + clamped[..., None] * (seg / length[:, None])[None]
        dist = np.linalg.norm(p[:, None, :] - foot, axis=2)
        k = np.argmin(dist, axis=1)
        rows = np.arange(p.shape[0])
        best[s:s + step] = dist[rows, k]
        best_cos[s:s + step] = cos_slant[k]
        best_t[s:s + step] = start_t[k] + clamped[rows, k]
        cross = seg[k, 0] * rel[rows, k, 1] - seg[k, 1] * rel[rows, k, 0]
        best_off[s:s + step] = np.sign(cross) * dist[rows, k]
    inside = best <= np.maximum(MIN_HALF_PX, (half[near] * best_cos))
    return LaneMembers(near[inside], best_t[inside], best_off[inside])
