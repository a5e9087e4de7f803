"""SaladNet: a slim CNN encoder, an all-MLP decoder to stride 4 and SALAD's two branches.

The paper uses SegFormer-B2; this keeps its shape (multi-level features fused at H/4 x W/4 by
1x1 projections, global context at the coarsest level) at a size a 2-core CPU runs at camera
rate: ResNet basic blocks (fhld_ros.model.backbone) with one self-attention layer over the
stride-32 cells. Branches (paper §4.2, §4.3):

* semantic awareness: one logit per cell, lane or not;
* spatial contextual: (du, dv), the sub-cell offset from the cell centre to the lane, in
  cells, and dz, the depth residual on the row's shift and scale (config.row_shift/scale).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from fhld_ros.model.backbone import BasicBlock, ConvBN, SpatialSelfAttention
from fhld_ros.salad.config import SaladConfig

# ImageNet statistics: a common normalisation, and what a pretrained encoder would expect
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
SEG_PRIOR = 0.02  # lane cells are rare: the logit starts at this probability


class Encoder(nn.Module):
    """Stem (stride 2) and four stages of basic blocks at strides 4, 8, 16 and 32."""

    def __init__(self, widths: tuple[int, ...], attention_layers: int) -> None:
        super().__init__()
        self.stem = ConvBN(3, widths[0], 3, 2)
        self.stages = nn.ModuleList(
            nn.Sequential(BasicBlock(cin, cout, 2), BasicBlock(cout, cout, 1))
            for cin, cout in zip(widths[:-1], widths[1:]))
        self.attention = (SpatialSelfAttention(widths[-1], 4, 2 * widths[-1], attention_layers)
                          if attention_layers else nn.Identity())

    def forward(self, x: Tensor) -> list[Tensor]:
        x = F.relu(self.stem(x), inplace=True)
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        feats[-1] = self.attention(feats[-1])
        return feats


class SaladNet(nn.Module):
    """(B, 3, H, W) uint8-range RGB of the virtual camera -> (seg (B, 1, h, w) logits,
    spatial (B, 3, h, w): du, dv, dz), h, w = H / 4, W / 4."""

    def __init__(self, cfg: SaladConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg.widths, cfg.attention_layers)
        self.project = nn.ModuleList(ConvBN(c, cfg.decoder_dim, 1) for c in cfg.widths[1:])
        self.fuse = ConvBN(cfg.decoder_dim, cfg.decoder_dim, 3)
        self.seg_head = nn.Conv2d(cfg.decoder_dim, 1, 1)
        self.spatial_head = nn.Conv2d(cfg.decoder_dim, 3, 1)
        nn.init.constant_(self.seg_head.bias, float(torch.logit(torch.tensor(SEG_PRIOR))))
        nn.init.normal_(self.spatial_head.weight, std=1e-3)
        nn.init.zeros_(self.spatial_head.bias)
        self.register_buffer('mean', torch.tensor(MEAN).view(1, 3, 1, 1) * 255, persistent=False)
        self.register_buffer('std', torch.tensor(STD).view(1, 3, 1, 1) * 255, persistent=False)

    def forward(self, image: Tensor) -> tuple[Tensor, Tensor]:
        x = (image.float() - self.mean) / self.std
        feats = self.encoder(x)
        size = feats[0].shape[-2:]
        fused = sum(F.interpolate(p(f), size=size, mode='bilinear', align_corners=False)
                    if f.shape[-2:] != size else p(f)
                    for p, f in zip(self.project, feats))
        fused = F.relu(self.fuse(F.relu(fused, inplace=True)), inplace=True)
        return self.seg_head(fused), self.spatial_head(fused)
