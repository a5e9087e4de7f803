"""Global branch: transformer encoder + decoder with N queries -> class logits and curves.

Every decoder layer goes through the same heads (their outputs get auxiliary losses).
Curve head: 12 numbers (p_s, p_e, a, b) per query, see curve.py. Terminal u, v pass through a
sigmoid stretched to [-0.05, 1.05] so terminals on the window border stay reachable.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from fhld_ros.model.config import FhldConfig
from fhld_ros.model.curve import make_curve
from fhld_ros.model.position_encoding import sine_position_encoding
from fhld_ros.model.transformer import Transformer


class MLP(nn.Sequential):
    def __init__(self, dim: int, hidden: int, out: int, layers: int) -> None:
        mods: list[nn.Module] = []
        for i in range(layers - 1):
            mods += [nn.Linear(dim if i == 0 else hidden, hidden), nn.ReLU(inplace=True)]
        super().__init__(*mods, nn.Linear(hidden if layers > 1 else dim, out))


class GlobalBranch(nn.Module):
    def __init__(self, cfg: FhldConfig) -> None:
        super().__init__()
        self.input_proj = nn.Conv2d(cfg.widths[-1], cfg.d_model, 1)
        self.transformer = Transformer(cfg.d_model, cfg.n_heads, cfg.ffn_dim, cfg.enc_layers,
                                       cfg.dec_layers, cfg.dropout)
        self.query_pos = nn.Parameter(torch.randn(cfg.num_queries, cfg.d_model))
        self.class_head = nn.Linear(cfg.d_model, 2)  # [non-lane, lane]
        self.curve_head = MLP(cfg.d_model, cfg.d_model, 12, 3)
        self.curve_model = make_curve(cfg.adaptive_axis)

    def forward(self, feature: Tensor) -> tuple[Tensor, Tensor]:
        """F (B, C, h, w) -> logits (layers, B, N, 2), curves (layers, B, N, 12)."""
        src = self.input_proj(feature)
        _, dim, h, w = src.shape
        pos = sine_position_encoding(h, w, dim, device=src.device)
        hidden = self.transformer(src.flatten(2).transpose(1, 2), pos, self.query_pos)
        raw = self.curve_head(hidden)
        terminal_uv = torch.sigmoid(raw[..., [0, 1, 3, 4]]) * 1.1 - 0.05
        raw = torch.cat([terminal_uv[..., :2], raw[..., 2:3], terminal_uv[..., 2:],
                         raw[..., 5:]], dim=-1)
        return self.class_head(hidden), self.curve_model.constrain(raw)
