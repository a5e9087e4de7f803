"""Ground surface: road plane, curbs, sidewalks, verges and terrain as an analytic height
h(s, d), its materials, and a tiled heightfield cache for fast ray marching.

The analytic height is the truth (GT z and the final ray intersections use it). The cache
holds h, s and d sampled on a world-aligned grid so the ray marcher can bracket hits with
plain array gathers and refine them with exact heights at interpolated (s, d).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fhld_ros.sim.layout import Layout
from fhld_ros.sim.road import DS, ReferenceLine

# ground materials (obstacle materials continue in obstacles.py)
ASPHALT, PAINT, CONCRETE, GRAVEL, GRASS = 1, 2, 3, 4, 5
GROUND_MATERIALS = (ASPHALT, PAINT, CONCRETE, GRAVEL, GRASS)


@dataclass(frozen=True)
class Roadside:
    """Cross-section beyond one paved edge."""

    curb_h: float  # curb height (0: no curb)
    walk_w: float  # sidewalk width (0: none)
    verge_w: float  # gravel strip width before the terrain starts (no sidewalk)
    slope: float  # terrain slope beyond (+ rising, - falling)
    ditch: float  # ditch depth just beyond the verge


@dataclass(frozen=True)
class RoadLook:
    """What real pavements vary beyond the usual asphalt (defaults: the usual road).

    KITTI's asphalt reads ~3x brighter than the usual simulated one, so its concrete
    sidewalks and gutters hardly stand out; gutters and sealed seams are paint-like stripes
    that are not lane lines.
    """

    asphalt_rho: float | None = None  # pavement diffuse reflectance; None: U(0.07, 0.14)
    gutter_ratio: float | None = None  # a 0.25-0.6 m strip along each paved edge, x pavement
    seams: bool = False  # dark sealed cracks along the lanes and joints across them


def _roadside(rng: np.random.Generator, road_class: str) -> Roadside:
    if road_class == 'urban':
        return Roadside(rng.uniform(0.10, 0.18), rng.uniform(1.5, 4.0), 0.0,
                        rng.uniform(-0.02, 0.05), 0.0)
    return Roadside(0.0, 0.0, rng.uniform(0.3, 1.2), rng.uniform(-0.25, 0.3),
                    rng.uniform(0.0, 0.6) if rng.random() < 0.6 else 0.0)


@dataclass(frozen=True)
class Seams:
    """Sealed cracks: wandering stripes along the road at offsets d0 (one row per seam), and
    joints across it every `joint_period` m (0: none), all darker than the pavement."""

    d0: np.ndarray
    amp: np.ndarray
    k: np.ndarray
    phase: np.ndarray
    half_w: np.ndarray
    factor: np.ndarray
    joint_period: float
    joint_half_w: float
    joint_factor: float


def _draw_seams(rng: np.random.Generator, left: np.ndarray, right: np.ndarray) -> Seams:
    n = int(rng.integers(1, 4))
    lo, hi = float(np.median(right)), float(np.median(left))
    joints = rng.random() < 0.4  # concrete slabs or sealed transverse cracks
    return Seams(rng.uniform(lo, hi, n), rng.uniform(0.0, 0.4, n),
                 2 * np.pi / rng.uniform(10.0, 60.0, n), rng.uniform(0, 2 * np.pi, n),
                 rng.uniform(0.02, 0.07, n), rng.uniform(0.35, 0.75, n),
                 float(rng.uniform(4.0, 8.0)) if joints else 0.0,
                 float(rng.uniform(0.02, 0.05)), float(rng.uniform(0.4, 0.8)))


def _seam_factor(seams: Seams, s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Reflectance factor (<= 1) of the seams at road coordinates."""
    centre = seams.d0 + seams.amp * np.sin(np.multiply.outer(s, seams.k) + seams.phase)
    on = np.abs(d[:, None] - centre) <= seams.half_w
    factor = np.where(on, seams.factor, 1.0).min(axis=1)
    if seams.joint_period:
        phase = np.mod(s, seams.joint_period)
        near = np.minimum(phase, seams.joint_period - phase) <= seams.joint_half_w
        factor = np.where(near, np.minimum(factor, seams.joint_factor), factor)
    return factor


class Surface:
    """Analytic ground height and material in road coordinates."""

    def __init__(self, ref: ReferenceLine, layout: Layout, rng: np.random.Generator,
                 road_class: str, look: RoadLook = RoadLook()) -> None:
        self.ref, self.layout, self.road_class = ref, layout, road_class
        left, right = layout.paved_extent()
        gore_hi, gore_lo = layout.gore_span()
        # columns: z centre, bank, left edge, right edge, gore left, gore right
        self.table = np.stack([ref.column('z'), ref.column('bank'), left, right,
                               np.nan_to_num(gore_hi, nan=-1e9), np.nan_to_num(gore_lo, nan=1e9)],
                              axis=1)
        diff = np.diff(self.table, axis=0, append=self.table[-1:])
        self._lerp6 = np.ascontiguousarray(np.concatenate([self.table, diff], axis=1))
        self._lerp4 = np.ascontiguousarray(np.concatenate([self.table[:, :4], diff[:, :4]],
                                                          axis=1))
        self.sides = (_roadside(rng, road_class), _roadside(rng, road_class))  # left, right
        self.asphalt = rng.uniform(0.07, 0.14)
        # terrain undulation: a few plane waves in (s, d), wavelengths 8-60 m
        k = 2 * np.pi / rng.uniform(8.0, 60.0, 4)
        ang = rng.uniform(0, np.pi, 4)
        self._waves = np.stack([k * np.cos(ang), k * np.sin(ang), rng.uniform(0, 2 * np.pi, 4)],
                               axis=1)
        self._relief = rng.uniform(0.1, 0.8)
        # asphalt patches: lower-frequency pattern of repaired / aged surface
        kp = 2 * np.pi / rng.uniform(5.0, 25.0, 3)
        angp = rng.uniform(0, np.pi, 3)
        self._patches = np.stack([kp * np.cos(angp), kp * np.sin(angp),
                                  rng.uniform(0, 2 * np.pi, 3)], axis=1)
        # drawn last, so a road without them is the same road as before
        if look.asphalt_rho is not None:
            self.asphalt = float(look.asphalt_rho)
        self.gutter = (None if look.gutter_ratio is None else
                       (float(rng.uniform(0.25, 0.6)), float(look.gutter_ratio)))
        self.seams = _draw_seams(rng, left, right) if look.seams else None

    def _rows(self, s: np.ndarray, cols: int = 6) -> np.ndarray:
        """The first `cols` (4 or 6) table columns at s, linearly interpolated: one gather
        from a table that stores each row next to its difference to the following row."""
        table = self._lerp4 if cols == 4 else self._lerp6
        f = np.clip((s - self.ref.s0) / DS, 0.0, self.ref.size - 1.000001)
        i = f.astype(np.intp)
        rows = table[i]
        n = table.shape[1] // 2
        out = rows[:, n:] * (f - i)[:, None]
        out += rows[:, :n]
        return out

    def _side(self, left: np.ndarray, name: str) -> np.ndarray:
        return np.where(left, getattr(self.sides[0], name), getattr(self.sides[1], name))

    def _waves_at(self, waves: np.ndarray, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Mean of plane waves sin(ks s + kd d + phase) (float32 is plenty for texture)."""
        s32, d32 = s.astype(np.float32), d.astype(np.float32)
        out = np.zeros(s32.shape, dtype=np.float32)
        for ks, kd, ph in waves.astype(np.float32):
            out += np.sin(ks * s32 + kd * d32 + ph)
        return out / np.float32(len(waves))

    def height(self, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Ground height at road coordinates (any matching shapes)."""
        s, d = np.broadcast_arrays(np.asarray(s, dtype=np.float64),
                                   np.asarray(d, dtype=np.float64))
        shape = s.shape
        s, d = s.reshape(-1), d.reshape(-1)
        r = self._rows(s, 4)
        e_left, e_right = r[:, 2], r[:, 3]
        z = r[:, 0] + r[:, 1] * np.clip(d, e_right, e_left)
        u = np.maximum(np.maximum(d - e_left, e_right - d), 0.0)  # distance beyond the edge
        off = np.flatnonzero(u > 0)
        if off.size:
            z[off] += self._beyond(s[off], d[off], u[off], d[off] > 0.5 * (
                e_left[off] + e_right[off]))
        return z.reshape(shape)

    def _beyond(self, s: np.ndarray, d: np.ndarray, u: np.ndarray, left: np.ndarray
                ) -> np.ndarray:
        """Height above the paved edge of points u > 0 beyond it: curb, sidewalk, terrain."""
        walk = self._side(left, 'walk_w')
        z = self._side(left, 'curb_h') + 0.02 * np.minimum(u, walk)
        ut = np.maximum(u - walk - self._side(left, 'verge_w'), 0.0)  # terrain coordinate
        z += 4.0 * np.tanh(self._side(left, 'slope') * np.maximum(ut - 0.5, 0.0) / 4.0)
        bump = np.where((ut > 0.3) & (ut < 3.3), np.sin(np.pi * (ut - 0.3) / 3.0) ** 2, 0.0)
        z -= self._side(left, 'ditch') * bump
        rough = np.flatnonzero(ut > 0)  # relief grows with distance from the road edge
        if rough.size:
            z[rough] += self._relief * (1.0 - np.exp(-ut[rough] / 4.0)) * self._waves_at(
                self._waves, s[rough], d[rough])
        return z

    def is_terrain(self, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Points of open terrain, beyond the pavement, curbs, sidewalks and verges."""
        r = self._rows(s, 4)
        u = np.maximum(d - r[:, 2], r[:, 3] - d)
        left = d > 0.5 * (r[:, 2] + r[:, 3])
        return u > self._side(left, 'walk_w') + self._side(left, 'verge_w') + 0.5

    def rows(self, s: np.ndarray) -> np.ndarray:
        """Cross-section table at s, to share between material() and normal_slopes()."""
        return self._rows(s)

    def material(self, s: np.ndarray, d: np.ndarray, rows: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Ground material id and diffuse reflectance (no paint) at road coordinates."""
        r = self._rows(s) if rows is None else rows
        e_left, e_right, g_hi, g_lo = r[:, 2], r[:, 3], r[:, 4], r[:, 5]
        u = np.maximum(np.maximum(d - e_left, e_right - d), 0.0)
        left = d > 0.5 * (e_left + e_right)
        mat = np.full(s.shape, ASPHALT, dtype=np.uint8)
        walk = self._side(left, 'walk_w')
        verge = self._side(left, 'verge_w')
        mat[(u > 0) & (u <= walk)] = CONCRETE
        mat[(u > walk) & (u <= walk + verge)] = GRAVEL
        mat[u > walk + verge] = GRASS
        mat[(d < g_hi - 0.3) & (d > g_lo + 0.3) & (g_hi - g_lo > 2.5)] = GRASS  # open gore
        patches = self._waves_at(self._patches, s, d)
        rho = np.select([mat == ASPHALT, mat == CONCRETE, mat == GRAVEL],
                        [self.asphalt * (1.0 + 0.25 * np.round(2 * patches) / 2),
                         np.full(s.shape, 0.30), np.full(s.shape, 0.22)],
                        0.35 + 0.1 * patches)
        paved = mat == ASPHALT
        if self.gutter is not None:
            width, ratio = self.gutter
            edge = np.minimum(e_left - d, d - e_right)  # distance inside the paved edge
            rho = np.where(paved & (edge <= width), rho * ratio, rho)
        if self.seams is not None and paved.any():
            index = np.flatnonzero(paved)
            rho[index] *= _seam_factor(self.seams, s[index], d[index])
        return mat, rho

    def normal_slopes(self, s: np.ndarray, d: np.ndarray, z: np.ndarray, eps: float = 0.03,
                      rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """dz/ds and dz/dd at ground points of height z: the road plane's grade and bank on
        the pavement, forward differences beyond it (curb faces come out steep)."""
        r = self._rows(s) if rows is None else rows
        dzs = np.interp(s, self.ref.s, self.ref.column('grade'))
        dzd = r[:, 1].copy()
        off = np.flatnonzero((d > r[:, 2] - eps) | (d < r[:, 3] + eps))
        if off.size:
            so, do, zo = s[off], d[off], z[off]
            dzs[off] = (self.height(so + eps, do) - zo) / eps
            dzd[off] = (self.height(so, do + eps) - zo) / eps
        return dzs, dzd
