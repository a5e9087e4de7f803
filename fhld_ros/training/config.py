"""The training YAML: sections seed, model, data, augment, train (config/*.yaml).

``model`` holds FhldConfig overrides (fhld_ros/model/config.py), ``augment`` the ranges of
training/augment.py; ``data`` and ``train`` are described field by field below (each field's
doc and the values it takes: dataclass_dict.documented). Unknown keys are errors; in
``topologies``, ``none`` is None (the layout's own topology), and ``sensors`` / ``topologies``
also take ``all``.

``base: other.yaml`` (relative to the file) starts from another config: the file's keys are
merged over the base's, mapping by mapping (a list replaces the base's list), so an experiment
states only what it changes (config/experiments/).

``data`` holds the training cache's CacheSettings (data/cache.py) under their own names, but
``train_windows_per_seed`` and ``train_size_px`` (the test cache has ``test_windows_per_seed``
and the model's raster); the raster's resolution and intensity encoding are the model's.

``data.bags`` adds labelled bags (/points, /odom, /lanes_gt) as training windows beside the
simulator cache (data/bag_source.py), each entry a mapping:

    bags:
      - path: out/autolabel/drive_0      # the bag (checked when the config loads)
        weight: 0.5                      # > 0: its share of the draws ...
        lanes_topic: /lanes_gt           # optional: the GT MarkerArray topic
    sim_weight: 1.0                      # ... relative to the simulator cache's (0: bags only)

Each batch item is drawn from source i with probability weight_i / (sim_weight + sum of the
bags' weights), a window of it uniformly (dataset.WeightedSourceSampler).
"""
from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import yaml

from fhld_ros.data.bag_source import LabelledBag
from fhld_ros.data.cache import TEST_SEED_BASE, CacheSettings
from fhld_ros.data.variation import SHARES
from fhld_ros.dataclass_dict import check_fields, documented, from_dict
from fhld_ros.errors import ConfigError
from fhld_ros.model.config import FhldConfig
from fhld_ros.training.augment import AugmentParams
from fhld_ros.training.distill import CURVE_WEIGHT, PARTS

SCHEDULES = ('constant', 'cosine', 'step')
SECTIONS = ('seed', 'model', 'data', 'augment', 'train')
COUNT, NON_NEGATIVE = '[1, inf)', '[0, inf)'
# data keys that name a training-cache setting otherwise; the model sets the raster's
# resolution and intensity encoding, so data cannot
CACHE_KEYS = {'train_windows_per_seed': 'windows_per_seed', 'train_size_px': 'size_px'}
_DATA_KEYS = {name: key for key, name in CACHE_KEYS.items()}
FROM_MODEL = ('resolution_m', 'intensity_encoding')
_SHA256 = re.compile(r'[0-9a-f]{64}')


@dataclass(frozen=True)
class DataSection:
    train_cache: str = documented('.cache/fhld/train', 'training cache directory',
                                  length='[1, inf)')
    test_cache: str = documented('.cache/fhld/test', 'held-out cache directory',
                                 length='[1, inf)')
    train_seeds: tuple[int, int] = documented((0, 240), 'simulator seeds [start, stop)',
                                              range=NON_NEGATIVE, length=2)
    test_seeds: tuple[int, int] = documented(
        (TEST_SEED_BASE, TEST_SEED_BASE + 24), 'held-out seeds [start, stop), apart from '
        'train_seeds', range=NON_NEGATIVE, length=2)
    test_windows_per_seed: int = documented(5, "held-out windows per seed (at the model's "
                                            'raster)', range=COUNT)
    cache_workers: int = documented(2, 'cache-building processes', range=NON_NEGATIVE)
    # labelled bags as more training windows (module doc; data/bag_source.py), cached in
    # <parent of train_cache>/bags/ by the same --cache-only step
    bags: tuple[LabelledBag, ...] = documented((), 'labelled bags (module doc)')
    sim_weight: float = documented(1.0, "the simulator cache's weight among the sources (0: "
                                   'bags only)', range=NON_NEGATIVE)
    # the training cache's settings: larger raster (the model's input is cropped from it after
    # augmentation); training seeds draw sensor and road variation, held-out ones never
    cache: CacheSettings = CacheSettings(size_px=800)

    def validate(self, where: str = 'data') -> None:
        """ConfigError naming the first section part with unusable values."""
        check_fields(self, where)
        self.cache.validate(where, {v: k for k, v in CACHE_KEYS.items()})
        for name in ('train_seeds', 'test_seeds'):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ConfigError(f'{where}.{name} must be [start, stop) with start < stop, '
                                  f'not {list(getattr(self, name))}')
        (a, b), (c, d) = self.train_seeds, self.test_seeds
        if max(a, c) < min(b, d):
            raise ConfigError(f'{where}.train_seeds {[a, b]} and {where}.test_seeds {[c, d]} '
                              'overlap: the test set must be held out')
        if self.sim_weight == 0 and not self.bags:
            raise ConfigError(f'{where}.sim_weight is 0 and there are no {where}.bags: nothing '
                              'to train on')


@dataclass(frozen=True)
class TrainSection:
    iterations: int = documented(3000, 'iterations of the run', range=COUNT)
    batch_size: int = documented(2, 'windows per iteration, per process', range=COUNT)
    lr: float = documented(1e-4, 'Adam learning rate', range=NON_NEGATIVE)
    weight_decay: float = documented(0.0, 'Adam weight decay', range=NON_NEGATIVE)
    schedule: str = documented('cosine', 'learning-rate schedule', choices=SCHEDULES)
    lr_warmup: int = documented(0, 'linear ramp over the first iterations', range=NON_NEGATIVE)
    min_lr_ratio: float = documented(0.1, 'cosine floor', range=NON_NEGATIVE)
    step_milestones: tuple[int, ...] = documented((), "'step': iterations where the lr drops",
                                                  range=NON_NEGATIVE, kind=int)
    step_gamma: float = documented(0.1, "'step': the factor at each milestone",
                                   range=NON_NEGATIVE)
    grad_clip: float = documented(1.0, 'max gradient norm (0: off)', range=NON_NEGATIVE)
    num_workers: int = documented(0, 'DataLoader worker processes', range=NON_NEGATIVE)
    threads: int = documented(0, "torch CPU threads per process (0: torch's default)",
                              range=NON_NEGATIVE)
    log_every: int = documented(10, 'iterations per log line', range=COUNT)
    eval_every: int = documented(500, 'iterations between evaluations', range=COUNT)
    ckpt_every: int = documented(100, 'iterations between checkpoints', range=COUNT)
    eval_windows: int = documented(0, 'test windows per evaluation, evenly spread (0: all)',
                                   range=NON_NEGATIVE)
    eval_batch_size: int = documented(2, 'evaluation batch size', range=COUNT)
    score_threshold: float = documented(0.5, 'lane confidence the evaluation counts',
                                        range='[0, 1]')
    freeze_batchnorm: bool = documented(False, 'BatchNorm layers normalise with their running '
                                        'statistics and keep them (fine-tuning at small '
                                        'batches)')
    init: str = documented('', "a checkpoint whose weights start the run (fine-tuning); '' = "
                           'random initialisation. Only the weights: the model section must '
                           'build the same layers; a resume ignores it')
    init_sha256: str = documented('', 'sha256 (hex) the init file must have; empty = any')
    teacher: str = documented('', "a checkpoint to distil (training/distill.py): the model's "
                              '`distill` part learns its outputs, every other layer is copied '
                              "from it and frozen; '' = train on the labels")
    teacher_sha256: str = documented('', 'sha256 (hex) the teacher file must have; empty = any')
    distill: str = documented('global_branch', 'the part a distillation trains',
                              choices=PARTS)
    distill_class_weight: float = documented(1.0, 'global_branch: weight of the '
                                             'lane-probability (KL) term', range=NON_NEGATIVE)
    distill_curve_weight: float = documented(CURVE_WEIGHT, 'global_branch: weight of the curve '
                                             '(L1) term', range=NON_NEGATIVE)
    distill_no_lane_weight: float = documented(
        0.0, 'global_branch: > 0 = windows without labelled lanes teach "no lane" at this '
        'weight', range=NON_NEGATIVE)
    distill_output_weight: float = documented(
        0.0, "backbone / stem: > 0 = the teacher's local map and per-query outputs, computed "
        "by the frozen branches from the student's maps, are also learnt, at this weight",
        range=NON_NEGATIVE)

    def validate(self, where: str = 'train') -> None:
        check_fields(self, where)
        if self.init and self.teacher:
            raise ConfigError(f'{where}.init and {where}.teacher exclude each other: a '
                              'distillation starts from its teacher')
        for key in ('init', 'teacher'):
            digest = getattr(self, f'{key}_sha256')
            if digest and not _SHA256.fullmatch(digest):
                raise ConfigError(f'{where}.{key}_sha256 must be 64 lower-case hex digits, '
                                  f'not {digest!r}')
            if digest and not getattr(self, key):
                raise ConfigError(f'{where}.{key}_sha256 is given without {where}.{key}')

    def verified(self, key: str) -> str:
        """The file of train.init or train.teacher (`key`), once it is the file the config's
        <key>_sha256 names (when it names one): a recipe runs from the weights it was made
        with or not at all."""
        path, wanted = getattr(self, key), getattr(self, f'{key}_sha256')
        if wanted:
            try:
                got = file_sha256(path)
            except OSError as exc:
                raise ConfigError(f'train.{key} {path}: cannot read it ({exc.strerror})'
                                  ) from None
            if got != wanted:
                raise ConfigError(f'train.{key} {path} has sha256 {got}, the config asks for '
                                  f'{wanted} (train.{key}_sha256): not the file it names')
        return path


@dataclass(frozen=True)
class TrainConfig:
    seed: int = documented(0, 'seed of the run (draws, initialisation)', range=NON_NEGATIVE)
    model: dict = field(default_factory=dict)  # FhldConfig overrides
    data: DataSection = DataSection()
    augment: AugmentParams = AugmentParams()
    train: TrainSection = TrainSection()

    def validate(self) -> None:
        """ConfigError naming the first section with an unusable value."""
        check_fields(self)
        FhldConfig.from_dict(self.model).validate('model')
        self.data.validate('data')
        self.augment.validate('augment')
        self.train.validate('train')
        for i, bag in enumerate(self.data.bags):
            bag.check(f'data.bags[{i}]')


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, 'rb') as f:
        for block in iter(lambda: f.read(1 << 20), b''):
            digest.update(block)
    return digest.hexdigest()


def read_yaml(path: str | os.PathLike, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A config file's mapping with its `base:` chain merged in (module doc)."""
    path = Path(path)
    if path.resolve() in seen:
        chain = ' -> '.join(str(p) for p in (*seen, path.resolve()))
        raise ConfigError(f'{path}: its base chain is a cycle ({chain})')
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except OSError as exc:
        raise ConfigError(f'cannot read config {path}: {exc.strerror}') from None
    except yaml.YAMLError as exc:
        raise ConfigError(f'cannot read config {path}: {" ".join(str(exc).split())}') from None
    if not isinstance(raw, dict):
        raise ConfigError(f'{path}: expected a mapping at the top level')
    base = raw.pop('base', None)
    if base is None:
        return raw
    if not isinstance(base, str) or not base:
        raise ConfigError(f'{path}: base must name a YAML file, not {base!r}')
    if not (path.parent / base).is_file():
        raise ConfigError(f'{path}: its base {base} does not exist ({path.parent / base})')
    return merged(read_yaml(path.parent / base, (*seen, path.resolve())), raw)


def merged(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """over's keys over base's, mapping by mapping; an empty (null) section keeps the base's."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(out.get(key), Mapping) and (value is None or isinstance(value, Mapping)):
            value = merged(out[key], value or {})
        out[key] = value
    return out


def load_config(path: str | os.PathLike) -> TrainConfig:
    """Parse and check a training YAML; ConfigError naming what is wrong."""
    raw = read_yaml(path)
    unknown = sorted(set(raw) - set(SECTIONS))
    if unknown:
        raise ConfigError(f'unknown section(s) {", ".join(map(str, unknown))} '
                          f'(known: base, {", ".join(SECTIONS)})')
    model = raw.get('model') or {}
    model_cfg = FhldConfig.from_dict(model)
    cfg = TrainConfig(seed=raw.get('seed', 0), model=dict(model),
                      data=_data_section(raw.get('data') or {}, model_cfg),
                      augment=_section(AugmentParams, raw.get('augment'), 'augment'),
                      train=_section(TrainSection, raw.get('train'), 'train'))
    cfg.validate()
    return cfg


def _section(cls: type, data: Any, where: str) -> Any:
    """One YAML section as cls (None: the defaults); unknown keys refused."""
    return cls() if data is None else from_dict(cls, data, where=f'section {where}')


def _data_section(data: Any, model: FhldConfig) -> DataSection:
    """The data section: its own keys, and the training cache's settings (module doc)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f'section data must be a mapping, not {type(data).__name__}')
    own = [f.name for f in fields(DataSection) if f.name != 'cache']
    settings = {_DATA_KEYS.get(f.name, f.name): f.name for f in fields(CacheSettings)
                if f.name not in FROM_MODEL}  # data key -> CacheSettings field
    unknown = [str(k) for k in data if k not in own and k not in settings]
    if unknown:
        raise ConfigError(f'unknown key(s) {", ".join(unknown)} in section data '
                          f'(known: {", ".join([*own, *settings])})')
    cache = {settings[k]: v for k, v in data.items() if k in settings}
    for name in ('sensors', 'topologies'):
        if cache.get(name) == 'all':
            cache[name] = getattr(CacheSettings, name)
    if isinstance(cache.get('topologies'), list):
        cache['topologies'] = [None if t in ('none', 'None') else t
                               for t in cache['topologies']]
    defaults = {name: getattr(DataSection.cache, name) for name in CACHE_KEYS.values()}
    cache = from_dict(CacheSettings, {**defaults, **cache,
                                      **{name: getattr(model, name) for name in FROM_MODEL}})
    section = from_dict(DataSection, {k: v for k, v in data.items() if k in own})
    bags = section.bags
    if isinstance(bags, tuple):  # else validate names it
        bags = tuple(from_dict(LabelledBag, entry, where=f'data.bags[{i}]')
                     for i, entry in enumerate(bags))
    return replace(section, cache=cache, bags=bags)


def cache_settings(cfg: TrainConfig, split: str) -> CacheSettings:
    """CacheSettings of the train (larger raster) or test (model's raster) cache."""
    model = FhldConfig.from_dict(cfg.model)
    train = replace(cfg.data.cache, resolution_m=model.resolution_m,
                    intensity_encoding=model.intensity_encoding)
    if split == 'train':
        return train
    # held out as simulated: the model's raster, no variation drawn
    return replace(train, windows_per_seed=cfg.data.test_windows_per_seed,
                   size_px=model.size_px, sensor_variation=False, road_look=False,
                   bare_curbs=False, laser_gains=False, **SHARES)
