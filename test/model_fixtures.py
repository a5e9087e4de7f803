"""A small FHLD configuration shared by the model, loss and checkpoint tests, and the SALAD
weights the camera node tests run."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from fhld_ros.model.config import FhldConfig
from fhld_ros.salad.checkpoint import save_salad
from fhld_ros.salad.config import SaladConfig
from fhld_ros.salad.model import SaladNet


def small_config(**overrides) -> FhldConfig:
    """A 128 px / 0.2 m raster (same 25.6 m window) and a narrow network: fast tests."""
    base = dict(size_px=128, resolution_m=0.2, widths=(8, 16, 32, 64), d_model=64, ffn_dim=128,
                enc_layers=1, dec_layers=2, num_queries=6, cell_px=8, cells_per_lane=16,
                noise_px=1.0, infer_spacing_px=6.0, local_channels=16, local_hidden=64)
    return FhldConfig(**{**base, **overrides})


def lane_everywhere_salad(path: Path) -> Path:
    """An untrained SALAD whose lane logit is pushed up: every cell a lane cell, so it decodes
    one lane straight ahead in any image (the camera node's tests need no trained weights)."""
    cfg = SaladConfig()
    rows = cfg.grid[1]
    cfg = dataclasses.replace(cfg, row_shift=tuple(np.linspace(60.0, 3.0, rows)),
                              row_scale=tuple(np.linspace(10.0, 0.5, rows)))
    torch.manual_seed(0)
    model = SaladNet(cfg)
    with torch.no_grad():
        model.seg_head.bias.fill_(5.0)
    save_salad(path, model, 'test_camera_node')
    return path
