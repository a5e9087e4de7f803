"""Lane metrics of docs/design.md §6: the FHLD point metric and the ONCE-3DLanes lane metric.

Pure numpy/scipy, no ROS. Every function takes lanes as a list of (K, 3) polylines in the
*window frame* (x forward, y left, z up, metres, ego at the origin).

Point metric (FHLD paper, after DAGMapper): lanes are resampled densely (<= 2 cm spacing);
precision = share of predicted points within tau of a GT point, recall = share of GT points within
tau of a predicted point, 3D distances, tau = 10 cm and 30 cm, counts summed over frames.

ONCE-3DLanes lane metric, two modes:

* paper (`once_counts`): lanes drawn 1.5 m wide at 5 cm/px in top view, Hungarian assignment
  on 1 - IoU, pairs with IoU >= 0.3 are candidates, a candidate is a true positive when the
  unilateral chamfer distance GT -> prediction (mean over GT points of the 3D distance to the
  nearest predicted point) is <= 0.3 m. P = TP / #pred, R = TP / #GT, CD = mean CD of the TPs.
* official (`once_counts_official`): what the authors' released evaluator does, which differs
  from the paper. Lanes are first mapped to its camera frame (x right, y down, z forward):
  ``x_cam = -y, y_cam = -z, z_cam = x`` (`window_to_camera`). Then
  - predictions are kept when score > t (strict); GT lanes need >= 2 points, predictions do not;
  - IoU images are 1000 x 400 px (rows: forward 0..50 m, cols: lateral -10..10 m) at 5 cm/px, built
    from the lane's own vertices with forward < 10 m only (no resampling, so a sparse lane may lose
    every segment), joined by 30 px thick lines; pixel indices are truncated toward zero;
  - Hungarian on 1 - IoU assigns min(#GT, #pred) pairs and the 0.3 IoU threshold is never applied;
  - the CD of a pair samples 10 GT points at arc-length fractions 0.05, 0.15, ..., 0.95 and
    measures 2D point-to-polyline distances in the (x_cam, y_cam) lateral/height plane; arc
    length is measured in that plane as well, so the forward axis is ignored entirely;
  - TP when CD < 0.3 (strict); mean CD = sum / (TP + 1e-5).
  The thick lines approximate cv2.line (a capsule of radius thickness/2 around each segment).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from fhld_ros.geometry import resample_polyline

SAMPLE_STEP = 0.02  # m, dense resampling of the point metric (<= 2 cm)
POINT_THRESHOLDS = (0.10, 0.30)  # m
ONCE_IOU_THRESH = 0.3
ONCE_CD_THRESH = 0.3  # m
ONCE_LANE_WIDTH = 1.5  # m, top-view drawing width (paper mode)
ONCE_RES = 0.05  # m/px
# Released evaluator (cfg/eval.json of once_3dlanes_benchmark)
OFFICIAL_SIDE = 10.0  # m, lateral half range -> 400 px wide
OFFICIAL_FWD = 50.0  # m, forward range -> 1000 px tall
OFFICIAL_FWD_CUT = 10.0  # m, only vertices with z_cam < 10 are drawn
OFFICIAL_THICKNESS = 30  # px
OFFICIAL_FRACTIONS = np.arange(0.05, 1.0, 0.1)

Lanes = Sequence[np.ndarray]


# --- geometry -----------------------------------------------------------------------------

def resample_lanes(lanes: Lanes, step: float = SAMPLE_STEP) -> np.ndarray:
    """All lanes resampled and stacked, (N, 3)."""
    parts = [resample_polyline(lane, step) for lane in lanes]
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def clip_polyline_to_square(points: np.ndarray, half_size: float) -> list[np.ndarray]:
    """The parts of a polyline with |x|, |y| <= half_size, split where it leaves the square.

    Liang-Barsky on every segment at once; z is interpolated along the cut segments.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return []
    if len(pts) == 1:
        inside = np.all(np.abs(pts[0, :2]) <= half_size)
        return [pts.copy()] if inside else []
    p0, d = pts[:-1], np.diff(pts, axis=0)
    t0, t1 = np.zeros(len(d)), np.ones(len(d))
    with np.errstate(divide='ignore', invalid='ignore'):
        for axis in (0, 1):
            for sign in (-1.0, 1.0):  # the half planes sign * coord <= half_size
                num = half_size - sign * p0[:, axis]
                den = sign * d[:, axis]
                t = num / den
                parallel = den == 0
                entering, leaving = den < 0, den > 0
                t0 = np.where(entering, np.maximum(t0, t), t0)
                t1 = np.where(leaving, np.minimum(t1, t), t1)
                t1 = np.where(parallel & (num < 0), -1.0, t1)  # parallel and outside
    keep = t0 <= t1
    if not keep.any():
        return []
    starts = p0 + t0[:, None] * d
    ends = np.where((t1 == 1.0)[:, None], pts[1:], p0 + t1[:, None] * d)  # vertices exact
    idx = np.flatnonzero(keep)
    # a kept segment continues the previous piece when both share an inside vertex
    prev_ok = np.concatenate([[False], (idx[1:] == idx[:-1] + 1) & (t1[idx[:-1]] == 1.0)])
    new_piece = ~(prev_ok & (t0[idx] == 0.0))
    piece = np.cumsum(new_piece) - 1
    # each segment contributes its start only when it opens a piece, and always its end
    stacked = np.stack([starts[idx], ends[idx]], axis=1).reshape(-1, 3)
    use = np.stack([new_piece, np.ones_like(new_piece)], axis=1).reshape(-1)
    owner = np.repeat(piece, 2)[use]
    out = stacked[use]
    bounds = np.flatnonzero(np.diff(owner)) + 1
    # a segment that only touches the square leaves a zero-length piece: not a lane
    return [part for part in np.split(out, bounds) if np.ptp(part, axis=0).any()]


def clip_lanes_to_square(lanes: Lanes, half_size: float) -> list[np.ndarray]:
    """Every lane clipped to the window square; a lane may become several pieces or none."""
    return [part for lane in lanes for part in clip_polyline_to_square(lane, half_size)]


def window_to_camera(points: np.ndarray) -> np.ndarray:
    """Window frame (x fwd, y left, z up) -> ONCE camera frame (x right, y down, z fwd)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return np.stack([-pts[:, 1], -pts[:, 2], pts[:, 0]], axis=1)


# --- point metric -------------------------------------------------------------------------

def _ratio(num: float, den: float) -> float:
    """Percentage; 0 when there is nothing to divide by (zero_division=0)."""
    return float(100.0 * num / den) if den > 0 else 0.0


def _f1(p: float, r: float) -> float:
    return float(2.0 * p * r / (p + r)) if p + r > 0 else 0.0


@dataclass
class PointCounts:
    """Additive counts of the point metric; `pred_hits[k]`, `gt_hits[k]` at thresholds[k]."""

    n_pred: int = 0
    n_gt: int = 0
    pred_hits: np.ndarray = field(default_factory=lambda: np.zeros(len(POINT_THRESHOLDS), int))
    gt_hits: np.ndarray = field(default_factory=lambda: np.zeros(len(POINT_THRESHOLDS), int))
    thresholds: tuple[float, ...] = POINT_THRESHOLDS

    def __add__(self, other: PointCounts) -> PointCounts:
        return PointCounts(self.n_pred + other.n_pred, self.n_gt + other.n_gt,
                           self.pred_hits + other.pred_hits, self.gt_hits + other.gt_hits,
                           self.thresholds)

    def scores(self) -> dict[str, float]:
        """{'P@10', 'R@10', 'F1@10', 'P@30', ...} in percent."""
        out: dict[str, float] = {}
        for k, tau in enumerate(self.thresholds):
            cm = f'{round(tau * 100):d}'
            p = _ratio(self.pred_hits[k], self.n_pred)
            r = _ratio(self.gt_hits[k], self.n_gt)
            out.update({f'P@{cm}': p, f'R@{cm}': r, f'F1@{cm}': _f1(p, r)})
        return out


def _hits(query: np.ndarray, ref: np.ndarray, thresholds: Sequence[float]) -> np.ndarray:
    """How many query points lie within each threshold (<=) of some ref point."""
    if len(query) == 0 or len(ref) == 0:
        return np.zeros(len(thresholds), dtype=int)
    dist, _ = cKDTree(ref).query(query, distance_upper_bound=max(thresholds) * 1.0001)
    return np.array([(dist <= tau).sum() for tau in thresholds], dtype=int)


def point_counts(pred_lanes: Lanes, gt_lanes: Lanes,
                 thresholds: Sequence[float] = POINT_THRESHOLDS,
                 step: float = SAMPLE_STEP) -> PointCounts:
    """Point-metric counts of one frame (lanes already clipped to the window)."""
    pred = resample_lanes(pred_lanes, step)
    gt = resample_lanes(gt_lanes, step)
    return PointCounts(len(pred), len(gt), _hits(pred, gt, thresholds),
                       _hits(gt, pred, thresholds), tuple(thresholds))


# --- ONCE lane metric ---------------------------------------------------------------------

@dataclass
class LaneCounts:
    """Additive counts of the ONCE metric."""

    n_pred: int = 0
    n_gt: int = 0
    tp: int = 0
    cd_sum: float = 0.0
    official: bool = False

    def __add__(self, other: LaneCounts) -> LaneCounts:
        return LaneCounts(self.n_pred + other.n_pred, self.n_gt + other.n_gt,
                          self.tp + other.tp, self.cd_sum + other.cd_sum,
                          self.official or other.official)

    def scores(self) -> dict[str, float]:
        """{'P', 'R', 'F1'} in percent and 'CD' (mean CD of true positives, m)."""
        p, r = _ratio(self.tp, self.n_pred), _ratio(self.tp, self.n_gt)
        if self.official:
            cd = self.cd_sum / (self.tp + 1e-5)  # as the released evaluator divides
        else:
            cd = self.cd_sum / self.tp if self.tp else 0.0
        return {'P': p, 'R': r, 'F1': _f1(p, r), 'CD': float(cd)}


def _capsule_mask(line_px: np.ndarray, shape: tuple[int, int], radius: float,
                  centre: float) -> np.ndarray:
    """Pixels of `shape` whose centre lies within `radius` px of a polyline.

    `line_px` (N, 2) holds (row, col) vertices in continuous pixel units; pixel (i, j) has its
    centre at (i + centre, j + centre). A distance transform from the pixels nearest to a
    dense chain of points (<= 0.25 px apart) on the polyline's bounding box settles every pixel
    but those within a pixel of the border; those get exact distances to the chain.
    """
    mask = np.zeros(shape, dtype=bool)
    if len(line_px) == 0:
        return mask
    chain = resample_polyline(np.column_stack([line_px, np.zeros(len(line_px))]), 0.25)[:, :2]
    pad = int(np.ceil(radius)) + 2
    near = np.floor(chain - centre + 0.5).astype(np.int64)
    ok = np.all((near >= -pad) & (near < np.array(shape) + pad), axis=1)
    if not ok.any():
        return mask
    chain, near = chain[ok], near[ok]
    lo = near.min(axis=0) - pad
    canvas = np.ones(tuple(near.max(axis=0) - lo + pad + 1), dtype=bool)
    canvas[near[:, 0] - lo[0], near[:, 1] - lo[1]] = False
    edt = distance_transform_edt(canvas)
    # a pixel centre is within 0.5 * sqrt(2) px of its chain point's pixel centre
    sure = np.argwhere(edt <= radius - 0.75) + lo
    unsure = np.argwhere((edt > radius - 0.75) & (edt <= radius + 0.75)) + lo
    dist, _ = cKDTree(chain).query(unsure + centre, distance_upper_bound=radius + 1e-9)
    hits = np.concatenate([sure, unsure[np.isfinite(dist)]])
    hits = hits[np.all((hits >= 0) & (hits < np.array(shape)), axis=1)]
    mask[hits[:, 0], hits[:, 1]] = True
    return mask


def _iou_matrix(masks_a: list[np.ndarray], masks_b: list[np.ndarray]) -> np.ndarray:
    """IoU of every pair of boolean images (0 where the union is empty)."""
    every = np.logical_or.reduce([*masks_a, *masks_b])
    if not every.any():
        return np.zeros((len(masks_a), len(masks_b)))
    rows, cols = np.flatnonzero(every.any(1)), np.flatnonzero(every.any(0))
    box = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]  # only where something is drawn
    a = np.stack([m[box].ravel() for m in masks_a]).astype(np.float32)
    b = np.stack([m[box].ravel() for m in masks_b]).astype(np.float32)
    inter = a @ b.T
    union = a.sum(1)[:, None] + b.sum(1)[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0)


def topview_mask(lane: np.ndarray, half_size: float, res: float = ONCE_RES,
                 width: float = ONCE_LANE_WIDTH) -> np.ndarray:
    """Paper mode: the lane drawn `width` wide on the window's top view, res m/px.

    Image rows follow x (forward), columns y (left), covering [-half_size, half_size]^2.
    """
    n = round(2 * half_size / res)
    pts = np.asarray(lane, dtype=np.float64).reshape(-1, 3)
    line_px = (pts[:, :2] + half_size) / res  # (row from x, col from y)
    return _capsule_mask(line_px, (n, n), width / res / 2, centre=0.5)


def unilateral_chamfer(gt_lane: np.ndarray, pred_lane: np.ndarray,
                       step: float = SAMPLE_STEP) -> float:
    """Mean 3D distance from equally spaced GT points to the nearest predicted point."""
    gt = resample_polyline(gt_lane, step)
    pred = resample_polyline(pred_lane, step)
    if len(gt) == 0 or len(pred) == 0:
        return float('inf')
    dist, _ = cKDTree(pred).query(gt)
    return float(dist.mean())


def once_matches(pred_lanes: Lanes, gt_lanes: Lanes, half_size: float,
                 iou_thresh: float = ONCE_IOU_THRESH) -> list[tuple[int, int, float]]:
    """(GT index, prediction index, unilateral chamfer distance) of the pairs the paper's
    metric compares: Hungarian assignment on 1 - top-view IoU, pairs below iou_thresh
    dropped. Score them at any tau_CD with lane_counts."""
    if not pred_lanes or not gt_lanes:
        return []
    iou = _iou_matrix([topview_mask(g, half_size) for g in gt_lanes],
                      [topview_mask(p, half_size) for p in pred_lanes])
    return [(int(gi), int(pi), unilateral_chamfer(gt_lanes[gi], pred_lanes[pi]))
            for gi, pi in zip(*linear_sum_assignment(1.0 - iou)) if iou[gi, pi] >= iou_thresh]


def lane_counts(matches: Sequence[tuple[int, int, float]], n_pred: int, n_gt: int,
                cd_thresh: float = ONCE_CD_THRESH) -> LaneCounts:
    """Counts of one frame from its once_matches: a match is a TP when its CD <= cd_thresh."""
    counts = LaneCounts(n_pred=n_pred, n_gt=n_gt)
    for _, _, cd in matches:
        if cd <= cd_thresh:
            counts.tp += 1
            counts.cd_sum += cd
    return counts


def once_counts(pred_lanes: Lanes, gt_lanes: Lanes, half_size: float,
                iou_thresh: float = ONCE_IOU_THRESH,
                cd_thresh: float = ONCE_CD_THRESH) -> LaneCounts:
    """ONCE-3DLanes counts of one frame as the paper defines the metric (see module doc)."""
    return lane_counts(once_matches(pred_lanes, gt_lanes, half_size, iou_thresh),
                       len(pred_lanes), len(gt_lanes), cd_thresh)


# --- ONCE released evaluator --------------------------------------------------------------

def official_mask(lane_cam: np.ndarray) -> np.ndarray:
    """The released evaluator's 1000 x 400 IoU image of a lane in camera coordinates."""
    pts = lane_cam[lane_cam[:, 2] < OFFICIAL_FWD_CUT]
    shape = (int(OFFICIAL_FWD / ONCE_RES), int(2 * OFFICIAL_SIDE / ONCE_RES))
    if len(pts) < 2:  # it draws segments between consecutive kept vertices only
        return np.zeros(shape, dtype=bool)
    cols = np.trunc(pts[:, 0] / ONCE_RES).astype(np.int64) + int(OFFICIAL_SIDE / ONCE_RES)
    rows = np.trunc(-pts[:, 2] / ONCE_RES).astype(np.int64) + int(OFFICIAL_FWD / ONCE_RES)
    # cv2.line draws between integer pixel coordinates, whose centres are the integers
    return _capsule_mask(np.column_stack([rows, cols]).astype(np.float64), shape,
                         OFFICIAL_THICKNESS / 2, centre=0.0)


def _interpolate_normalized(line: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Points at fractions of the 2D length of a polyline (the first point if it has none)."""
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    if arc[-1] <= 0:
        return np.repeat(line[:1], len(fractions), axis=0)
    t = fractions * arc[-1]
    return np.stack([np.interp(t, arc, line[:, k]) for k in range(line.shape[1])], axis=1)


def point_to_polyline_2d(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Exact 2D distance of each point to a polyline (a single vertex counts as a point)."""
    if len(line) == 1:
        return np.linalg.norm(points - line[0], axis=1)
    a, d = line[:-1], np.diff(line, axis=0)  # (S, 2)
    rel = points[:, None, :] - a[None, :, :]  # (M, S, 2)
    den = (d * d).sum(1)
    t = np.clip((rel * d[None]).sum(2) / np.where(den > 0, den, 1.0), 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * d[None], axis=2).min(axis=1)


def official_chamfer(gt_cam: np.ndarray, pred_cam: np.ndarray) -> float:
    """CD of the released evaluator: 10 GT samples, 2D distances in the (x_cam, y_cam) plane."""
    gt_xy, pred_xy = gt_cam[:, :2], pred_cam[:, :2]
    samples = _interpolate_normalized(gt_xy, OFFICIAL_FRACTIONS)
    return float(point_to_polyline_2d(samples, pred_xy).mean())


def _sort_lane_z(lane_cam: np.ndarray) -> np.ndarray:
    """The evaluator's sort_lanes_z: reversed when the first point is farther than the second."""
    if len(lane_cam) > 1 and lane_cam[0, 2] > lane_cam[1, 2]:
        return lane_cam[::-1]
    return lane_cam


def once_counts_official(pred_lanes: Lanes, pred_scores: Sequence[float], gt_lanes: Lanes,
                         score_thresh: float = 0.1,
                         cd_thresh: float = ONCE_CD_THRESH) -> LaneCounts:
    """ONCE-3DLanes counts of one frame as the released evaluator computes them (module doc)."""
    scores = np.asarray(pred_scores, dtype=np.float64)
    if len(scores) != len(pred_lanes):
        raise ValueError(f'{len(pred_lanes)} predicted lanes but {len(scores)} scores')
    gts = [_sort_lane_z(window_to_camera(g)) for g in gt_lanes if len(g) >= 2]
    preds = [_sort_lane_z(window_to_camera(p))
             for p, s in zip(pred_lanes, scores) if s > score_thresh and len(p) > 0]
    counts = LaneCounts(n_pred=len(preds), n_gt=len(gts), official=True)
    if not preds or not gts:
        return counts
    iou = _iou_matrix([official_mask(g) for g in gts], [official_mask(p) for p in preds])
    for gi, pi in zip(*linear_sum_assignment(1.0 - iou)):  # no IoU threshold, as released
        cd = official_chamfer(gts[gi], preds[pi])
        if cd < cd_thresh:
            counts.tp += 1
            counts.cd_sum += cd
    return counts
