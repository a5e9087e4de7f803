"""RoIAlign (Mask R-CNN) for square, axis-aligned cells, written with grid_sample.

Cells are given by their centres in normalised map coordinates (u along the width, v along the
height, both in [0, 1] over the whole map) and one side length in the same units. Each of the
out x out bins averages sampling x sampling bilinear samples, as torchvision's roi_align with
aligned=True. With align_corners=False, grid coordinate 2u - 1 is exactly position u on the map
whatever its stride, so the same cells can be pooled from any feature level.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def cell_offsets(out: int, sampling: int, device: torch.device | str = 'cpu') -> Tensor:
    """Sample offsets within a unit cell, (out * sampling,) in (-0.5, 0.5), bin-major."""
    steps = torch.arange(out * sampling, device=device, dtype=torch.float32)
    return (steps + 0.5) / (out * sampling) - 0.5


def roi_align(features: Tensor, centres: Tensor, batch: Tensor, side: float, out: int,
              sampling: int = 2) -> Tensor:
    """features (B, C, h, w), centres (n, 2) as (u, v), batch (n,) item index -> (n, C, out, out).

    Bin (i, j) covers rows i (v) and columns j (u) of the cell. Samples outside the map read 0.
    """
    n, channels = centres.shape[0], features.shape[1]
    if n == 0:
        return features.new_zeros((0, channels, out, out))
    offsets = cell_offsets(out, sampling, features.device) * side
    grid_u = centres[:, None, None, 0] + offsets[None, None, :]   # (n, 1, S)
    grid_v = centres[:, None, None, 1] + offsets[None, :, None]   # (n, S, 1)
    size = out * sampling
    grid = torch.stack(torch.broadcast_tensors(grid_u, grid_v), dim=-1) * 2 - 1  # (n, S, S, 2)
    items = torch.unique(batch).tolist()
    result = features.new_empty((n, channels, out, out)) if len(items) > 1 else None
    for item in items:
        sel = (batch == item).nonzero(as_tuple=True)[0]
        # All cells of one item side by side in one grid (1, S, len(sel) * S, 2), so one
        # grid_sample and one average pool (kernel = sampling, never straddling two cells).
        flat = grid[sel].permute(1, 0, 2, 3).reshape(1, size, -1, 2)
        sampled = F.grid_sample(features[item:item + 1], flat, mode='bilinear',
                                padding_mode='zeros', align_corners=False)
        pooled = F.avg_pool2d(sampled, sampling) if sampling > 1 else sampled
        pooled = pooled.reshape(channels, out, len(sel), out).permute(2, 0, 1, 3)
        if result is None:
            return pooled.contiguous()
        result[sel] = pooled
    return result
