"""The training YAML: sections seed, model, data, augment, train (config/train_*.yaml).

``model`` holds FhldConfig overrides (fhld_ros/model/config.py), ``augment`` the ranges of
training/augment.py; ``data`` and ``train`` are described field by field below. Unknown keys
are errors; in lists, ``none`` is None (the layout's own topology), and ``sensors`` /
``topologies`` also take ``all``.

``data.bags`` adds labelled bags (/points, /odom, /lanes_gt) as training windows beside the
simulator cache (training/bag_source.py), each entry a mapping:

    bags:
      - path: out/autolabel/drive_0      # the bag (checked when the config loads)
        weight: 0.5                      # > 0: its share of the draws ...
        lanes_topic: /lanes_gt           # optional: the GT MarkerArray topic
    sim_weight: 1.0                      # ... relative to the simulator cache's (0: bags only)

Each batch item is drawn from source i with probability weight_i / (sim_weight + sum of the
bags' weights), a window of it uniformly (dataset.WeightedSourceSampler).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import yaml

from fhld_ros.data.bag_source import LabelledBag
from fhld_ros.data.cache import ALL_SENSORS, ALL_TOPOLOGIES, TEST_SEED_BASE, CacheSettings
from fhld_ros.data.variation import SHARES
from fhld_ros.dataclass_dict import from_dict
from fhld_ros.model.config import FhldConfig
from fhld_ros.training.augment import AugmentParams
from fhld_ros.training.distill import CURVE_WEIGHT

SCHEDULES = ('constant', 'cosine', 'step')
SECTIONS = ('seed', 'model', 'data', 'augment', 'train')


@dataclass(frozen=True)
class DataSection:
    train_cache: str = '.cache/fhld/train'
    test_cache: str = '.cache/fhld/test'
    train_seeds: tuple[int, int] = (0, 240)  # [start, stop)
    test_seeds: tuple[int, int] = (TEST_SEED_BASE, TEST_SEED_BASE + 24)
    train_windows_per_seed: int = 8
    test_windows_per_seed: int = 5
    train_size_px: int = 800  # cached training raster; the model's input is cropped from it
    sweeps_per_sample: int = 10
    stride: int = 10
    sensors: tuple[str, ...] = ALL_SENSORS
    topologies: tuple[str | None, ...] = ALL_TOPOLOGIES
    odom_noise_max: float = 1.0
    motion_distortion_prob: float = 0.25
    # training seeds draw sensor and road variation (variation.sensor_variation); held-out never
    sensor_variation: bool = False
    road_look: bool = False  # with sensor_variation: pavements (KITTI-like, gutters, seams), tilt
    bare_curbs: bool = False  # with sensor_variation: half the roads without lines at the curbs
    laser_gains: bool = False  # with sensor_variation: half the drives with per-laser gain spread
    # with sensor_variation, shares of the training seeds (training/variation.py): roads
    # without paint, single sweeps without odometry, KITTI-like bright pavement (road_look)
    no_markings_share: float = SHARES['no_markings_share']
    single_sweep_share: float = SHARES['single_sweep_share']
    bright_asphalt_share: float = SHARES['bright_asphalt_share']
    cache_workers: int = 2
    # labelled bags as more training windows (module doc; training/bag_source.py), cached in
    # <parent of train_cache>/bags/ by the same --cache-only step
    bags: tuple[LabelledBag, ...] = ()
    sim_weight: float = 1.0  # the simulator cache's weight among the sources (0: bags only)


@dataclass(frozen=True)
class TrainSection:
    iterations: int = 3000
    batch_size: int = 2  # per process
    lr: float = 1e-4
    weight_decay: float = 0.0
    schedule: str = 'cosine'  # constant | cosine | step
    lr_warmup: int = 0  # linear ramp over the first iterations
    min_lr_ratio: float = 0.1  # cosine floor
    step_milestones: tuple[int, ...] = ()
    step_gamma: float = 0.1
    grad_clip: float = 1.0  # max gradient norm (0: off)
    num_workers: int = 0  # DataLoader worker processes
    threads: int = 0  # torch CPU threads per process (0: torch's default)
    log_every: int = 10
    eval_every: int = 500
    ckpt_every: int = 100
    eval_windows: int = 0  # test windows per evaluation, evenly spread (0: all)
    eval_batch_size: int = 2
    score_threshold: float = 0.5
    # a checkpoint whose weights start the run (fine-tuning); '' = random initialisation.
    # Only the weights: the model section must build the same layers; a resume ignores it
    init: str = ''
    # a checkpoint to distil (training/distill.py): the model section's `distill` part
    # ('global_branch', 'backbone', 'stem' or 'features') learns its outputs, every other layer is
    # copied from it and frozen; '' = train on the labels
    teacher: str = ''
    distill: str = 'global_branch'
    # global_branch: weights of the lane-probability (KL) and curve (L1) terms (distill.py)
    distill_class_weight: float = 1.0
    distill_curve_weight: float = CURVE_WEIGHT
    # global_branch: > 0 = windows without labelled lanes teach "no lane" at this weight
    distill_no_lane_weight: float = 0.0
    # backbone / stem: > 0 = the teacher's local map and per-query outputs, computed by the
    # frozen branches from the student's maps, are also learnt, at this weight
    distill_output_weight: float = 0.0


@dataclass(frozen=True)
class TrainConfig:
    seed: int = 0
    model: dict = field(default_factory=dict)  # FhldConfig overrides
    data: DataSection = DataSection()
    augment: AugmentParams = AugmentParams()
    train: TrainSection = TrainSection()


def _section(cls: type, data: Any, where: str) -> Any:
    """One YAML section as cls: 'all' and 'none' resolved, lists checked, unknown keys refused."""
    if data is None:
        return cls()
    if isinstance(data, dict):
        data = dict(data)
        for item in fields(cls):
            if item.name not in data or not isinstance(item.default, tuple):
                continue
            value = data[item.name]
            if value == 'all':
                value = item.default
            elif isinstance(value, (list, tuple)):
                value = tuple(None if x in ('none', 'None') else x for x in value)
            else:
                raise ValueError(f'{where}.{item.name} must be a list' + (
                    ' or "all"' if item.name in ('sensors', 'topologies') else ''))
            data[item.name] = value
    return from_dict(cls, data, where=f'section {where}')


def load_config(path: str | os.PathLike) -> TrainConfig:
    """Parse and check a training YAML."""
    raw = yaml.safe_load(Path(path).read_text()) or {}
    if not isinstance(raw, dict):
        raise ValueError(f'{path}: expected a mapping at the top level')
    unknown = sorted(set(raw) - set(SECTIONS))
    if unknown:
        raise ValueError(f'unknown section(s) {", ".join(unknown)} '
                         f'(known: {", ".join(SECTIONS)})')
    data = _section(DataSection, raw.get('data'), 'data')
    data = replace(data, bags=tuple(from_dict(LabelledBag, entry, where=f'data.bags[{i}]')
                                    for i, entry in enumerate(data.bags)))
    cfg = TrainConfig(seed=int(raw.get('seed', 0)), model=dict(raw.get('model') or {}),
                      data=data,
                      augment=_section(AugmentParams, raw.get('augment'), 'augment'),
                      train=_section(TrainSection, raw.get('train'), 'train'))
    FhldConfig.from_dict(cfg.model).validate()
    cfg.augment.validate()
    _check(cfg.train, cfg.data)
    return cfg


def _check_non_negative(name: str, value: object) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not (math.isfinite(value) and value >= 0):
        raise ValueError(f'{name} must be a number >= 0, not {value!r}')


def _check(t: TrainSection, d: DataSection) -> None:
    if t.schedule not in SCHEDULES:
        raise ValueError(f'train.schedule must be one of {", ".join(SCHEDULES)}')
    if t.init and t.teacher:
        raise ValueError('train.init and train.teacher exclude each other: a distillation '
                         'starts from its teacher')
    for name in ('distill_class_weight', 'distill_curve_weight', 'distill_no_lane_weight',
                 'distill_output_weight'):
        _check_non_negative(f'train.{name}', getattr(t, name))
    if t.iterations < 1 or t.batch_size < 1 or t.eval_every < 1 or t.ckpt_every < 1:
        raise ValueError('train.iterations, batch_size, eval_every, ckpt_every must be >= 1')
    for name in ('train_seeds', 'test_seeds'):
        lo, hi = getattr(d, name)
        if not 0 <= lo < hi:
            raise ValueError(f'data.{name} must be [start, stop) with 0 <= start < stop')
    if max(d.train_seeds[0], d.test_seeds[0]) < min(d.train_seeds[1], d.test_seeds[1]):
        raise ValueError(f'data.train_seeds {list(d.train_seeds)} and data.test_seeds '
                         f'{list(d.test_seeds)} overlap: the test set must be held out')
    _check_non_negative('data.sim_weight', d.sim_weight)
    if d.sim_weight == 0 and not d.bags:
        raise ValueError('data.sim_weight is 0 and there are no data.bags: nothing to train on')
    for i, bag in enumerate(d.bags):
        bag.check(f'data.bags[{i}]')


def cache_settings(cfg: TrainConfig, split: str) -> CacheSettings:
    """CacheSettings of the train (larger raster) or test (model's raster) cache."""
    model, d = FhldConfig.from_dict(cfg.model), cfg.data
    train = split == 'train'
    return CacheSettings(
        windows_per_seed=d.train_windows_per_seed if train else d.test_windows_per_seed,
        size_px=d.train_size_px if train else model.size_px,
        resolution_m=model.resolution_m, sweeps_per_sample=d.sweeps_per_sample,
        stride=d.stride, sensors=tuple(d.sensors), topologies=tuple(d.topologies),
        odom_noise_max=d.odom_noise_max, motion_distortion_prob=d.motion_distortion_prob,
        intensity_encoding=model.intensity_encoding,
        sensor_variation=d.sensor_variation and train, road_look=d.road_look and train,
        bare_curbs=d.bare_curbs and train, laser_gains=d.laser_gains and train,
        **{name: getattr(d, name) if train else default for name, default in SHARES.items()})
