"""Road paint: lane lines (dash patterns, wear) and distractor markings, looked up at (s, d).

Lines live in road coordinates, so "is this ground hit on paint" is a table gather per line
(offset, dash phase by arc length along the line, wear) instead of a nearest-neighbour search.
Distractors (arrows, stop lines, crosswalks, text) are small boolean stencils in (s, d).
The ground-truth polylines go through the centre of each painted stripe and run across dash
gaps, worn gaps and crosswalk interruptions (the line is there, the paint is not).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from matplotlib.path import Path

from fhld_ros.sim.layout import Layout
from fhld_ros.sim.road import DS, ReferenceLine

STENCIL_RES = 0.05  # m per stencil cell
NONE, LINE, MARKING = 0, 1, 2

# 5x7 block letters for road text (rows top to bottom)
_FONT = {
    'A': ('01110', '10001', '10001', '11111', '10001', '10001', '10001'),
    'B': ('11110', '10001', '10001', '11110', '10001', '10001', '11110'),
    'C': ('01111', '10000', '10000', '10000', '10000', '10000', '01111'),
    'E': ('11111', '10000', '10000', '11110', '10000', '10000', '11111'),
    'G': ('01111', '10000', '10000', '10011', '10001', '10001', '01111'),
    'I': ('11111', '00100', '00100', '00100', '00100', '00100', '11111'),
    'K': ('10001', '10010', '10100', '11000', '10100', '10010', '10001'),
    'L': ('10000', '10000', '10000', '10000', '10000', '10000', '11111'),
    'N': ('10001', '11001', '10101', '10011', '10001', '10001', '10001'),
    'O': ('01110', '10001', '10001', '10001', '10001', '10001', '01110'),
    'P': ('11110', '10001', '10001', '11110', '10000', '10000', '10000'),
    'R': ('11110', '10001', '10001', '11110', '10100', '10010', '10001'),
    'S': ('01111', '10000', '10000', '01110', '00001', '00001', '11110'),
    'T': ('11111', '00100', '00100', '00100', '00100', '00100', '00100'),
    'U': ('10001', '10001', '10001', '10001', '10001', '10001', '01110'),
    'W': ('10001', '10001', '10001', '10101', '10101', '11011', '10001'),
    'X': ('10001', '10001', '01010', '00100', '01010', '10001', '10001'),
    'Y': ('10001', '10001', '01010', '00100', '00100', '00100', '00100'),
}
WORDS = ('STOP', 'SLOW', 'BUS', 'ONLY', 'XING', 'TAXI', 'EXIT', 'KEEP')
assert all(ch in _FONT for word in WORDS for ch in word)


@dataclass
class Marking:
    """A stencil of paint: cell (iu, iv) covers s0 + iu*res along, v0 + iv*res across (d)."""

    kind: str
    s0: float
    v0: float
    mask: np.ndarray  # (nu, nv) bool
    contrast: float

    @property
    def s1(self) -> float:
        return self.s0 + self.mask.shape[0] * STENCIL_RES


def _rasterise(polygons: list[np.ndarray], length: float, width: float) -> np.ndarray:
    """Polygons in (u, v) metres, v centred on 0 -> stencil (nu, nv)."""
    nu, nv = int(np.ceil(length / STENCIL_RES)), int(np.ceil(width / STENCIL_RES))
    u, v = np.meshgrid((np.arange(nu) + 0.5) * STENCIL_RES,
                       (np.arange(nv) + 0.5) * STENCIL_RES - width / 2, indexing='ij')
    pts = np.stack([u.ravel(), v.ravel()], axis=1)
    mask = np.zeros(nu * nv, dtype=bool)
    for poly in polygons:
        mask |= Path(poly).contains_points(pts)
    return mask.reshape(nu, nv)


def _arrow(start: tuple[float, float], angle: float, length: float) -> np.ndarray:
    """Arrow polygon (shaft 0.2 m, head 1.3 x 0.8 m) from start along angle (rad, 0 = +u)."""
    head = min(1.3, 0.5 * length)
    shape = np.array([[0, -0.1], [length - head, -0.1], [length - head, -0.4], [length, 0],
                      [length - head, 0.4], [length - head, 0.1], [0, 0.1]])
    c, s = np.cos(angle), np.sin(angle)
    return shape @ np.array([[c, s], [-s, c]]) + np.asarray(start)


def arrow_stencil(kind: str) -> np.ndarray:
    """'straight' | 'left' | 'right' | 'straight_left' | 'straight_right' -> stencil 5 x 2.4 m."""
    polys = []
    if kind.startswith('straight'):
        polys.append(_arrow((0.0, 0.0), 0.0, 5.0))
    else:
        polys.append(np.array([[0, -0.1], [2.6, -0.1], [2.6, 0.1], [0, 0.1]]))
    if kind.endswith('left'):  # +v is left (d grows to the left)
        polys.append(_arrow((2.4, 0.0), np.deg2rad(50), 2.2))
    if kind.endswith('right'):
        polys.append(_arrow((2.4, 0.0), -np.deg2rad(50), 2.2))
    return _rasterise(polys, 5.0, 2.4)


def text_stencil(word: str, letter_len: float = 2.4, letter_w: float = 0.6) -> np.ndarray:
    """Road text, letters elongated along the road; read from the approaching car, so glyph
    row 0 (top) is the far end (large u) and column 0 the left (large v)."""
    nu = int(round(letter_len / STENCIL_RES))
    nv_letter = int(round(letter_w / STENCIL_RES))
    gap = np.zeros((nu, int(round(0.25 / STENCIL_RES))), dtype=bool)
    rows = np.arange(nu) * 7 // nu  # glyph row of each stencil row, top first
    cols = np.arange(nv_letter) * 5 // nv_letter
    reading = []  # as printed: rows top to bottom, columns left to right
    for ch in word:
        glyph = np.array([[c == '1' for c in row] for row in _FONT[ch]])
        reading += [glyph[rows][:, cols], gap]
    # top of the text is far (large u), left is large v (d grows to the left)
    return np.concatenate(reading[:-1], axis=1)[::-1, ::-1].copy()


def bars_stencil(length: float, width: float, period: float = 0.0, duty: float = 0.5
                 ) -> np.ndarray:
    """Solid bar (period 0) or zebra bars across the road (crosswalk) of length x width."""
    nu, nv = int(np.ceil(length / STENCIL_RES)), int(np.ceil(width / STENCIL_RES))
    if period <= 0:
        return np.ones((nu, nv), dtype=bool)
    v = (np.arange(nv) + 0.5) * STENCIL_RES
    return np.broadcast_to(((v % period) < duty * period)[None, :], (nu, nv)).copy()


class Paint:
    """All paint of a road: stacked line tables and distractor stencils."""

    def __init__(self, ref: ReferenceLine, layout: Layout, rng: np.random.Generator,
                 road_class: str) -> None:
        self.ref, self.layout = ref, layout
        lines = layout.lines
        size, n = layout.size, len(lines)
        self.offset = np.full((n, size), np.nan)
        self.dash_on = np.zeros((n, size))
        self.dash_off = np.zeros((n, size))
        self.arc = np.zeros((n, size))
        self.contrast = np.zeros((n, size), dtype=np.float32)
        self.half_width = np.array([0.5 * ln.width for ln in lines])
        self.yellow = np.array([ln.yellow for ln in lines], dtype=bool)
        kappa = ref.column('kappa')
        for k, ln in enumerate(lines):
            sl = slice(ln.i0, ln.i1 + 1)
            self.offset[k, sl] = ln.offset
            self.dash_on[k, sl] = ln.dash_on
            self.dash_off[k, sl] = ln.dash_off
            # arc length along the stripe: the reference line scaled by (1 - kappa d)
            dd = np.gradient(ln.offset, DS) if ln.offset.size > 1 else np.zeros(1)
            step = np.hypot(1.0 - kappa[sl] * ln.offset, dd) * DS
            self.arc[k, sl] = ln.phase + np.concatenate([[0.0], np.cumsum(step[:-1])])
            self.contrast[k, sl] = _wear_profile(rng, ln.i1 - ln.i0 + 1, ln.wear)
        self.markings = _place_markings(rng, layout, road_class)
        for m in self.markings:  # lane lines stop at crosswalks and stop lines
            if m.kind in ('crosswalk', 'stop_line'):
                rows = layout.row(np.array([m.s0 - 0.5, m.s1 + 0.5]))
                for k, ln in enumerate(lines):
                    if ln.kind != 'edge':
                        self.contrast[k, rows[0]:rows[1] + 1] = 0.0
        self._marking_s0 = np.array([m.s0 for m in self.markings])
        self._marking_s1 = np.array([m.s1 for m in self.markings])

    def lookup(self, s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Paint at road coordinates -> (kind NONE/LINE/MARKING, contrast 0-1, line index)."""
        n = s.shape[0]
        kind = np.zeros(n, dtype=np.int8)
        contrast = np.zeros(n, dtype=np.float32)
        line = np.full(n, -1, dtype=np.int32)
        if len(self.layout.lines):
            i, w = self.ref.index(s)
            off = self.offset[:, i] * (1.0 - w) + self.offset[:, i + 1] * w  # (L, N)
            near = np.abs(d[None, :] - off) <= self.half_width[:, None]
            cand_l, cand_p = np.nonzero(near)  # NaN offsets (no line) compare False
            if cand_p.size:
                ip, wp = i[cand_p], w[cand_p]
                arc = self.arc[cand_l, ip] * (1.0 - wp) + self.arc[cand_l, ip + 1] * wp
                on, off_len = self.dash_on[cand_l, ip], self.dash_off[cand_l, ip]
                period = np.where(off_len > 0, on + off_len, 1.0)
                dash = (off_len <= 0) | (np.mod(arc, period) < on)
                c = self.contrast[cand_l, ip] * dash
                painted = c > 0
                kind[cand_p[painted]] = LINE
                contrast[cand_p[painted]] = c[painted]
                line[cand_p[painted]] = cand_l[painted]
        if self.markings:
            smin, smax = float(s.min()), float(s.max())
            for k in np.flatnonzero((self._marking_s1 >= smin) & (self._marking_s0 <= smax)):
                m = self.markings[k]
                iu = np.floor((s - m.s0) / STENCIL_RES).astype(np.intp)
                iv = np.floor((d - m.v0) / STENCIL_RES).astype(np.intp)
                nu, nv = m.mask.shape
                inside = (iu >= 0) & (iu < nu) & (iv >= 0) & (iv < nv) & (kind == NONE)
                idx = np.flatnonzero(inside)
                hit = idx[m.mask[iu[idx], iv[idx]]]
                kind[hit] = MARKING
                contrast[hit] = m.contrast
        return kind, contrast, line

    def polylines(self, step_m: float = 0.5) -> list[np.ndarray]:
        """GT: (K, 3) world polylines through each stripe centre, on the road plane."""
        out = []
        stride = max(1, int(round(step_m / DS)))
        for ln in self.layout.lines:
            rows = np.arange(ln.i0, ln.i1 + 1, stride)
            if rows[-1] != ln.i1:
                rows = np.append(rows, ln.i1)
            s = self.ref.s0 + rows * DS
            out.append(self.ref.to_world(s, ln.offset[rows - ln.i0]))
        return out


def _smooth_noise(rng: np.random.Generator, n: int, knot_rows: int) -> np.ndarray:
    """Smooth noise in [-1, 1] over n table rows, knots every knot_rows rows."""
    knots = rng.uniform(-1.0, 1.0, n // knot_rows + 2)
    return np.interp(np.arange(n) / knot_rows, np.arange(knots.size), knots)


def _wear_profile(rng: np.random.Generator, n: int, wear: float) -> np.ndarray:
    """Paint contrast along a line: 1 fresh, lower when worn, 0 in worn-through gaps."""
    coarse = _smooth_noise(rng, n, int(4.0 / DS))
    fine = _smooth_noise(rng, n, 2)
    c = 1.0 - wear * (0.55 + 0.35 * coarse + 0.3 * fine)
    c = np.clip(c, 0.0, 1.0)
    c[c < 0.2] = 0.0
    return c.astype(np.float32)


def _lane_span(layout: Layout, k: int, row: int) -> tuple[float, float]:
    return float(layout.offsets[k + 1, row]), float(layout.offsets[k, row])


def _place_markings(rng: np.random.Generator, layout: Layout, road_class: str) -> list[Marking]:
    """Distractors along the road: crosswalks with stop lines (urban), arrows, text."""
    marks: list[Marking] = []
    if not layout.style.marked:
        return marks
    s = layout.s
    lanes = layout.lane_indices(1)
    fresh = lambda: float(rng.uniform(0.5, 1.0))  # noqa: E731
    pos = s[0] + rng.uniform(20, 120)
    spacing = {'urban': (120, 350), 'highway': (250, 600), 'rural': (250, 700)}[road_class]
    while pos < s[-1] - 60:
        row = layout.row(pos)
        open_lanes = [k for k in lanes if layout.drivable(k)[row]]
        kind = rng.choice(['crosswalk', 'arrows', 'text'], p=(
            [0.35, 0.45, 0.2] if road_class == 'urban' else [0.0, 0.7, 0.3]))
        if kind == 'crosswalk':
            left, right = layout.offsets[0, row], layout.offsets[-1, row]
            length = rng.uniform(3.0, 4.0)
            bars = bars_stencil(length, left - right, period=rng.uniform(1.0, 1.3))
            marks.append(Marking('crosswalk', pos, right, bars, fresh()))
            if open_lanes:  # stop line across the ego-direction lanes before it
                lo, hi = _lane_span(layout, open_lanes[-1], row)[0], _lane_span(
                    layout, open_lanes[0], row)[1]
                bar = bars_stencil(rng.uniform(0.3, 0.5), hi - lo)
                marks.append(Marking('stop_line', pos - rng.uniform(1.5, 3.0) - 0.5, lo, bar,
                                     fresh()))
        elif open_lanes:
            k = open_lanes[rng.integers(len(open_lanes))]
            lo, hi = _lane_span(layout, k, row)
            centre = 0.5 * (lo + hi)
            if kind == 'arrows':
                which = rng.choice(['straight', 'left', 'right', 'straight_left',
                                    'straight_right'])
                st = arrow_stencil(str(which))
            else:
                st = text_stencil(str(rng.choice(WORDS)))
            marks.append(Marking(str(kind), pos, centre - st.shape[1] * STENCIL_RES / 2, st,
                                 fresh()))
        pos += rng.uniform(*spacing)
    return marks
