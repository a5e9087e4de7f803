"""Hungarian matching of the N global predictions to the GT lanes (paper eq. 13).

cost(pred j, GT i) = -w_class * P_j(lane) + w_terminal * L1(terminals of j, terminals of i).
A lane has no natural direction, so the terminal L1 is the smaller of the two orientations
(the curve loss does the same). Solving the rectangular N x M problem equals the paper's
square matrix padded with non-lanes up to a factor on the class weight.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor

from fhld_ros.model.targets import LaneTargets


def terminal_l1(pred: Tensor, gt: Tensor, z_scale: float) -> Tensor:
    """pred (N, 2, 3), gt (M, 2, 3) terminals -> (N, M) orientation-free L1 distance."""
    scale = pred.new_tensor([1.0, 1.0, z_scale])
    p = (pred * scale).flatten(1)
    forward = torch.cdist(p, (gt * scale).flatten(1), p=1)
    backward = torch.cdist(p, (gt.flip(1) * scale).flatten(1), p=1)
    return torch.minimum(forward, backward)


class HungarianMatcher:
    def __init__(self, class_weight: float = 1.0, terminal_weight: float = 1.0,
                 z_scale: float = 1.0 / 25.6) -> None:
        self.class_weight = class_weight
        self.terminal_weight = terminal_weight
        self.z_scale = z_scale

    @torch.no_grad()
    def __call__(self, logits: Tensor, curves: Tensor,
                 gt: LaneTargets) -> list[tuple[Tensor, Tensor]]:
        """logits (B, N, 2), curves (B, N, 12) -> per item (pred indices, GT indices)."""
        prob = logits.softmax(-1)[..., 1]
        pred_terminals = curves[..., :6].reshape(*curves.shape[:2], 2, 3)
        result = []
        for b, count in enumerate(gt.counts()):
            cost = (-self.class_weight * prob[b, :, None]
                    + self.terminal_weight * terminal_l1(pred_terminals[b],
                                                         gt.terminals[b, :count], self.z_scale))
            rows, cols = linear_sum_assignment(cost.float().cpu().numpy())
            order = np.argsort(cols)  # matches listed in GT order
            result.append((torch.as_tensor(rows[order], dtype=torch.long, device=curves.device),
                           torch.as_tensor(cols[order], dtype=torch.long, device=curves.device)))
        return result
