"""SaladConfig: what builds a SALAD model and decodes its output; saved in its checkpoint."""
from __future__ import annotations

from dataclasses import dataclass, field

from fhld_ros.salad.virtual_camera import VirtualCamera

STRIDE = 4  # output cells per input pixel, each way (the paper's H/4 x W/4 maps)


@dataclass(frozen=True)
class SaladConfig:
    camera: VirtualCamera = field(default_factory=VirtualCamera)
    widths: tuple[int, ...] = (16, 32, 64, 96, 128)  # stem, then strides 4, 8, 16, 32
    decoder_dim: int = 48
    attention_layers: int = 1  # self-attention over the stride-32 cells (global context)
    # depth z = row_shift[r] + row_scale[r] * dz per output row r (paper eq. 3): the mean and
    # spread of the training set's depths in that row, measured before training (targets.py)
    row_shift: tuple[float, ...] = ()
    row_scale: tuple[float, ...] = ()
    seg_threshold: float = 0.5  # lane cell when its probability exceeds this
    score_threshold: float = 0.5  # a decoded lane is kept when its mean probability does
    max_depth_m: float = 60.0  # lane points decoded farther away are dropped
    pos_weight: float = 4.0  # BCE weight of the (rare) lane cells
    depth_weight: float = 1.0  # lambda of paper eq. 6, for the depth residual
    offset_weight: float = 1.0  # lambda of paper eq. 6, for du, dv

    @property
    def grid(self) -> tuple[int, int]:
        """(width, height) of the output maps."""
        return self.camera.width // STRIDE, self.camera.height // STRIDE

    def validate(self) -> None:
        w, h = self.grid
        if self.camera.width % 32 or self.camera.height % 32:
            raise ValueError(f'the virtual camera must be a multiple of 32 px each way, got '
                             f'{self.camera.width} x {self.camera.height}')
        if self.row_shift and (len(self.row_shift) != h or len(self.row_scale) != h):
            raise ValueError(f'row_shift and row_scale need {h} values (one per output row), '
                             f'got {len(self.row_shift)} and {len(self.row_scale)}')
        if self.row_scale and min(self.row_scale) <= 0:
            raise ValueError('row_scale values must be positive')
