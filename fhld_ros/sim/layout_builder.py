"""Random road layouts: a base cross-section plus topology events, built slot by slot.

LayoutBuilder starts from a road class's lanes and shoulders and adds events as width changes
(see layout.py for the model); make_layout draws a layout with a few events that stays within
MAX_LINES_PER_WINDOW painted lines per detector window.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.sim.layout import (
    DASH_PATTERNS,
    GORE,
    LANE,
    MAX_LINES_PER_WINDOW,
    PARKING,
    SHOULDER,
    Layout,
    PaintStyle,
    Slot,
    TopologyEvent,
    max_lines_per_window,
    paint_lines,
)
from fhld_ros.sim.road import smoothstep


def _slot(kind: str, direction: int, width: float | np.ndarray, size: int,
          dotted: bool = False) -> Slot:
    w = np.broadcast_to(np.asarray(width, dtype=np.float64), (size,)).copy()
    no = np.zeros(size, dtype=bool)
    return Slot(kind, direction, w, np.ones(size, dtype=bool), no.copy(), no.copy(), dotted,
                float(np.max(w)))


def _ramp(s: np.ndarray, a: float, b: float) -> np.ndarray:
    return smoothstep((s - a) / max(b - a, 1e-6))


class LayoutBuilder:
    """Random cross-section and topology events for one road class."""

    def __init__(self, rng: np.random.Generator, s: np.ndarray, road_class: str,
                 n_lanes: int | None = None) -> None:
        self.rng, self.s, self.cls = rng, s, road_class
        self.size = s.shape[0]
        self.lane_w = rng.uniform(3.0, 3.9)
        self.events: list[TopologyEvent] = []
        r = rng
        marked = not (road_class == 'rural' and r.random() < 0.12)
        self.style = PaintStyle(
            dash=DASH_PATTERNS[r.integers(len(DASH_PATTERNS))],
            edge_width=r.uniform(0.15, 0.20), divider_width=r.uniform(0.10, 0.15),
            centre=r.choice(['double_solid', 'solid_dashed', 'dashed', 'solid'],
                            p=[0.45, 0.2, 0.25, 0.1]),
            centre_yellow=bool(r.random() < 0.6), double_gap=r.uniform(0.10, 0.18),
            marked=marked)
        self.slots: list[Slot] = []
        self.anchor = 0  # boundary index that stays at d = 0
        self._base_section(n_lanes)

    def _lane(self, direction: int) -> Slot:
        w = float(np.clip(self.lane_w + self.rng.normal(0, 0.08), 3.0, 3.9))
        return _slot(LANE, direction, w, self.size)

    def _base_section(self, n_lanes: int | None) -> None:
        r, size = self.rng, self.size
        if self.cls == 'highway':
            n = n_lanes or int(r.integers(2, 6))
            self.slots = [_slot(SHOULDER, 0, r.uniform(0.5, 1.2), size)]
            self.slots += [self._lane(1) for _ in range(n)]
            self.slots.append(_slot(SHOULDER, 0, r.uniform(1.5, 3.0), size))
            self.anchor = 1
            return
        two_way = self.cls == 'rural' or r.random() < 0.7
        if self.cls == 'rural':  # mostly one lane each way, sometimes a single-lane road
            n_opp, n_ego = (0, 1) if r.random() < 0.15 else (1, n_lanes or 1)
            edge = (SHOULDER, r.uniform(0.3, 1.0))
        else:
            n_ego = n_lanes or int(r.integers(1, 3) if two_way else r.integers(1, 4))
            n_opp = int(r.integers(1, 3)) if two_way else 0
            edge = (PARKING, 2.2) if r.random() < 0.5 else (SHOULDER, r.uniform(0.3, 0.6))
        self.slots = [_slot(edge[0], 0, edge[1], size)]
        self.slots += [self._lane(-1) for _ in range(n_opp)]
        self.anchor = len(self.slots)  # the centre line (or left edge of a one-way road)
        self.slots += [self._lane(1) for _ in range(n_ego)]
        self.slots.append(_slot(edge[0], 0, edge[1], size))

    # -- events --
    def _through_lanes(self, s_at: float) -> list[int]:
        """Ego-direction lanes open at s_at (not ramps): where new slots may attach."""
        row = min(int(np.searchsorted(self.s, s_at)), self.size - 1)
        return [k for k, sl in enumerate(self.slots)
                if sl.kind == LANE and sl.direction == 1 and not sl.ramp and sl.active[row]
                and sl.width[row] >= 0.5 * sl.nominal]

    def add_event(self, kind: str, s_start: float) -> float:
        """Insert a topology event starting at s_start; returns the s where it ends."""
        r, s = self.rng, self.s
        lanes = self._through_lanes(s_start)
        if not lanes:
            return s_start
        hwy = self.cls == 'highway'
        taper = r.uniform(60, 120) if hwy else r.uniform(30, 60)
        if kind in ('lane_added', 'lane_dropped'):
            side = 'left' if self.cls == 'rural' else 'right'
            w = self._lane(1)
            grow = _ramp(s, s_start, s_start + taper)
            w.width = w.nominal * (grow if kind == 'lane_added' else 1.0 - grow)
            w.dotted = hwy
            if side == 'right':  # the edge line bends out/in; the divider appears/ends
                w.hide_left = w.width < 0.5 * w.nominal
                self.slots.insert(len(self.slots) - 1, w)  # outermost, inside the shoulder
            else:  # next to the centre line, which stays put
                w.hide_right = w.width < 0.5 * w.nominal
                self.slots.insert(lanes[0], w)
            end = s_start + taper
        elif kind in ('split', 'merge'):
            side = 'middle'
            length = r.uniform(80, 150) if hwy else r.uniform(25, 50)
            w = self._lane(1)
            grow = _ramp(s, s_start, s_start + length)
            w.width = w.nominal * (grow if kind == 'split' else 1.0 - grow)
            w.hide_right = w.width < 0.05  # a Y: the new line starts on the kept one
            # between two lanes where possible, else left of the only lane (turn pocket)
            pos = lanes[int(r.integers(1, len(lanes)))] if len(lanes) > 1 else lanes[0]
            self.slots.insert(pos, w)
            end = s_start + length
        elif kind in ('exit_ramp', 'entrance_ramp'):
            side = 'right'
            end = self._ramp_event(kind, s_start, taper)
        else:
            raise ValueError(f'unknown topology {kind!r}')
        self.events.append(TopologyEvent(kind, float(s_start), float(end), side))
        return end

    def _ramp_event(self, kind: str, s_start: float, taper: float) -> float:
        """Exit lane (taper + parallel), then a gore opening to ~15 m until the ramp ends.

        Built for an exit and mirrored in s about its middle for an entrance."""
        r, s = self.rng, self.s
        parallel = r.uniform(60, 160)
        diverge = r.uniform(120, 180)
        gore_max = r.uniform(12, 16)
        total = taper + parallel + diverge
        # distance along the event in the exit's direction of travel
        u = (s - s_start) if kind == 'exit_ramp' else (s_start + total - s)
        nose = taper + parallel
        exit_lane = self._lane(1)
        exit_lane.dotted = exit_lane.ramp = True
        exit_lane.width = exit_lane.nominal * smoothstep(u / taper)
        # the opening between main road and ramp: first the main road's new shoulder, then
        # the gore; the ramp's left edge line starts at the nose on the dotted divider
        opening = gore_max * np.clip((u - nose) / diverge, 0, 1) ** 2
        shoulder_w = r.uniform(1.0, 2.0)
        main_sh = _slot(SHOULDER, 0, np.minimum(opening, shoulder_w), self.size)
        gore = _slot(GORE, 0, opening - main_sh.width, self.size)
        main_sh.ramp = gore.ramp = True
        # before the nose the dotted divider sits on main_sh's left boundary; the edge line
        # (the exit lane's right boundary) bends out during the taper
        main_sh.hide_left = exit_lane.width < 0.5 * exit_lane.nominal
        main_sh.hide_right = np.ones(self.size, dtype=bool)
        gore.hide_right = opening < 0.05
        gone = u > total  # the ramp has left the corridor
        outer = self.slots[-1]  # the right shoulder: the ramp's shoulder until it leaves
        for slot in (exit_lane, gore, outer):
            slot.active = slot.active & ~gone
        main_sh.width = np.where(gone, main_sh.width.max(), main_sh.width)
        # outermost, inside the right shoulder: lanes that exist elsewhere along the road
        # (dropped or added ones, narrow here) stay between the through lanes and the ramp
        self.slots[-1:-1] = [main_sh, gore, exit_lane]
        return s_start + total

    # -- result --
    def build(self, rng_paint: np.random.Generator) -> Layout:
        offsets = np.zeros((len(self.slots) + 1, self.size))
        width = [sl.width * sl.active for sl in self.slots]  # inactive slots take no space
        for j in range(self.anchor + 1, len(self.slots) + 1):
            offsets[j] = offsets[j - 1] - width[j - 1]
        for j in range(self.anchor - 1, -1, -1):
            offsets[j] = offsets[j + 1] + width[j]
        layout = Layout(float(self.s[0]), self.size, self.slots, offsets, list(self.events),
                        self.style)
        layout.lines = paint_lines(layout, rng_paint)
        return layout


RAMPS = ('exit_ramp', 'entrance_ramp')
EVENTS_BY_CLASS = {
    'highway': ('exit_ramp', 'entrance_ramp', 'lane_added', 'lane_dropped', 'split', 'merge'),
    'urban': ('split', 'merge', 'lane_added', 'lane_dropped'),
    'rural': ('lane_added', 'lane_dropped'),
}


def make_layout(rng: np.random.Generator, rng_paint: np.random.Generator, s: np.ndarray,
                road_class: str, s_first: float, s_last: float,
                topology: str | None = None) -> Layout:
    """Random layout of a road class with a few events (more on long roads), the first one
    near s_first (the ego's start) so that short runs see topology; at most
    MAX_LINES_PER_WINDOW lines per window; at most one ramp, after which only splits and
    merges (between through lanes) follow.

    ``topology`` forces the first event's kind (any class; ramps make it a highway)."""
    for attempt in range(30):
        builder = LayoutBuilder(rng, s, road_class)
        kinds = EVENTS_BY_CLASS[road_class]
        per_km = (s[-1] - s_first) / 1000.0  # long roads get more events
        n_events = int(rng.integers(0 if topology is None else 1, 4 + int(2 * per_km))
                       ) if attempt < 20 else 0
        pos = s_first + rng.uniform(-40.0, 120.0)
        if topology is not None:  # forced: its key part (a ramp's gore) just ahead
            pos = s_first + rng.uniform(-40.0, 40.0) - {'exit_ramp': 150.0,
                                                        'entrance_ramp': 60.0}.get(topology, 0.0)
        for k in range(n_events):
            kind = topology if (k == 0 and topology) else kinds[rng.integers(len(kinds))]
            if pos + 450.0 > s[-1]:
                break
            pos = builder.add_event(kind, pos) + rng.uniform(120.0, 400.0)
            if kind in RAMPS:  # the ramp's slots sit outermost: later events stay in the middle
                kinds = tuple(kd for kd in kinds if kd in ('split', 'merge'))
            if not kinds:
                break
        layout = builder.build(rng_paint)
        if max_lines_per_window(layout) <= MAX_LINES_PER_WINDOW and layout.lane_indices():
            return layout
    return layout
