"""The road's depth per image row, shared by every lane and fitted to the network's own lane
cells: no mount needed.

On a road without cross slope, the rays of one image row meet the road at one depth whatever
lane they fall on: on a level road inverse depth is linear in the row, grades bend it. The
network's depth scatters from lane to lane within a row (docs/salad.md, "Where the F1 goes":
2.6 % of depth left after each row's own scale against 3.6 % after the image's), so every lane
cell's depth is pulled half way to the profile all of them fit together: inverse depth a cubic
in the row plus a term in the column (roll, cross slope), robustly weighted by the cells'
probability. Half, not all the way: curves and crossfall part the lanes of one row in depth,
and all the way scored lower on the validation drives (docs/salad.md, "One depth per row").
The profile does not correct the image's scale: the cells' mean depth stays theirs. Where the
camera's mount is known, RoadPlane then gives the near depth (decode.lane_points).
"""
from __future__ import annotations

import numpy as np

from fhld_ros.salad.virtual_camera import VirtualCamera

MIX = 0.5  # a cell's depth moves this share of the way to the profile's
DEGREE = 3  # inverse depth: a polynomial of this degree in the row's slope to the axis
MIN_CELLS = 30  # fewer lane cells fit no profile
MIN_DEPTH_M, MAX_DEPTH_M = 1.0, 60.0  # cells outside fit nothing and stay as they are
ROUNDS = 3  # least-squares rounds, each without the cells far from the previous fit
OUTLIER = 3.0  # ... farther than this many median residuals (relative depth) ...
MIN_RESIDUAL = 0.01  # ... and than this share of their depth


def shared_row_depth(z: np.ndarray, u: np.ndarray, v: np.ndarray, weight: np.ndarray,
                     camera: VirtualCamera, mix: float = MIX) -> np.ndarray:
    """Depths z of lane cells at pixels (u, v) of the virtual camera, each moved `mix` of the
    way to the profile the cells fit (weight: their lane probability); z itself where no
    profile fits (module doc)."""
    column, row = (u - camera.cx) / camera.focal, (v - camera.cy) / camera.focal
    fit = (z > MIN_DEPTH_M) & (z < MAX_DEPTH_M)
    if fit.sum() < MIN_CELLS:
        return z
    design = np.column_stack([column, *(row ** k for k in range(DEGREE + 1))])
    inverse = 1.0 / np.where(fit, z, 1.0)
    keep = fit
    for _ in range(ROUNDS):
        root_weight = np.sqrt(weight[keep])
        coef, *_ = np.linalg.lstsq(design[keep] * root_weight[:, None],
                                   inverse[keep] * root_weight, rcond=None)
        fitted = design @ coef
        residual = np.abs(fitted - inverse) * z  # relative depth
        keep = fit & (residual < max(OUTLIER * np.median(residual[keep]), MIN_RESIDUAL))
    move = fit & (fitted > 1.0 / (2.0 * MAX_DEPTH_M))  # the profile is in front and not far
    profile = 1.0 / np.where(move, fitted, 1.0)
    return np.where(move, (1.0 - mix) * z + mix * profile, z)
