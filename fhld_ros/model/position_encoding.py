"""2D sine position encoding (DETR) for attention over BEV feature maps."""
from __future__ import annotations

import math

import torch
from torch import Tensor


def sine_position_encoding(height: int, width: int, dim: int, temperature: float = 10000.0,
                           device: torch.device | str = 'cpu') -> Tensor:
    """(height * width, dim) encoding, row-major like ``x.flatten(2)``; half the channels
    encode the row (v), half the column (u), each as interleaved sin/cos of the cell centre."""
    if dim % 4:
        raise ValueError(f'position encoding dim must be a multiple of 4, got {dim}')
    quarter = dim // 4
    freq = temperature ** (torch.arange(quarter, device=device, dtype=torch.float32) / quarter)
    rows = (torch.arange(height, device=device, dtype=torch.float32) + 0.5) / height * 2 * math.pi
    cols = (torch.arange(width, device=device, dtype=torch.float32) + 0.5) / width * 2 * math.pi

    def encode(pos: Tensor) -> Tensor:
        angles = pos[:, None] / freq
        return torch.stack([angles.sin(), angles.cos()], dim=-1).flatten(1)  # (n, dim / 2)

    enc_rows, enc_cols = encode(rows), encode(cols)
    return torch.cat([enc_rows[:, None].expand(height, width, -1),
                      enc_cols[None].expand(height, width, -1)], dim=-1).reshape(-1, dim)
