"""FhldDetector: backbone -> global curves -> dynamic anchor cells -> local segments.

Training: ``outputs = model(raster, targets=targets)``; the last decoder layer is matched to
the GT inside forward so the anchor cells can follow the matched predicted curves; the matches,
prepared GT, anchors and local predictions are returned for the criterion (losses.py).
Inference: ``model.detect(raster, score_threshold)`` -> one Detections per batch item, lanes as
ordered (K, 3) point sequences in window-frame metres. No NMS: one query is one lane. Each
cell is re-centred on the segment it found and classified again (cfg.local_refine_steps), so a
curve that is off by more than the training noise still yields its lane. Lane heights then
follow the surface measured in the raster (heights.py).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor, nn

from fhld_ros.model.anchors import inference_anchors, training_anchors
from fhld_ros.model.backbone import SlimResNet
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.global_branch import GlobalBranch
from fhld_ros.model.heights import refine_lane_heights
from fhld_ros.model.local_branch import LocalFeatures, LocalHead
from fhld_ros.model.matcher import HungarianMatcher
from fhld_ros.model.targets import LaneTargets, prepare_targets, to_metres


@dataclass
class Detections:
    lanes: list[np.ndarray] = field(default_factory=list)  # (K, 3) window-frame m, ordered
    confidences: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # Every global curve above the score threshold, sampled; a curve whose cells the local
    # branch all rejects has no lane, so curves may outnumber lanes.
    curves: list[np.ndarray] = field(default_factory=list)


class FhldDetector(nn.Module):
    def __init__(self, cfg: FhldConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or FhldConfig()
        cfg.validate()
        self.backbone = SlimResNet(cfg.in_channels, cfg.widths, cfg.blocks_per_stage,
                                   cfg.backbone_attention_layers, cfg.n_heads, cfg.stem_kernel)
        self.global_branch = GlobalBranch(cfg)
        self.local_features = LocalFeatures(cfg)
        self.local_head = LocalHead(cfg)
        self.curve_model = self.global_branch.curve_model
        self.matcher = HungarianMatcher(cfg.match_class_weight, cfg.match_terminal_weight,
                                        cfg.z_scale)
        # mkldnn convolutions are several times faster on channels-last tensors on CPU.
        self.to(memory_format=torch.channels_last)

    def check_input(self, raster: Tensor) -> None:
        cfg = self.cfg
        expected = (cfg.in_channels, cfg.size_px, cfg.size_px)
        if raster.ndim != 4 or tuple(raster.shape[1:]) != expected:
            raise ValueError(f'raster must be (B, {", ".join(map(str, expected))}), '
                             f'got {tuple(raster.shape)}')

    def features(self, raster: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        self.check_input(raster)
        feats = self.backbone(raster.contiguous(memory_format=torch.channels_last))
        logits, curves = self.global_branch(feats[32])
        return logits, curves, self.local_features(feats)

    def forward(self, raster: Tensor,
                targets: Sequence[Sequence[np.ndarray]] | LaneTargets | None = None,
                anchors_on_gt: bool | None = None) -> dict:
        """Raw outputs; with targets also matches, anchors and local predictions.

        logits (B, N, 2) and curves (B, N, 12) of the last decoder layer; aux_logits and
        aux_curves hold the earlier layers.
        """
        logits, curves, local_map = self.features(raster)
        out = {'logits': logits[-1], 'curves': curves[-1],
               'aux_logits': list(logits[:-1]), 'aux_curves': list(curves[:-1])}
        if targets is None:
            return out
        gt = prepare_targets(targets, self.cfg, raster.device)
        matches = self.matcher(out['logits'], out['curves'], gt)
        on_gt = self.cfg.anchors_on_gt if anchors_on_gt is None else anchors_on_gt
        positive, negative = training_anchors(out['curves'], matches, gt, self.cfg,
                                              self.curve_model, on_gt=on_gt)
        out.update(gt=gt, matches=matches,
                   anchors={'positive': positive, 'negative': negative},
                   local={'positive': self.local_head(local_map, positive),
                          'negative': self.local_head(local_map, negative)})
        return out

    @torch.inference_mode()
    def detect(self, raster: Tensor, score_threshold: float = 0.5,
               curve_points: int = 0, refine_heights: bool = True,
               features: tuple[Tensor, Tensor, Tensor] | None = None,
               refine_steps: int | None = None) -> list[Detections]:
        """Lanes per batch item. curve_points > 0 also samples each global curve.

        refine_heights: lane heights follow the measured surface in the raster (heights.py);
        False keeps the local branch's own heights. features: this raster's features() computed
        elsewhere (serving_features in inference.py). refine_steps: cell re-centring passes,
        default cfg.local_refine_steps.
        """
        if features is None:
            was_training = self.training
            self.eval()
            try:
                features = self.features(raster)
            finally:
                self.train(was_training)
        logits, curves, local_map = features
        cfg = self.cfg
        prob = logits[-1].softmax(-1)[..., 1]
        batch, query = (prob >= score_threshold).nonzero(as_tuple=True)
        params = curves[-1][batch, query]
        anchors = inference_anchors(params, batch, query, cfg, self.curve_model)
        local = self.local_head(local_map, anchors)
        steps = cfg.local_refine_steps if refine_steps is None else refine_steps
        for _ in range(steps):  # cells follow the segments they found
            local = self.local_head(local_map, anchors.moved_to(local.centre))
        keep = anchors.valid & (local.logits.sigmoid() >= cfg.local_score_threshold)
        keep &= ((local.centre >= 0) & (local.centre <= 1)).all(-1)
        points = torch.cat([local.centre, local.z.unsqueeze(-1)], -1).cpu().numpy()
        reach = (0.5 * local.length.unsqueeze(-1) * local.heading).cpu().numpy()
        keep_np, batch_np = keep.cpu().numpy(), batch.cpu().numpy()
        conf_np = prob[batch, query].cpu().numpy()
        if curve_points:
            t = torch.linspace(0, 1, curve_points, device=params.device)
            sampled = self.curve_model.evaluate(params, t.expand(len(params), -1)).cpu().numpy()
        results = [Detections() for _ in range(raster.shape[0])]
        for i, item in enumerate(batch_np):  # one iteration per detected lane
            det = results[item]
            if curve_points:  # every curve: the global branch's own result
                det.curves.append(to_metres(sampled[i], cfg.window_m))
            lane = points[i][keep_np[i]]
            if len(lane) < 2:
                continue
            lane = with_segment_ends(lane, reach[i][keep_np[i]])
            det.lanes.append(to_metres(lane, cfg.window_m))
            det.confidences = np.append(det.confidences, conf_np[i])
        if refine_heights:
            for item, det in enumerate(results):
                det.lanes = refine_lane_heights(det.lanes, raster[item].cpu().numpy(),
                                                cfg.resolution_m)
        return results


def with_segment_ends(centres: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Ordered cell centres (K, 3) u, v, z plus the outer ends of the first and last segments.

    A lane's first and last cells carry segments reaching past their centres (reach: half the
    segment, (K, 2) along its heading, sign arbitrary); a lane of centres alone stops short by
    half a segment at each end. The end points keep their cell's height.
    """
    ends = []
    for cell, inward in ((0, 1), (-1, -2)):
        step = reach[cell] if reach[cell] @ (centres[cell, :2] - centres[inward, :2]) > 0 \
            else -reach[cell]
        end = centres[cell].copy()
        end[:2] = np.clip(end[:2] + step, 0.0, 1.0)
        ends.append(end)
    return np.concatenate([ends[0][None], centres, ends[1][None]])
