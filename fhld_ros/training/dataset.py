"""Training windows from the cache (cache.py) as a torch Dataset.

Training items are augmented (augment.py) with a generator keyed by (seed, epoch, index), so an
item is the same whatever loader process or resumed run reads it; held-out items are exact
centre crops to the model's raster.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from fhld_ros.training.augment import (
    AugmentParams,
    centre_crop,
    sample_similarity,
    similarity_theta,
    warp_lanes,
    warp_raster,
)
from fhld_ros.training.cache import cache_seeds, read_meta, shard_path


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
            meta = read_meta(path)
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
