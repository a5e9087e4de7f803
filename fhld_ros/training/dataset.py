"""Training windows from the cache (cache.py) as a torch Dataset.

Training items are augmented (augment.py) with a generator keyed by (seed, epoch, index), so an
item is the same whatever loader process or resumed run reads it; held-out items are exact
centre crops to the model's raster. With labelled bags (bag_source.py) the training windows
come from several sources, drawn by their weights (SourcesDataset, WeightedSourceSampler).
"""
from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import ConcatDataset, Dataset, DistributedSampler, Sampler

from fhld_ros.data.bag_source import bag_cache
from fhld_ros.data.cache import cache_seeds, read_meta, shard_path
from fhld_ros.errors import ConfigError
from fhld_ros.training.augment import (
    AugmentParams,
    centre_crop,
    sample_similarity,
    similarity_theta,
    warp_lanes,
    warp_raster,
)
from fhld_ros.training.config import TrainConfig, cache_settings

WEIGHTED_DRAWS_KEY = 0x50CE5  # the weighted draws' own generator stream


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
        self.key_offset = 0  # added to the index in the augmentation key (SourcesDataset)
        chosen = cache_seeds(self.cache_dir) if seeds is None else list(seeds)
        self.index: list[tuple[Path, int, int]] = []  # (path, seed, window)
        sizes = set()
        for s in chosen:
            path = shard_path(self.cache_dir, s)
            if not path.exists():
                raise ConfigError(f'cache shard missing: {path}')
            meta = read_meta(path)
            sizes.add((meta['size_px'], meta['resolution_m']))
            self.index.extend((path, s, i) for i in range(meta['windows']))
        if len(sizes) > 1:
            raise ConfigError(f'cache {self.cache_dir} mixes raster specs {sorted(sizes)}')
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
            rng = np.random.default_rng([self.seed, self.epoch, self.key_offset + idx])
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


class SourcesDataset(ConcatDataset):
    """The training windows of several sources (the simulator cache, labelled bags) as one
    dataset, with each source's weight in the draws. The augmentation key of a window is its
    index in the whole, so no two windows share one."""

    def __init__(self, sources: Sequence[CacheDataset], weights: Sequence[float],
                 provenance: Sequence[dict] = ()) -> None:
        super().__init__(sources)
        if len(weights) != len(sources) or not all(w > 0 for w in weights):
            raise ValueError(f'one weight > 0 per source, got {list(weights)}')
        empty = [str(s.cache_dir) for s in sources if not len(s)]
        if empty:
            raise ConfigError(f'training source(s) without windows: {", ".join(empty)}')
        for source, offset in zip(sources, [0, *self.cumulative_sizes[:-1]]):
            source.key_offset = offset
        self.weights = [float(w) for w in weights]
        self.provenance = list(provenance)  # the labelled bags (checkpoint meta)

    def set_epoch(self, epoch: int) -> None:
        for source in self.datasets:
            source.set_epoch(epoch)

    @property
    def sizes(self) -> list[int]:
        return [len(source) for source in self.datasets]


class WeightedSourceSampler(Sampler[int]):
    """Indices into a SourcesDataset: every epoch len(dataset) // num_replicas draws per
    process, each from source i with probability weights[i] / sum(weights) and a window of it
    uniformly (with replacement). The draws are a function of (seed, epoch) alone, split
    between the processes as DistributedSampler splits its permutation (rank::num_replicas), so
    a resumed run draws what the run that never stopped drew."""

    def __init__(self, sizes: Sequence[int], weights: Sequence[float], num_replicas: int = 1,
                 rank: int = 0, seed: int = 0) -> None:
        sizes_a, weights_a = np.asarray(sizes, np.int64), np.asarray(weights, np.float64)
        per_item = np.repeat(weights_a / weights_a.sum() / sizes_a, sizes_a)
        self.p = per_item / per_item.sum()
        self.num_replicas, self.rank, self.seed, self.epoch = num_replicas, rank, seed, 0
        self.num_samples = int(sizes_a.sum()) // num_replicas

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.num_samples

    def __iter__(self) -> Iterator[int]:
        rng = np.random.default_rng([self.seed, self.epoch, WEIGHTED_DRAWS_KEY])
        draws = rng.choice(len(self.p), self.num_samples * self.num_replicas, p=self.p)
        return iter(draws[self.rank::self.num_replicas].tolist())


def training_sampler(dataset: Dataset, num_replicas: int, rank: int,
                     seed: int) -> DistributedSampler | WeightedSourceSampler:
    """The sampler of the training windows: the weighted draws of a SourcesDataset, else (the
    simulator cache alone) a shuffled DistributedSampler, as before labelled bags existed."""
    if isinstance(dataset, SourcesDataset):
        return WeightedSourceSampler(dataset.sizes, dataset.weights, num_replicas, rank, seed)
    return DistributedSampler(dataset, num_replicas=num_replicas, rank=rank, shuffle=True,
                              seed=seed, drop_last=True)


def training_set(cfg: TrainConfig, out_size: int, defer_warp: bool = False,
                 build: bool = False) -> CacheDataset | SourcesDataset:
    """The config's augmented training windows: the simulator cache's seeds, and with data.bags
    a SourcesDataset of it (unless data.sim_weight is 0) and the bags' cached windows (built
    first when missing and build is True; bag_source.bag_cache)."""
    d = cfg.data

    def source(cache_dir: str | os.PathLike, seeds: Sequence[int] | None) -> CacheDataset:
        return CacheDataset(cache_dir, out_size, cfg.augment, cfg.seed, seeds=seeds,
                            defer_warp=defer_warp)

    sim = source(d.train_cache, range(*d.train_seeds)) if d.sim_weight > 0 else None
    if not d.bags:
        return sim
    settings = cache_settings(cfg, 'train')
    indexes = [bag_cache(bag, settings, d.train_cache, build, progress=False)
               for bag in d.bags]
    bags = [source(index['dir'], None) for index in indexes]
    provenance = [{'path': bag.path, 'key': index['key'], 'weight': bag.weight,
                   'windows': len(data), 'lanes_topic': bag.lanes_topic}
                  for bag, index, data in zip(d.bags, indexes, bags)]
    sources = ([sim] if sim is not None else []) + bags
    weights = ([d.sim_weight] if sim is not None else []) + [bag.weight for bag in d.bags]
    return SourcesDataset(sources, weights, provenance)
