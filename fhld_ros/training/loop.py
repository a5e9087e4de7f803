"""The training loop: from the run's state (fresh, or last.pt) to cfg.train.iterations.

Optimisation as in the FHLD paper: Adam, lr 1e-4 with an optional schedule, L_LSM switched on
after model.lsm_warmup iterations. Every eval_every iterations (and at the end) rank 0 scores
the held-out cache with the FHLD point metric (counts summed over windows) and keeps best.pt by
F1@10. last.pt is written every ckpt_every iterations, at the end and when the run stops early:
on its time budget or SIGINT/SIGTERM, which every rank agrees on after the same iteration.
"""
from __future__ import annotations

import dataclasses
import math
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset

from fhld_ros.data.bag_source import bag_cache
from fhld_ros.data.cache import build_cache, shard_path
from fhld_ros.errors import ConfigError
from fhld_ros.evaluation.metrics import PointCounts, point_counts
from fhld_ros.model.checkpoint import load_checkpoint
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.detector import FhldDetector
from fhld_ros.model.losses import FhldCriterion
from fhld_ros.training.augment import warp_rasters
from fhld_ros.training.config import TrainConfig, TrainSection, cache_settings
from fhld_ros.training.dataset import (
    CacheDataset,
    SourcesDataset,
    collate,
    training_sampler,
    training_set,
)
from fhld_ros.training.distill import Teacher
from fhld_ros.training.distributed import Dist, any_rank, barrier, setup_distributed
from fhld_ros.training.resume import RunState, rank_seed, resume_run, save_run
from fhld_ros.training.runlog import LossMeter, RunLog


def train(cfg: TrainConfig, out_dir: Path, resume: bool = False,
          max_minutes: float | None = None, device: str = 'auto', progress: bool = True,
          command: str | None = None) -> dict:
    """Run (or continue) training; returns a summary dict."""
    deadline = time.monotonic() + 60 * max_minutes if max_minutes is not None else None
    dist = setup_distributed(device)
    if (out_dir / 'last.pt').exists() and not resume:
        raise ConfigError(f'{out_dir / "last.pt"} exists: pass --resume to continue it, '
                          'or choose another --out')
    summary: dict[str, Any] = {'out': str(out_dir), 'iteration': 0, 'stopped': None}
    if not ensure_caches(cfg, deadline, progress=progress and dist.main, world=dist.world):
        summary['stopped'] = 'time budget reached while building the cache'
        return summary
    run = start_run(cfg, out_dir, dist, resume, command or f'fhld train (config seed {cfg.seed})')
    train_set, test_set = datasets(cfg, dist)
    if isinstance(train_set, SourcesDataset):  # provenance of the labelled bags
        run.state.bag_sources = train_set.provenance
    summary['stopped'] = fit(run, train_set, test_set, deadline, progress)
    summary.update(iteration=run.state.iteration, best_f1=run.state.best_f1,
                   eval=run.state.last_eval, skipped_steps=run.skipped)
    return summary


def ensure_caches(cfg: TrainConfig, deadline: float | None, workers: int | None = None,
                  progress: bool = True, world: int = 1) -> bool:
    """Build missing shards and labelled bags' windows (single process only). True when every
    cache is complete."""
    complete = True
    for split, cache_dir, (lo, hi) in (('test', cfg.data.test_cache, cfg.data.test_seeds),
                                       ('train', cfg.data.train_cache, cfg.data.train_seeds)):
        if split == 'train' and cfg.data.sim_weight == 0:  # bags only
            continue
        missing = [s for s in range(lo, hi) if not shard_path(cache_dir, s).exists()]
        if not missing:
            continue
        if world > 1:
            raise ConfigError(f'{split} cache {cache_dir} lacks {len(missing)} shards; build it '
                              'first with: fhld train --config CONFIG --cache-only')
        report = build_cache(cache_dir, range(lo, hi), cache_settings(cfg, split),
                             workers=workers or cfg.data.cache_workers, deadline=deadline,
                             progress=progress)
        if report.windows:
            print(f'{split} cache {cache_dir}: {report.windows} windows in '
                  f'{report.seconds:.0f} s ({report.windows_per_hour:.0f} windows/h)',
                  file=sys.stderr)
        complete &= report.complete
    for bag in cfg.data.bags:  # reading a bag takes seconds to minutes, not hours: no deadline
        if deadline is not None and time.monotonic() >= deadline:
            return False
        bag_cache(bag, cache_settings(cfg, 'train'), cfg.data.train_cache, build=world == 1,
                  progress=progress)
    return complete


# --- the run's pieces, in the order a run uses them -------------------------------------------

@dataclass
class Run:
    cfg: TrainConfig
    dist: Dist
    out_dir: Path
    module: FhldDetector
    model: torch.nn.Module  # the module, or its DDP wrapper
    opt: torch.optim.Optimizer
    criterion: FhldCriterion
    state: RunState
    teacher: Teacher | None = None  # train.teacher: a distillation (training/distill.py)
    skipped: int = 0  # steps skipped for a non-finite gradient norm

    def save(self, name: str, with_state: bool) -> None:
        save_run(self.out_dir / name, self.module, self.opt, self.state, self.cfg, self.dist,
                 with_state)


def start_run(cfg: TrainConfig, out_dir: Path, dist: Dist, resume: bool, command: str) -> Run:
    """Model, optimizer and RNG as a fresh run starts them, or as OUT/last.pt left them."""
    t = cfg.train
    model_cfg = FhldConfig.from_dict(cfg.model)
    model_cfg.validate()
    if t.threads > 0:
        torch.set_num_threads(t.threads)
    torch.manual_seed(cfg.seed)  # identical initial weights on every rank
    np.random.seed(cfg.seed)
    module = FhldDetector(model_cfg).to(dist.device)
    opt = torch.optim.Adam(module.parameters(), lr=t.lr, weight_decay=t.weight_decay)
    torch.manual_seed(rank_seed(cfg.seed, dist))  # anchor noise / negatives differ per rank
    state = RunState()
    resuming = resume and (out_dir / 'last.pt').exists()
    if t.init and not resuming:
        init_weights(module, t.verified('init'))
    if t.teacher and dist.world > 1:
        raise ConfigError('train.teacher: a distillation runs in one process')
    teacher = (Teacher(t.verified('teacher'), module, t.distill, copy_weights=not resuming,
                       class_weight=t.distill_class_weight,
                       curve_weight=t.distill_curve_weight,
                       no_lane_weight=t.distill_no_lane_weight,
                       output_weight=t.distill_output_weight) if t.teacher else None)
    if resuming:
        state = resume_run(out_dir / 'last.pt', module, opt, model_cfg, cfg.seed, dist)
        if dist.main:
            print(f'resuming {out_dir / "last.pt"} at iteration {state.iteration}',
                  file=sys.stderr)
    if teacher is not None:
        state.teacher = teacher.provenance
    state.commands.append(command)
    if dist.device.type == 'cuda':
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    model = (DistributedDataParallel(module, device_ids=[dist.device.index]
                                     if dist.device.type == 'cuda' else None)
             if dist.world > 1 else module)
    return Run(cfg, dist, out_dir, module, model, opt, FhldCriterion(model_cfg), state, teacher)


def init_weights(module: FhldDetector, path: str) -> None:
    """Start from another checkpoint's weights (train.init); its layers must match."""
    source = load_checkpoint(path).model.state_dict()
    try:
        module.load_state_dict(source)
    except RuntimeError as exc:
        raise ConfigError(f'train.init {path}: its layers differ from the model section\'s: '
                          f'{str(exc).splitlines()[0]}') from exc


def datasets(cfg: TrainConfig, dist: Dist) -> tuple[Dataset, CacheDataset]:
    """Augmented training windows (with data.bags from several sources) and the held-out test
    windows, at the model's raster."""
    size = FhldConfig.from_dict(cfg.model).size_px
    # on a GPU the loader only decompresses; the batch is warped (augmented) on the device
    train_set = training_set(cfg, size, defer_warp=dist.device.type == 'cuda')
    test_set = CacheDataset(cfg.data.test_cache, size, None, seeds=range(*cfg.data.test_seeds))
    return train_set, test_set


def fit(run: Run, train_set: Dataset, test_set: CacheDataset, deadline: float | None,
        progress: bool) -> str | None:
    """Iterate to the end or to a stop; the reason for an early stop ('time budget', 'signal')."""
    t, dist = run.cfg.train, run.dist
    eval_idx = eval_indices(len(test_set), t.eval_windows)
    if dist.main:
        run.out_dir.mkdir(parents=True, exist_ok=True)
    report = RunLog(run.out_dir / 'log.jsonl' if dist.main else None, t.iterations,
                    run.state.iteration, progress and dist.main)
    meter = LossMeter()
    stream = batch_stream(train_set, t.batch_size, run.state.iteration, t.iterations, dist,
                          run.cfg.seed, t.num_workers, dist.device.type == 'cuda')
    step_s, tock = 0.0, time.monotonic()
    with report, StopFlag() as stop:
        for it, batch in stream:
            lr = learning_rate(it, t)
            meter.add(train_step(run, it, batch, lr))
            done = run.state.iteration = it + 1
            step_s = time.monotonic() - tock  # data loading + step, without eval
            report.bar.update(1)
            if done % t.log_every == 0 or done == t.iterations:
                report.losses(done, lr, step_s, run.skipped, meter.means())
            if done % t.eval_every == 0 or done == t.iterations:
                evaluate_and_keep_best(run, test_set, eval_idx, report)
            out_of_time = deadline is not None and time.monotonic() + step_s >= deadline
            halt = any_rank(stop.requested or out_of_time, dist)
            if halt or done % t.ckpt_every == 0 or done == t.iterations:
                run.save('last.pt', with_state=True)
            if halt:
                return 'time budget' if out_of_time else 'signal'
            tock = time.monotonic()
    return None


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


def batch_stream(dataset: Dataset, batch_size: int, start_it: int, total: int, dist: Dist,
                 seed: int, num_workers: int, pin: bool) -> Iterator[tuple[int, dict]]:
    """(iteration, batch) from start_it to total; epoch e is the sampler's draw for e
    (training_sampler), so iteration it always sees the same windows."""
    sampler = training_sampler(dataset, dist.world, dist.rank, seed)
    per_epoch = len(sampler) // batch_size
    if per_epoch == 0:
        raise ConfigError(f'{len(dataset)} training windows are fewer than one batch of '
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


def train_step(run: Run, it: int, batch: dict, lr: float) -> dict[str, Tensor]:
    """One optimisation step on one batch; its losses, still on the device."""
    for group in run.opt.param_groups:
        group['lr'] = lr
    raster = batch['raster'].to(run.dist.device, non_blocking=True)
    if 'theta' in batch:  # augmentation deferred to the device (datasets())
        raster = warp_rasters(raster, batch['theta'].to(run.dist.device),
                              run.module.cfg.size_px)
    run.opt.zero_grad(set_to_none=True)
    if run.teacher is not None:
        losses = run.teacher.losses(run.module, raster, batch['lanes'])
        losses['loss'].backward()
    else:
        run.module.train()
        if run.cfg.train.freeze_batchnorm:
            for module in run.module.modules():
                if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                    module.eval()
        outputs = run.model(raster, targets=batch['lanes'])
        losses = run.criterion(outputs, batch['lanes'], it)
        (losses['loss'] + graph_anchor(outputs)).backward()
    clip = run.cfg.train.grad_clip
    norm = torch.nn.utils.clip_grad_norm_(run.module.parameters(),
                                          clip if clip > 0 else math.inf)
    if torch.isfinite(norm):  # grads are all-reduced: every rank agrees
        run.opt.step()
    else:
        run.skipped += 1
    return losses


def graph_anchor(outputs: dict) -> Tensor | float:
    """0 with a gradient path to every output. Before L_LSM is switched on the local branch's
    outputs are not in the loss; DDP would wait for their gradients forever, and Adam would see
    the branch's parameters only from then on in one process but from the start under DDP.
    Empty slices: zero gradients without touching values (no 0 * inf)."""
    terms = [t.reshape(-1)[:0].sum() for t in _tensors(outputs)
             if t.requires_grad and t.is_floating_point()]
    return sum(terms[1:], terms[0]) if terms else 0.0


def _tensors(obj: Any) -> Iterator[Tensor]:
    if isinstance(obj, Tensor):
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


def eval_indices(windows: int, wanted: int) -> list[int]:
    """`wanted` test windows evenly spread over all of them (all when wanted <= 0)."""
    n = windows if wanted <= 0 else min(wanted, windows)
    return sorted({int(i) for i in np.linspace(0, windows - 1, n).round()})


def evaluate_and_keep_best(run: Run, test_set: CacheDataset, eval_idx: list[int],
                           report: RunLog) -> None:
    """Rank 0 scores the test windows and writes best.pt on a new best F1@10; all ranks wait."""
    t = run.cfg.train
    if run.dist.main:
        scores = evaluate(run.module, test_set, eval_idx, t.eval_batch_size, t.score_threshold,
                          run.dist.device)
        run.state.last_eval = scores
        report.evaluation(run.state.iteration, scores)
        if scores['F1@10'] > run.state.best_f1:
            run.state.best_f1 = scores['F1@10']
            run.save('best.pt', with_state=False)
    barrier(run.dist)


def evaluate(model: FhldDetector, dataset: CacheDataset, indices: list[int], batch_size: int,
             score_threshold: float, device: torch.device) -> dict[str, float]:
    """FHLD point metric of model.detect on the given test windows (counts summed)."""
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


class StopFlag:
    """SIGINT/SIGTERM request a clean stop after the current iteration (a second SIGINT
    interrupts at once)."""

    def __init__(self) -> None:
        self.requested = False
        self._old: dict[int, Any] = {}

    def __enter__(self) -> StopFlag:
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
