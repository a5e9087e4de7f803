"""FHLD training losses: L = L_GSM + L_LSM (paper eq. 4-12).

L_GSM, on the last decoder layer and (cfg.aux_loss) on every earlier one, each with its own
Hungarian matching: lambda1 * cross-entropy (lane / non-lane) + curve fitting L_f: GT points
are projected on the axis of the GT terminals (eq. 5) and compared with the predicted curve at
the same t (eq. 6); the smaller of the two lane orientations counts.
L_LSM, from iteration cfg.lsm_warmup on (paper: 2k): lambda2 * L_kl (symmetric KL between GT
and predicted segment Gaussians) + lambda3 * L_sm (second differences of consecutive outputs)
+ lambda1 * L_cls (cell class) + L_z (squared height error, m^2).
Sums in the paper become means (per point, lane, cell), so weights do not depend on batch size.
Distances are in normalised units with z scaled by cfg.z_scale (see config.py).
Ablations: cfg.shape_matching=False replaces L_kl by an L1 on p_o in half-cell units;
cfg.smoothness_loss=False drops L_sm.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from fhld_ros.model.anchors import AnchorGrid
from fhld_ros.model.cell_targets import cell_targets
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.curve import AxisCubicCurve, make_curve
from fhld_ros.model.local_branch import LocalPrediction
from fhld_ros.model.matcher import HungarianMatcher
from fhld_ros.model.targets import LaneTargets, prepare_targets


def segment_covariance(length: Tensor, heading: Tensor, across: float | Tensor) -> Tensor:
    """Sigma of the bar Gaussian (eq. 9): std l/2 along the heading (unit vector, (..., 2)),
    `across` (twice the bar width w_l) perpendicular to it -> (..., 2, 2)."""
    rot = torch.stack([heading, torch.stack([-heading[..., 1], heading[..., 0]], -1)], -1)
    across = torch.as_tensor(across, dtype=length.dtype, device=length.device)
    var = torch.stack([(length / 2) ** 2, (across ** 2).expand_as(length)], -1)
    return rot @ torch.diag_embed(var) @ rot.transpose(-1, -2)


def gaussian_kl(mu0: Tensor, cov0: Tensor, mu1: Tensor, cov1: Tensor) -> Tensor:
    """KL(N0 || N1) for 2D Gaussians, batched over leading dims."""
    inv1 = torch.linalg.inv(cov1)
    diff = (mu1 - mu0).unsqueeze(-1)
    trace = (inv1 * cov0.transpose(-1, -2)).sum((-1, -2))
    maha = (diff.transpose(-1, -2) @ inv1 @ diff).squeeze(-1).squeeze(-1)
    logdet = torch.logdet(cov1) - torch.logdet(cov0)
    return 0.5 * (trace + maha - 2 + logdet)


def symmetric_kl(mu0: Tensor, cov0: Tensor, mu1: Tensor, cov1: Tensor) -> Tensor:
    """Eq. (11): (KL(g | g^) + KL(g^ | g)) / 2."""
    return 0.5 * (gaussian_kl(mu0, cov0, mu1, cov1) + gaussian_kl(mu1, cov1, mu0, cov0))


def scaled_norm(diff: Tensor, z_scale: float) -> Tensor:
    return (diff * diff.new_tensor([1.0, 1.0, z_scale])).norm(dim=-1)


def curve_fit_loss(curve_model: AxisCubicCurve, params: Tensor, lanes: Tensor,
                   z_scale: float) -> Tensor:
    """L_f (eq. 6) per matched pair: params (n, 12), GT lanes (n, P, 3) -> (n,)."""
    t = curve_model.project(lanes, lanes[:, 0], lanes[:, -1])
    fits = []
    for tt in (t, 1 - t):  # the same GT lane, read in either direction
        fits.append(scaled_norm(curve_model.evaluate(params, tt) - lanes, z_scale).mean(-1))
    return torch.minimum(*fits)


class FhldCriterion:
    def __init__(self, cfg: FhldConfig) -> None:
        self.cfg = cfg
        self.curve_model = make_curve(cfg.adaptive_axis)
        self.matcher = HungarianMatcher(cfg.match_class_weight, cfg.match_terminal_weight,
                                        cfg.z_scale)

    def __call__(self, outputs: dict, targets: Sequence[Sequence[np.ndarray]] | LaneTargets,
                 iteration: int) -> dict[str, Tensor]:
        cfg = self.cfg
        logits = outputs['logits']
        gt = outputs.get('gt') or prepare_targets(targets, cfg, logits.device)
        losses: dict[str, Tensor] = {}
        layers = list(zip(outputs['aux_logits'], outputs['aux_curves'])) if cfg.aux_loss else []
        for i, (lg, cv) in enumerate(layers):
            cls, fit = self.global_loss(lg, cv, gt, self.matcher(lg, cv, gt))
            losses[f'loss_cls_{i}'], losses[f'loss_curve_{i}'] = cls, fit
        matches = outputs.get('matches') or self.matcher(logits, outputs['curves'], gt)
        losses['loss_cls'], losses['loss_curve'] = self.global_loss(
            logits, outputs['curves'], gt, matches)
        total = sum(cfg.lambda1 * v if k.startswith('loss_cls') else v
                    for k, v in losses.items())
        if 'local' in outputs:
            local = self.local_loss(outputs['local'], outputs['anchors'], gt)
            losses.update(local)
            lsm = (cfg.lambda2 * local['loss_shape'] + cfg.lambda3 * local['loss_sm']
                   + cfg.lambda1 * local['loss_cell_cls'] + local['loss_z'])
            losses['loss_lsm'] = lsm
            if iteration >= cfg.lsm_warmup:
                total = total + lsm
        losses['loss'] = total
        return losses

    def global_loss(self, logits: Tensor, curves: Tensor, gt: LaneTargets,
                    matches: list[tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor]:
        """Cross-entropy over all queries and mean L_f over the matched ones."""
        labels = torch.zeros(logits.shape[:2], dtype=torch.long, device=logits.device)
        for b, (pred, _) in enumerate(matches):
            labels[b, pred] = 1
        weight = logits.new_tensor([self.cfg.no_lane_weight, 1.0])
        cls = F.cross_entropy(logits.flatten(0, 1), labels.flatten(), weight=weight)
        batch = torch.cat([torch.full_like(p, b) for b, (p, _) in enumerate(matches)])
        pred = torch.cat([p for p, _ in matches])
        if len(pred) == 0:
            return cls, curves.sum() * 0
        gt_idx = torch.cat([g for _, g in matches])
        fit = curve_fit_loss(self.curve_model, curves[batch, pred], gt.points[batch, gt_idx],
                             self.cfg.z_scale)
        return cls, fit.mean()

    def local_loss(self, local: dict[str, LocalPrediction], anchors: dict[str, AnchorGrid],
                   gt: LaneTargets) -> dict[str, Tensor]:
        cfg = self.cfg
        pos, neg = local['positive'], local['negative']
        tgt_pos = cell_targets(anchors['positive'], gt, cfg)
        tgt_neg = cell_targets(anchors['negative'], gt, cfg)
        zero = pos.logits.sum() * 0 + neg.logits.sum() * 0

        def cat(field: str, gt_field: str | None = None) -> tuple[Tensor, Tensor]:
            """Prediction and GT of one field over positive and negative cells, flat."""
            gt_field = gt_field or field
            return (torch.cat([getattr(p, field).flatten(0, 1) for p in (pos, neg)]),
                    torch.cat([getattr(t, gt_field).flatten(0, 1) for t in (tgt_pos, tgt_neg)]))

        logits, label = cat('logits', 'label')
        out = {'loss_cell_cls': (F.binary_cross_entropy_with_logits(logits, label.float())
                                 if len(logits) else zero)}
        keep = label
        if keep.any():
            (centre, centre_gt), (length, length_gt) = cat('centre'), cat('length')
            (heading, heading_gt), (z, z_gt) = cat('heading'), cat('z')
            if cfg.shape_matching:
                across = 2 * cfg.bar_width_m / cfg.window_m
                cov = segment_covariance(length[keep], heading[keep], across)
                cov_gt = segment_covariance(length_gt[keep], heading_gt[keep], across)
                out['loss_shape'] = symmetric_kl(centre_gt[keep], cov_gt, centre[keep], cov).mean()
            else:
                half = cfg.cell_norm / 2
                out['loss_shape'] = ((centre[keep] - centre_gt[keep]).abs() / half).sum(-1).mean()
            out['loss_z'] = ((z[keep] - z_gt[keep]) ** 2).mean()
        else:
            out['loss_shape'] = out['loss_z'] = zero
        out['loss_sm'] = self.smoothness(pos, tgt_pos.label) if cfg.smoothness_loss else zero
        return out

    def smoothness(self, pred: LocalPrediction, label: Tensor) -> Tensor:
        """L_sm (eq. 12) over runs of three consecutive positive cells of a lane."""
        points = torch.cat([pred.centre, pred.z.unsqueeze(-1)], dim=-1)   # (L, K, 3)
        second = points[:, 2:] - 2 * points[:, 1:-1] + points[:, :-2]
        ok = label[:, 2:] & label[:, 1:-1] & label[:, :-2]
        if not ok.any():
            return points.sum() * 0
        return scaled_norm(second[ok], self.cfg.z_scale).mean()
