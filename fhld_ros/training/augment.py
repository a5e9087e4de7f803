"""Joint augmentation of a window's raster and its GT lanes (shift, rotate, flip, scale, crop).

One similarity transform of the window plane, p' = s R(theta) F p + t with F the y -> -y
mirror, is applied to the raster (grid sampling) and to the GT polylines (the same map, then
clipped to the output square again), as in the FHLD paper. "Crop": the output window (the
model's size, 640 px) is cut from the cached raster, which for training is larger (800 px as
in the paper) so rotated and shifted windows still have data in their corners. Heights are not
scaled: the raster's height channels stay consistent with z.

Raster sampling: a cell is occupied (density > 0) exactly when its nearest source cell is, so
empty cells stay empty and the empty marker is never blended; an occupied cell's channels are
the bilinear mean over the *occupied* source neighbours only (no blending with the zeros of
empty cells), which keeps thin stripes sub-pixel accurate under rotation.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from fhld_ros.bev import EMPTY_MIN_HEIGHT
from fhld_ros.dataclass_dict import check_fields, documented
from fhld_ros.errors import ConfigError
from fhld_ros.sim.gt_lines import clip_to_square

DENSITY = 1  # channel whose zero marks an empty cell (bev.py)
EMPTY_VALUES = (0.0, 0.0, 0.0, EMPTY_MIN_HEIGHT)


@dataclass(frozen=True)
class AugmentParams:
    """Random ranges; each draw is uniform within them."""

    shift_m: float = documented(1.0, '|t_x|, |t_y| <= shift_m (m)', range='[0, inf)')
    rotate_deg: float = documented(10.0, '|theta| <= rotate_deg', range='[0, inf)')
    flip_prob: float = documented(0.5, 'probability of the y -> -y mirror', range='[0, 1]')
    scale_min: float = documented(0.9, 'smallest scale', range='(0, inf)')
    scale_max: float = documented(1.1, 'largest scale, >= scale_min', range='(0, inf)')

    def validate(self, where: str = '') -> None:
        """ConfigError naming every unusable range (fields as `where.name`)."""
        check_fields(self, where)
        if self.scale_min > self.scale_max:
            at = f'{where}.' if where else ''
            raise ConfigError(f'{at}scale_min {self.scale_min} exceeds {at}scale_max '
                              f'{self.scale_max}')


@dataclass(frozen=True)
class Similarity:
    """p' = scale * R(angle) * diag(1, -1 if flip else 1) * p + shift (window-plane metres)."""

    angle: float = 0.0  # radians, counter-clockwise
    scale: float = 1.0
    flip: bool = False
    shift: tuple[float, float] = (0.0, 0.0)

    @property
    def matrix(self) -> np.ndarray:
        c, s = math.cos(self.angle), math.sin(self.angle)
        mirror = -1.0 if self.flip else 1.0
        return self.scale * np.array([[c, -s * mirror], [s, c * mirror]])

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        out = np.array(xyz, dtype=np.float64, copy=True)
        out[:, :2] = out[:, :2] @ self.matrix.T + np.asarray(self.shift)
        return out


def sample_similarity(rng: np.random.Generator, params: AugmentParams = AugmentParams()
                      ) -> Similarity:
    angle = math.radians(rng.uniform(-params.rotate_deg, params.rotate_deg))
    scale = rng.uniform(params.scale_min, params.scale_max)
    flip = bool(rng.random() < params.flip_prob)
    shift = tuple(float(v) for v in rng.uniform(-params.shift_m, params.shift_m, 2))
    return Similarity(float(angle), float(scale), flip, shift)  # type: ignore[arg-type]


def similarity_theta(transform: Similarity, size: int, out_size: int, resolution_m: float
                     ) -> np.ndarray:
    """affine_grid's (2, 3) theta: output pixel centres -> source, both normalised to [-1, 1]."""
    half_src, half_out = size * resolution_m / 2, out_size * resolution_m / 2
    inv = np.linalg.inv(transform.matrix)
    # output p' (normalised by half_out) -> source p = inv (p' - t), normalised by half_src
    return np.concatenate([inv * (half_out / half_src),
                           (-inv @ np.asarray(transform.shift) / half_src)[:, None]], axis=1)


def warp_rasters(rasters: Tensor, theta: Tensor, out_size: int) -> Tensor:
    """(B, C, S, S) rasters sampled on (B, 2, 3) thetas -> (B, C, out_size, out_size) float32;
    batched so the training loop can warp on the GPU."""
    src = rasters.float()
    grid = F.affine_grid(theta.to(src), [src.shape[0], src.shape[1], out_size, out_size],
                         align_corners=False)
    occupied = (src[:, DENSITY:DENSITY + 1] > 0).to(src.dtype)
    keep = F.grid_sample(occupied, grid, mode='nearest', padding_mode='zeros',
                         align_corners=False) > 0.5
    sums = F.grid_sample(torch.cat([src * occupied, occupied], 1), grid, mode='bilinear',
                         padding_mode='zeros', align_corners=False)
    values = sums[:, :-1] / sums[:, -1:].clamp_min(1e-6)
    empty = torch.tensor(EMPTY_VALUES, dtype=src.dtype, device=src.device).view(1, -1, 1, 1)
    return torch.where(keep, values, empty)


def warp_raster(raster: Tensor, transform: Similarity, out_size: int, resolution_m: float
                ) -> Tensor:
    """(C, S, S) raster at resolution_m -> (C, out_size, out_size) of the transformed window."""
    theta = similarity_theta(transform, raster.shape[-1], out_size, resolution_m)
    return warp_rasters(raster[None], torch.from_numpy(theta)[None], out_size)[0]


def warp_lanes(lanes: Sequence[np.ndarray], transform: Similarity, out_size: int,
               resolution_m: float) -> list[np.ndarray]:
    moved = [transform.apply(lane) for lane in lanes]
    return clip_to_square(moved, out_size * resolution_m / 2)[0]


def augment(raster: Tensor, lanes: Sequence[np.ndarray], rng: np.random.Generator,
            params: AugmentParams = AugmentParams(), out_size: int | None = None,
            resolution_m: float = 0.04) -> tuple[Tensor, list[np.ndarray]]:
    """Random shift / rotate / flip / scale of a window, cropped to out_size (default: the
    input size), applied jointly to the raster and its GT lanes (window-frame metres)."""
    transform = sample_similarity(rng, params)
    out_size = out_size or raster.shape[-1]
    return (warp_raster(raster, transform, out_size, resolution_m),
            warp_lanes(lanes, transform, out_size, resolution_m))


def centre_crop(raster: Tensor, lanes: Sequence[np.ndarray], out_size: int,
                resolution_m: float) -> tuple[Tensor, list[np.ndarray]]:
    """Exact centre cut (no resampling); with an even margin the cells equal a window
    rasterised at out_size directly."""
    size = raster.shape[-1]
    if size == out_size:
        return raster, list(lanes)
    if out_size > size or (size - out_size) % 2:
        raise ValueError(f'cannot centre-crop a {size} px raster to {out_size} px')
    a = (size - out_size) // 2
    return (raster[:, a:a + out_size, a:a + out_size],
            clip_to_square(list(lanes), out_size * resolution_m / 2)[0])
