"""Labelled bags as training windows beside the simulator cache (data.bags of the training YAML).

A labelled bag holds /points (sensor_msgs/PointCloud2), /odom (nav_msgs/Odometry) and GT lanes
on /lanes_gt (visualization_msgs/MarkerArray, the /lanes contract): what `fhld simulate` writes,
or a drive labelled by hand or by `fhld autolabel`. Its sweeps go through the node's own pipeline
(pipeline.LanePipeline: cloud decoding, odometry interpolation at the sweep stamp, the rolling
grid), and the window of every sweep that ends one is kept: windows of sweeps_per_sample sweeps,
one every `stride` sweeps, the rule and accumulation of the simulator's windows
(samples.window_ends, samples.accumulation). A window's GT is the newest /lanes_gt message at or
before its stamp, brought into the window frame and cut to the window square as the simulator's
GT is (samples.lanes_in_window). Windows before the first label, or in another frame than the
labels (sweeps the odometry did not cover), are skipped and counted. A bag without /odom gives
single sweeps in the cloud frame, as the node does without odometry (its labels must be in
that frame then), one window every `stride` sweeps from the first.

The windows are stored as simulator shards (cache.pack_samples, WINDOWS_PER_SHARD each) in a
folder per bag beside the simulator cache, ``<parent of data.train_cache>/bags/<bag name>-<key>``;
the key hashes the bag's files (names, sizes, modification times), the raster settings and the
GT topic, so a changed bag or other settings get a folder of their own and never mix in.
INDEX_NAME is written last: a folder without it is an interrupted build, redone from the start.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from fhld_ros.bagio import BagError, bag_topics, read_lane_sets, read_messages, topic_counts
from fhld_ros.bev import BevSpec
from fhld_ros.data.cache import (
    SHARD_FORMAT,
    CacheSettings,
    pack_samples,
    shard_path,
    write_shard,
)
from fhld_ros.data.samples import TrainingSample, accumulation, lanes_in_window, window_ends
from fhld_ros.errors import ConfigError
from fhld_ros.parameters import DetectorParams
from fhld_ros.pipeline import LanePipeline
from fhld_ros.rolling_grid import BevWindow
from msg_adapters.lanes import LaneSet

BAG_FORMAT = 1  # raise when the windows of the same bag and settings would change
POINTS, ODOM, LANES_GT = '/points', '/odom', '/lanes_gt'
TOPIC_TYPES = {POINTS: 'sensor_msgs/msg/PointCloud2', ODOM: 'nav_msgs/msg/Odometry'}
MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'
WINDOWS_PER_SHARD = 16  # ~10 MB of float32 rasters each at 800 px while a shard is packed
INDEX_NAME = 'bag.json'


@dataclass(frozen=True)
class LabelledBag:
    """One entry of data.bags: a labelled bag and its weight in the draws."""

    path: str = ''
    weight: float = 1.0  # share of the draws, relative to data.sim_weight and the other bags
    lanes_topic: str = LANES_GT  # the GT lanes (MarkerArray)

    def check(self, where: str) -> None:
        """ConfigError (one line, naming `where`) unless the bag can give training windows."""
        if not isinstance(self.path, str) or not self.path:
            raise ConfigError(f'{where}.path must name a bag')
        if isinstance(self.weight, bool) or not isinstance(self.weight, (int, float)) or \
                not (math.isfinite(self.weight) and self.weight > 0):
            raise ConfigError(f'{where}.weight must be a number > 0, not {self.weight!r}')
        if not isinstance(self.lanes_topic, str) or not self.lanes_topic.startswith('/'):
            raise ConfigError(f'{where}.lanes_topic must be a topic name, not '
                              f'{self.lanes_topic!r}')
        try:
            types, counts = bag_topics(self.path), topic_counts(self.path)
        except BagError as exc:
            raise ConfigError(f'{where}: {exc}') from exc
        required = {POINTS: TOPIC_TYPES[POINTS], self.lanes_topic: MARKER_ARRAY}
        for topic in required:
            if topic not in types:
                raise ConfigError(f'{where}: bag {self.path} has no topic {topic} (it has: '
                                  f'{", ".join(sorted(types)) or "nothing"})')
            if not counts.get(topic):
                raise ConfigError(f'{where}: bag {self.path} has no messages on {topic}')
        for topic, msgtype in {**required, ODOM: TOPIC_TYPES[ODOM]}.items():
            if topic in types and types[topic] != msgtype:
                raise ConfigError(f'{where}: bag {self.path}: {topic} is {types[topic]}, '
                                  f'not {msgtype}')


def window_settings(settings: CacheSettings) -> dict:
    """What of the simulator's CacheSettings shapes a bag's windows."""
    return {'size_px': settings.size_px, 'resolution_m': settings.resolution_m,
            'sweeps_per_sample': settings.sweeps_per_sample, 'stride': settings.stride,
            'intensity_encoding': settings.intensity_encoding}


def bag_key(bag: LabelledBag, settings: CacheSettings) -> str:
    """Hash of the bag's files (name, size, mtime), the window settings and the GT topic."""
    path = Path(bag.path)
    files = sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]
    stats = [[p.name, st.st_size, st.st_mtime_ns] for p in files for st in [p.stat()]]
    blob = json.dumps({'format': BAG_FORMAT, 'files': stats, 'lanes_topic': bag.lanes_topic,
                       'settings': window_settings(settings)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def bag_cache_dir(bag: LabelledBag, settings: CacheSettings, train_cache: str | os.PathLike,
                  key: str | None = None) -> Path:
    """The bag's folder beside the simulator cache (see the module doc)."""
    name = Path(bag.path).resolve().name
    return Path(train_cache).parent / 'bags' / f'{name}-{key or bag_key(bag, settings)}'


class _NoModel:
    """The pipeline's detector slot: windows are taken, never detected on; the pipeline reads
    the intensity encoding of its grid from it."""

    def __init__(self, intensity_encoding: str) -> None:
        self.intensity_encoding = intensity_encoding

    def __call__(self, window: BevWindow) -> Any:
        raise NotImplementedError('bag windows are not detected on')


class _WindowTaker(LanePipeline):
    """The node's pipeline keeping the window of each inserted sweep whose index is in `ends`
    (the sweeps in insertion order, which the pipeline keeps in stamp order)."""

    def __init__(self, params: DetectorParams, intensity_encoding: str, expect_odometry: bool,
                 ends: set[int]) -> None:
        super().__init__(params, _NoModel(intensity_encoding), expect_odometry)
        self.ends = ends
        self.taken: list[tuple[int, BevWindow, str]] = []  # (sweep, window, its frame)

    def _insert(self, stamp_ns: int, frame: str, cloud: tuple, pose: np.ndarray | None) -> None:
        super()._insert(stamp_ns, frame, cloud, pose)
        sweep = self.counters['clouds'] - 1
        if sweep in self.ends:
            self.taken.append((sweep, self.grid.window(), self.output_frame or frame))


def read_labels(path: str | os.PathLike, topic: str = LANES_GT) -> list[LaneSet]:
    """The GT lane sets of a bag in stamp order (an empty MarkerArray at its log time)."""
    return sorted(read_lane_sets(path, topic), key=lambda s: s.stamp_ns)


def label_at(labels: list[LaneSet], stamps: np.ndarray, stamp_ns: int) -> LaneSet | None:
    """A window's GT: the newest of the lane sets (stamps: theirs, ascending) at or before
    stamp_ns; None before the first."""
    index = int(np.searchsorted(stamps, stamp_ns, side='right')) - 1
    return labels[index] if index >= 0 else None


def bag_samples(bag: LabelledBag, settings: CacheSettings, stats: Counter | None = None,
                progress: bool = False) -> Iterator[TrainingSample]:
    """The training windows of a labelled bag (see the module doc). `stats` counts sweeps,
    windows and what was skipped: dropped_clouds (malformed), bad_odometry, unlabelled
    (windows before the first label), other_frame (windows in another frame than their
    labels). ValueError, saying why, when the bag gives no window at all."""
    stats = Counter() if stats is None else stats
    counts = topic_counts(bag.path)
    labels = read_labels(bag.path, bag.lanes_topic)
    label_stamps = np.array([s.stamp_ns for s in labels], dtype=np.int64)
    spec = BevSpec(settings.size_px, settings.resolution_m)
    accumulate_sec, max_sweeps = accumulation(settings.sweeps_per_sample)
    params = DetectorParams(size_px=settings.size_px, resolution_m=settings.resolution_m,
                            accumulate_sec=accumulate_sec, max_sweeps=max_sweeps)
    sweeps, odometry = counts.get(POINTS, 0), counts.get(ODOM, 0) > 0
    # without odometry every window is one sweep (as in the node), so each sweep is one
    ends = set(window_ends(sweeps, settings.sweeps_per_sample, settings.stride) if odometry
               else range(0, sweeps, settings.stride))
    pipeline = _WindowTaker(params, settings.intensity_encoding, odometry, ends)
    topics = [POINTS] + ([ODOM] if ODOM in counts else [])
    mismatch: set[str] = set()

    def labelled() -> Iterator[TrainingSample]:
        for sweep, window, frame in pipeline.taken:
            label = label_at(labels, label_stamps, window.stamp_ns)
            if label is None:
                stats['unlabelled'] += 1
                continue
            if label.lanes and label.frame_id != frame:
                stats['other_frame'] += 1
                mismatch.add(f'{bag.lanes_topic} in {label.frame_id!r}, windows in {frame!r}')
                continue
            lanes, src = lanes_in_window(label.lanes, window.window_to_output, spec.length_m / 2)
            stats['windows'] += 1
            yield TrainingSample(window.raster, lanes, window.window_to_output, {
                'sweep': sweep, 'stamp_ns': window.stamp_ns, 'label_stamp_ns': label.stamp_ns,
                'line_ids': [int(label.ids[i]) for i in src]})
        pipeline.taken.clear()

    bar = tqdm(total=counts.get(POINTS, 0), unit='sweep', disable=not progress,
               desc=f'bag {Path(bag.path).name}', dynamic_ncols=True)
    with bar:
        for topic, _, msg in read_messages(bag.path, topics):
            if topic == POINTS:
                stats['sweeps'] += 1
                bar.update()
                dropped = pipeline.receive_cloud(msg).dropped
            else:
                dropped = pipeline.receive_odometry(msg).dropped
            if dropped is not None:  # as the node drops it
                stats['dropped_clouds' if topic == POINTS else 'bad_odometry'] += 1
            yield from labelled()
        while pipeline.insert_waiting():  # the last sweeps, past the end of the odometry
            yield from labelled()
    if not stats['windows']:
        why = ', '.join(f'{k} {v}' for k, v in sorted(stats.items()) if k != 'windows')
        raise ConfigError(f'bag {bag.path} gives no training window ({why or "no sweep"}'
                          + ''.join(f'; {m}' for m in sorted(mismatch)) + ')')


def build_bag_cache(bag: LabelledBag, settings: CacheSettings, train_cache: str | os.PathLike,
                    progress: bool = True) -> dict:
    """Pack the bag's windows into its folder (bag_cache_dir) unless they are there; its index
    (read_bag_index). ValueError when the bag gives no window (bag_samples)."""
    key = bag_key(bag, settings)
    out = bag_cache_dir(bag, settings, train_cache, key)
    if (out / INDEX_NAME).exists():
        return read_bag_index(out)
    out.mkdir(parents=True, exist_ok=True)
    for stale in [*out.glob('shard_*.npz'), *out.glob('.shard_*.tmp.npz')]:  # interrupted
        stale.unlink()
    start = time.perf_counter()
    stats: Counter = Counter()
    chunk: list[TrainingSample] = []
    shards = 0

    def flush() -> None:
        nonlocal shards
        meta = {'format': SHARD_FORMAT, 'bag': str(bag.path), 'key': key, 'shard': shards,
                'windows': len(chunk), **window_settings(settings)}
        write_shard(shard_path(out, shards), pack_samples(chunk, meta))
        shards += 1
        chunk.clear()

    for sample in bag_samples(bag, settings, stats, progress):
        chunk.append(sample)
        if len(chunk) == WINDOWS_PER_SHARD:
            flush()
    if chunk:
        flush()
    index = {'format': BAG_FORMAT, 'bag': str(bag.path), 'key': key, 'shards': shards,
             'settings': window_settings(settings), 'lanes_topic': bag.lanes_topic,
             'stats': dict(stats),
             'seconds': round(time.perf_counter() - start, 1)}
    tmp = out / f'.{INDEX_NAME}.{os.getpid()}.tmp'
    tmp.write_text(json.dumps(index, indent=1))
    os.replace(tmp, out / INDEX_NAME)
    print(f'bag {bag.path}: {stats["windows"]} windows from {stats["sweeps"]} sweeps in '
          f'{index["seconds"]:.0f} s -> {out}', file=sys.stderr)
    return read_bag_index(out)


def read_bag_index(out: Path) -> dict:
    """A built bag folder's index: bag, key, settings, stats (windows, sweeps, skips) and
    'dir', the folder."""
    return {**json.loads((out / INDEX_NAME).read_text()), 'dir': str(out)}


def bag_cache(bag: LabelledBag, settings: CacheSettings, train_cache: str | os.PathLike,
              build: bool = True, progress: bool = True) -> dict:
    """The index of the bag's windows, built first when missing (unless build is False:
    then a ConfigError naming the --cache-only step)."""
    out = bag_cache_dir(bag, settings, train_cache)
    if (out / INDEX_NAME).exists():
        return read_bag_index(out)
    if not build:
        raise ConfigError(f'the windows of bag {bag.path} are not cached ({out}); build them '
                          'first with: fhld train --config CONFIG --cache-only')
    return build_bag_cache(bag, settings, train_cache, progress)
