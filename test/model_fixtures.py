"""A small FHLD configuration shared by the model, loss and checkpoint tests."""
from __future__ import annotations

from fhld_ros.model.config import FhldConfig


def small_config(**overrides) -> FhldConfig:
    """A 128 px / 0.2 m raster (same 25.6 m window) and a narrow network: fast tests."""
    base = dict(size_px=128, resolution_m=0.2, widths=(8, 16, 32, 64), d_model=64, ffn_dim=128,
                enc_layers=1, dec_layers=2, num_queries=6, cell_px=8, cells_per_lane=16,
                noise_px=1.0, infer_spacing_px=6.0, local_channels=16, local_hidden=64)
    return FhldConfig(**{**base, **overrides})
