"""SALAD's loss (paper eq. 6-8): pixel-wise binary cross-entropy on the segmentation plus
smooth L1 on the spatial branch: (du, dv) at lane cells, the depth residual wherever the
completed depth is labelled (the dense map gives the depth head signal off the lanes too);
with cfg.lane_depth_weight, the depth residual at the lane cells once more, near L1
(docs/salad.md, "Depth weighed at the lanes")."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from fhld_ros.salad.config import SaladConfig


class SaladCriterion(nn.Module):
    """targets: 'seg' (B, h, w) {0, 1}, 'offsets' (B, 2, h, w) cells, 'depth' (B, h, w) m,
    'depth_mask' (B, h, w) bool."""

    def __init__(self, cfg: SaladConfig) -> None:
        super().__init__()
        if not cfg.row_shift:
            raise ValueError('the config has no row_shift / row_scale: measure them on the '
                             'training set first (targets.row_statistics)')
        self.cfg = cfg
        self.register_buffer('shift', torch.tensor(cfg.row_shift).view(1, -1, 1))
        self.register_buffer('scale', torch.tensor(cfg.row_scale).view(1, -1, 1))
        # a buffer, so the weight follows the criterion to the training device
        self.register_buffer('pos_weight', torch.tensor(cfg.pos_weight), persistent=False)

    def forward(self, seg_logits: Tensor, spatial: Tensor,
                targets: dict[str, Tensor]) -> dict[str, Tensor]:
        seg = targets['seg']
        seg_loss = F.binary_cross_entropy_with_logits(
            seg_logits[:, 0], seg, pos_weight=self.pos_weight)
        lane = seg > 0.5
        offset_loss = _masked_smooth_l1(spatial[:, :2], targets['offsets'], lane)
        residual = (targets['depth'] - self.shift) / self.scale
        depth_mask = targets['depth_mask']
        depth_loss = _masked_smooth_l1(spatial[:, 2:], residual[:, None], depth_mask)
        total = (seg_loss + self.cfg.offset_weight * offset_loss
                 + self.cfg.depth_weight * depth_loss)
        losses = {'seg': seg_loss.detach(), 'offsets': offset_loss.detach(),
                  'depth': depth_loss.detach()}
        if self.cfg.lane_depth_weight > 0:
            lane_depth = _masked_smooth_l1(spatial[:, 2:], residual[:, None], lane & depth_mask,
                                           self.cfg.lane_depth_beta)
            total = total + self.cfg.lane_depth_weight * lane_depth
            losses['lane_depth'] = lane_depth.detach()
        return {'loss': total, **losses}


def _masked_smooth_l1(pred: Tensor, target: Tensor, mask: Tensor, beta: float = 1.0) -> Tensor:
    """Mean smooth L1 over the masked cells ((B, C, h, w) against (B, h, w) mask); 0 when
    none is masked (an image without lanes)."""
    weight = mask[:, None].expand_as(pred).float()
    loss = F.smooth_l1_loss(pred, target, reduction='none', beta=beta) * weight
    return loss.sum() / weight.sum().clamp(min=1.0)
