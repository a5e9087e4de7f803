"""FhldConfig: every hyper-parameter of the detector and its losses, stored in checkpoints.

Coordinates inside the model ("normalised"): u = (x + L/2) / L, v = (y + L/2) / L with L the
window length (size_px * resolution_m), so u, v are in [0, 1] over the window; z stays in metres.
u runs along the raster width (ix), v along its height (iy), as in the BEV raster.
Pixel quantities (cell size r, anchor noise) are in raster pixels of the configured raster.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fhld_ros.dataclass_dict import check_fields, documented, from_dict, to_plain
from fhld_ros.errors import ConfigError
from fhld_ros.intensity import INTENSITY_ENCODINGS

MAX_WIDTH = 4096  # channels of any layer
# Every field is bounded, generously (far above any real model), so a hostile checkpoint config
# is refused before a model is built (d_model = 2**20 would ask for terabytes).
WIDTH = f'[1, {MAX_WIDTH}]'
LAYERS = '[0, 64]'
SIZE_PX = '[32, 4096]'  # DetectorParams' too
REFINE_STEPS = LAYERS  # DetectorParams' too
WEIGHT = '[0, inf)'  # loss weights, distances, ratios


@dataclass(frozen=True)
class FhldConfig:
    """Every hyper-parameter; each field's doc and the values it takes (dataclass_dict)."""

    size_px: int = documented(640, 'raster side the checkpoint expects (bev.py), cells; a '
                              'multiple of 32', range=SIZE_PX)
    resolution_m: float = documented(0.04, 'raster cell size, m (640 px at 4 cm = 25.6 m)',
                                     range='(0, inf)')
    in_channels: int = documented(4, 'raster channels', range='[1, 64]')
    intensity_encoding: str = documented(
        'contrast', "how channel 0 reads intensity (intensity.py): 'contrast' against each "
        "sweep's ground, the same on every sensor; 'absolute' for weights trained on "
        'full-scale intensity', choices=INTENSITY_ENCODINGS)

    # Backbone: slim ResNet-18 (paper widths) + self-attention on the stride-32 map.
    widths: tuple[int, ...] = documented((16, 32, 64, 128), 'channels of the 4 ResNet stages',
                                         range=WIDTH, length=4)
    blocks_per_stage: int = documented(2, 'residual blocks per stage', range='[1, 64]')
    stem_kernel: int = documented(3, 'stem conv k x k, stride 2, + max-pool; ResNet: 7 (+9 ms)',
                                  range='[1, 15]')
    backbone_attention_layers: int = documented(1, 'self-attention layers on the stride-32 map',
                                                range=LAYERS)

    # Global branch (DETR-like); the authors' release uses d=128, 4 heads, 3 + 3 layers.
    d_model: int = documented(128, 'transformer width; a multiple of n_heads', range=WIDTH)
    n_heads: int = documented(4, 'attention heads', range='[1, 256]')
    ffn_dim: int = documented(256, 'transformer feed-forward width',
                              range=f'[1, {4 * MAX_WIDTH}]')
    enc_layers: int = documented(3, 'transformer encoder layers', range=LAYERS)
    dec_layers: int = documented(3, 'transformer decoder layers', range='[1, 64]')
    dropout: float = documented(0.0, 'transformer dropout', range='[0, 1)')
    num_queries: int = documented(15, 'lane queries', range='[1, 1000]')

    # Local branch: features F'' at local_stride, RoIAlign roi_size x roi_size bins per cell.
    local_stride: int = documented(8, "stride of the local branch's features F''",
                                   choices=(4, 8, 16, 32))
    local_channels: int = documented(32, "channels of F''", range=WIDTH)
    roi_size: int = documented(4, 'RoIAlign bins per cell side', range='[1, 64]')
    roi_sampling: int = documented(1, 'RoIAlign samples per bin; 1 = torchvision adaptive for '
                                   'r = 4 cells of stride 8', range='[1, 16]')
    local_hidden: int = documented(128, 'hidden width of the local head', range=WIDTH)

    # Anchor cells: r x r px, B cells per matched lane when training (paper: r=32, B=40).
    cell_px: int = documented(32, 'anchor cell side r, px; at most size_px', range='[1, 4096]')
    cells_per_lane: int = documented(40, 'training anchor cells B per matched lane',
                                     range='[1, 1000]')
    negative_ratio: float = documented(0.25, 'negatives sampled around positives, per positive',
                                       range=WEIGHT)
    noise_px: float = documented(4.0, 'std of the position noise on positive anchors, px',
                                 range=WEIGHT)
    infer_spacing_px: float = documented(24.0, 'inference: base spacing of cells along a '
                                         'curve, px', range=WEIGHT)
    curvature_ref: float = documented(0.05, 'curvature (1/m) that doubles the inference '
                                      'density', range=WEIGHT)
    infer_min_cells: int = documented(4, 'inference: fewest cells per curve; at most '
                                      'infer_max_cells', range='[1, 1000]')
    infer_max_cells: int = documented(60, 'inference: most cells per curve', range='[1, 1000]')
    min_segment_frac: float = documented(0.2, 'a cell is positive if its GT segment is >= this '
                                         '* r', range=WEIGHT)
    bar_width_m: float = documented(0.15, 'w_l; the Gaussian uses 2 * w_l across the segment',
                                    range=WEIGHT)
    local_score_threshold: float = documented(0.5, 'local head score a cell needs',
                                              range=WEIGHT)
    # Training places cells within ~0.3 m of a lane (curve error + noise); a global curve
    # 0.5-1 m off leaves its cells where the head rejects the segment it still locates
    # (docs/accuracy.md). Inference only: any checkpoint.
    local_refine_steps: int = documented(
        2, 'inference: each cell is moved to the segment centre it predicted and classified '
        'again, this many times', range=REFINE_STEPS)

    # Ablation flags (paper Table 2) and training switches.
    adaptive_axis: bool = documented(True, 'False: cubic w.r.t. the window x axis')
    shape_matching: bool = documented(True, 'False: L1 point regression of the segment centre')
    smoothness_loss: bool = documented(True, 'L_sm on second differences')
    anchor_noise: bool = documented(True, 'position noise on training anchors')
    anchors_on_gt: bool = documented(False, 'training anchors along GT instead of predicted '
                                     'curves')

    # Losses: lambda1 (classification), lambda2 (KL), lambda3 (smoothness).
    lambda1: float = documented(1.0, 'classification loss weight', range=WEIGHT)
    lambda2: float = documented(1.0, 'KL (shape) loss weight', range=WEIGHT)
    lambda3: float = documented(0.5, 'smoothness loss weight', range=WEIGHT)
    no_lane_weight: float = documented(1.0, 'CE weight of the non-lane class', range=WEIGHT)
    z_weight: float = documented(1.0, 'weight of height errors relative to ground-plane ones',
                                 range=WEIGHT)
    lsm_warmup: int = documented(2000, 'iterations before L_LSM is optimised',
                                 range=f'[0, {10**9}]')
    aux_loss: bool = documented(True, 'supervise every decoder layer')
    match_class_weight: float = documented(1.0, 'matching cost of the class', range=WEIGHT)
    match_terminal_weight: float = documented(1.0, 'matching cost of the end points',
                                              range=WEIGHT)
    gt_points: int = documented(100, 'GT lanes are resampled to this many points',
                                range='[2, 10000]')

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

    def validate(self, where: str = '') -> None:
        """ConfigError naming every unusable value (fields as `where.name`)."""
        check_fields(self, where)
        at = f'{where}.' if where else ''
        problems = []
        if self.size_px % 32:
            problems.append(f'{at}size_px must be a multiple of 32, not {self.size_px}')
        if self.d_model % self.n_heads:
            problems.append(f'{at}d_model {self.d_model} must be a multiple of {at}n_heads '
                            f'{self.n_heads}')
        if self.cell_px > self.size_px:
            problems.append(f'{at}cell_px {self.cell_px} exceeds {at}size_px {self.size_px}')
        if self.infer_min_cells > self.infer_max_cells:
            problems.append(f'{at}infer_min_cells {self.infer_min_cells} exceeds '
                            f'{at}infer_max_cells {self.infer_max_cells}')
        if problems:
            raise ConfigError('; '.join(problems))
