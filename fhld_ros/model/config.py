"""FhldConfig: every hyper-parameter of the detector and its losses, stored in checkpoints.

Coordinates inside the model ("normalised"): u = (x + L/2) / L, v = (y + L/2) / L with L the
window length (size_px * resolution_m), so u, v are in [0, 1] over the window; z stays in metres.
u runs along the raster width (ix), v along its height (iy), as in the BEV raster.
Pixel quantities (cell size r, anchor noise) are in raster pixels of the configured raster.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from fhld_ros.dataclass_dict import from_dict, to_plain
from fhld_ros.intensity import INTENSITY_ENCODINGS


@dataclass(frozen=True)
class FhldConfig:
    # Raster the checkpoint expects (fhld_ros/bev.py): 640 px at 4 cm = 25.6 m window.
    size_px: int = 640
    resolution_m: float = 0.04
    in_channels: int = 4
    # How channel 0 reads intensity (fhld_ros/intensity.py): 'contrast' against each sweep's
    # ground, the same on every sensor; 'absolute' for weights trained on full-scale intensity.
    intensity_encoding: str = 'contrast'

    # Backbone: slim ResNet-18 (paper widths) + self-attention on the stride-32 map.
    widths: tuple[int, ...] = (16, 32, 64, 128)
    blocks_per_stage: int = 2
    stem_kernel: int = 3              # stem conv k x k, stride 2, + max-pool; ResNet: 7 (+9 ms)
    backbone_attention_layers: int = 1

    # Global branch (DETR-like); the authors' release uses d=128, 4 heads, 3 + 3 layers.
    d_model: int = 128
    n_heads: int = 4
    ffn_dim: int = 256
    enc_layers: int = 3
    dec_layers: int = 3
    dropout: float = 0.0
    num_queries: int = 15

    # Local branch: features F'' at local_stride, RoIAlign roi_size x roi_size bins per cell.
    local_stride: int = 8
    local_channels: int = 32
    roi_size: int = 4
    roi_sampling: int = 1             # 1 = torchvision adaptive for r = 4 cells of stride 8
    local_hidden: int = 128

    # Anchor cells: r x r px, B cells per matched lane when training (paper: r=32, B=40).
    cell_px: int = 32
    cells_per_lane: int = 40
    negative_ratio: float = 0.25      # negatives sampled around positives, per positive
    noise_px: float = 4.0             # std of the position noise on positive anchors
    infer_spacing_px: float = 24.0    # inference: base spacing of cells along a curve
    curvature_ref: float = 0.05       # 1/m; curvature that doubles the inference density
    infer_min_cells: int = 4
    infer_max_cells: int = 60
    min_segment_frac: float = 0.2     # a cell is positive if its GT segment is >= this * r
    bar_width_m: float = 0.15         # w_l; the Gaussian uses 2 * w_l across the segment
    local_score_threshold: float = 0.5
    # Inference: each cell is moved to the segment centre it predicted and classified again,
    # this many times. Training places cells within ~0.3 m of a lane (curve error + noise);
    # a global curve 0.5-1 m off leaves its cells where the head rejects the segment it still
    # locates (docs/accuracy.md). Inference only: any checkpoint.
    local_refine_steps: int = 2

    # Ablation flags (paper Table 2) and training switches.
    adaptive_axis: bool = True        # False: cubic w.r.t. the window x axis
    shape_matching: bool = True       # False: L1 point regression of the segment centre
    smoothness_loss: bool = True      # L_sm on second differences
    anchor_noise: bool = True         # position noise on training anchors
    anchors_on_gt: bool = False       # training anchors along GT instead of predicted curves

    # Losses: lambda1 (classification), lambda2 (KL), lambda3 (smoothness).
    lambda1: float = 1.0
    lambda2: float = 1.0
    lambda3: float = 0.5
    no_lane_weight: float = 1.0       # CE weight of the non-lane class
    z_weight: float = 1.0             # weight of height errors relative to ground-plane ones
    lsm_warmup: int = 2000            # iterations before L_LSM is optimised
    aux_loss: bool = True             # supervise every decoder layer
    match_class_weight: float = 1.0
    match_terminal_weight: float = 1.0
    gt_points: int = 100              # GT lanes are resampled to this many points

    @property
    def window_m(self) -> float:
        return self.size_px * self.resolution_m

    @property
    def z_scale(self) -> float:
        """Factor taking z (m) to normalised units in distances: z_weight / L."""
        return self.z_weight / self.window_m

    @property
    def cell_norm(self) -> float:
        """Cell side r in normalised units."""
        return self.cell_px / self.size_px

    def to_dict(self) -> dict[str, Any]:
        """Plain types only (lists, not tuples), so torch.load(weights_only=True) accepts it."""
        return to_plain(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FhldConfig:
        return from_dict(cls, data, where='the model config')

    def validate(self) -> None:
        """ValueError naming the first unusable value. Every size is bounded (generously: far
        above any real model) so a hostile checkpoint config is refused before a model is
        built (d_model = 2**20 would ask for terabytes)."""
        for name, (low, high) in _INT_BOUNDS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f'{name} must be an integer in [{low}, {high}], got {value!r}')
        for name in _FLOAT_FIELDS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                    math.isfinite(value) and value >= 0):
                raise ValueError(f'{name} must be a finite number >= 0, got {value!r}')
        for name in _BOOL_FIELDS:
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f'{name} must be true or false, got {getattr(self, name)!r}')
        widths = self.widths
        if not isinstance(widths, (tuple, list)) or len(widths) != 4 or not all(
                isinstance(w, int) and not isinstance(w, bool) and 1 <= w <= MAX_WIDTH
                for w in widths):
            raise ValueError(f'widths must be 4 integers in [1, {MAX_WIDTH}], got {widths!r}')
        if self.intensity_encoding not in INTENSITY_ENCODINGS:
            raise ValueError(f'intensity_encoding must be one of '
                             f'{", ".join(INTENSITY_ENCODINGS)}, got {self.intensity_encoding!r}')
        if self.size_px % 32:
            raise ValueError(f'size_px must be a multiple of 32, got {self.size_px}')
        if self.local_stride not in (4, 8, 16, 32):
            raise ValueError(f'local_stride must be 4, 8, 16 or 32, got {self.local_stride}')
        if self.d_model % self.n_heads:
            raise ValueError('d_model must be divisible by n_heads')
        if not self.resolution_m > 0:
            raise ValueError(f'resolution_m must be > 0, got {self.resolution_m}')
        if not self.dropout < 1:
            raise ValueError(f'dropout must be < 1, got {self.dropout}')
        if self.cell_px > self.size_px:
            raise ValueError(f'cell_px {self.cell_px} exceeds size_px {self.size_px}')
        if self.infer_min_cells > self.infer_max_cells:
            raise ValueError('infer_min_cells must be <= infer_max_cells')


MAX_WIDTH = 4096  # channels of any layer
# Inclusive bounds of the integer fields: generous, far above any real model.
_INT_BOUNDS: dict[str, tuple[int, int]] = {
    'size_px': (32, 4096), 'in_channels': (1, 64), 'blocks_per_stage': (1, 64),
    'stem_kernel': (1, 15), 'backbone_attention_layers': (0, 64), 'd_model': (1, MAX_WIDTH),
    'n_heads': (1, 256), 'ffn_dim': (1, 4 * MAX_WIDTH), 'enc_layers': (0, 64),
    'dec_layers': (1, 64), 'num_queries': (1, 1000), 'local_stride': (4, 32),
    'local_channels': (1, MAX_WIDTH), 'roi_size': (1, 64), 'roi_sampling': (1, 16),
    'local_hidden': (1, MAX_WIDTH), 'cell_px': (1, 4096), 'cells_per_lane': (1, 1000),
    'infer_min_cells': (1, 1000), 'infer_max_cells': (1, 1000), 'local_refine_steps': (0, 64),
    'lsm_warmup': (0, 10**9), 'gt_points': (2, 10_000),
}
_FLOAT_FIELDS = ('resolution_m', 'dropout', 'negative_ratio', 'noise_px', 'infer_spacing_px',
                 'curvature_ref', 'min_segment_frac', 'bar_width_m', 'local_score_threshold',
                 'lambda1', 'lambda2', 'lambda3', 'no_lane_weight', 'z_weight',
                 'match_class_weight', 'match_terminal_weight')
_BOOL_FIELDS = ('adaptive_axis', 'shape_matching', 'smoothness_loss', 'anchor_noise',
                'anchors_on_gt', 'aux_loss')
