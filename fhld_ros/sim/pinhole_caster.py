"""The obstacle caster for a pinhole image (sim/camera.py): the LiDAR's caster picks, for each
object, the block of beams and evenly spaced columns of a spinning sensor it can cover; an
image's rows and columns are not evenly spaced in angle, so the blocks come from each pixel
row's elevation range and each pixel column's azimuth range instead; and the normals of the
hits, from their neighbouring pixels (screen_normals)."""
from __future__ import annotations

import numpy as np

from fhld_ros.sim.obstacles import Boxes
from fhld_ros.sim.raycast import ObstacleCaster, RayBundle

ANGLE_MARGIN = 0.02  # rad: the caster's pixel blocks grow by this (cylinder spans estimate)


class PinholeCaster(ObstacleCaster):
    """ObstacleCaster for an image: blocks of rows x columns from each row's elevation range
    and each column's azimuth range (world frame, exact per pixel, made monotonic), instead of
    a spinning sensor's beams and evenly spaced columns. cull=False tests every pixel."""

    def __init__(self, rays: RayBundle, elevation: np.ndarray, azimuth: np.ndarray,
                 cull: bool = True) -> None:
        """elevation: (H, any) samples along each row; azimuth: (any, W) down each column."""
        super().__init__(rays, tilt_margin=ANGLE_MARGIN, yaw_margin=ANGLE_MARGIN)
        self.cull = cull
        # -elevation grows down the image and -azimuth to the right: ascending bounds for
        # searchsorted (a running max of the upper and a reverse running min of the lower
        # bounds only ever widen the blocks)
        nel, naz = -elevation, -azimuth
        self._row_hi = np.maximum.accumulate(nel.max(axis=1))
        self._row_lo = np.minimum.accumulate(nel.min(axis=1)[::-1])[::-1]
        self._col_hi = np.maximum.accumulate(naz.max(axis=0))
        self._col_lo = np.minimum.accumulate(naz.min(axis=0)[::-1])[::-1]

    def _spans(self, az: np.ndarray, half_az: np.ndarray, el_lo: np.ndarray, el_hi: np.ndarray,
               skip: np.ndarray) -> list[tuple[int, slice, slice]]:
        nb, nw = self.t.shape
        if not self.cull:
            return [(int(i), slice(0, nb), slice(0, nw)) for i in np.flatnonzero(~skip)]
        r0 = np.searchsorted(self._row_hi, -el_hi - self.tilt)
        r1 = np.searchsorted(self._row_lo, -el_lo + self.tilt, side='right')
        a = (az + np.pi) % (2 * np.pi) - np.pi
        half = half_az + self.yaw_margin
        # the object's azimuth interval may wrap: try it shifted by -2pi, 0, 2pi
        shifts = np.array([-2 * np.pi, 0.0, 2 * np.pi])
        lo = (-a - half)[:, None] + shifts
        hi = (-a + half)[:, None] + shifts
        c0 = np.searchsorted(self._col_hi, lo)
        c1 = np.searchsorted(self._col_lo, hi, side='right')
        hit = c1 > c0
        c0 = np.where(hit, c0, nw).min(axis=1)
        c1 = np.where(hit, c1, 0).max(axis=1)
        full = half_az >= np.pi
        c0, c1 = np.where(full, 0, c0), np.where(full, nw, c1)
        keep = np.flatnonzero((r1 > r0) & (c1 > c0) & ~skip)
        return [(int(i), slice(int(r0[i]), int(r1[i])), slice(int(c0[i]), int(c1[i])))
                for i in keep]

    def _box_spans(self, boxes: Boxes) -> list[tuple[int, slice, slice]]:
        """Exact angular extents of upright boxes: azimuth from the footprint corners,
        elevation from the top and bottom faces at the nearest / farthest footprint point."""
        c, s = boxes.rot[:, 0, 0], boxes.rot[:, 1, 0]
        hx, hy, hz = boxes.half.T
        rx, ry = self.sensor[0] - boxes.centre[:, 0], self.sensor[1] - boxes.centre[:, 1]
        lx, ly = rx * c + ry * s, ry * c - rx * s  # the camera in box axes
        d_min = np.hypot(lx - np.clip(lx, -hx, hx), ly - np.clip(ly, -hy, hy))
        sx = np.array([-1.0, -1.0, 1.0, 1.0])[None]
        sy = np.array([-1.0, 1.0, -1.0, 1.0])[None]
        px = (sx * hx[:, None]) * c[:, None] - (sy * hy[:, None]) * s[:, None] - rx[:, None]
        py = (sx * hx[:, None]) * s[:, None] + (sy * hy[:, None]) * c[:, None] - ry[:, None]
        d_max = np.hypot(px, py).max(axis=1)
        az = np.arctan2(py, px)
        daz = (az - az[:, :1] + np.pi) % (2 * np.pi) - np.pi
        span = daz.max(1) - daz.min(1)
        top = boxes.centre[:, 2] + hz - self.sensor[2]
        bottom = boxes.centre[:, 2] - hz - self.sensor[2]
        el_hi = np.arctan2(top, np.where(top > 0, d_min, d_max))
        el_lo = np.arctan2(bottom, np.where(bottom < 0, d_min, d_max))
        around = (span > np.pi) | (d_min < 0.5)
        mid = az[:, 0] + 0.5 * (daz.max(1) + daz.min(1)) - self.rays.yaw
        return self._spans(mid, np.where(around, np.pi, 0.5 * span),
                           np.where(around, -np.pi / 2, el_lo), np.where(around, np.pi / 2, el_hi),
                           d_min > self.rays.t_max)


def screen_normals(origin: np.ndarray, dirs: np.ndarray, t: np.ndarray, mask: np.ndarray
                    ) -> np.ndarray:
    """World normals (N, 3) at the mask's pixels from the hit points' differences to the
    neighbouring pixels, taking on each axis the neighbour at the nearer range (so an edge keeps
    its own surface), turned to face the camera."""
    h, w = t.shape
    idx = np.flatnonzero(mask)
    row, col = np.divmod(idx, w)
    flat_t = t.astype(np.float32).ravel()
    comps = [dirs[..., i].astype(np.float32).ravel() for i in range(3)]
    t0 = flat_t[idx]

    def tangent(step: int, has_prev: np.ndarray, has_next: np.ndarray) -> list[np.ndarray]:
        prev, nxt = np.where(has_prev, idx - step, idx), np.where(has_next, idx + step, idx)
        with np.errstate(invalid='ignore'):  # inf - inf beside the sky: never chosen
            gap_p = np.where(has_prev, np.abs(t0 - flat_t[prev]), np.inf)
            gap_n = np.where(has_next, np.abs(flat_t[nxt] - t0), np.inf)
        back = gap_p < gap_n
        j = np.where(back, prev, nxt)
        tj = np.where(np.isfinite(flat_t[j]), flat_t[j], t0)
        sign = np.where(back, np.float32(-1), np.float32(1))
        # (p_j - p_0) without the common origin
        return [sign * (tj * c[j] - t0 * c[idx]) for c in comps]

    ax, ay, az = tangent(1, col > 0, col < w - 1)
    bx, by, bz = tangent(w, row > 0, row < h - 1)
    n = np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=1)
    d = np.stack([c[idx] for c in comps], axis=1)
    norm = np.sqrt((n * n).sum(axis=1, keepdims=True))
    n = np.where(norm > 0, n / np.maximum(norm, 1e-12), -d)
    return np.where(((n * d).sum(axis=1) > 0)[:, None], -n, n)
