"""Local branch: per anchor cell, a lane segment eta = (p_o, l, alpha), its height and a class.

F'' is built top-down from the attended stride-32 map F and the finer backbone stages down to
cfg.local_stride (a light FPN: the paper encodes F with convolutions; finer maps add the detail
that 4 cm, 10 cm-threshold outputs need). Each cell's RoIAlign features go through an MLP.
Outputs per cell: class logit; centre p_o as an offset from the cell centre in half-cells (so
any point of the cell is reachable); length l in (0.1, 1.5) r; heading as a unit vector;
height as a residual on the height of the global curve at the cell.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from fhld_ros.model.anchors import AnchorGrid
from fhld_ros.model.backbone import ConvBN
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.roi_align import roi_align


@dataclass
class LocalPrediction:
    logits: Tensor   # (L, K)
    centre: Tensor   # (L, K, 2) absolute p_o (u, v)
    length: Tensor   # (L, K) segment length l, normalised units
    heading: Tensor  # (L, K, 2) unit vector (cos alpha, sin alpha) in the (u, v) plane
    z: Tensor        # (L, K) height of p_o (m)


class LocalFeatures(nn.Module):
    """F'': top-down sum of 1x1 projections of the stages at strides local_stride..32."""

    def __init__(self, cfg: FhldConfig) -> None:
        super().__init__()
        strides = [s for s in (4, 8, 16, 32) if s >= cfg.local_stride]
        width = dict(zip((4, 8, 16, 32), cfg.widths))
        self.strides = strides[::-1]  # coarse to fine
        self.lateral = nn.ModuleDict({str(s): nn.Conv2d(width[s], cfg.local_channels, 1)
                                      for s in strides})
        self.out = ConvBN(cfg.local_channels, cfg.local_channels, 3)

    def forward(self, feats: dict[int, Tensor]) -> Tensor:
        x = None
        for s in self.strides:
            lat = self.lateral[str(s)](feats[s])
            x = lat if x is None else lat + F.interpolate(x, size=lat.shape[-2:], mode='nearest')
        return F.relu(self.out(x), inplace=True)


class LocalHead(nn.Module):
    def __init__(self, cfg: FhldConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.mlp = nn.Sequential(
            nn.Linear(cfg.local_channels * cfg.roi_size ** 2, cfg.local_hidden),
            nn.ReLU(inplace=True), nn.Linear(cfg.local_hidden, cfg.local_hidden),
            nn.ReLU(inplace=True), nn.Linear(cfg.local_hidden, 7))

    def forward(self, local_map: Tensor, anchors: AnchorGrid) -> LocalPrediction:
        cfg = self.cfg
        lanes, cells = anchors.shape
        batch = anchors.batch.unsqueeze(1).expand(-1, cells).reshape(-1)
        pooled = roi_align(local_map, anchors.centres.reshape(-1, 2), batch, cfg.cell_norm,
                           cfg.roi_size, cfg.roi_sampling)
        raw = self.mlp(pooled.flatten(1)).reshape(lanes, cells, 7)
        half = cfg.cell_norm / 2
        return LocalPrediction(
            logits=raw[..., 0],
            centre=anchors.centres + 1.2 * torch.tanh(raw[..., 1:3]) * half,
            length=cfg.cell_norm * (0.1 + 1.4 * torch.sigmoid(raw[..., 3])),
            heading=F.normalize(raw[..., 4:6], dim=-1, eps=1e-6),
            z=anchors.z + raw[..., 6])
