"""Distillation of a checkpoint's global branch into a smaller one (train.teacher).

The global branch's transformer encoder runs on every window and costs ~6 ms of the served
model's ~28 on a 2-core CPU for its three layers. A student with fewer encoder layers takes
every other layer from the teacher by name and shape (the backbone, the local branch, the
decoder, the heads, the first encoder layers) and keeps the backbone and local branch frozen,
so the local segments, which place every published lane point, come from the teacher's own
weights. Only the global branch trains, towards the teacher's per-query outputs on the
training windows: each query's lane probability (a KL divergence) and, weighted by that
probability, its curve (L1 over the 12 curve numbers), at every decoder layer. Queries keep
their identity, so no matching is needed, and the student learns what the teacher does on
the varied windows rather than the labels alone.
"""
from __future__ import annotations

import torch
from torch import Tensor

from fhld_ros.model.checkpoint import load_checkpoint
from fhld_ros.model.detector import FhldDetector

TRAINED_PREFIX = 'global_branch.'
CURVE_WEIGHT = 10.0  # curve numbers are normalised window coordinates: 0.01 = 26 cm


class Teacher:
    """The teacher model and the student's distillation loss."""

    def __init__(self, path: str, student: FhldDetector, copy_weights: bool = True) -> None:
        loaded = load_checkpoint(path)
        teacher = loaded.model.to(next(student.parameters()).device).eval()
        # the student's checkpoints carry where its teacher came from (meta['teacher'])
        self.provenance = {'path': str(path), 'code_version': loaded.code_version,
                           'train_command': loaded.train_command,
                           'meta': {k: v for k, v in loaded.meta.items() if k != 'train_state'}}
        for p in teacher.parameters():
            p.requires_grad_(False)
        self.model = teacher
        if teacher.cfg.intensity_encoding != student.cfg.intensity_encoding:
            raise ValueError(f'train.teacher {path} reads intensity as '
                             f'{teacher.cfg.intensity_encoding!r}, the model section as '
                             f'{student.cfg.intensity_encoding!r}')
        source = teacher.state_dict()
        target = student.state_dict()
        matching = {k: v for k, v in source.items()
                    if k in target and target[k].shape == v.shape}
        frozen_missing = sorted(k for k in target
                                if not k.startswith(TRAINED_PREFIX) and k not in matching)
        if frozen_missing:
            raise ValueError(f'train.teacher {path}: the student must keep the teacher\'s '
                             f'backbone and local branch; it differs at {frozen_missing[0]}')
        if copy_weights:
            student.load_state_dict(matching, strict=False)
        for name, p in student.named_parameters():
            p.requires_grad_(name.startswith(TRAINED_PREFIX))

    def losses(self, student: FhldDetector, raster: Tensor) -> dict[str, Tensor]:
        """Distillation losses of one batch. One backbone pass serves both (it is the same and
        frozen); the student stays in eval mode, so batch norm keeps the teacher's statistics
        (the global branch has no dropout or batch norm)."""
        student.eval()
        with torch.no_grad():
            feats = student.backbone(raster.contiguous(memory_format=torch.channels_last))
            t_logits, t_curves = self.model.global_branch(feats[32])
        s_logits, s_curves = student.global_branch(feats[32])
        p_lane = t_logits.softmax(-1)
        kl = (p_lane * (p_lane.clamp_min(1e-8).log() - s_logits.log_softmax(-1))).sum(-1)
        curve = (s_curves - t_curves).abs().sum(-1) * p_lane[..., 1]
        loss_class, loss_curve = kl.mean(), CURVE_WEIGHT * curve.mean()
        return {'loss': loss_class + loss_curve, 'loss_cls': loss_class,
                'loss_curve': loss_curve,
                'prob_err': (s_logits.softmax(-1)[..., 1] - p_lane[..., 1]).abs().max()}

