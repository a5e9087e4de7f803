"""Lane heights from the measured road surface: a post-processing step of FhldDetector.detect.

The local branch places lanes well in the ground plane (on the held-out windows, 80 % of
predicted points lie within 10 cm of a GT lane in x, y) but its heights are coarse (median
error 10 cm), and at a 10 cm threshold in 3D that costs most of the precision. The raster
already holds the measured surface: the min-height channel. Each lane point takes the median
minimum height of the occupied cells around it (a 5 x 5 cell patch); samples further than
GATE_M from the predicted height are rejected (cars, kerbs, empty or occluded road), and the
remaining ones are fitted with a robust cubic in arc length, so one lane gets one smooth
profile. Lanes with too few accepted samples keep the model's heights.

The patch size, gate and cubic were chosen on held-out windows (docs/accuracy.md has the
measurements and the variants tried). `refine_heights=False` in detect() turns it off.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.bev import BevSpec, min_height_m

PATCH_CELLS = 5      # side of the cell patch sampled around each lane point
GATE_M = 0.30        # a surface sample this far from the predicted height is not the lane's
FIT_DEGREE = 3       # height profile along the lane: a cubic in arc length
REWEIGHT_ROUNDS = 3  # iteratively reweighted fit (Huber-like weights beyond 2 robust sigma)
MIN_SIGMA_M = 0.01   # floor of the robust residual scale


def surface_heights(raster: np.ndarray, xy: np.ndarray, resolution_m: float) -> np.ndarray:
    """Median measured surface height (min-height channel of the (4, H, W) raster, occupied
    cells only) in the PATCH_CELLS patch at each window-frame xy; NaN where all are empty."""
    size = raster.shape[-1]
    cell = np.floor(BevSpec(size, resolution_m).world_to_pixel(xy)).astype(np.intp)
    r = PATCH_CELLS // 2
    offsets = np.arange(-r, r + 1)
    cols = np.clip(cell[:, 0, None] + offsets[None, :], 0, size - 1)
    rows = np.clip(cell[:, 1, None] + offsets[None, :], 0, size - 1)
    # (P, 4, k, k) patches; only these cells are decoded, not the whole raster
    patches = np.moveaxis(raster[:, rows[:, :, None], cols[:, None, :]], 0, 1)
    return _row_medians(min_height_m(patches).reshape(len(xy), -1))


def _row_medians(values: np.ndarray) -> np.ndarray:
    """Median of the non-NaN values of each row of (R, K); NaN for a row without any."""
    ordered = np.sort(values, axis=1)  # NaN sorts last
    valid = np.count_nonzero(~np.isnan(ordered), axis=1)
    index = np.arange(len(ordered))
    # the middle one or two valid values
    return 0.5 * (ordered[index, np.maximum(valid - 1, 0) // 2] + ordered[index, valid // 2])


def robust_profiles(arc: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust polynomials z(arc) through the finite samples of each row of (L, K) arrays.

    All lanes at once: iteratively reweighted least squares (weights on the unsquared
    residuals, as np.polyfit takes them) in arc length scaled to [0, 1] per lane, which
    spans the same cubics and keeps the 4 x 4 normal equations well conditioned. Returns the
    fitted heights (L, K) and which rows had enough samples (more than FIT_DEGREE).
    """
    ok = np.isfinite(z) & np.isfinite(arc)
    s = np.where(np.isfinite(arc), arc, 0.0)
    s /= np.maximum(s.max(axis=1, keepdims=True), 1e-9)
    # (L, K, degree + 1); the samples outside ok get weight 0, so one basis serves fit and output
    basis = s[..., None] ** np.arange(FIT_DEGREE, -1, -1)
    y = np.where(ok, z, 0.0)
    weights = ok.astype(np.float64)
    for _ in range(REWEIGHT_ROUNDS):
        w2 = weights ** 2
        normal = np.einsum('lki,lk,lkj->lij', basis, w2, basis)
        rhs = np.einsum('lki,lk->li', basis, w2 * y)
        coef = np.einsum('lij,lj->li', np.linalg.pinv(normal), rhs)
        resid = np.abs(y - np.einsum('lki,li->lk', basis, coef))
        # fmax: a row without samples has a NaN median
        sigma = np.fmax(1.4826 * _row_medians(np.where(ok, resid, np.nan)), MIN_SIGMA_M)
        weights = np.where(ok, 1.0 / np.maximum(1.0, resid / (2.0 * sigma[:, None])), 0.0)
    return np.einsum('lki,li->lk', basis, coef), ok.sum(axis=1) > FIT_DEGREE


def refine_lane_heights(lanes: list[np.ndarray], raster: np.ndarray,
                        resolution_m: float) -> list[np.ndarray]:
    """New (K, 3) window-frame lanes whose z follows the measured surface of raster (4, H, W)."""
    if not lanes:
        return []
    points = np.concatenate(lanes)
    measured = surface_heights(raster, points[:, :2], resolution_m)
    measured[np.abs(measured - points[:, 2]) > GATE_M] = np.nan
    # lanes as rows of (L, K) arrays padded with NaN: all profiles fitted at once
    lengths = np.array([len(lane) for lane in lanes])
    starts = np.repeat(np.cumsum(lengths) - lengths, lengths)  # per point: its lane's start
    row = np.repeat(np.arange(len(lanes)), lengths)
    col = np.arange(len(points)) - starts
    step = np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1)
    arc_flat = np.cumsum(np.r_[0.0, step])
    arc_flat -= arc_flat[starts]  # from each lane's start
    arc = np.full((len(lanes), lengths.max()), np.nan)
    z = arc.copy()
    arc[row, col], z[row, col] = arc_flat, measured
    profiles, fitted = robust_profiles(arc, z)
    refined = [lane.copy() for lane in lanes]
    for index in np.flatnonzero(fitted):  # lanes with too few samples keep the model's z
        refined[index][:, 2] = profiles[index, :lengths[index]]
    return refined
