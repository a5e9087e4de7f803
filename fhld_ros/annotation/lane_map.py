"""The lane map of a drive: the 3D lanes of all its labelled images (one frame, the odometry's)
merged so that one physical line seen from many images becomes one polyline
(docs/annotation.md, "Training bags: --lane-map").

1. **Groups.** Every lane is resampled every STEP_M. Over the overlap of two lanes (the points
   of one within OVERLAP_M of the other, point to segment, in top view, at least MIN_OVERLAP_M
   long) their distance is the median distance. Two lanes are pieces of one line when each is
   the other's nearest among the lanes of its image and they are at most MERGE_TOL_M apart. The
   pieces of one line agree within a few centimetres where the lift is good and within
   decimetres where it is not (labels a few pixels off, far lines shaded from the LiDAR); the
   stripes of a double line (0.2-0.33 m apart, centre to centre) stay apart because an image
   that labels both offers the nearer one, and lanes of one image never end in one group
   (pairs are joined nearest first, skipping a join that would). A group of fewer than
   MIN_IMAGES images is dropped (a lift gone wrong matches no other image: a line the car
   passes is in many).
2. **Fusion.** A group's lanes are placed along a reference: its longest lane, extended by the
   others where they run past its ends. Every point of the group gets a station along the
   reference, an offset across it and a height; per STEP_M of station the median offset and
   height (robust to a bad piece) give the line's point, weighted by 1 / range^2 from the
   camera that saw it (a label's pixel error grows on the road with range). Stations no lane
   covers split the line: gaps where nothing was seen stay gaps.
3. **Joining.** Fused lines whose ends meet within JOIN_GAP_M, heading the same way and in
   line, are one line (pieces that touch without overlapping enough to be grouped).
"""
from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.spatial import cKDTree

from fhld_ros.geometry import resample_polyline

STEP_M = 0.5  # lanes are compared and fused at this spacing (autolabel's own)
OVERLAP_M = 0.6  # a point this close to another lane lies beside it
MERGE_TOL_M = 0.3  # the most two pieces of one line may lie apart (median over the overlap)
MIN_OVERLAP_M = 2.0
REF_SMOOTH_M = 1.0  # the reference is averaged over this length: joins are not kinks
JOIN_GAP_M = 1.0
JOIN_COS = np.cos(np.radians(15.0))
JOIN_ACROSS_M = 0.15  # a line continues another when it starts this close to its extension
MIN_LINE_M = 1.0  # shorter fused pieces are dropped
MIN_IMAGES = 3
NEAR_M = 5.0  # points nearer their camera than this weigh as much as at this range
CHUNK_POINTS = 5_000  # query points per pairing pass: ~0.5M pairs, ~50 MB at once


@dataclass
class MapLine:
    points: np.ndarray  # (K, 3) every STEP_M
    label_id: int  # the label id most of its pieces carry
    support: np.ndarray  # (K,) how many lane points were fused into each point


def build_lane_map(lanes: list[np.ndarray], label_ids: list[int] | None = None,
                   images: list[int] | None = None,
                   origins: list[np.ndarray] | None = None) -> list[MapLine]:
    """The merged lines of lanes ((K, 3) polylines in one frame; see the module doc). images:
    the image of each lane (default: each lane its own); origins: the (x, y) of the camera
    that saw each lane (default: all points weigh the same)."""
    label_ids = list(label_ids) if label_ids is not None else [0] * len(lanes)
    images = list(images) if images is not None else list(range(len(lanes)))
    keep = [k for k, lane in enumerate(lanes) if len(lane) >= 2]
    dense = [resample_polyline(np.asarray(lanes[k], dtype=np.float64), STEP_M) for k in keep]
    if not dense:
        return []
    groups = group_lanes(dense, np.unique([images[k] for k in keep], return_inverse=True)[1])
    out = []
    for g in range(groups.max() + 1):
        members = np.flatnonzero(groups == g)
        if len({images[keep[k]] for k in members}) < MIN_IMAGES:
            continue
        ids = Counter(label_ids[keep[k]] for k in members)
        seen_from = None if origins is None else [origins[keep[k]][:2] for k in members]
        for points, support in fuse_group([dense[k] for k in members], seen_from):
            out.append(MapLine(points, ids.most_common(1)[0][0], support))
    return join_lines(out)


def group_lanes(lanes: list[np.ndarray], images: np.ndarray) -> np.ndarray:
    """(L,) group of each lane (resampled every STEP_M; images: (L,) the image of each, 0..):
    pieces of one line share a group."""
    a, b, dist, count = _pair_distances(lanes)
    n = len(lanes)
    ok = count * STEP_M >= MIN_OVERLAP_M
    same = ok & (images[a] == images[b])  # two lines of one image: never one group
    apart = a[same], b[same]
    ok &= ~same
    a, b, dist = a[ok], b[ok], dist[ok]
    # each lane's nearest lane of every other image, if close enough
    order = np.lexsort((dist, images[b], a))
    key = a[order] * (images.max() + 1) + images[b[order]]
    first = order[np.diff(key, prepend=-1) != 0]
    a, b, dist = a[first], b[first], dist[first]
    close = dist <= MERGE_TOL_M
    a, b, dist = a[close], b[close], dist[close]
    mutual = np.isin(b * n + a, a * n + b)
    order = np.argsort(dist[mutual], kind='stable')
    return _union(n, a[mutual][order], b[mutual][order], *apart)


def _union(n: int, a: np.ndarray, b: np.ndarray, apart_a: np.ndarray, apart_b: np.ndarray
           ) -> np.ndarray:
    """(n,) group of each of n lanes joined along the edges (a, b), nearest first, except where
    the two groups would hold lanes (apart_a, apart_b) that must stay apart (a loop over
    edges: a group's members and the lanes it excludes are sets)."""
    group = list(range(n))
    members = [{k} for k in range(n)]
    excluded = [set() for _ in range(n)]
    for x, y in zip(apart_a.tolist(), apart_b.tolist()):
        excluded[x].add(y)
        excluded[y].add(x)
    for x, y in zip(a.tolist(), b.tolist()):
        gx, gy = group[x], group[y]
        if gx == gy or not excluded[gx].isdisjoint(members[gy]):
            continue
        if len(members[gx]) < len(members[gy]):
            gx, gy = gy, gx
        for k in members[gy]:
            group[k] = gx
        members[gx] |= members[gy]
        excluded[gx] |= excluded[gy]
        members[gy], excluded[gy] = set(), set()
    return np.unique(group, return_inverse=True)[1]


def _pair_distances(lanes: list[np.ndarray]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, median distance, points) of every ordered pair of lanes where lane a runs
    beside lane b: the median over a's points within OVERLAP_M of b, and how many they are."""
    n = len(lanes)
    sizes = np.array([len(lane) for lane in lanes])
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    lane_of = np.repeat(np.arange(n), sizes)
    xy = np.concatenate(lanes)[:, :2]
    # segments from each point to the next of its lane, found through their midpoints
    seg = np.flatnonzero(lane_of[:-1] == lane_of[1:])
    start, d = xy[seg], xy[seg + 1] - xy[seg]
    tree = cKDTree(start + d / 2)
    reach = OVERLAP_M + float(np.linalg.norm(d, axis=1).max(initial=0.0)) / 2
    parts = []
    first = 0
    while first < n:  # chunks of whole lanes: a pair's points all lie in one chunk
        last = max(first + 1, int(np.searchsorted(bounds, bounds[first] + CHUNK_POINTS,
                                                  side='right')) - 1)
        q = xy[bounds[first]:bounds[last]]
        pairs = cKDTree(q).sparse_distance_matrix(tree, reach, output_type='ndarray')
        p, s = pairs['i'].astype(np.int64) + bounds[first], pairs['j'].astype(np.int64)
        other = lane_of[seg[s]]
        apart = other != lane_of[p]
        p, s, other = p[apart], s[apart], other[apart]
        t = np.clip(np.einsum('ij,ij->i', xy[p] - start[s], d[s]) /
                    np.maximum(np.einsum('ij,ij->i', d[s], d[s]), 1e-12), 0.0, 1.0)
        dist = np.linalg.norm(xy[p] - start[s] - t[:, None] * d[s], axis=1)
        # each point's distance to each other lane: the nearest of that lane's segments
        key = p * n + other
        order = np.lexsort((dist, key))
        near = order[np.diff(key[order], prepend=-1) != 0]
        near = near[dist[near] <= OVERLAP_M]
        parts.append(_group_medians(lane_of[p[near]] * n + other[near], dist[near]))
        first = last
    keys = np.concatenate([k for k, _, _ in parts])
    return (keys // n, keys % n, np.concatenate([m for _, m, _ in parts]),
            np.concatenate([c for _, _, c in parts]))


def _group_medians(keys: np.ndarray, values: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique keys, the median of their values and their counts."""
    order = np.lexsort((values, keys))
    keys, values = keys[order], values[order]
    starts = np.flatnonzero(np.diff(keys, prepend=-1) != 0)
    counts = np.diff(np.append(starts, len(keys)))
    mid = (values[starts + (counts - 1) // 2] + values[starts + counts // 2]) / 2
    return keys[starts], mid, counts


class _Polyline:
    """Stations and offsets of points along a polyline (x, y), through its nearest vertex."""

    def __init__(self, xy: np.ndarray) -> None:
        self.xy = xy
        self.station = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0),
                                                                      axis=1))])
        tangent = np.gradient(xy, axis=0) if len(xy) > 1 else np.array([[1.0, 0.0]])
        self.tangent = tangent / np.maximum(np.linalg.norm(tangent, axis=1), 1e-12)[:, None]
        self.normal = np.column_stack([-self.tangent[:, 1], self.tangent[:, 0]])  # left
        self.tree = cKDTree(xy)

    @property
    def length(self) -> float:
        return float(self.station[-1])

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(station, offset to the left) of each point; past the ends along the end tangent."""
        _, v = self.tree.query(xy)
        rel = xy - self.xy[v]
        return (self.station[v] + np.einsum('ij,ij->i', rel, self.tangent[v]),
                np.einsum('ij,ij->i', rel, self.normal[v]))

    def at(self, station: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """Points at the given stations and offsets."""
        x = np.interp(station, self.station, self.xy[:, 0])
        y = np.interp(station, self.station, self.xy[:, 1])
        nx = np.interp(station, self.station, self.normal[:, 0])
        ny = np.interp(station, self.station, self.normal[:, 1])
        norm = np.maximum(np.hypot(nx, ny), 1e-12)
        return np.column_stack([x + offset * nx / norm, y + offset * ny / norm])


def _reference(lanes: list[np.ndarray]) -> _Polyline:
    """The group's longest lane, extended by each further lane where it runs past the ends.
    Lanes go in breadth-first order of overlap; one that does not overlap the reference yet
    (it overlaps a lane placed later) waits for the next pass."""
    order = _overlap_order(lanes)
    ref = lanes[order[0]][:, :2]
    pending = order[1:]
    while pending:
        waiting = []
        for k in pending:
            extended = _extend(ref, lanes[k][:, :2])
            if extended is None:
                waiting.append(k)
            else:
                ref = extended
        if len(waiting) == len(pending):
            break  # overlap nothing placed: their points count where they lie beside it
        pending = waiting
    smooth = max(1, int(round(REF_SMOOTH_M / STEP_M)) | 1)
    return _Polyline(uniform_filter1d(ref, smooth, axis=0, mode='nearest'))


def _extend(ref: np.ndarray, xy: np.ndarray) -> np.ndarray | None:
    """ref (x, y) extended by the parts of lane xy past its ends; None when xy runs beside
    ref over fewer than two points."""
    line = _Polyline(ref)
    s, off = line.project(xy)
    inside = np.flatnonzero((s >= 0) & (s <= line.length) & (np.abs(off) <= OVERLAP_M))
    if len(inside) < 2:
        return None
    if s[inside[-1]] < s[inside[0]]:  # runs the other way: turn it
        xy, s, inside = xy[::-1], s[::-1], len(xy) - 1 - inside[::-1]
    head, tail = xy[:inside[0]], xy[inside[-1] + 1:]
    return np.concatenate([head[s[:inside[0]] < 0], ref, tail[s[inside[-1] + 1:] > line.length]])


def _overlap_order(lanes: list[np.ndarray]) -> list[int]:
    """Breadth-first order from the longest lane over lanes whose top views overlap."""
    lengths = [float(np.linalg.norm(np.diff(lane[:, :2], axis=0), axis=1).sum())
               for lane in lanes]
    lane_of = np.repeat(np.arange(len(lanes)), [len(lane) for lane in lanes])
    tree = cKDTree(np.concatenate(lanes)[:, :2])
    start = int(np.argmax(lengths))
    seen, order, queue = {start}, [], deque([start])
    while queue:
        k = queue.popleft()
        order.append(k)
        hits = tree.query_ball_point(lanes[k][:, :2], OVERLAP_M, return_sorted=False)
        for j in np.unique(lane_of[np.concatenate([np.asarray(h, dtype=np.int64)
                                                   for h in hits])]):
            if int(j) not in seen:
                seen.add(int(j))
                queue.append(int(j))
    return order + [k for k in range(len(lanes)) if k not in seen]


def fuse_group(lanes: list[np.ndarray], origins: list[np.ndarray] | None = None
               ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (points, support) pieces of one line from its lanes (see the module doc); origins:
    the (x, y) each lane was seen from, whose nearer points then weigh more."""
    ref = _reference(lanes)
    fine = [resample_polyline(lane, STEP_M / 2) for lane in lanes]
    pts = np.concatenate(fine)
    weight = np.ones(len(pts))
    if origins is not None:  # a label's pixel error grows on the road with range squared
        seen_from = np.repeat(np.asarray(origins, dtype=np.float64).reshape(-1, 2),
                              [len(f) for f in fine], axis=0)
        weight = np.maximum(np.linalg.norm(pts[:, :2] - seen_from, axis=1), NEAR_M) ** -2
    s, off = ref.project(pts[:, :2])
    use = np.abs(off) <= OVERLAP_M  # a piece that leaves the line there is not it
    s, off, z, weight = s[use], off[use], pts[use, 2], weight[use]
    bins = np.floor(s / STEP_M).astype(np.int64)
    index, support = np.unique(bins, return_counts=True)
    fused_s, fused_off, fused_z = (_weighted_medians(bins, v, weight) for v in (s, off, z))
    xyz = np.column_stack([ref.at(fused_s, fused_off), fused_z])
    runs = np.split(np.arange(len(index)), np.flatnonzero(np.diff(index) > 1) + 1)
    return [(xyz[run], support[run]) for run in runs
            if len(run) >= 2 and fused_s[run[-1]] - fused_s[run[0]] >= MIN_LINE_M]


def _weighted_medians(bins: np.ndarray, values: np.ndarray, weights: np.ndarray
                      ) -> np.ndarray:
    """Per bin (ascending), the weighted median of its values: the first value, in value
    order, by which half its weight is reached."""
    order = np.lexsort((values, bins))
    bins, values, weights = bins[order], values[order], weights[order]
    starts = np.flatnonzero(np.diff(bins, prepend=bins[0] - 1) != 0)
    counts = np.diff(np.append(starts, len(bins)))
    cum = np.cumsum(weights)
    before = np.repeat(cum[starts] - weights[starts], counts)
    total = np.repeat(np.add.reduceat(weights, starts), counts)
    below = (cum - before) < total / 2  # False from the median on, within each bin
    return values[starts + np.add.reduceat(below.astype(np.int64), starts)]


def join_lines(lines: list[MapLine]) -> list[MapLine]:
    """Lines whose end meets another's start (within JOIN_GAP_M, heading the same way and in
    line within JOIN_ACROSS_M) joined into one."""
    lines = list(lines)
    joined = True
    while joined:
        joined = False
        for a in range(len(lines)):
            end = lines[a].points
            heading = _unit(end[-1, :2] - end[-2, :2])
            for b in range(len(lines)):
                start = lines[b].points
                gap = start[0, :2] - end[-1, :2]
                if a == b or np.linalg.norm(gap) > JOIN_GAP_M or \
                        heading @ _unit(start[1, :2] - start[0, :2]) < JOIN_COS or \
                        abs(heading[0] * gap[1] - heading[1] * gap[0]) > JOIN_ACROSS_M:
                    continue
                ahead = (start[:, :2] - end[-1, :2]) @ heading > 0  # not back over a
                lines[a] = MapLine(np.concatenate([end, start[ahead]]), lines[a].label_id,
                                   np.concatenate([lines[a].support, lines[b].support[ahead]]))
                del lines[b]
                joined = True
                break
            if joined:
                break
    return lines


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)
