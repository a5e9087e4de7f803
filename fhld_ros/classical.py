"""Rule-based LiDAR lane detector: the classical baseline FHLD is compared against.

The pipeline of intensity-threshold detectors (e.g. the one ONCE-3DLanes cites as [13]):

1. ground extraction: per-cell minimum height on a coarse grid, a plane fitted robustly to the
   cell minima (iteratively trimmed least squares), ground points = points just above the
   minimum of a cell that lies on the plane (cars, walls and poles drop out);
2. adaptive intensity threshold per window: Otsu on the ground points' intensities, never
   below a percentile (markings cover a minority of the road), and no markings at all when the
   two Otsu classes do not differ by `min_contrast`;
3. clustering: bright ground points on a fine top-view grid (pixels where most ground points are
   bright), connected components of the grid dilated by `link_radius_m`, so sparse ring
   crossings of one marking join;
4. per cluster a curve in its own PCA frame (lateral offset = polynomial of the position along
   the principal axis); clusters too short, too wide (arrows, crosswalk bars, text) or too
   sparse are rejected;
5. collinear clusters (dashed lines) are merged when their facing ends line up, and every
   merged group is refitted; z follows a low-order fit to the marking points' own heights.

Input: accumulated window points (BevWindow.points_window, window frame) and intensity already
normalised to [0, 1]. Output: lanes as (K, 3) float64 polylines in the window frame and
confidences, as the FHLD detector returns them, so replay and eval treat both alike.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class ClassicalConfig:
    """Tunables of the baseline; defaults suit a 25.6 m window of ~10 accumulated sweeps."""

    ground_cell_m: float = 1.0  # grid of per-cell minimum heights
    ground_band_m: float = 0.12  # ground point: at most this above its cell's minimum
    plane_residual_m: float = 0.25  # cell minimum this far from the ground plane: not ground
    min_ground_points: int = 100  # fewer ground points: nothing to detect
    intensity_floor_percentile: float = 80.0  # threshold >= this percentile of ground points
    min_contrast: float = 0.15  # bright minus dark class mean (intensity in [0, 1])
    pixel_m: float = 0.1  # top-view grid of bright points
    min_bright_fraction: float = 0.5  # a pixel is marking when this share of its points is
    link_radius_m: float = 0.3  # bright pixels within 2x this join one cluster
    min_cluster_points: int = 10
    min_cluster_length_m: float = 0.8  # shorter blobs are noise
    max_width_m: float = 0.4  # wider blobs are arrows, bars, text or double lines gone wrong
    merge_angle_deg: float = 12.0  # dashes of one line point the same way ...
    merge_lateral_m: float = 0.6  # ... each end lies this close to the other's end tangent ...
    merge_gap_m: float = 12.0  # ... and the gap between them is at most this
    min_lane_length_m: float = 2.5  # shorter merged groups are dropped
    sample_step_m: float = 0.5  # spacing of the output polyline
    full_confidence_length_m: float = 15.0  # lanes this long (and well covered) get conf 1


@dataclass
class _Curve:
    """A polynomial curve t = f(s) in the frame (centre, u, v) of a point set."""

    centre: np.ndarray  # (2,)
    u: np.ndarray  # (2,) principal axis
    v: np.ndarray  # (2,) normal
    coef: np.ndarray  # lateral polynomial in s
    s_min: float
    s_max: float
    width: float  # robust spread of the lateral residuals (m)

    def xy(self, s: np.ndarray) -> np.ndarray:
        return self.centre + np.outer(s, self.u) + np.outer(np.polyval(self.coef, s), self.v)

    def end(self, which: int) -> tuple[np.ndarray, np.ndarray]:
        """End point and outward unit tangent of end 0 (s_min) or 1 (s_max)."""
        s = self.s_max if which else self.s_min
        slope = np.polyval(np.polyder(self.coef), s) if len(self.coef) > 1 else 0.0
        tangent = self.u + slope * self.v
        tangent = tangent / np.linalg.norm(tangent)
        return self.xy(np.array([s]))[0], tangent if which else -tangent


def _degree(extent: float) -> int:
    """Polynomial degree a cluster of this length supports."""
    return 1 if extent < 4.0 else 2 if extent < 10.0 else 3


def _fit_curve(xy: np.ndarray) -> _Curve:
    centre = xy.mean(axis=0)
    rel = xy - centre
    _, vecs = np.linalg.eigh(rel.T @ rel)
    u = vecs[:, 1]
    v = np.array([-u[1], u[0]])
    s, t = rel @ u, rel @ v
    s_min, s_max = float(s.min()), float(s.max())
    coef = np.polyfit(s, t, _degree(s_max - s_min)) if s_max > s_min else np.zeros(1)
    width = 2.0 * float(np.percentile(np.abs(t - np.polyval(coef, s)), 95))
    return _Curve(centre, u, v, coef, s_min, s_max, width)


def ground_mask(points: np.ndarray, cfg: ClassicalConfig = ClassicalConfig()) -> np.ndarray:
    """Points on the road surface (see module doc, step 1)."""
    xy = points[:, :2].astype(np.float64)
    z = points[:, 2].astype(np.float64)
    ij = np.floor((xy - xy.min(axis=0)) / cfg.ground_cell_m).astype(np.int64)
    flat = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    if flat.max() < 4 * len(flat):  # a window: a dense table beats sorting
        count = np.bincount(flat)
        cells = np.flatnonzero(count)
        lookup = np.zeros(len(count), dtype=np.int64)
        lookup[cells] = np.arange(len(cells))
        inverse, count = lookup[flat], count[cells]
    else:
        cells, inverse, count = np.unique(flat, return_inverse=True, return_counts=True)
    cell_min = np.full(len(cells), np.inf)
    np.minimum.at(cell_min, inverse, z)
    cell_xy = np.stack([np.bincount(inverse, xy[:, k], len(cells)) for k in (0, 1)], 1)
    cell_xy /= count[:, None]
    design = np.column_stack([cell_xy, np.ones(len(cells))])
    # most cells are road: start from cells near the median minimum, then trim to the plane
    inlier = np.abs(cell_min - np.median(cell_min)) < 0.5
    plane = np.zeros(3)
    for _ in range(3):
        if inlier.sum() < 3:
            return np.zeros(len(points), dtype=bool)
        plane, *_ = np.linalg.lstsq(design[inlier], cell_min[inlier], rcond=None)
        inlier = np.abs(cell_min - design @ plane) < cfg.plane_residual_m
    return inlier[inverse] & (z - cell_min[inverse] < cfg.ground_band_m)


def otsu_threshold(values: np.ndarray, bins: int = 256) -> tuple[float, float]:
    """Otsu threshold of values in [0, 1] and the difference of the two class means."""
    hist, edges = np.histogram(values, bins=bins, range=(0.0, 1.0))
    centres = (edges[:-1] + edges[1:]) / 2
    w0 = np.cumsum(hist).astype(np.float64)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    mean0 = m0 / np.maximum(w0, 1)
    mean1 = (m0[-1] - m0) / np.maximum(w1, 1)
    between = w0 * w1 * (mean0 - mean1) ** 2
    k = int(np.argmax(between))
    return float(edges[k + 1]), float(mean1[k] - mean0[k])


class ClassicalLaneDetector:
    """Ground extraction, adaptive intensity threshold, clustering and curve fitting."""

    def __init__(self, config: ClassicalConfig = ClassicalConfig()) -> None:
        self.config = config

    def marking_points(self, points: np.ndarray, intensity01: np.ndarray) -> np.ndarray:
        """Window-frame points classified as lane marking (ground and bright), (M, 3)."""
        cfg = self.config
        ground = ground_mask(points, cfg)
        if ground.sum() < cfg.min_ground_points:
            return np.zeros((0, 3))
        values = intensity01[ground]
        otsu, contrast = otsu_threshold(values)
        if contrast < cfg.min_contrast:
            return np.zeros((0, 3))
        thresh = max(otsu, float(np.percentile(values, cfg.intensity_floor_percentile)))
        pts = points[ground].astype(np.float64)
        bright = values > thresh
        # a pixel counts when most of its ground points are bright (isolated glints do not)
        origin = pts[:, :2].min(axis=0)
        pix = np.floor((pts[:, :2] - origin) / cfg.pixel_m).astype(np.int64)
        shape = tuple(pix.max(axis=0) + 1)
        flat = np.ravel_multi_index((pix[:, 0], pix[:, 1]), shape)
        n_all = np.bincount(flat, minlength=int(np.prod(shape)))
        n_bright = np.bincount(flat[bright], minlength=n_all.size)
        marked = n_bright >= np.maximum(cfg.min_bright_fraction * n_all, 1)
        return pts[bright & marked[flat]]

    def _clusters(self, marks: np.ndarray) -> list[np.ndarray]:
        """Marking points grouped by connected components of the dilated top-view grid."""
        cfg = self.config
        origin = marks[:, :2].min(axis=0)
        pix = np.floor((marks[:, :2] - origin) / cfg.pixel_m).astype(np.int64)
        grid = np.zeros(tuple(pix.max(axis=0) + 1), dtype=bool)
        grid[pix[:, 0], pix[:, 1]] = True
        r = max(round(cfg.link_radius_m / cfg.pixel_m), 0)
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        labels, _ = ndimage.label(ndimage.binary_dilation(grid, structure=xx**2 + yy**2 <= r * r),
                                  structure=np.ones((3, 3)))
        point_label = labels[pix[:, 0], pix[:, 1]]
        order = np.argsort(point_label, kind='stable')
        bounds = np.flatnonzero(np.diff(point_label[order])) + 1
        return [marks[idx] for idx in np.split(order, bounds)
                if len(idx) >= cfg.min_cluster_points]

    def _mergeable(self, a: _Curve, b: _Curve) -> bool:
        cfg = self.config
        if abs(float(a.u @ b.u)) < np.cos(np.deg2rad(cfg.merge_angle_deg)):
            return False
        ends = [(a.end(i), b.end(j)) for i in (0, 1) for j in (0, 1)]
        (pa, ta), (pb, tb) = min(ends, key=lambda e: np.linalg.norm(e[0][0] - e[1][0]))
        gap = pb - pa
        if np.linalg.norm(gap) > cfg.merge_gap_m or gap @ ta < -0.5 or -gap @ tb < -0.5:
            return False  # too far, or side by side rather than one after the other

        def lateral(d: np.ndarray, t: np.ndarray) -> float:
            return abs(float(d[0] * t[1] - d[1] * t[0]))
        return max(lateral(gap, ta), lateral(gap, tb)) <= cfg.merge_lateral_m

    def _groups(self, curves: list[_Curve]) -> np.ndarray:
        """Group id of every curve: union-find over mergeable pairs."""
        parent = np.arange(len(curves))

        def root(i: int) -> int:
            while parent[i] != i:
                i = parent[i]
            return i
        for i in range(len(curves)):
            for j in range(i + 1, len(curves)):
                if self._mergeable(curves[i], curves[j]):
                    parent[root(j)] = root(i)
        return np.array([root(i) for i in range(len(curves))])

    def _lane(self, pts: np.ndarray) -> tuple[np.ndarray, float] | None:
        """Polyline and confidence of one merged group of marking points."""
        cfg = self.config
        curve = _fit_curve(pts[:, :2])
        length = curve.s_max - curve.s_min
        if length < cfg.min_lane_length_m:
            return None
        n = int(np.ceil(length / cfg.sample_step_m)) + 1
        s = np.linspace(curve.s_min, curve.s_max, n)
        s_pts = (pts[:, :2] - curve.centre) @ curve.u
        z_coef = np.polyfit(s_pts, pts[:, 2], min(_degree(length), 2))
        lane = np.column_stack([curve.xy(s), np.polyval(z_coef, s)])
        # coverage: share of the curve with marking points nearby (dashes cover less)
        occupied = np.unique(np.floor((s_pts - curve.s_min) / cfg.sample_step_m).astype(int))
        coverage = min(1.0, len(occupied) / max(n - 1, 1))
        conf = min(1.0, length / cfg.full_confidence_length_m) * (0.5 + 0.5 * coverage)
        return lane, conf

    def detect(self, points_window: np.ndarray,
               intensity01: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        """Lanes ((K, 3) float64, window frame) and confidences (L,) of one window."""
        cfg = self.config
        points = np.asarray(points_window, dtype=np.float32).reshape(-1, 3)
        inten = np.asarray(intensity01, dtype=np.float32).reshape(-1)
        if len(points) != len(inten):
            raise ValueError(f'{len(points)} points but {len(inten)} intensities')
        finite = np.isfinite(points).all(axis=1) & np.isfinite(inten)
        points, inten = points[finite], inten[finite]
        if len(points) < cfg.min_ground_points:
            return [], np.zeros(0)
        marks = self.marking_points(points, inten)
        if len(marks) < cfg.min_cluster_points:
            return [], np.zeros(0)
        clusters, curves = [], []
        for pts in self._clusters(marks):
            curve = _fit_curve(pts[:, :2])
            if curve.s_max - curve.s_min >= cfg.min_cluster_length_m and \
                    curve.width <= cfg.max_width_m:
                clusters.append(pts)
                curves.append(curve)
        if not curves:
            return [], np.zeros(0)
        group = self._groups(curves)
        lanes, confs = [], []
        for g in np.unique(group):
            members = np.flatnonzero(group == g)
            found = self._lane(np.concatenate([clusters[i] for i in members]))
            if found is not None:
                lanes.append(found[0])
                confs.append(found[1])
        order = np.argsort(confs)[::-1]  # most confident first
        return [lanes[i] for i in order], np.asarray(confs, dtype=np.float64)[order]

    def detect_window(self, window: Any) -> tuple[list[np.ndarray], np.ndarray]:
        """Lanes of a bev.BevWindow in the *output* frame (as /lanes publishes them)."""
        lanes, confs = self.detect(window.points_window, window.intensity)
        return [window.to_output(lane) for lane in lanes], confs
