"""Road reference line: plan curve, vertical profile and crossfall as functions of arc length s.

Everything lateral (lanes, paint, curbs, terrain) is expressed in road coordinates (s, d):
s = arc length along the reference line, d = signed lateral offset (left positive). The
reference line is tabulated every ``DS`` metres; lookups interpolate linearly in the table,
which is exact to well under a millimetre for curvature radii >= 50 m.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

DS = 0.25  # table spacing along s (m)
MAX_GRADE = 0.06
MAX_BANK = 0.03


@dataclass(frozen=True)
class RoadShape:
    """Limits that the generated plan and profile obey (per road class)."""

    min_radius_m: float = 50.0
    max_grade: float = MAX_GRADE
    max_bank: float = MAX_BANK
    max_heading_rad: float = np.deg2rad(75.0)  # keeps the road from looping onto itself


def smoothstep(x: np.ndarray) -> np.ndarray:
    """C2 ramp 0 -> 1 on [0, 1] (quintic), clipped outside."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _piecewise_linear(rng: np.random.Generator, s: np.ndarray, draw_segment) -> np.ndarray:
    """Knots (s, value) from repeated draw_segment(rng, last_value) -> list[(length, value)]."""
    knots_s, knots_v = [s[0] - 1.0], [0.0]
    while knots_s[-1] < s[-1] + 1.0:
        for length, value in draw_segment(rng, knots_v[-1]):
            knots_s.append(knots_s[-1] + length)
            knots_v.append(value)
    return np.interp(s, knots_s, knots_v)


class ReferenceLine:
    """Tabulated reference line: columns x, y, heading, curvature, z, grade, bank over s."""

    COLUMNS = ('x', 'y', 'heading', 'kappa', 'z', 'grade', 'bank')

    def __init__(self, s0: float, table: np.ndarray) -> None:
        self.s0 = float(s0)
        self.table = np.ascontiguousarray(table, dtype=np.float64)  # (M, 7)
        self.size = self.table.shape[0]
        self._tree = None  # scipy cKDTree, built on first use

    @property
    def s(self) -> np.ndarray:
        return self.s0 + DS * np.arange(self.size)

    @property
    def s_end(self) -> float:
        return self.s0 + DS * (self.size - 1)

    def column(self, name: str) -> np.ndarray:
        return self.table[:, self.COLUMNS.index(name)]

    def index(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Table row i and blend weight w of positions s (clamped to the table)."""
        f = np.clip((np.asarray(s, dtype=np.float64) - self.s0) / DS, 0.0, self.size - 1.000001)
        i = f.astype(np.intp)
        return i, f - i

    def sample(self, s: np.ndarray) -> np.ndarray:
        """All columns at s: (..., 7)."""
        i, w = self.index(s)
        return self.table[i] * (1.0 - w)[..., None] + self.table[i + 1] * w[..., None]

    def plane_z(self, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Height of the road plane (centre height + crossfall * d) at (s, d)."""
        row = self.sample(s)
        return row[..., 4] + row[..., 6] * d

    def to_world(self, s: np.ndarray, d: np.ndarray, z: np.ndarray | None = None) -> np.ndarray:
        """Road coordinates -> world (..., 3); z defaults to the road plane."""
        row = self.sample(s)
        d = np.asarray(d, dtype=np.float64)
        heading = row[..., 2]
        x = row[..., 0] - np.sin(heading) * d
        y = row[..., 1] + np.cos(heading) * d
        if z is None:
            z = row[..., 4] + row[..., 6] * d
        return np.stack(np.broadcast_arrays(x, y, z), axis=-1)

    def project(self, xy: np.ndarray, within: tuple[np.ndarray, float] | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """World xy (..., 2) -> road coordinates (s, d) of the nearest reference-line point.
        within (centre, radius): every point lies within radius of centre (a tile of the
        ground grid), so only the samples that can be nearest to one of them are searched."""
        xy = np.asarray(xy, dtype=np.float64)
        flat = xy.reshape(-1, 2)
        if self._tree is None:  # samples every 1 m; two Newton steps refine to sub-micron
            self._stride = max(1, round(1.0 / DS))
            self._tree = cKDTree(self.table[::self._stride, :2])
        if within is None:
            _, k = self._tree.query(flat)  # single-threaded: cache builders run many processes
        else:  # a point's nearest sample is within 2 radius + the centre's nearest of centre
            centre, radius = within
            reach, _ = self._tree.query(centre)
            samples = self._tree.data
            near = np.flatnonzero(np.hypot(*(samples - centre).T) <= reach + 2.0 * radius)
            k = near[cKDTree(samples[near]).query(flat)[1]]
        s = self.s0 + k * (self._stride * DS)
        for _ in range(2):
            row = self.sample(s)
            dx, dy = flat[:, 0] - row[:, 0], flat[:, 1] - row[:, 1]
            c, sn = np.cos(row[:, 2]), np.sin(row[:, 2])
            along, d = dx * c + dy * sn, -dx * sn + dy * c
            s = np.clip(s + along / np.maximum(1.0 - row[:, 3] * d, 0.2), self.s0, self.s_end)
        row = self.sample(s)
        d = -(flat[:, 0] - row[:, 0]) * np.sin(row[:, 2]) + (flat[:, 1] - row[:, 1]) * np.cos(
            row[:, 2])
        return s.reshape(xy.shape[:-1]), d.reshape(xy.shape[:-1])


def _curvature_segments(shape: RoadShape, heading_now: list[float]):
    """Segment generator for curvature: straights, clothoid transitions and arcs."""
    def draw(rng: np.random.Generator, kappa: float):
        if kappa != 0.0:  # leave the arc through a transition back to straight
            return [(rng.uniform(30, 90), 0.0), (rng.uniform(20, 250), 0.0)]
        radius = np.exp(rng.uniform(np.log(shape.min_radius_m), np.log(1500.0)))
        sign = rng.choice((-1.0, 1.0))
        if abs(heading_now[0]) > 0.5 * shape.max_heading_rad:  # turn back towards the start
            sign = -np.sign(heading_now[0])
        arc = rng.uniform(20, 150)
        k = sign / radius
        # keep the heading bounded: shorten the arc if it would exceed the limit
        budget = shape.max_heading_rad - sign * heading_now[0]
        arc = float(np.clip(min(arc, max(budget, 0.0) * radius), 5.0, None))
        heading_now[0] += k * (arc + 60.0)
        return [(rng.uniform(30, 90), k), (arc, k)]
    return draw


def _grade_segments(shape: RoadShape):
    def draw(rng: np.random.Generator, grade: float):
        new = rng.uniform(-shape.max_grade, shape.max_grade) if rng.random() < 0.8 else 0.0
        # vertical curve length ~ K * |delta grade in %|, K 10..40 m per %
        vc = float(np.clip(rng.uniform(10, 40) * abs(new - grade) * 100, 30, 300))
        return [(vc, new), (rng.uniform(40, 300), new)]
    return draw


def make_reference_line(rng: np.random.Generator, s_start: float, s_end: float,
                        shape: RoadShape, crossfall: float, s_origin: float) -> ReferenceLine:
    """Random smooth road between s_start and s_end, placed so s_origin sits at (0, 0, 0)
    heading +x (the ego starts there, so odom coordinates stay small)."""
    s = s_start + DS * np.arange(int(np.ceil((s_end - s_start) / DS)) + 1)
    heading_now = [0.0]
    kappa = _piecewise_linear(rng, s, _curvature_segments(shape, heading_now))
    grade = _piecewise_linear(rng, s, _grade_segments(shape))
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * DS)])
    z = np.concatenate([[0.0], np.cumsum(0.5 * (grade[1:] + grade[:-1]) * DS)])
    # superelevation towards the inside of curves (full at R <= 200 m) over the drainage
    # crossfall of straights; left curves (kappa > 0) bank down to the left (bank < 0)
    bank = np.clip(crossfall - kappa * 200.0 * shape.max_bank, -shape.max_bank, shape.max_bank)
    # integrate the plan curve with the midpoint heading (second-order accurate)
    mid = 0.5 * (heading[1:] + heading[:-1])
    x = np.concatenate([[0.0], np.cumsum(np.cos(mid) * DS)])
    y = np.concatenate([[0.0], np.cumsum(np.sin(mid) * DS)])
    # move s_origin to the world origin with heading 0
    k = int(round((s_origin - s_start) / DS))
    c, sn = np.cos(-heading[k]), np.sin(-heading[k])
    dx, dy = x - x[k], y - y[k]
    table = np.stack([c * dx - sn * dy, sn * dx + c * dy, heading - heading[k], kappa,
                      z - z[k], grade, bank], axis=1)
    return ReferenceLine(s[0], table)
