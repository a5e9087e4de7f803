"""`fhld train --config CONFIG [--resume] [--out DIR]`: FHLD training on cached simulator windows.

Data: the training cache (larger rasters, augmented and cropped to the model's input) and a
held-out test cache of other seeds at the model's exact raster (training/cache.py); missing
shards are simulated first (single process; under torchrun the cache must exist, build it with
``--cache-only``). Optimisation as in the FHLD paper: Adam, lr 1e-4 with an optional schedule,
L_LSM switched on after model.lsm_warmup iterations. Every eval_every iterations (and at the
end) the FHLD point metric on the test cache (counts summed over windows) picks best.pt by
F1@10; last.pt (every ckpt_every iterations and on stop) also holds optimizer and RNG state.
Both are fhld_ros.model.checkpoint files (torch.load(weights_only=True)) with the training
config and command line inside; best.pt loads with load_checkpoint like the shipped weights.

Resume is exact: the data order is a function of (seed, epoch), each item's augmentation of
(seed, epoch, index), and last.pt restores weights, Adam state and every rank's torch RNG.
``--max-minutes`` (or SIGINT/SIGTERM) stops after the current iteration with a checkpoint.
Multi-GPU / multi-machine: ``torchrun --nproc-per-node=N $(which fhld) train --config C``
(DDP, nccl on CUDA, gloo on CPU; the batch size is per process; only rank 0 writes/evaluates).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shlex
import signal
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fhld_ros.training.cache import ALL_SENSORS, ALL_TOPOLOGIES, TEST_SEED_BASE

SCHEDULES = ('constant', 'cosine', 'step')


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
    cache_workers: int = 2


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


@dataclass(frozen=True)
class TrainConfig:
    seed: int = 0
    model: dict = field(default_factory=dict)  # FhldConfig overrides
    data: DataSection = DataSection()
    augment: Any = None  # fhld_ros.training.dataset.AugmentParams (None: its defaults); that
    # module imports torch, which `fhld --help` must not wait for
    train: TrainSection = TrainSection()

    def to_dict(self) -> dict:
        def plain(v: Any) -> Any:
            if isinstance(v, dict):
                return {k: plain(x) for k, x in v.items()}
            return [plain(x) for x in v] if isinstance(v, (list, tuple)) else v
        return plain(dataclasses.asdict(self))


def _section(cls: type, data: Any, where: str) -> Any:
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise ValueError(f'section {where} must be a mapping')
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(f'unknown key(s) {", ".join(unknown)} in section {where} '
                         f'(known: {", ".join(known)})')
    defaults = cls()
    out = {}
    for k, v in data.items():
        if isinstance(getattr(defaults, k), tuple):
            if v == 'all':
                v = getattr(defaults, k)
            elif isinstance(v, (list, tuple)):
                v = tuple(None if x in ('none', 'None') else x for x in v)
            else:
                raise ValueError(f'{where}.{k} must be a list' + (
                    ' or "all"' if k in ('sensors', 'topologies') else ''))
        out[k] = v
    return cls(**out)


def load_config(path: str | os.PathLike) -> TrainConfig:
    """Parse and check a training YAML (sections: seed, model, data, augment, train)."""
    import yaml

    from fhld_ros.model.config import FhldConfig
    from fhld_ros.training.dataset import AugmentParams

    text = Path(path).read_text()
    raw = yaml.safe_load(text) or {}
    if not isinstance(raw, dict):
        raise ValueError(f'{path}: expected a mapping at the top level')
    unknown = sorted(set(raw) - {'seed', 'model', 'data', 'augment', 'train'})
    if unknown:
        raise ValueError(f'unknown section(s) {", ".join(unknown)} '
                         '(known: seed, model, data, augment, train)')
    cfg = TrainConfig(seed=int(raw.get('seed', 0)), model=dict(raw.get('model') or {}),
                      data=_section(DataSection, raw.get('data'), 'data'),
                      augment=_section(AugmentParams, raw.get('augment'), 'augment'),
                      train=_section(TrainSection, raw.get('train'), 'train'))
    FhldConfig.from_dict(cfg.model).validate()
    cfg.augment.validate()
    t, d = cfg.train, cfg.data
    if t.schedule not in SCHEDULES:
        raise ValueError(f'train.schedule must be one of {", ".join(SCHEDULES)}')
    if t.iterations < 1 or t.batch_size < 1 or t.eval_every < 1 or t.ckpt_every < 1:
        raise ValueError('train.iterations, batch_size, eval_every, ckpt_every must be >= 1')
    for name in ('train_seeds', 'test_seeds'):
        lo, hi = getattr(d, name)
        if not 0 <= lo < hi:
            raise ValueError(f'data.{name} must be [start, stop) with 0 <= start < stop')
    if max(d.train_seeds[0], d.test_seeds[0]) < min(d.train_seeds[1], d.test_seeds[1]):
        raise ValueError(f'data.train_seeds {list(d.train_seeds)} and data.test_seeds '
                         f'{list(d.test_seeds)} overlap: the test set must be held out')
    return cfg


def cache_settings(cfg: TrainConfig, split: str):
    """CacheSettings of the train (larger raster) or test (model's raster) cache."""
    from fhld_ros.model.config import FhldConfig
    from fhld_ros.training.cache import CacheSettings

    model, d = FhldConfig.from_dict(cfg.model), cfg.data
    train = split == 'train'
    return CacheSettings(
        windows_per_seed=d.train_windows_per_seed if train else d.test_windows_per_seed,
        size_px=d.train_size_px if train else model.size_px,
        resolution_m=model.resolution_m, sweeps_per_sample=d.sweeps_per_sample,
        stride=d.stride, sensors=tuple(d.sensors), topologies=tuple(d.topologies),
        odom_noise_max=d.odom_noise_max, motion_distortion_prob=d.motion_distortion_prob)


def learning_rate(it: int, t: TrainSection) -> float:
    """lr of iteration it (0-based): warm-up ramp times the schedule factor."""
    warm = min(1.0, (it + 1) / t.lr_warmup) if t.lr_warmup > 0 else 1.0
    if t.schedule == 'cosine':
        frac = min(1.0, it / max(1, t.iterations - 1))
        factor = t.min_lr_ratio + (1 - t.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * frac))
    elif t.schedule == 'step':
        factor = t.step_gamma ** sum(it >= m for m in t.step_milestones)
    else:
        factor = 1.0
    return t.lr * warm * factor


# --- distributed ---------------------------------------------------------------------------

@dataclass
class Dist:
    rank: int = 0
    world: int = 1
    device: Any = 'cpu'

    @property
    def main(self) -> bool:
        return self.rank == 0


def setup_distributed(device: str = 'auto') -> Dist:
    """torchrun (WORLD_SIZE > 1): one process group, nccl on CUDA, gloo on CPU."""
    import torch
    import torch.distributed as torch_dist

    cuda = torch.cuda.is_available() if device == 'auto' else device.startswith('cuda')
    world = int(os.environ.get('WORLD_SIZE', '1'))
    if world <= 1:
        return Dist(0, 1, torch.device('cuda' if cuda else 'cpu') if device == 'auto'
                    else torch.device(device))
    local_rank = int(os.environ.get('LOCAL_RANK', '0'))
    if cuda:
        torch.cuda.set_device(local_rank)
        dev = torch.device('cuda', local_rank)
    else:  # share the cores among the processes on this machine
        local_world = int(os.environ.get('LOCAL_WORLD_SIZE', world))
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // local_world))
        dev = torch.device('cpu')
    if not torch_dist.is_initialized():
        torch_dist.init_process_group('nccl' if cuda else 'gloo')
    return Dist(torch_dist.get_rank(), torch_dist.get_world_size(), dev)


def _any_rank(flag: bool, dist: Dist) -> bool:
    """True on every rank if any rank says so (all ranks stop at the same iteration)."""
    if dist.world == 1:
        return flag
    import torch
    import torch.distributed as torch_dist

    t = torch.tensor([float(flag)], device=dist.device)
    torch_dist.all_reduce(t, op=torch_dist.ReduceOp.MAX)
    return bool(t.item())


def _barrier(dist: Dist) -> None:
    if dist.world > 1:
        import torch.distributed as torch_dist
        torch_dist.barrier()


# --- pieces of the loop ---------------------------------------------------------------------

def _tensors(obj: Any) -> Iterator[Any]:
    import torch
    if isinstance(obj, torch.Tensor):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _tensors(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _tensors(v)
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            yield from _tensors(getattr(obj, f.name))


def graph_anchor(outputs: dict):
    """0 with a gradient path to every output. Before L_LSM is switched on the local branch's
    outputs are not in the loss; DDP would wait for their gradients forever, and Adam would see
    the branch's parameters only from then on in one process but from the start under DDP.
    Empty slices: zero gradients without touching values (no 0 * inf)."""
    terms = [t.reshape(-1)[:0].sum() for t in _tensors(outputs)
             if t.requires_grad and t.is_floating_point()]
    return sum(terms[1:], terms[0]) if terms else 0.0


def batch_stream(dataset, batch_size: int, start_it: int, total: int, dist: Dist, seed: int,
                 num_workers: int, pin: bool) -> Iterator[tuple[int, dict]]:
    """(iteration, batch) from start_it to total; epoch e is DistributedSampler's
    permutation for e, so iteration it always sees the same windows."""
    import torch
    from torch.utils.data import DataLoader, DistributedSampler

    from fhld_ros.training.dataset import collate

    sampler = DistributedSampler(dataset, num_replicas=dist.world, rank=dist.rank,
                                 shuffle=True, seed=seed, drop_last=True)
    per_epoch = len(sampler) // batch_size
    if per_epoch == 0:
        raise ValueError(f'{len(dataset)} training windows are fewer than one batch of '
                         f'{batch_size} x {dist.world} processes')
    it = start_it
    while it < total:
        epoch, step = divmod(it, per_epoch)
        sampler.set_epoch(epoch)
        dataset.set_epoch(epoch)
        indices = list(sampler)[step * batch_size:per_epoch * batch_size]
        # its own generator: a DataLoader draws its worker base seed from the global RNG
        # otherwise, which would shift the anchor noise after a resume
        loader = DataLoader(dataset, batch_size=batch_size, sampler=indices, collate_fn=collate,
                            num_workers=num_workers, drop_last=True, pin_memory=pin,
                            generator=torch.Generator().manual_seed(seed * 100_003 + epoch))
        for batch in loader:
            yield it, batch
            it += 1
            if it >= total:
                return


def evaluate(model, dataset, indices: list[int], batch_size: int, score_threshold: float,
             device: Any) -> dict[str, float]:
    """FHLD point metric of model.detect on the given test windows (counts summed)."""
    import torch
    from torch.utils.data import DataLoader

    from fhld_ros.evaluation.metrics import PointCounts, point_counts
    from fhld_ros.training.dataset import collate

    start = time.perf_counter()
    counts = PointCounts()
    loader = DataLoader(dataset, batch_size=batch_size, sampler=indices, collate_fn=collate,
                        generator=torch.Generator())  # leave the global RNG alone
    with torch.inference_mode():
        for batch in loader:
            dets = model.detect(batch['raster'].to(device), score_threshold)
            for det, gt in zip(dets, batch['lanes']):
                counts = counts + point_counts(det.lanes, gt)
    return {**counts.scores(), 'windows': len(indices), 'eval_s': time.perf_counter() - start}


def command_line(args: argparse.Namespace) -> str:
    """The training command as typed (for the checkpoint), rebuilt from the parsed options."""
    world = int(os.environ.get('WORLD_SIZE', '1'))
    argv = ['train', '--config', args.config]
    argv += ['--out', args.out] if args.out else []
    argv += ['--resume'] if args.resume else []
    argv += ['--max-minutes', f'{args.max_minutes:g}'] if args.max_minutes is not None else []
    argv += ['--device', args.device] if args.device != 'auto' else []
    launcher = f'torchrun --nproc-per-node={world} $(which fhld)' if world > 1 else 'fhld'
    return f'{launcher} {shlex.join(argv)}'


class _StopFlag:
    """SIGINT/SIGTERM request a clean stop after the current iteration (a second SIGINT
    interrupts at once)."""

    def __init__(self) -> None:
        self.requested = False
        self._old: dict[int, Any] = {}

    def __enter__(self) -> _StopFlag:
        import threading
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


# --- the training run -----------------------------------------------------------------------

def ensure_caches(cfg: TrainConfig, dist: Dist, deadline: float | None,
                  workers: int | None = None, progress: bool = True) -> bool:
    """Build missing shards (single process only). True when both caches are complete."""
    from fhld_ros.training.cache import build_cache, shard_path

    complete = True
    for split, cache_dir, (lo, hi) in (('test', cfg.data.test_cache, cfg.data.test_seeds),
                                       ('train', cfg.data.train_cache, cfg.data.train_seeds)):
        missing = [s for s in range(lo, hi) if not shard_path(cache_dir, s).exists()]
        if not missing:
            continue
        if dist.world > 1:
            raise ValueError(f'{split} cache {cache_dir} lacks {len(missing)} shards; build it '
                             'first with: fhld train --config CONFIG --cache-only')
        report = build_cache(cache_dir, range(lo, hi), cache_settings(cfg, split),
                             workers=workers or cfg.data.cache_workers, deadline=deadline,
                             progress=progress)
        if report.windows:
            print(f'{split} cache {cache_dir}: {report.windows} windows in '
                  f'{report.seconds:.0f} s ({report.windows_per_hour:.0f} windows/h)',
                  file=sys.stderr)
        complete &= report.complete
    return complete


def _rng_state(dist: Dist) -> dict:
    import torch
    state = {'cpu': torch.get_rng_state()}
    if dist.device.type == 'cuda':  # anchor noise on the GPU draws from the device generator
        state['cuda'] = torch.cuda.get_rng_state(dist.device)
    return state


def _train_state(opt, dist: Dist) -> dict:
    """Optimizer state and every rank's RNG state (a collective call under DDP)."""
    import torch.distributed as torch_dist

    rng = _rng_state(dist)
    if dist.world > 1:
        gathered: list = [None] * dist.world
        torch_dist.all_gather_object(gathered, rng)
    else:
        gathered = [rng]
    return {'optimizer': opt.state_dict(), 'rng': gathered}


def _restore_rng(states: list[dict], dist: Dist, reseed: int) -> None:
    import torch
    if len(states) != dist.world:  # another process count: no exact continuation possible
        torch.manual_seed(reseed)
        return
    torch.set_rng_state(states[dist.rank]['cpu'])
    if 'cuda' in states[dist.rank] and dist.device.type == 'cuda':
        torch.cuda.set_rng_state(states[dist.rank]['cuda'], dist.device)


def train(cfg: TrainConfig, out_dir: Path, resume: bool = False,
          max_minutes: float | None = None, device: str = 'auto', progress: bool = True,
          command: str | None = None) -> dict:
    """Run (or continue) training; returns a summary dict."""
    import numpy as np
    import torch
    from torch.nn.parallel import DistributedDataParallel
    from tqdm import tqdm

    from fhld_ros.model.checkpoint import load_checkpoint, save_checkpoint
    from fhld_ros.model.config import FhldConfig
    from fhld_ros.model.detector import FhldDetector
    from fhld_ros.model.losses import FhldCriterion
    from fhld_ros.training.dataset import AugmentParams, CacheDataset, warp_rasters

    started = time.monotonic()
    deadline = started + 60 * max_minutes if max_minutes is not None else None
    dist = setup_distributed(device)
    command = command or f'fhld train (config seed {cfg.seed})'
    t = cfg.train
    model_cfg = FhldConfig.from_dict(cfg.model)
    model_cfg.validate()
    last_path, best_path = out_dir / 'last.pt', out_dir / 'best.pt'
    if last_path.exists() and not resume:
        raise FileExistsError(f'{last_path} exists: pass --resume to continue it, or choose '
                              'another --out')
    summary: dict[str, Any] = {'out': str(out_dir), 'iteration': 0, 'stopped': None}
    if not ensure_caches(cfg, dist, deadline, progress=progress and dist.main):
        summary['stopped'] = 'time budget reached while building the cache'
        return summary

    if t.threads > 0:
        torch.set_num_threads(t.threads)
    torch.manual_seed(cfg.seed)  # identical initial weights on every rank
    np.random.seed(cfg.seed)
    module = FhldDetector(model_cfg).to(dist.device)
    opt = torch.optim.Adam(module.parameters(), lr=t.lr, weight_decay=t.weight_decay)
    start_it, best_f1, last_eval = 0, -1.0, None
    history: list[str] = []
    torch.manual_seed(cfg.seed + 1 + dist.rank)  # anchor noise / negatives differ per rank
    if resume and last_path.exists():
        ckpt = load_checkpoint(last_path, map_location='cpu')
        if ckpt.config != model_cfg:
            raise ValueError(f'{last_path} was trained with another model config; the config '
                             'file\'s model section must not change across a resume')
        module.load_state_dict(ckpt.model.state_dict())
        state = ckpt.meta['train_state']
        opt.load_state_dict(state['optimizer'])
        start_it, best_f1 = int(ckpt.meta['iteration']), float(ckpt.meta['best_f1'])
        last_eval, history = ckpt.meta.get('eval'), list(ckpt.meta.get('commands', []))
        _restore_rng(state['rng'], dist, cfg.seed + 1 + dist.rank + 7919 * start_it)
        if dist.main:
            print(f'resuming {last_path} at iteration {start_it}', file=sys.stderr)
    history.append(command)
    if dist.device.type == 'cuda':
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    model = (DistributedDataParallel(module, device_ids=[dist.device.index]
                                     if dist.device.type == 'cuda' else None)
             if dist.world > 1 else module)

    # on a GPU the loader only decompresses; the batch is warped (augmented) on the device
    train_set = CacheDataset(cfg.data.train_cache, model_cfg.size_px,
                             cfg.augment or AugmentParams(), cfg.seed,
                             seeds=range(*cfg.data.train_seeds),
                             defer_warp=dist.device.type == 'cuda')
    test_set = CacheDataset(cfg.data.test_cache, model_cfg.size_px, None,
                            seeds=range(*cfg.data.test_seeds))
    n_eval = len(test_set) if t.eval_windows <= 0 else min(t.eval_windows, len(test_set))
    eval_idx = sorted(set(np.linspace(0, len(test_set) - 1, n_eval).round().astype(int)))
    criterion = FhldCriterion(model_cfg)
    if dist.main:
        out_dir.mkdir(parents=True, exist_ok=True)
    log = (out_dir / 'log.jsonl').open('a') if dist.main else None

    def save(path: Path, it: int, with_state: bool) -> None:
        state = _train_state(opt, dist) if with_state else None  # collective: all ranks
        if not dist.main:
            return
        meta = {'iteration': it, 'best_f1': best_f1, 'eval': last_eval,
                'world_size': dist.world, 'commands': history,
                'train_config': cfg.to_dict()}
        if state is not None:
            meta['train_state'] = state
        save_checkpoint(path, module, command, meta)

    def write_log(record: dict) -> None:
        if log is not None:
            log.write(json.dumps(record) + '\n')
            log.flush()

    bar = tqdm(total=t.iterations, initial=start_it, disable=not (progress and dist.main),
               unit='it', dynamic_ncols=True, desc='train')
    sums: dict[str, Any] = {}  # loss tensors summed on the device: one sync per log line
    n_sum, skipped, it_done = 0, 0, start_it
    step_s, tock = 0.0, time.monotonic()
    stream = batch_stream(train_set, t.batch_size, start_it, t.iterations, dist, cfg.seed,
                          t.num_workers, dist.device.type == 'cuda')
    try:
        with _StopFlag() as stop:
            for it, batch in stream:
                lr = learning_rate(it, t)
                for group in opt.param_groups:
                    group['lr'] = lr
                module.train()
                raster = batch['raster'].to(dist.device, non_blocking=True)
                if 'theta' in batch:
                    raster = warp_rasters(raster, batch['theta'].to(dist.device),
                                          model_cfg.size_px)
                outputs = model(raster, targets=batch['lanes'])
                losses = criterion(outputs, batch['lanes'], it)
                opt.zero_grad(set_to_none=True)
                (losses['loss'] + graph_anchor(outputs)).backward()
                norm = torch.nn.utils.clip_grad_norm_(
                    module.parameters(), t.grad_clip if t.grad_clip > 0 else math.inf)
                if torch.isfinite(norm):  # grads are all-reduced: every rank agrees
                    opt.step()
                else:
                    skipped += 1
                it_done = it + 1
                for k, v in losses.items():
                    sums[k] = sums.get(k, 0.0) + v.detach()
                n_sum += 1
                step_s = time.monotonic() - tock  # data loading + step, without eval
                bar.update(1)
                if it_done % t.log_every == 0 or it_done == t.iterations:
                    means = {k: float(v) / n_sum for k, v in sums.items()}
                    bar.set_postfix(loss=f'{means["loss"]:.3f}', cls=f'{means["loss_cls"]:.3f}',
                                    curve=f'{means["loss_curve"]:.4f}',
                                    lsm=f'{means.get("loss_lsm", 0.0):.3f}', lr=f'{lr:.1e}')
                    write_log({'iteration': it_done, 'lr': lr, 's_per_it': step_s,
                               'skipped': skipped, **means})
                    sums, n_sum = {}, 0
                if it_done % t.eval_every == 0 or it_done == t.iterations:
                    if dist.main:
                        last_eval = evaluate(module, test_set, eval_idx, t.eval_batch_size,
                                             t.score_threshold, dist.device)
                        bar.write(f'eval @ {it_done}: ' + ' '.join(
                            f'{k}={v:.1f}' for k, v in last_eval.items() if '@' in k))
                        write_log({'iteration': it_done, 'eval': last_eval})
                        if last_eval['F1@10'] > best_f1:
                            best_f1 = last_eval['F1@10']
                            save(best_path, it_done, with_state=False)
                    _barrier(dist)
                out_of_time = deadline is not None and time.monotonic() + step_s >= deadline
                halt = _any_rank(stop.requested or out_of_time, dist)
                if halt or it_done % t.ckpt_every == 0 or it_done == t.iterations:
                    save(last_path, it_done, with_state=True)
                if halt:
                    summary['stopped'] = 'time budget' if out_of_time else 'signal'
                    break
                tock = time.monotonic()
    finally:
        bar.close()
        if log is not None:
            log.close()
    summary.update(iteration=it_done, best_f1=best_f1, eval=last_eval, skipped_steps=skipped)
    return summary


# --- CLI ------------------------------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--config', required=True, help='training YAML (config/train_cpu.yaml, '
                        'config/train_gpu.yaml)')
    parser.add_argument('--out', help='run directory for last.pt, best.pt, log.jsonl '
                        '(default: out/train/<config name>)')
    parser.add_argument('--resume', action='store_true',
                        help='continue from OUT/last.pt (starts fresh when there is none)')
    parser.add_argument('--max-minutes', type=float,
                        help='stop cleanly with a checkpoint after this much wall time')
    parser.add_argument('--device', default='auto', help='auto (cuda if available), cpu, cuda')
    parser.add_argument('--cache-only', action='store_true',
                        help='only build the missing training/test cache shards')
    parser.add_argument('--workers', type=int,
                        help='cache-building processes (default: data.cache_workers)')
    parser.add_argument('--quiet', action='store_true', help='no progress bars')


def run(args: argparse.Namespace) -> int:
    from fhld_ros.cli import CliError
    from fhld_ros.model.checkpoint import CheckpointError

    path = Path(args.config)
    if not path.is_file():
        raise CliError(f'config not found: {path}')
    if args.max_minutes is not None and args.max_minutes < 0:
        raise CliError(f'--max-minutes must be >= 0, got {args.max_minutes:g}')
    try:
        cfg = load_config(path)
    except (ValueError, TypeError) as exc:
        raise CliError(f'bad config {path}: {exc}') from exc
    except Exception as exc:  # YAML syntax errors
        raise CliError(f'cannot read config {path}: {" ".join(str(exc).split())}') from exc
    out_dir = Path(args.out) if args.out else Path('out/train') / path.stem
    try:
        if args.cache_only:
            deadline = (time.monotonic() + 60 * args.max_minutes
                        if args.max_minutes is not None else None)
            done = ensure_caches(cfg, Dist(), deadline, args.workers, not args.quiet)
            print('cache complete' if done else 'cache incomplete (time budget); run again')
            return 0
        summary = train(cfg, out_dir, args.resume, args.max_minutes, args.device,
                        not args.quiet, command_line(args))
    except (ValueError, FileExistsError, FileNotFoundError, CheckpointError) as exc:
        raise CliError(str(exc)) from exc
    finally:
        import torch.distributed as torch_dist
        if torch_dist.is_available() and torch_dist.is_initialized():
            torch_dist.destroy_process_group()
    if int(os.environ.get('RANK', '0')) == 0:
        how = f'stopped ({summary["stopped"]})' if summary['stopped'] else 'done'
        print(f'{how} at iteration {summary["iteration"]}/{cfg.train.iterations}, best F1@10 '
              f'{summary.get("best_f1", -1):.1f}; {out_dir}' +
              (' (continue with --resume)' if summary['stopped'] else ''))
    return 130 if summary['stopped'] == 'signal' else 0
