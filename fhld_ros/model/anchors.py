"""Dynamic anchor cells along global curves (paper: "Dynamic anchors generation").

Training: B cells per matched lane, evenly spaced in t along the matched *predicted* curve (or
the GT lane, cfg.anchors_on_gt), with Gaussian position noise (cfg.anchor_noise), plus negative
cells sampled at 1-2.5 r around random positives. Inference: cells along each kept curve with a
density proportional to 1 + curvature / curvature_ref, so bends get more output points; the
detector then moves each cell to the segment it predicted (AnchorGrid.moved_to) and asks again.
Anchor centres are detached: the local branch never moves the global curves.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from fhld_ros.model.config import FhldConfig
from fhld_ros.model.curve import AxisCubicCurve
from fhld_ros.model.targets import LaneTargets


@dataclass
class AnchorGrid:
    """K ordered cells for each of L lanes."""

    centres: Tensor  # (L, K, 2) normalised u, v
    z: Tensor        # (L, K) height of the curve at the cell (m), the local branch's z prior
    valid: Tensor    # (L, K) bool; inference lanes have different cell counts
    batch: Tensor    # (L,) batch item of each lane
    query: Tensor    # (L,) query (global prediction) the cells follow
    gt: Tensor       # (L,) matched GT lane, -1 at inference

    @property
    def shape(self) -> tuple[int, int]:
        return self.centres.shape[0], self.centres.shape[1]

    def moved_to(self, centres: Tensor) -> AnchorGrid:
        """The same cells re-centred at centres (L, K, 2), kept inside the window."""
        return replace(self, centres=centres.clamp(0, 1))


def lerp_polyline(points: Tensor, frac: Tensor) -> Tensor:
    """Points at fractions (L, K) of polylines (L, P, 3) sampled evenly in arc length."""
    pos = frac.clamp(0, 1) * (points.shape[1] - 1)
    lo = pos.floor().long().clamp(max=points.shape[1] - 2)
    w = (pos - lo).unsqueeze(-1)
    index = lo.unsqueeze(-1).expand(-1, -1, 3)
    return points.gather(1, index) * (1 - w) + points.gather(1, index + 1) * w


def training_anchors(curves: Tensor, matches: list[tuple[Tensor, Tensor]], gt: LaneTargets,
                     cfg: FhldConfig, curve_model: AxisCubicCurve, on_gt: bool = False,
                     generator: torch.Generator | None = None) -> tuple[AnchorGrid, AnchorGrid]:
    """Positive and negative cells for the matched queries of the last decoder layer."""
    device = curves.device
    batch = torch.cat([torch.full((len(p),), b, dtype=torch.long, device=device)
                       for b, (p, _) in enumerate(matches)])
    query = torch.cat([p for p, _ in matches]).to(device)
    gt_idx = torch.cat([g for _, g in matches]).to(device)
    lanes, cells = len(batch), cfg.cells_per_lane
    t = ((torch.arange(cells, device=device) + 0.5) / cells).expand(lanes, -1)
    if on_gt:
        pos = lerp_polyline(gt.points[batch, gt_idx], t)
    else:
        pos = curve_model.evaluate(curves[batch, query].detach(), t)
    centres, z = pos[..., :2].clone(), pos[..., 2].clone()
    if cfg.anchor_noise and cfg.noise_px > 0:
        sigma = cfg.noise_px / cfg.size_px
        noise = torch.randn(centres.shape, device=device, generator=generator) * sigma
        centres = centres + noise.clamp(-2 * sigma, 2 * sigma)
    centres = centres.clamp(0, 1)
    valid = torch.ones(lanes, cells, dtype=torch.bool, device=device)
    positives = AnchorGrid(centres, z, valid, batch, query, gt_idx)

    count = round(cfg.negative_ratio * cells)
    pick = torch.randint(cells, (lanes, count), device=device, generator=generator)
    angle = torch.rand(lanes, count, device=device, generator=generator) * 2 * math.pi
    dist = (1 + 1.5 * torch.rand(lanes, count, device=device, generator=generator)) * cfg.cell_norm
    around = centres.gather(1, pick.unsqueeze(-1).expand(-1, -1, 2))
    neg_centres = (around + dist.unsqueeze(-1) * torch.stack([angle.cos(), angle.sin()], -1))
    negatives = AnchorGrid(neg_centres.clamp(0, 1), z.gather(1, pick), valid[:, :count],
                           batch, query, gt_idx)
    return positives, negatives


def inference_anchors(params: Tensor, batch: Tensor, query: Tensor, cfg: FhldConfig,
                      curve_model: AxisCubicCurve, samples: int = 64) -> AnchorGrid:
    """Cells along curves params (L, 12), denser where the curve bends."""
    device, lanes = params.device, params.shape[0]
    t_dense = torch.linspace(0, 1, samples, device=device)
    dense = curve_model.evaluate(params, t_dense.expand(lanes, -1))
    step_m = (dense[:, 1:, :2] - dense[:, :-1, :2]).norm(dim=-1) * cfg.window_m
    t_mid = (t_dense[1:] + t_dense[:-1]).expand(lanes, -1) / 2
    kappa = curve_model.curvature_xy(params, t_mid) / cfg.window_m  # 1/m
    cum = torch.cat([step_m.new_zeros(lanes, 1),
                     torch.cumsum(step_m * (1 + kappa / cfg.curvature_ref), dim=1)], dim=1)
    total = cum[:, -1]
    spacing_m = cfg.infer_spacing_px * cfg.resolution_m
    count = (total / spacing_m).round().long().clamp(cfg.infer_min_cells, cfg.infer_max_cells)
    cells = int(count.max()) if lanes else 0
    k = torch.arange(cells, device=device)
    levels = (k + 0.5) / count.unsqueeze(1) * total.unsqueeze(1)
    hi = torch.searchsorted(cum, levels.contiguous()).clamp(1, samples - 1)
    c_lo, c_hi = cum.gather(1, hi - 1), cum.gather(1, hi)
    w = ((levels - c_lo) / (c_hi - c_lo).clamp_min(1e-9)).clamp(0, 1)
    t = t_dense[hi - 1] + w * (t_dense[hi] - t_dense[hi - 1])
    pos = curve_model.evaluate(params, t)
    gt = torch.full((lanes,), -1, dtype=torch.long, device=device)
    return AnchorGrid(pos[..., :2].clamp(0, 1), pos[..., 2], k < count.unsqueeze(1), batch,
                      query, gt)
