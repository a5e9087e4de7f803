"""SALAD's training data: samples resampled to the virtual camera once and packed on disk, one
shard per simulated drive (`simulated_shard`) or per DATASET_SHARD_SAMPLES samples of a dataset
on disk (`dataset_shards`: ONCE-3DLanes, OpenLane), then read with augmentation and turned into
targets per draw.

A shard (`<name>.npz`) holds `images` (N, H, W, 3) uint8, `points` (M, 3) float32 (every
lane's points, optical frame), `lane_ends` (L,) int64 (each lane's end in points) and
`sample_ends` (N,) int64 (each sample's end in lanes); a shard is written to a temporary name
and renamed, so an interrupted build leaves no half shard and a rerun skips what is done.
"""
from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable
from itertools import islice
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from fhld_ros.salad.augment import IDENTITY, SaladAugment, augment_images, draw
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.sim_source import SEEDS_OWN, DriveVariant, simulated_samples
from fhld_ros.salad.targets import lane_targets
from fhld_ros.salad.virtual_camera import VirtualCamera

SHARD_SUFFIX = '.npz'
DATASET_SHARD_SAMPLES = 256  # ~94 MB of virtual-camera images per shard


def to_virtual(sample: CameraLaneSample, camera: VirtualCamera) -> CameraLaneSample:
    """The sample as the virtual camera sees it (lanes unchanged: same optical frame)."""
    return CameraLaneSample(camera.warp(sample.image, sample.intrinsics), camera.intrinsics,
                            sample.lanes, sample.name)


def temporary_path(path: Path) -> Path:
    """Where a shard is written before it is renamed to path (finished_shards skips it)."""
    return path.with_name(f'.{path.stem}.tmp{SHARD_SUFFIX}')


def write_shard(path: Path, samples: Iterable[CameraLaneSample], camera: VirtualCamera) -> int:
    """Pack the samples, resampled to the camera, into one shard; returns how many."""
    images, lanes, per_sample = [], [], []
    for sample in samples:
        images.append(to_virtual(sample, camera).image)
        kept = [lane.astype(np.float32) for lane in sample.lanes if len(lane) >= 2]
        lanes.extend(kept)
        per_sample.append(len(kept))
    points = np.concatenate(lanes) if lanes else np.zeros((0, 3), dtype=np.float32)
    tmp = temporary_path(path)
    np.savez(tmp, images=np.stack(images) if images else
             np.zeros((0, camera.height, camera.width, 3), dtype=np.uint8),
             points=points, lane_ends=np.cumsum([len(lane) for lane in lanes], dtype=np.int64),
             sample_ends=np.cumsum(per_sample, dtype=np.int64))
    os.replace(tmp, path)
    return len(images)


def simulated_shard_path(out_dir: Path, seed: int, variant: DriveVariant = SEEDS_OWN) -> Path:
    """Where the drive's shard lives; a variant other than the seeds' own is in the name, so
    drives rendered for another variant are never taken for these."""
    return out_dir / f'sim_{seed}{variant.tag()}{SHARD_SUFFIX}'


def simulated_shard(out_dir: Path, seed: int, frames: int, camera: VirtualCamera,
                    variant: DriveVariant = SEEDS_OWN) -> Path:
    """The shard of one simulated drive (skipped when it exists; variant: where its camera
    sits and how its road looks, sim_source.DriveVariant). Rendered at 1.5 times the virtual
    camera's width, so the resampling averages pixels (antialiasing) as it would a real
    high-resolution image."""
    path = simulated_shard_path(out_dir, seed, variant)
    if not path.exists():
        size = (3 * camera.width // 2, round(3 * camera.width // 2 * 9 / 16))
        write_shard(path, simulated_samples(seed, frames, size, variant=variant), camera)
    return path


def dataset_shards(cache: Path, kind: str, source: str,
                   samples: Iterable[CameraLaneSample], camera: VirtualCamera) -> list[Path]:
    """A dataset's samples (kind: 'once', 'openlane'; source: what names it, e.g. its
    resolved folder and split) packed DATASET_SHARD_SAMPLES to a shard as
    <kind>-<digest of source>-<k>.npz. A finished set is recorded in <kind>-<digest>.json and
    reused; an unfinished one is written again. A changed dataset needs another cache."""
    prefix = f'{kind}-{hashlib.sha1(source.encode()).hexdigest()[:10]}'
    index = cache / f'{prefix}.json'
    if index.exists():
        return [cache / name for name in json.loads(index.read_text())['shards']]
    cache.mkdir(parents=True, exist_ok=True)
    shards, count, it = [], 0, iter(samples)
    while chunk := list(islice(it, DATASET_SHARD_SAMPLES)):
        shards.append(cache / f'{prefix}-{len(shards):05d}{SHARD_SUFFIX}')
        count += write_shard(shards[-1], chunk, camera)
    if not count:
        raise ValueError(f'{source}: no labelled images')
    tmp = index.with_name(f'.{index.name}.tmp')
    tmp.write_text(json.dumps({'source': source, 'samples': count,
                               'shards': [p.name for p in shards]}) + '\n')
    os.replace(tmp, index)
    return shards


def finished_shards(cache: Path) -> list[Path]:
    """The shards in cache, without the temporary file of a shard whose writing was cut off
    (pathlib's glob matches names that start with a dot)."""
    return sorted(p for p in cache.glob(f'*{SHARD_SUFFIX}') if not p.name.startswith('.'))


def dataset_sources(cache: Path) -> list[str]:
    """The sources of the finished datasets packed in cache (dataset_shards' indexes)."""
    return [json.loads(p.read_text())['source'] for p in sorted(cache.glob('*.json'))]


class ShardSamples:
    """Every sample of a set of shards, in memory (images stay uint8)."""

    def __init__(self, paths: Iterable[Path], camera: VirtualCamera | None = None) -> None:
        """camera: ValueError naming a shard whose images are not that camera's size."""
        self.images: list[np.ndarray] = []
        self.lanes: list[list[np.ndarray]] = []
        for path in sorted(paths):
            with np.load(path) as shard:
                images = shard['images']
                size = images.shape[1:3]
                if camera is not None and size != (camera.height, camera.width):
                    raise ValueError(f'{path} holds {size[1]}x{size[0]} images, the virtual '
                                     f'camera is {camera.width}x{camera.height}')
                lanes = np.split(shard['points'].astype(np.float64), shard['lane_ends'][:-1]) \
                    if len(shard['lane_ends']) else []
                starts = np.concatenate([[0], shard['sample_ends'][:-1]])
                for image, a, b in zip(images, starts, shard['sample_ends']):
                    self.images.append(image)
                    self.lanes.append(lanes[a:b])

    def __len__(self) -> int:
        return len(self.images)

    def sample(self, index: int, camera: VirtualCamera) -> CameraLaneSample:
        return CameraLaneSample(self.images[index], camera.intrinsics, self.lanes[index],
                                f'sample {index}')


class SaladDataset(Dataset):
    """Augmented images (3, H, W) uint8 and the targets of their lanes as tensors. Each draw of
    an index is augmented anew (seeded by index and epoch, so a resumed run draws the same).
    With `defer_images` the image is only flipped, and its zoom and colour draws come as
    'augment' (6,) for the training loop to apply to the batch (augment.augment_images, on a
    GPU: the loader's share of the work halves)."""

    def __init__(self, samples: ShardSamples, camera: VirtualCamera,
                 aug: SaladAugment | None = None, seed: int = 0,
                 defer_images: bool = False) -> None:
        self.samples, self.camera, self.aug, self.seed = samples, camera, aug, seed
        self.defer_images = defer_images

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, torch.Tensor]:
        """key: (epoch, index), as EpochBatches gives, or an index (drawn as in epoch 0)."""
        epoch, index = key if isinstance(key, tuple) else (0, key)
        sample = self.samples.sample(index, self.camera)
        image, lanes, params = sample.image, sample.lanes, IDENTITY
        if self.aug is not None:
            rng = np.random.default_rng([self.seed, epoch, index])
            image, lanes, params = draw(image, lanes, rng, self.aug)
        image = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)
        params = torch.from_numpy(params)
        if self.aug is not None and not self.defer_images:
            image = augment_images(image[None], params[None], self.camera)[0].round().byte()
            params = torch.from_numpy(IDENTITY)
        t = lane_targets(lanes, self.camera)
        return {'image': image, 'augment': params,
                'seg': torch.from_numpy(t.seg), 'offsets': torch.from_numpy(t.offsets),
                'depth': torch.from_numpy(t.depth),
                'depth_mask': torch.from_numpy(t.depth_mask)}


class EpochBatches(Sampler):
    """Batches of (epoch, index) keys without end, from the batch `first` of the run on: each
    epoch the indices in an order seeded by the epoch, its last partial batch dropped. One
    loader serves a whole slice, so its workers start once, not every epoch, and a resumed run
    draws what an uninterrupted one would have."""

    def __init__(self, size: int, batch: int, first: int = 0) -> None:
        if not 0 < batch <= size:
            raise ValueError(f'a batch of {batch} needs at least {batch} training images; '
                             f'there are {size}')
        self.size, self.batch, self.per_epoch = size, batch, size // batch
        self.epoch, self.skip = divmod(first, self.per_epoch)

    def __iter__(self):
        epoch, skip = self.epoch, self.skip
        while True:
            order = torch.randperm(self.size, generator=torch.Generator().manual_seed(epoch))
            for b in range(skip, self.per_epoch):
                yield [(epoch, i) for i in order[b * self.batch:(b + 1) * self.batch].tolist()]
            epoch, skip = epoch + 1, 0
