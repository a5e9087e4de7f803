"""Ground-truth lanes: window-frame metres -> padded tensors in normalised units.

Targets come as one list per batch item of (K, 3) lanes (ordered polylines or dense samples, in
window-frame metres). Each lane is resampled to cfg.gt_points points equally spaced in arc length
so the curve loss weighs every part of a lane alike and everything batches into one tensor.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from fhld_ros.geometry import resample_to_count
from fhld_ros.model.config import FhldConfig


@dataclass
class LaneTargets:
    points: Tensor  # (B, M, P, 3) normalised u, v, z (m); padded lanes are zeros
    mask: Tensor    # (B, M) bool, True for real lanes

    @property
    def terminals(self) -> Tensor:
        """(B, M, 2, 3): first and last point of each lane."""
        return self.points[:, :, [0, -1]]

    def counts(self) -> list[int]:
        return self.mask.sum(1).tolist()


def to_normalised(xyz: np.ndarray, window_m: float) -> np.ndarray:
    """Window-frame metres (x, y, z) -> (u, v, z): u, v in [0, 1] over the window."""
    out = np.array(xyz, dtype=np.float64, copy=True)
    out[..., :2] = out[..., :2] / window_m + 0.5
    return out


def to_metres(uvz: np.ndarray, window_m: float) -> np.ndarray:
    out = np.array(uvz, dtype=np.float64, copy=True)
    out[..., :2] = (out[..., :2] - 0.5) * window_m
    return out


def prepare_targets(targets: Sequence[Sequence[np.ndarray]] | LaneTargets, cfg: FhldConfig,
                    device: torch.device | str = 'cpu') -> LaneTargets:
    if isinstance(targets, LaneTargets):
        return LaneTargets(targets.points.to(device), targets.mask.to(device))
    per_item = []
    for lanes in targets:
        resampled = (resample_to_count(lane, cfg.gt_points) for lane in lanes)
        per_item.append([to_normalised(r, cfg.window_m) for r in resampled if r is not None])
    batch, width = len(per_item), max([1, *(len(lanes) for lanes in per_item)])
    points = np.zeros((batch, width, cfg.gt_points, 3), dtype=np.float32)
    mask = np.zeros((batch, width), dtype=bool)
    for b, lanes in enumerate(per_item):
        if lanes:
            points[b, :len(lanes)] = np.stack(lanes)
            mask[b, :len(lanes)] = True
    return LaneTargets(torch.from_numpy(points).to(device), torch.from_numpy(mask).to(device))
