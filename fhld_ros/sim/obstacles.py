"""Things that stand on the ground: buildings, vegetation, poles, barriers and vehicles.

Three primitives cover them all: oriented boxes (buildings, barriers, vehicle bodies), vertical
cylinders (poles, trunks) and spheres (tree crowns, porous to the beam). Static objects are
placed once along the road; vehicles follow lane centres at constant speed and are turned
into boxes at any time t, never overlapping the ego's planned path or each other.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fhld_ros.sim.layout import LANE, PARKING, Layout
from fhld_ros.sim.road import DS, ReferenceLine
from fhld_ros.sim.scene import Surface

VEHICLE, BUILDING, VEGETATION, POLE, BARRIER, EGO = 10, 11, 12, 13, 14, 15

# vehicle types: parts as (length, width, z0, z1, forward offset) of the box, plus mass share
VEHICLE_TYPES = {
    'car': [(4.5, 1.8, 0.25, 1.0, 0.0), (2.4, 1.6, 1.0, 1.5, -0.3)],
    'suv': [(4.8, 1.95, 0.3, 1.15, 0.0), (3.0, 1.8, 1.15, 1.8, -0.3)],
    'van': [(5.4, 2.05, 0.3, 2.3, 0.0)],
    'truck': [(2.3, 2.5, 0.4, 3.0, 4.6), (8.5, 2.55, 0.9, 3.9, -1.0)],
    'bus': [(12.0, 2.55, 0.3, 3.2, 0.0)],
}
TYPE_NAMES = tuple(VEHICLE_TYPES)
TYPE_P = (0.55, 0.2, 0.1, 0.1, 0.05)


@dataclass
class Boxes:
    centre: np.ndarray  # (n, 3) world centre
    rot: np.ndarray  # (n, 3, 3) box axes (columns) in world
    half: np.ndarray  # (n, 3) half extents
    material: np.ndarray  # (n,) uint8
    rho: np.ndarray  # (n,) diffuse reflectance

    @staticmethod
    def empty() -> Boxes:
        return Boxes(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)),
                     np.zeros(0, np.uint8), np.zeros(0))

    def __len__(self) -> int:
        return self.centre.shape[0]

    def concat(self, other: Boxes) -> Boxes:
        return Boxes(*(np.concatenate([a, b]) for a, b in zip(
            (self.centre, self.rot, self.half, self.material, self.rho),
            (other.centre, other.rot, other.half, other.material, other.rho))))


@dataclass
class Cylinders:
    base: np.ndarray  # (n, 3) axis foot (x, y, z0)
    height: np.ndarray  # (n,)
    radius: np.ndarray  # (n,)
    material: np.ndarray
    rho: np.ndarray


@dataclass
class Spheres:
    centre: np.ndarray  # (n, 3)
    radius: np.ndarray
    material: np.ndarray
    rho: np.ndarray
    porosity: np.ndarray  # share of beams that pass through


def yaw_boxes(xy: np.ndarray, z0: np.ndarray, z1: np.ndarray, yaw: np.ndarray,
              length: np.ndarray, width: np.ndarray, material: int | np.ndarray,
              rho: np.ndarray) -> Boxes:
    """Upright boxes from footprint centre, yaw, size and vertical extent."""
    n = xy.shape[0]
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.zeros((n, 3, 3))
    rot[:, 0, 0], rot[:, 1, 0], rot[:, 0, 1], rot[:, 1, 1], rot[:, 2, 2] = c, s, -s, c, 1.0
    centre = np.column_stack([xy, 0.5 * (z0 + z1)])
    half = np.column_stack([0.5 * length, 0.5 * width, 0.5 * (z1 - z0)])
    return Boxes(centre, rot, half, np.broadcast_to(np.asarray(material, np.uint8), (n,)).copy(),
                 np.asarray(rho, dtype=np.float64).reshape(n))


@dataclass
class StaticObjects:
    boxes: Boxes
    cylinders: Cylinders
    spheres: Spheres


def _along(rng: np.random.Generator, s0: float, s1: float, gap: tuple[float, float]
           ) -> np.ndarray:
    """Positions from s0 to s1 with random gaps."""
    n = int((s1 - s0) / gap[0]) + 2
    pos = s0 + np.cumsum(rng.uniform(*gap, n))
    return pos[pos < s1]


def place_static(rng: np.random.Generator, ref: ReferenceLine, layout: Layout,
                 surface: Surface, road_class: str) -> StaticObjects:
    """Buildings, trees, poles and barriers along both sides of the road."""
    s_lo, s_hi = ref.s0 + 5.0, ref.s_end - 5.0
    left_edge, right_edge = layout.paved_extent()
    boxes = Boxes.empty()
    cyl: list[tuple] = []  # (s, d, height, radius, material, rho)
    sph: list[tuple] = []  # (s, d, z above ground, radius, rho, porosity)

    def edge(side: int, s: np.ndarray) -> np.ndarray:
        rows = layout.row(s)
        return left_edge[rows] if side > 0 else right_edge[rows]

    def roadside_boxes(s: np.ndarray, length: np.ndarray, d_near: np.ndarray, depth: np.ndarray,
                       z0: np.ndarray, z1: np.ndarray, side: int, material: int,
                       rho: np.ndarray) -> Boxes:
        mid = s + 0.5 * length
        d = d_near + side * 0.5 * depth
        xy = ref.to_world(mid, d)[:, :2]
        ground = surface.height(mid, d)
        yaw = ref.sample(mid)[:, 2]
        return yaw_boxes(xy, ground + z0, ground + z1, yaw, length, depth, material, rho)

    for side in (1, -1):  # +1 left, -1 right
        rs = surface.sides[0 if side > 0 else 1]
        setback = rs.walk_w + rs.verge_w
        if road_class == 'urban':
            s = _along(rng, s_lo, s_hi, (10.0, 32.0))
            s = s[rng.random(s.size) < 0.8]
            length = rng.uniform(8.0, 25.0, s.size)
            depth = rng.uniform(8.0, 18.0, s.size)
            near = edge(side, s) + side * (setback + rng.uniform(0.2, 4.0, s.size))
            height = rng.uniform(4.0, 30.0, s.size)
            boxes = boxes.concat(roadside_boxes(s, length, near, depth, -0.5, height, side,
                                                BUILDING, rng.uniform(0.15, 0.5, s.size)))
            for st in _along(rng, s_lo, s_hi, (8.0, 18.0)):  # street trees in the sidewalk
                if rng.random() < 0.6:
                    d = float(edge(side, np.array([st]))[0]) + side * rng.uniform(0.6, 1.0)
                    cyl.append((st, d, rng.uniform(2.0, 3.0), rng.uniform(0.12, 0.25),
                                VEGETATION, 0.25))
                    sph.append((st, d, rng.uniform(3.5, 5.5), rng.uniform(1.5, 3.0),
                                rng.uniform(0.3, 0.5), rng.uniform(0.2, 0.5)))
            for st in _along(rng, s_lo, s_hi, (25.0, 40.0)):  # street lights
                d = float(edge(side, np.array([st]))[0]) + side * 0.4
                cyl.append((st, d, rng.uniform(6.0, 9.0), 0.1, POLE, 0.35))
            continue
        if road_class == 'highway':
            s = np.arange(s_lo, s_hi, 12.0)
            length = np.full(s.size, 12.3)
            if side > 0:  # concrete median barrier
                near = edge(side, s) + 0.3
                boxes = boxes.concat(roadside_boxes(s, length, near, np.full(s.size, 0.6), 0.0,
                                                    0.9, side, BARRIER, np.full(s.size, 0.35)))
            else:  # steel guardrail: a beam on posts, rays below it pass
                near = edge(side, s) - 0.5
                boxes = boxes.concat(roadside_boxes(s, length, near, np.full(s.size, 0.25),
                                                    0.45, 0.78, side, BARRIER,
                                                    np.full(s.size, 0.45)))
                for st in s[rng.random(s.size) < 0.15]:  # lamp posts / sign posts
                    d = float(edge(side, np.array([st]))[0]) - 1.2
                    cyl.append((st, d, rng.uniform(4.0, 10.0), 0.12, POLE, 0.35))
        else:  # rural utility poles
            for st in _along(rng, s_lo, s_hi, (35.0, 60.0)):
                d = float(edge(side, np.array([st]))[0]) + side * rng.uniform(2.0, 5.0)
                cyl.append((st, d, rng.uniform(7.0, 10.0), 0.15, POLE, 0.2))
        # trees and bushes further out
        for st in _along(rng, s_lo, s_hi, (4.0, 25.0)):
            d = float(edge(side, np.array([st]))[0]) + side * (setback + rng.uniform(4.0, 25.0))
            r = rng.uniform(1.0, 4.0)
            if r > 2.0:
                cyl.append((st, d, r + 1.0, rng.uniform(0.15, 0.4), VEGETATION, 0.25))
            sph.append((st, d, r + (1.0 if r > 2.0 else 0.2), r, rng.uniform(0.3, 0.55),
                        rng.uniform(0.1, 0.5)))
    return StaticObjects(boxes, _cylinders(ref, surface, cyl), _spheres(ref, surface, sph))


def _cylinders(ref: ReferenceLine, surface: Surface, items: list[tuple]) -> Cylinders:
    a = np.array(items, dtype=np.float64).reshape(-1, 6)
    xy = ref.to_world(a[:, 0], a[:, 1])[:, :2]
    z0 = surface.height(a[:, 0], a[:, 1]) - 0.2
    return Cylinders(np.column_stack([xy, z0]), a[:, 2] + 0.2, a[:, 3],
                     a[:, 4].astype(np.uint8), a[:, 5])


def _spheres(ref: ReferenceLine, surface: Surface, items: list[tuple]) -> Spheres:
    a = np.array(items, dtype=np.float64).reshape(-1, 6)
    xy = ref.to_world(a[:, 0], a[:, 1])[:, :2]
    z = surface.height(a[:, 0], a[:, 1]) + a[:, 2]
    return Spheres(np.column_stack([xy, z]), a[:, 3], np.full(len(a), VEGETATION, np.uint8),
                   a[:, 4], a[:, 5])


@dataclass
class Traffic:
    """Vehicles driving along lane centres: s(t) = s0 + v t in slot `lane`."""

    lane: np.ndarray  # (n,) slot index
    s0: np.ndarray
    v: np.ndarray  # signed speed along s
    kind: np.ndarray  # (n,) index into TYPE_NAMES
    rho: np.ndarray
    centres: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 0)))

    def boxes(self, ref: ReferenceLine, surface: Surface, t: float,
              near_xy: np.ndarray | None = None, radius: float = np.inf) -> Boxes:
        """All vehicle parts at time t (optionally only vehicles within radius of near_xy)."""
        if self.lane.size == 0:
            return Boxes.empty()
        s = self.s0 + self.v * t
        rows = np.clip(np.round((s - ref.s0) / DS).astype(int), 0, self.centres.shape[1] - 1)
        d = self.centres[self.lane, rows]
        xy = ref.to_world(s, d)[:, :2]
        keep = np.ones(s.size, dtype=bool)
        if near_xy is not None:
            keep = np.hypot(*(xy - near_xy).T) < radius
        out = Boxes.empty()
        heading = ref.sample(s)[:, 2] + np.where(self.v < 0, np.pi, 0.0)
        ground = surface.height(s, d)
        for k, name in enumerate(TYPE_NAMES):
            sel = keep & (self.kind == k)
            if not sel.any():
                continue
            for length, width, z0, z1, fwd in VEHICLE_TYPES[name]:
                c, sn = np.cos(heading[sel]), np.sin(heading[sel])
                pxy = xy[sel] + fwd * np.column_stack([c, sn])
                n = int(sel.sum())
                out = out.concat(yaw_boxes(pxy, ground[sel] + z0, ground[sel] + z1, heading[sel],
                                           np.full(n, length), np.full(n, width), VEHICLE,
                                           self.rho[sel]))
        return out


def place_traffic(rng: np.random.Generator, layout: Layout, ego_s: np.ndarray,
                  ego_d: np.ndarray, times: np.ndarray, ego_speed: float,
                  road_class: str) -> Traffic:
    """Vehicles in lanes that stay drivable along their whole path, clear of the ego's plan
    (sampled at `times`) and of each other (one speed per lane, gaps checked at t=0)."""
    centres = np.array([layout.lane_centre(k) for k in range(len(layout.slots))])
    spacing = {'highway': 45.0, 'urban': 30.0, 'rural': 120.0}[road_class]
    s_lo = float(ego_s.min()) - 150.0
    s_hi = float(ego_s.max()) + 150.0
    lanes, s0s, vs, kinds = [], [], [], []
    for k, slot in enumerate(layout.slots):
        if slot.kind == LANE:
            speed = slot.direction * max(ego_speed * rng.uniform(0.7, 1.25), 0.0)
            if ego_speed < 1.0 and slot.direction > 0:
                speed = 0.0
        elif slot.kind == PARKING:
            speed = 0.0
        else:
            continue
        pos = s_lo + rng.uniform(0, spacing)
        while pos < s_hi:
            kind = int(rng.choice(len(TYPE_NAMES), p=TYPE_P if slot.kind == LANE else
                                  (0.7, 0.25, 0.05, 0, 0)))
            length = VEHICLE_TYPES[TYPE_NAMES[kind]][0][0] + 4.0
            path = np.array([pos + speed * times[0], pos + speed * times[-1]])
            rows = layout.row(np.linspace(path.min() - length, path.max() + length, 64))
            drivable = slot.active[rows].all() and (slot.width[rows] >= 0.9 * slot.nominal).all()
            s_path = pos + speed * times
            d_path = centres[k, layout.row(s_path)]
            clear = ~((np.abs(s_path - ego_s) < 0.5 * length + 5.0) &
                      (np.abs(d_path - ego_d) < 2.6)).any()
            if drivable and clear and rng.random() < 0.75:
                lanes.append(k)
                s0s.append(pos)
                vs.append(speed)
                kinds.append(kind)
            pos += length + rng.exponential(spacing)
    rho = rng.uniform(0.05, 0.7, len(lanes))
    return Traffic(np.array(lanes, dtype=int), np.array(s0s), np.array(vs),
                   np.array(kinds, dtype=int), rho, centres)
