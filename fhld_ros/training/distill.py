"""Distillation into a smaller model (train.teacher, train.distill).

The served model's cost on a 2-core CPU sits in two places a retraining can shrink: the
global branch's transformer encoder (~6 ms of ~28 for three layers) and the backbone's 7 x 7
stem (~3 ms). A student differs from its teacher in one part, `train.distill`, and takes every
other layer from the teacher by name and shape, frozen:

- 'global_branch': the student's global branch (e.g. fewer encoder layers) learns the
  teacher's per-query outputs: each query's lane probability (a KL divergence, times
  `class_weight`) and, weighted by that probability, its curve (L1 over the 12 curve numbers,
  times `curve_weight`), at every decoder layer. Queries keep their identity, so no matching
  is needed. Backbone and local branch are the teacher's
  own, so the local segments, which place every published lane point, are unchanged. With
  `no_lane_weight` > 0 a window whose labels hold no lane (an unmarked road) teaches every
  query "no lane" instead of the teacher's probability, times that weight: the teacher's false
  lanes there are unlearnt while every other window holds the student to the teacher.
- 'backbone': the student's backbone (e.g. a 3 x 3 stem) learns the teacher's feature maps at
  strides 4-32 (mean squared error relative to each map's mean square); both branches are the
  teacher's.
- 'stem': as 'backbone', but only a stem of another size (e.g. 5 x 5) and the two stages
  after it (strides 4 and 8) learn; the deeper stages and the backbone's attention stay the
  teacher's too, so the maps the global curves are drawn from move only as far as the first
  stages fail to make up for the stem.
  With `output_weight` > 0 ('backbone', 'stem') the student's maps are also held to what the
  teacher's frozen branches make of them: the local map the local head places every lane point
  on, and the per-query outputs (as for 'global_branch'). A map error of a few per cent spread
  evenly costs little; the same error where the paint is moves lanes.
- 'features': everything the served features graph computes learns at once (e.g. a 3 x 3 stem
  and one encoder layer): the backbone's maps at strides 8-32, the local map that the local
  head reads, and the global branch's per-query outputs as for 'global_branch'. Only the local
  head is the teacher's, frozen: it reads a local map that is held to the teacher's, while the
  layers that make that map may all move to make up for each other (with 'backbone' the frozen
  branches could not absorb what the changed backbone got wrong).

Where the student's part has a layer of the teacher's name and shape it starts from it. A stem
of another kernel size starts from the least-squares fit of the teacher's stem convolution on
the first batch (same stride and centres: the best linear k x k stand-in), so the layers
after it see inputs of the scale they were trained on from the first step. The targets are
what the teacher does on the varied training windows, not the labels, so the student learns
to behave as the teacher (also where the teacher is unsure).
"""
from __future__ import annotations

import torch
from torch import Tensor

from fhld_ros.errors import ConfigError
from fhld_ros.model.checkpoint import load_checkpoint
from fhld_ros.model.detector import FhldDetector

# the layers each part trains (state-dict prefixes); every other layer is the teacher's, frozen
_TRAINED = {'global_branch': ('global_branch.',), 'backbone': ('backbone.',),
            'stem': ('backbone.stem.', 'backbone.stages.0.', 'backbone.stages.1.'),
            'features': ('backbone.', 'local_features.', 'global_branch.')}
PARTS = tuple(_TRAINED)
# curve numbers are normalised window coordinates (0.01 = 26 cm) and heights in metres
CURVE_WEIGHT = 10.0
STEM = 'backbone.stem.conv.weight'
STEM_FIT_PIXELS = 200_000  # output pixels of the first batch the stem's least squares use


class Teacher:
    """The teacher model and the student's distillation loss for one trained part."""

    def __init__(self, path: str, student: FhldDetector, part: str = 'global_branch',
                 copy_weights: bool = True, class_weight: float = 1.0,
                 curve_weight: float = CURVE_WEIGHT, no_lane_weight: float = 0.0,
                 output_weight: float = 0.0) -> None:
        if part not in PARTS:
            raise ValueError(f'train.distill must be one of {", ".join(PARTS)}, not {part!r}')
        loaded = load_checkpoint(path)
        teacher = loaded.model.to(next(student.parameters()).device).eval()
        # the student's checkpoints carry where its teacher came from (meta['teacher'])
        self.provenance = {'path': str(path), 'part': part,
                           'code_version': loaded.code_version,
                           'train_command': loaded.train_command,
                           'meta': {k: v for k, v in loaded.meta.items() if k != 'train_state'}}
        for p in teacher.parameters():
            p.requires_grad_(False)
        self.model, self.part = teacher, part
        self.class_weight, self.curve_weight = class_weight, curve_weight
        self.no_lane_weight, self.output_weight = no_lane_weight, output_weight
        if teacher.cfg.intensity_encoding != student.cfg.intensity_encoding:
            raise ConfigError(f'train.teacher {path} reads intensity as '
                              f'{teacher.cfg.intensity_encoding!r}, the model section as '
                              f'{student.cfg.intensity_encoding!r}')
        source, target = teacher.state_dict(), student.state_dict()
        matching = {k: v for k, v in source.items()
                    if k in target and target[k].shape == v.shape}
        prefixes = _TRAINED[part]
        differs = sorted(k for k in target if not k.startswith(prefixes) and k not in matching)
        if differs:
            parts = ', '.join(prefix[:-1] for prefix in prefixes)
            raise ConfigError(f'train.teacher {path}: the student may differ from its teacher '
                              f'only in its {parts} (train.distill); it differs at {differs[0]}')
        if copy_weights:
            student.load_state_dict(matching, strict=False)
        # fitted on the first batch (losses); a resumed run has it in its weights already
        self.stem_to_fit = copy_weights and STEM.startswith(prefixes) and STEM not in matching
        for name, p in student.named_parameters():
            p.requires_grad_(name.startswith(prefixes))

    def losses(self, student: FhldDetector, raster: Tensor,
               lanes: list[list] | None = None) -> dict[str, Tensor]:
        """Distillation losses of one batch (lanes: each window's labelled lanes, read only for
        no_lane_weight). The student stays in eval mode: batch norm keeps the statistics it was
        given and acts as a fixed scale and shift."""
        student.eval()
        raster = raster.contiguous(memory_format=torch.channels_last)
        if self.stem_to_fit:
            fit_stem(student.backbone.stem.conv, self.model.backbone.stem.conv, raster)
            self.stem_to_fit = False
        if self.part in ('backbone', 'stem'):
            return self._feature_losses(student, raster, lanes)
        if self.part == 'features':
            return self._features_graph_losses(student, raster, lanes)
        with torch.no_grad():  # one backbone pass serves both: it is the same, and frozen
            feats = student.backbone(raster)
            t_logits, t_curves = self.model.global_branch(feats[32])
        s_logits, s_curves = student.global_branch(feats[32])
        return self._query_losses(s_logits, s_curves, t_logits, t_curves, lanes)

    def _query_losses(self, s_logits: Tensor, s_curves: Tensor, t_logits: Tensor,
                      t_curves: Tensor, lanes: list[list] | None) -> dict[str, Tensor]:
        """The global branch's per-query terms: lane probability (KL) and curve (L1)."""
        p_lane = t_logits.softmax(-1)  # (layers, B, N, 2)
        target, weight = p_lane, torch.ones_like(p_lane[..., 0])
        if self.no_lane_weight > 0 and lanes is not None:
            empty = torch.tensor([len(window) == 0 for window in lanes], device=p_lane.device)
            target = torch.where(empty[:, None, None], p_lane.new_tensor([1.0, 0.0]), p_lane)
            weight = torch.where(empty[:, None], self.no_lane_weight, weight)
        kl = (target * (target.clamp_min(1e-8).log() - s_logits.log_softmax(-1))).sum(-1)
        curve = (s_curves - t_curves).abs().sum(-1) * p_lane[..., 1]
        loss_class = self.class_weight * (weight * kl).mean()
        loss_curve = self.curve_weight * curve.mean()
        return {'loss': loss_class + loss_curve, 'loss_cls': loss_class,
                'loss_curve': loss_curve,
                'prob_err': (s_logits.softmax(-1)[..., 1] - p_lane[..., 1]).abs().max()}

    def _feature_losses(self, student: FhldDetector, raster: Tensor,
                        lanes: list[list] | None) -> dict[str, Tensor]:
        with torch.no_grad():
            target = self.model.backbone(raster)
        feats = student.backbone(raster)
        per_stride = {s: relative_error(feats[s], t) for s, t in target.items()}
        loss = sum(per_stride.values(), torch.zeros((), device=raster.device))
        errors = {f'feature_{s}': value for s, value in per_stride.items()}
        if self.output_weight == 0:
            zero = torch.zeros((), device=raster.device)  # the progress bar's class/curve columns
            return {'loss': loss, 'loss_cls': zero, 'loss_curve': zero, **errors}
        # the branches are frozen here: these terms reach only the student's part
        outputs, errors['feature_local'] = self._branch_losses(student, feats, target, lanes)
        outputs['loss'] = loss + self.output_weight * (outputs['loss'] + errors['feature_local'])
        return {**outputs, **errors}

    def _features_graph_losses(self, student: FhldDetector, raster: Tensor,
                               lanes: list[list] | None) -> dict[str, Tensor]:
        with torch.no_grad():
            target = self.model.backbone(raster)
        feats = student.backbone(raster)
        losses, local = self._branch_losses(student, feats, target, lanes)
        errors = {f'feature_{s}': relative_error(feats[s], target[s]) for s in (8, 16, 32)}
        errors['feature_local'] = local
        losses['loss'] = losses['loss'] + sum(errors.values())
        return {**losses, **errors}

    def _branch_losses(self, student: FhldDetector, feats: dict[int, Tensor],
                       target: dict[int, Tensor], lanes: list[list] | None
                       ) -> tuple[dict[str, Tensor], Tensor]:
        """What the student's branches make of its maps against what the teacher's make of
        its own: the per-query terms and the local map's relative error."""
        with torch.no_grad():
            t_logits, t_curves = self.model.global_branch(target[32])
            t_local = self.model.local_features(target)
        s_logits, s_curves = student.global_branch(feats[32])
        local = relative_error(student.local_features(feats), t_local)
        return self._query_losses(s_logits, s_curves, t_logits, t_curves, lanes), local


def relative_error(value: Tensor, target: Tensor) -> Tensor:
    """Mean squared error relative to the target's mean square (maps of any scale count alike)."""
    return (value - target).pow(2).mean() / target.pow(2).mean().clamp_min(1e-12)


@torch.no_grad()
def fit_stem(conv: torch.nn.Conv2d, teacher: torch.nn.Conv2d, raster: Tensor) -> None:
    """conv's weights := the least-squares k x k kernels that best reproduce teacher's output
    on raster (both without bias, same stride, padding k // 2: the same output centres)."""
    target = torch.nn.functional.conv2d(raster, teacher.weight, None, teacher.stride,
                                        teacher.padding)  # (B, C_out, h, w)
    k = conv.kernel_size[0]
    patches = torch.nn.functional.unfold(raster, k, padding=k // 2, stride=conv.stride)
    x = patches.transpose(1, 2).reshape(-1, patches.shape[1])  # (B h w, C_in k k)
    y = target.flatten(2).transpose(1, 2).reshape(-1, target.shape[1])
    rows = torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(0))
    rows = rows[:STEM_FIT_PIXELS].to(x.device)
    solution = torch.linalg.lstsq(x[rows].double(), y[rows].double()).solution
    conv.weight.copy_(solution.T.reshape(conv.weight.shape).to(conv.weight.dtype))
