"""`fhld salad-train OUT`: train SALAD on simulated camera drives, a user's ONCE-3DLanes or
OpenLane data (--once, --openlane), or both (and any shards in --cache).

Drives come from SALAD's training seeds (sim_source.salad_seeds), each its own camera (height,
pitch, field of view, principal point), rendered once into OUT/cache (dataset.py); a
dataset's images are resampled to the virtual camera once into the same cache (`--drives 0`:
the dataset alone; `fhld autolabel --once-dataset` writes a drive's labelled images in the
ONCE layout). The row shift and scale of the depth head (paper eq. 3) are measured on the
training images before the first step and saved with the weights. Runs in slices:
OUT/state.pt is written every --save-every steps, and --resume continues from it with the same
draws; OUT/salad.pt, the weights alone with their config and provenance (and the datasets of
the cache), is written at the end of every slice.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from fhld_ros.errors import ConfigError
from fhld_ros.salad.augment import SaladAugment, augment_images
from fhld_ros.salad.checkpoint import config_from_plain, load_salad, save_salad
from fhld_ros.salad.config import SaladConfig
from fhld_ros.salad.dataset import (
    SHARD_SUFFIX,
    EpochBatches,
    SaladDataset,
    ShardSamples,
    dataset_shards,
    dataset_sources,
    finished_shards,
    simulated_shard,
)
from fhld_ros.salad.losses import SaladCriterion
from fhld_ros.salad.model import SaladNet
from fhld_ros.salad.once_format import SPLITS as ONCE_SPLITS
from fhld_ros.salad.once_format import read_once
from fhld_ros.salad.openlane_format import read_openlane
from fhld_ros.salad.sim_source import salad_seeds
from fhld_ros.salad.targets import lane_targets, row_statistics

ROW_STATS_SAMPLES = 400
WARMUP_STEPS = 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('out', type=Path, help='run folder (state.pt, salad.pt, cache/)')
    parser.add_argument('--cache', type=Path, help='shard folder (default OUT/cache)')
    parser.add_argument('--drives', type=int, default=200, help='simulated training drives')
    parser.add_argument('--frames', type=int, default=10, help='images per drive, 1 s apart')
    parser.add_argument('--once', type=Path, metavar='ROOT',
                        help='also train on an ONCE-3DLanes folder (its --once-split)')
    parser.add_argument('--once-split', default='train', choices=ONCE_SPLITS)
    parser.add_argument('--openlane', type=Path, metavar='ROOT',
                        help='also train on an OpenLane folder (its --openlane-labels)')
    parser.add_argument('--openlane-labels', type=Path, metavar='DIR',
                        help='the training labels, e.g. ROOT/lane3d_1000/training (default: '
                        'every lane3d* folder under ROOT)')
    parser.add_argument('--steps', type=int, default=6000, help='optimiser steps in all')
    parser.add_argument('--slice-steps', type=int, help='stop after this many (then --resume)')
    parser.add_argument('--batch', type=int, default=8)
    parser.add_argument('--lr', type=float, default=2e-3)
    parser.add_argument('--workers', type=int, default=1, help='data and render processes')
    parser.add_argument('--save-every', type=int, default=250)
    parser.add_argument('--resume', action='store_true', help='continue OUT/state.pt')
    parser.add_argument('--init', type=Path, metavar='CHECKPOINT',
                        help='start from these SALAD weights (their config and row depth '
                             'statistics; a fresh optimiser and schedule), e.g. the shipped')
    parser.add_argument('--device', default='cpu')
    parser.add_argument('--threads', type=int, default=0,
                        help='torch threads (0: torch\'s default); 1 keeps a shared machine '
                        'from thrashing')


def build_cache(cache: Path, drives: int, frames: int, cfg: SaladConfig, workers: int) -> None:
    cache.mkdir(parents=True, exist_ok=True)
    seeds = [s for s in salad_seeds('train', drives)
             if not (cache / f'sim_{s}{SHARD_SUFFIX}').exists()]
    if not seeds:
        return
    print(f'rendering {len(seeds)} drives x {frames} images into {cache}', file=sys.stderr)
    start = time.monotonic()
    with ProcessPoolExecutor(max(workers, 1)) as pool:
        list(pool.map(simulated_shard, [cache] * len(seeds), seeds, [frames] * len(seeds),
                      [cfg.camera] * len(seeds)))
    print(f'rendered in {time.monotonic() - start:.0f} s', file=sys.stderr)


def build_datasets(cache: Path, args: argparse.Namespace, cfg: SaladConfig) -> None:
    """The shards of --once and --openlane (dataset.dataset_shards), once per dataset."""
    if args.openlane_labels and not args.openlane:
        raise ConfigError('--openlane-labels needs --openlane ROOT')
    sources = []
    if args.once:
        sources.append(('once', f'{args.once.resolve()} {args.once_split}',
                        lambda: read_once(args.once, args.once_split)))
    if args.openlane:
        labels = args.openlane_labels
        sources.append(('openlane', f'{args.openlane.resolve()} '
                        f'{labels.resolve() if labels else "lane3d*"}',
                        lambda: read_openlane(args.openlane, labels)))
    for kind, source, samples in sources:
        print(f'packing {kind} {source} into {cache}', file=sys.stderr)
        try:
            shards = dataset_shards(cache, kind, source, samples(), cfg.camera)
        except ValueError as exc:  # the readers name the file
            raise ConfigError(f'--{kind}: {exc}') from None
        print(f'{kind}: {len(shards)} shards', file=sys.stderr)


def measure_rows(samples: ShardSamples, cfg: SaladConfig) -> SaladConfig:
    """cfg with the row shift and scale of the first ROW_STATS_SAMPLES training images."""
    targets = [lane_targets(samples.lanes[i], cfg.camera)
               for i in range(min(len(samples), ROW_STATS_SAMPLES))]
    shift, scale = row_statistics(np.stack([t.depth for t in targets]),
                                  np.stack([t.depth_mask for t in targets]))
    return dataclasses.replace(cfg, row_shift=tuple(map(float, shift)),
                               row_scale=tuple(map(float, scale)))


def learning_rate(step: int, steps: int, peak: float) -> float:
    """Linear warm-up, then cosine to zero."""
    if step < WARMUP_STEPS:
        return peak * (step + 1) / WARMUP_STEPS
    return 0.5 * peak * (1 + math.cos(math.pi * min(step / steps, 1.0)))


def _start(args: argparse.Namespace, samples: ShardSamples) -> tuple[SaladNet, dict]:
    """The model and the run state, fresh or from OUT/state.pt."""
    state_path = args.out / 'state.pt'
    if args.resume:
        if not state_path.exists():
            raise ConfigError(f'--resume: no {state_path} to continue')
        state = torch.load(state_path, map_location=args.device, weights_only=True)
        model = SaladNet(config_from_plain(state['config']))
        model.load_state_dict(state['model'])
        return model.to(args.device), state
    if state_path.exists():
        raise ConfigError(f'{state_path} exists: --resume to continue it, or another OUT')
    state = {'step': 0, 'command': ' '.join(sys.argv)}
    if args.init is not None:
        model, info = load_salad(args.init)
        return model.to(args.device), {**state, 'init': str(args.init),
                                       'init_steps': info.get('meta', {}).get('steps')}
    cfg = measure_rows(samples, SaladConfig())
    cfg.validate()
    return SaladNet(cfg).to(args.device), state


def run(args: argparse.Namespace) -> int:
    if args.threads:
        torch.set_num_threads(args.threads)
    cache = args.cache or args.out / 'cache'
    args.out.mkdir(parents=True, exist_ok=True)
    build_cache(cache, args.drives, args.frames, SaladConfig(), args.workers)
    build_datasets(cache, args, SaladConfig())
    samples = ShardSamples(finished_shards(cache))
    if not len(samples):
        raise ConfigError(f'no training images in {cache}')
    model, state = _start(args, samples)
    criterion = SaladCriterion(model.cfg).to(args.device)
    optimiser = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    if 'optimiser' in state:
        optimiser.load_state_dict(state['optimiser'])
    on_gpu = args.device != 'cpu'
    # on a GPU the batch is zoomed and recoloured there, off the loader (augment.py)
    dataset = SaladDataset(samples, model.cfg.camera, SaladAugment(), defer_images=on_gpu)
    # what salad.pt records besides its step count: the same for every save of this slice
    meta = {'images': len(samples), 'drives': args.drives, 'frames': args.frames,
            'datasets': dataset_sources(cache),
            **{key: state[key] for key in ('init', 'init_steps') if key in state}}
    step, stop = state['step'], min(args.steps, state['step'] + (args.slice_steps or args.steps))
    print(f'{len(samples)} images; steps {step}..{stop} of {args.steps}', file=sys.stderr)
    if step >= stop:
        return 0
    try:
        batches = EpochBatches(len(dataset), args.batch, step)
    except ValueError as exc:
        raise ConfigError(f'--batch: {exc}') from None
    loader = DataLoader(dataset, batch_sampler=batches, num_workers=args.workers,
                        pin_memory=on_gpu)
    model.train()
    started = time.monotonic()
    for batch in loader:
        for group in optimiser.param_groups:
            group['lr'] = learning_rate(step, args.steps, args.lr)
        batch = {k: v.to(args.device) for k, v in batch.items()}
        images = (augment_images(batch['image'], batch['augment'], model.cfg.camera)
                  if dataset.defer_images else batch['image'])
        losses = criterion(*model(images), batch)
        optimiser.zero_grad(set_to_none=True)
        losses['loss'].backward()
        optimiser.step()
        step += 1
        if step % 50 == 0 or step == stop:
            print(f'step {step} ' + ' '.join(f'{k} {float(v.detach()):.4f}' for k, v in
                                             losses.items())
                  + f' time {time.monotonic() - started:.1f}', file=sys.stderr, flush=True)
        if step % args.save_every == 0 or step == stop:
            _save(args, model, optimiser, state, step, meta)
        if step >= stop:
            break
    return 0


def _save(args: argparse.Namespace, model: SaladNet, optimiser: torch.optim.Optimizer,
          state: dict, step: int, meta: dict) -> None:
    state.update(step=step, model=model.state_dict(), optimiser=optimiser.state_dict(),
                 config=dataclasses.asdict(model.cfg))
    tmp = args.out / '.state.pt.tmp'
    torch.save(state, tmp)
    tmp.replace(args.out / 'state.pt')
    save_salad(args.out / 'salad.pt', model, state['command'], {'steps': step, **meta})
