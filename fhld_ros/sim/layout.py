"""Lateral road layout: slots (lanes, shoulders, parking, gores), topology events, lane lines.

The cross-section is an ordered list of slots from left to right, each with a width over the
s grid of the reference line. Boundary j separates slot j-1 and slot j; offsets are summed
outwards from an anchor boundary, so a slot that widens pushes everything on its far side.
Topology is nothing but width changes: a lane added/dropped at the edge is a tapering edge
slot, a split/merge is a slot opening/closing between two lanes (a Y of lines), an exit or
entrance ramp is an exit lane plus a gore that opens until the ramp leaves the corridor.
Which boundary carries paint while a slot is still narrow is stated by the event (hide
masks), and the line style follows from the slots on either side.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fhld_ros.sim.gt_lines import runs
from fhld_ros.sim.road import DS

LANE, SHOULDER, PARKING, GORE = 'lane', 'shoulder', 'parking', 'gore'
ROAD_CLASSES = ('highway', 'urban', 'rural')
TOPOLOGIES = ('split', 'merge', 'lane_added', 'lane_dropped', 'exit_ramp', 'entrance_ramp')
EPS_WIDTH = 0.02  # slots narrower than this are collapsed (their boundaries coincide)
MAX_LINES_PER_WINDOW = 8  # the detector's window (25.6 m) never holds more painted lines
DASH_PATTERNS = ((3.0, 6.0), (3.0, 9.0), (6.0, 9.0), (4.0, 8.0), (6.0, 12.0), (4.5, 7.5))
DOTTED_PATTERN = (1.0, 3.0)  # lane-drop / exit-lane dotted divider
# style codes of a boundary sample
NONE, EDGE, DIVIDER, CENTRE = 0, 1, 2, 3


@dataclass
class Slot:
    kind: str
    direction: int  # +1 the ego's direction, -1 oncoming, 0 not a traffic lane
    width: np.ndarray  # (M,) metres
    active: np.ndarray  # (M,) bool: part of the road at s
    hide_left: np.ndarray  # (M,) bool: no paint on this slot's left boundary
    hide_right: np.ndarray
    dotted: bool = False  # dividers next to this lane use the dotted pattern
    nominal: float = 0.0  # full width of a lane
    ramp: bool = False  # part of an exit/entrance ramp (no other event attaches to it)


@dataclass(frozen=True)
class TopologyEvent:
    kind: str
    s_start: float
    s_end: float
    side: str  # 'left' | 'right' | 'middle'


@dataclass(frozen=True)
class PaintStyle:
    """Per-road paint conventions."""

    dash: tuple[float, float]
    edge_width: float
    divider_width: float
    centre: str  # 'double_solid' | 'solid_dashed' | 'dashed' | 'solid'
    centre_yellow: bool
    double_gap: float
    marked: bool = True


@dataclass
class LaneLine:
    """One painted line (one stripe of a double line) over table rows i0..i1 (inclusive)."""

    id: int
    boundary: int
    i0: int
    i1: int
    offset: np.ndarray  # (i1 - i0 + 1,) lateral offset d of the stripe centre
    dash_on: np.ndarray  # (i1 - i0 + 1,) dash length, 0 where the line is solid
    dash_off: np.ndarray
    width: float
    yellow: bool
    kind: str  # 'edge' | 'divider' | 'centre'
    wear: float = 0.0
    phase: float = 0.0


@dataclass
class Layout:
    s0: float
    size: int
    slots: list[Slot]
    offsets: np.ndarray  # (n_slots + 1, M) boundary offsets
    events: list[TopologyEvent]
    style: PaintStyle
    lines: list[LaneLine] = field(default_factory=list)

    @property
    def s(self) -> np.ndarray:
        return self.s0 + DS * np.arange(self.size)

    def row(self, s: float | np.ndarray) -> np.ndarray:
        return np.clip(np.round((np.asarray(s) - self.s0) / DS), 0, self.size - 1).astype(int)

    def lane_indices(self, direction: int = 1) -> list[int]:
        return [k for k, slot in enumerate(self.slots)
                if slot.kind == LANE and slot.direction == direction]

    def lane_centre(self, k: int) -> np.ndarray:
        """(M,) offset of the centre of slot k."""
        return 0.5 * (self.offsets[k] + self.offsets[k + 1])

    def drivable(self, k: int) -> np.ndarray:
        """(M,) slot k is an active lane at (nearly) full width."""
        slot = self.slots[k]
        return slot.active & (slot.width >= 0.9 * slot.nominal) & (slot.kind == LANE)

    def paved_extent(self, taper: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
        """(M,) left and right offsets of the outermost active slots.

        Where a ramp leaves the corridor the pavement would stop at a cliff; instead the
        edge may move inwards by at most `taper` metres per metre (either direction of s)."""
        left = np.full(self.size, -np.inf)
        right = np.full(self.size, np.inf)
        for k, slot in enumerate(self.slots):
            on = slot.active & (slot.width > EPS_WIDTH)
            left = np.where(on, np.maximum(left, self.offsets[k]), left)
            right = np.where(on, np.minimum(right, self.offsets[k + 1]), right)
        ramp = taper * DS * np.arange(self.size)
        left = np.maximum(np.maximum.accumulate(left + ramp) - ramp,
                          np.maximum.accumulate((left - ramp)[::-1])[::-1] + ramp)
        right = np.minimum(np.minimum.accumulate(right - ramp) + ramp,
                           np.minimum.accumulate((right + ramp)[::-1])[::-1] - ramp)
        return left, right

    def gore_span(self) -> tuple[np.ndarray, np.ndarray]:
        """(M,) left/right offsets of an open gore (NaN where none)."""
        lo, hi = np.full(self.size, np.nan), np.full(self.size, np.nan)
        for k, slot in enumerate(self.slots):
            if slot.kind == GORE:
                on = slot.active & (slot.width > EPS_WIDTH)
                hi = np.where(on, self.offsets[k], hi)
                lo = np.where(on, self.offsets[k + 1], lo)
        return hi, lo


# --- construction -------------------------------------------------------------------------

# --- lines ---------------------------------------------------------------------------------

def _effective_neighbours(layout: Layout, j: int) -> tuple[np.ndarray, np.ndarray]:
    """(M,) index of the nearest open slot left/right of boundary j (-1 where none)."""
    n, size = len(layout.slots), layout.size
    open_ = np.array([sl.active & (sl.width > EPS_WIDTH) for sl in layout.slots])
    left = np.full(size, -1)
    for k in range(j - 1, -1, -1):
        left = np.where((left < 0) & open_[k], k, left)
    right = np.full(size, -1)
    for k in range(j, n):
        right = np.where((right < 0) & open_[k], k, right)
    return left, right


def _boundary_style(layout: Layout, j: int) -> tuple[np.ndarray, np.ndarray]:
    """(M,) style code and (M,) dotted flag of boundary j."""
    slots, size = layout.slots, layout.size
    left, right = _effective_neighbours(layout, j)
    kind = np.array([sl.kind for sl in slots] + ['none'])
    direction = np.array([sl.direction for sl in slots] + [0])
    dotted = np.array([sl.dotted for sl in slots] + [False])
    lk, rk = kind[left], kind[right]  # index -1 picks the 'none' sentinel
    l_lane, r_lane = lk == LANE, rk == LANE
    style = np.full(size, NONE)
    style[l_lane ^ r_lane] = EDGE
    both = l_lane & r_lane
    same = direction[left] == direction[right]
    style[both & same] = DIVIDER
    style[both & ~same] = CENTRE
    # hidden by an event: the boundary's own adjacent slots say so
    if j > 0:
        style[slots[j - 1].hide_right] = NONE
    if j < len(slots):
        style[slots[j].hide_left] = NONE
    # a boundary inside a collapsed group other than the one the neighbours see is hidden:
    # only the boundary right next to the nearest open slot on its left carries the paint
    collapsed_left = (left >= 0) & (left != j - 1)
    collapsed_right = (right >= 0) & (right != j)
    style[collapsed_left & collapsed_right] = NONE
    if not layout.style.marked:
        style[:] = NONE
    return style, dotted[left] | dotted[right]


def paint_lines(layout: Layout, rng: np.random.Generator) -> list[LaneLine]:
    st = layout.style
    lines: list[LaneLine] = []
    for j in range(len(layout.slots) + 1):
        style, dotted = _boundary_style(layout, j)
        for i0, stop in runs(style != NONE):
            i1 = stop - 1  # inclusive
            if (i1 - i0) * DS < 2.0:
                continue
            code = style[i0:i1 + 1]
            centre = code == CENTRE
            kind = 'centre' if centre.mean() > 0.5 else (
                'edge' if (code == EDGE).mean() > 0.5 else 'divider')
            d = layout.offsets[j, i0:i1 + 1]
            on = np.where(code == DIVIDER, np.where(dotted[i0:i1 + 1], DOTTED_PATTERN[0],
                                                   st.dash[0]), 0.0)
            off = np.where(code == DIVIDER, np.where(dotted[i0:i1 + 1], DOTTED_PATTERN[1],
                                                    st.dash[1]), 0.0)
            if kind == 'centre' and st.centre in ('double_solid', 'solid_dashed'):
                w = st.divider_width
                half = 0.5 * (w + st.double_gap)
                # left stripe dashed for 'solid_dashed' (passing allowed from the right)
                left_on = np.where(centre, st.dash[0] if st.centre == 'solid_dashed' else 0, on)
                left_off = np.where(centre, st.dash[1] if st.centre == 'solid_dashed' else 0,
                                    off)
                stripes = [(d + half, left_on, left_off), (d - half, np.where(centre, 0, on),
                                                           np.where(centre, 0, off))]
            else:
                if kind == 'centre' and st.centre == 'dashed':
                    on = np.where(centre, st.dash[0], on)
                    off = np.where(centre, st.dash[1], off)
                w = st.edge_width if kind == 'edge' else st.divider_width
                stripes = [(d, on, off)]
            for offset, don, doff in stripes:
                wear = float(rng.beta(1.2, 4.0)) if rng.random() < 0.85 else rng.uniform(0.5, 0.9)
                lines.append(LaneLine(
                    len(lines), j, i0, i1, offset.copy(), don.astype(float), doff.astype(float),
                    float(w), bool(kind == 'centre' and st.centre_yellow), kind, wear,
                    float(rng.uniform(0, 20.0))))
    return lines


def max_lines_per_window(layout: Layout, window_m: float = 30.0) -> int:
    """Largest number of lines whose s-range meets any window_m-long stretch of road."""
    half = int(np.ceil(0.5 * window_m / DS))
    delta = np.zeros(layout.size + 1, dtype=int)
    for line in layout.lines:
        delta[max(line.i0 - half, 0)] += 1
        delta[min(line.i1 + half + 1, layout.size)] -= 1
    return int(np.cumsum(delta).max()) if layout.lines else 0
