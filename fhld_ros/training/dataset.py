"""Training windows from the cache (cache.py) as a torch Dataset, with joint augmentation.

Augmentation (FHLD paper: shift, rotate, flip, scale, crop) is one similarity transform of the
window plane, p' = s R(theta) F p + t with F the y -> -y mirror, applied to the raster (grid
sampling) and to the GT polylines (the same map, then clipped to the output square again).
"Crop": the output window (the model's size, 640 px) is cut from the cached raster, which for
training is larger (e.g. 800 px as in the paper) so rotated and shifted windows still have data
in their corners. Heights are not scaled: the raster's height channels stay consistent with z.

Raster sampling: a cell is occupied (density > 0) exactly when its nearest source cell is, so
empty cells stay empty and the empty marker is never blended; an occupied cell's channels are
the bilinear mean over the *occupied* source neighbours only (no blending with the zeros of
empty cells), which keeps thin stripes sub-pixel accurate under rotation.
"""
from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import Dataset

from fhld_ros.bev import EMPTY_MIN_HEIGHT
from fhld_ros.sim.gt_lines import clip_to_square

DENSITY = 1  # channel whose zero marks an empty cell (bev.py)
EMPTY_VALUES = (0.0, 0.0, 0.0, EMPTY_MIN_HEIGHT)


@dataclass(frozen=True)
class AugmentParams:
    """Random ranges; each draw is uniform within them."""

    shift_m: float = 1.0  # |t_x|, |t_y| <= shift_m
    rotate_deg: float = 10.0  # |theta| <= rotate_deg
    flip_prob: float = 0.5  # probability of the y -> -y mirror
    scale_min: float = 0.9
    scale_max: float = 1.1

    def validate(self) -> None:
        if self.shift_m < 0 or self.rotate_deg < 0 or not 0 <= self.flip_prob <= 1:
            raise ValueError('augment needs shift_m >= 0, rotate_deg >= 0, 0 <= flip_prob <= 1')
        if not 0 < self.scale_min <= self.scale_max:
            raise ValueError('augment needs 0 < scale_min <= scale_max')


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


class CacheDataset(Dataset):
    """Windows of every shard in a cache directory.

    Items: {'raster': (4, out, out) float32 tensor, 'lanes': list of (K, 3) float64 window-frame
    metres, 'seed': shard seed, 'window': index in the shard}. With `augment` each item is
    transformed with a generator keyed by (seed, epoch, index), so an item is the same whatever
    worker or resumed run loads it; call set_epoch() every epoch. Without it, items are centre
    crops (the held-out evaluation). defer_warp=True leaves the raster as stored (float16, cache
    size) and adds its (2, 3) 'theta' for warp_rasters, so the loop can warp whole batches on
    the GPU instead of in the loader processes.
    """

    def __init__(self, cache_dir: str | os.PathLike, out_size: int | None = None,
                 augment: AugmentParams | None = None, seed: int = 0,
                 seeds: Sequence[int] | None = None, defer_warp: bool = False) -> None:
        from fhld_ros.training.cache import cache_seeds, shard_path

        self.cache_dir = Path(cache_dir)
        self.augment_params = augment
        self.defer_warp = defer_warp
        self.seed, self.epoch = int(seed), 0
        chosen = cache_seeds(self.cache_dir) if seeds is None else list(seeds)
        self.index: list[tuple[Path, int, int]] = []  # (path, seed, window)
        sizes = set()
        for s in chosen:
            path = shard_path(self.cache_dir, s)
            if not path.exists():
                raise FileNotFoundError(f'cache shard missing: {path}')
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z['meta']))
            sizes.add((meta['size_px'], meta['resolution_m']))
            self.index.extend((path, s, i) for i in range(meta['windows']))
        if len(sizes) > 1:
            raise ValueError(f'cache {self.cache_dir} mixes raster specs {sorted(sizes)}')
        self.size_px, self.resolution_m = sizes.pop() if sizes else (out_size or 640, 0.04)
        self.out_size = out_size or self.size_px
        if augment is not None:
            augment.validate()

    def __len__(self) -> int:
        return len(self.index)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def load(self, idx: int, dtype: type = np.float32) -> tuple[Tensor, list[np.ndarray]]:
        """The stored window: raster and lanes, untransformed."""
        path, _, i = self.index[idx]
        with np.load(path, allow_pickle=False) as z:
            raster = torch.from_numpy(z[f'raster_{i:04d}'].astype(dtype, copy=False))
            first, last = z['window_lanes'][i:i + 2]
            offsets = z['lane_offsets'][first:last + 1]
            points = z['lane_points'][offsets[0]:offsets[-1]].astype(np.float64)
        lanes = np.split(points, offsets[1:-1] - offsets[0]) if last > first else []
        return raster, lanes

    def __getitem__(self, idx: int) -> dict:
        _, seed, window = self.index[idx]
        deferred = self.defer_warp and self.augment_params is not None
        raster, lanes = self.load(idx, np.float16 if deferred else np.float32)
        item = {'seed': seed, 'window': window}
        if self.augment_params is None:
            raster, lanes = centre_crop(raster, lanes, self.out_size, self.resolution_m)
        else:
            rng = np.random.default_rng([self.seed, self.epoch, idx])
            transform = sample_similarity(rng, self.augment_params)
            lanes = warp_lanes(lanes, transform, self.out_size, self.resolution_m)
            if deferred:
                item['theta'] = torch.from_numpy(similarity_theta(
                    transform, self.size_px, self.out_size, self.resolution_m)).float()
            else:
                raster = warp_raster(raster, transform, self.out_size, self.resolution_m)
        return {**item, 'raster': raster.contiguous(), 'lanes': lanes}


def collate(items: Sequence[dict]) -> dict:
    """Rasters (and deferred thetas) stacked to (B, ...); lanes, seeds and windows as lists."""
    batch = {'raster': torch.stack([it['raster'] for it in items]),
             'lanes': [it['lanes'] for it in items],
             'seed': [it['seed'] for it in items], 'window': [it['window'] for it in items]}
    if 'theta' in items[0]:
        batch['theta'] = torch.stack([it['theta'] for it in items])
    return batch
