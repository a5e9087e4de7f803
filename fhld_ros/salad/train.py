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

`--minutes M` fits the whole command into M minutes of wall clock, as on a lent GPU: the drives
rendered within --render-share of it are the training set (the rest are left out, their
temporary files removed), and the learning-rate schedule runs on the time left rather than on
--steps (then only a cap), so its cosine reaches zero as the time runs out and the last save is
a finished schedule, whatever the machine's step rate. Such a run is one invocation: it is not
resumed (start another from its salad.pt with --init).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import multiprocessing
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from fhld_ros.errors import ConfigError
from fhld_ros.salad.augment import SaladAugment, augment_images
from fhld_ros.salad.checkpoint import config_from_plain, load_salad, save_salad
from fhld_ros.salad.config import SaladConfig, uncalibrated
from fhld_ros.salad.dataset import (
    EpochBatches,
    SaladDataset,
    ShardSamples,
    dataset_shards,
    dataset_sources,
    finished_shards,
    simulated_shard,
    simulated_shard_path,
    temporary_path,
)
from fhld_ros.salad.losses import SaladCriterion
from fhld_ros.salad.model import SaladNet
from fhld_ros.salad.once_format import SPLITS as ONCE_SPLITS
from fhld_ros.salad.once_format import read_once
from fhld_ros.salad.openlane_format import read_openlane
from fhld_ros.salad.sim_source import (
    SEEDS_OWN,
    DriveVariant,
    add_variant_arguments,
    drive_variant,
    salad_seeds,
)
from fhld_ros.salad.targets import lane_targets, row_statistics
from fhld_ros.salad.virtual_camera import VirtualCamera

ROW_STATS_SAMPLES = 400
WARMUP_STEPS = 200
DEFAULT_STEPS = 6000
SAVE_MARGIN_S = 5.0  # --minutes: the training ends this long before the budget, for the save


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('out', type=Path, help='run folder (state.pt, salad.pt, cache/)')
    parser.add_argument('--cache', type=Path, help='shard folder (default OUT/cache)')
    parser.add_argument('--drives', type=int, default=200, help='simulated training drives')
    parser.add_argument('--first-drive', type=int, default=0,
                        help="the drives from this one of SALAD's training seeds on (a later "
                        'run renders drives no earlier run saw)')
    parser.add_argument('--frames', type=int, default=10, help='images per drive, 1 s apart')
    add_variant_arguments(parser)
    parser.add_argument('--once', type=Path, metavar='ROOT',
                        help='also train on an ONCE-3DLanes folder (its --once-split)')
    parser.add_argument('--once-split', default='train', choices=ONCE_SPLITS)
    parser.add_argument('--openlane', type=Path, metavar='ROOT',
                        help='also train on an OpenLane folder (its --openlane-labels)')
    parser.add_argument('--openlane-labels', type=Path, metavar='DIR',
                        help='the training labels, e.g. ROOT/lane3d_1000/training (default: '
                        'every lane3d* folder under ROOT)')
    parser.add_argument('--steps', type=int,
                        help=f'optimiser steps in all (default {DEFAULT_STEPS}; with --minutes '
                        'a cap, none by default)')
    parser.add_argument('--minutes', type=float,
                        help='wall-clock budget of the command: rendering, then training on a '
                        'schedule that ends with it (module doc)')
    parser.add_argument('--render-share', type=float, default=0.3,
                        help='--minutes: the share of the budget the rendering may take')
    parser.add_argument('--slice-steps', type=int, help='stop after this many (then --resume)')
    parser.add_argument('--batch', type=int, default=8)
    parser.add_argument('--lr', type=float, default=2e-3)
    parser.add_argument('--workers', type=int, default=1, help='data and render processes')
    parser.add_argument('--save-every', type=int, default=250)
    parser.add_argument('--resume', action='store_true', help='continue OUT/state.pt')
    parser.add_argument('--init', type=Path, metavar='CHECKPOINT',
                        help='start from these SALAD weights (their config and row depth '
                             'statistics; a fresh optimiser and schedule), e.g. the shipped')
    parser.add_argument('--camera-width', type=int, metavar='PX',
                        help="the virtual camera's width (a multiple of 32; its rows stay the "
                        f"same): default --init's, else {VirtualCamera().width} (docs/salad.md, "
                        '"The width of the view")')
    parser.add_argument('--lane-depth-weight', type=float, metavar='W',
                        help="weigh the depth at the lane cells once more, near L1 (the "
                        "config's lane_depth_weight; default the weights' own, 0 for new ones; "
                        'docs/salad.md, "Depth weighed at the lanes")')
    parser.add_argument('--device', default='cpu')
    parser.add_argument('--bf16', action='store_true',
                        help='the network in bfloat16 (autocast; the weights, the optimiser and '
                        'the losses stay float32): ~1.8x the steps on a CPU with AVX512-BF16 '
                        '(docs/salad.md, "Training in bfloat16")')
    parser.add_argument('--threads', type=int, default=0,
                        help='torch threads (0: torch\'s default); 1 keeps a shared machine '
                        'from thrashing')


def build_cache(cache: Path, seeds: range, frames: int, camera: VirtualCamera, workers: int,
                seconds: float | None = None, variant: DriveVariant = SEEDS_OWN) -> None:
    """The shards of the seeds' drives not yet in cache; seconds: stop rendering then, and
    leave the unfinished drives out; variant: where the cameras sit and how the roads look
    (--camera-height, --camera-side, --road-look)."""
    cache.mkdir(parents=True, exist_ok=True)
    paths = {s: simulated_shard_path(cache, s, variant) for s in seeds}
    todo = [s for s in seeds if not paths[s].exists()]
    if not todo:
        return
    print(f'rendering {len(todo)} drives x {frames} images into {cache}', file=sys.stderr)
    start = time.monotonic()
    with multiprocessing.Pool(max(workers, 1)) as pool:  # leaving it terminates the workers
        rendering = pool.starmap_async(simulated_shard, [(cache, s, frames, camera,
                                                          variant) for s in todo],
                                       chunksize=1)
        rendering.wait(seconds)
        if rendering.ready():
            rendering.get()  # a drive's error, raised here
    done = sum(paths[s].exists() for s in todo)
    for seed in todo:  # the temporary files of the drives cut off (dataset.write_shard)
        temporary_path(paths[seed]).unlink(missing_ok=True)
    print(f'rendered {done} of {len(todo)} drives in {time.monotonic() - start:.0f} s',
          file=sys.stderr)


def build_datasets(cache: Path, args: argparse.Namespace, camera: VirtualCamera) -> None:
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
            shards = dataset_shards(cache, kind, source, samples(), camera)
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


def learning_rate(step: int, progress: float, peak: float) -> float:
    """A linear warm-up over the first steps times a cosine to zero as progress (the share of
    the steps or of the training time done) goes from 0 to 1: the rate ends at zero however
    few steps a short --minutes run makes."""
    warm = min((step + 1) / WARMUP_STEPS, 1.0)
    return warm * 0.5 * peak * (1 + math.cos(math.pi * min(progress, 1.0)))


class Schedule:
    """How far the run is: by its steps (`--steps`), or with --minutes by the training time
    too, whichever is further; done at 1."""

    def __init__(self, steps: int | None, seconds: float | None) -> None:
        self.steps, self.seconds = steps, seconds
        self.start = time.monotonic()

    def progress(self, step: int) -> float:
        by_steps = step / self.steps if self.steps else 0.0
        if self.seconds is None:
            return by_steps
        return max(by_steps, (time.monotonic() - self.start) / self.seconds)


def _start(args: argparse.Namespace) -> tuple[SaladNet | None, dict, VirtualCamera]:
    """The model (None for a fresh run: its rows are measured on the images), the run state,
    and the virtual camera the images are resampled to: OUT/state.pt's, --init's or the
    default, at --camera-width (rows as the weights': their depth statistics are per row)."""
    state_path = args.out / 'state.pt'
    if args.resume:
        if not state_path.exists():
            raise ConfigError(f'--resume: no {state_path} to continue')
        state = torch.load(state_path, map_location=args.device, weights_only=True)
        if state.get('minutes'):
            raise ConfigError(f'{state_path} is a --minutes run, whose schedule followed its '
                              'clock: start another from its salad.pt with --init')
        model = SaladNet(config_from_plain(state['config']))
        model.load_state_dict(state['model'])
        if args.camera_width not in (None, model.cfg.camera.width):
            raise ConfigError(f'--camera-width {args.camera_width}: a resumed run keeps its '
                              f'camera ({model.cfg.camera.width} px wide)')
        return model.to(args.device), state, model.cfg.camera
    if state_path.exists():
        raise ConfigError(f'{state_path} exists: --resume to continue it, or another OUT')
    state = {'step': 0, 'command': ' '.join(sys.argv), 'minutes': args.minutes or 0.0}
    model = None
    camera = SaladConfig().camera
    if args.init is not None:
        model, info = load_salad(args.init)
        state.update(init=str(args.init), init_steps=info.get('meta', {}).get('steps'))
        camera = model.cfg.camera
        model.cfg = uncalibrated(model.cfg)  # measured on the weights before training
    if args.camera_width is not None:
        camera = dataclasses.replace(camera, width=args.camera_width)
        SaladConfig(camera=camera).validate('--camera-width')
    if model is not None:  # its convolutions see any width; its rows stay
        model.cfg = dataclasses.replace(model.cfg, camera=camera)
        model = model.to(args.device)
    return model, state, camera


def _deadline(args: argparse.Namespace) -> float | None:
    """The end of --minutes on the monotonic clock (None without it; then --steps defaults)."""
    if args.minutes is None:
        args.steps = args.steps or DEFAULT_STEPS
        return None
    if args.resume:
        raise ConfigError('--minutes is one run from start to end, not a --resume: start '
                          'another from OUT/salad.pt with --init')
    if not args.minutes > 0 or not 0 < args.render_share < 1:
        raise ConfigError(f'--minutes must be > 0 and --render-share within (0, 1), got '
                          f'{args.minutes:g} and {args.render_share:g}')
    return time.monotonic() + 60.0 * args.minutes


def cpu_bf16_flags(cpuinfo: str | None = None) -> set[str] | None:
    """The CPU's bfloat16 instruction sets (avx512_bf16, amx_bf16) from /proc/cpuinfo's
    flags; None where there is no such file to read (not Linux)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path('/proc/cpuinfo').read_text()
        except OSError:
            return None
    flags = {word for line in cpuinfo.splitlines() if line.startswith('flags')
             for word in line.split(':', 1)[1].split()}
    return flags & {'avx512_bf16', 'amx_bf16'}


def _check_bf16(args: argparse.Namespace) -> None:
    """--bf16 on a CPU that has no bfloat16 instructions runs them in software: on an AVX2
    CPU under 50 steps in 19 minutes against ~1 s a step in float32 (docs/salad.md)."""
    if args.bf16 and args.device == 'cpu' and cpu_bf16_flags() == set():
        raise ConfigError(f'--bf16: this CPU ({torch.backends.cpu.get_cpu_capability()}) has '
                          'no bfloat16 instructions (avx512_bf16, amx_bf16), where bfloat16 '
                          'runs many times slower than float32: leave --bf16 out')


def run(args: argparse.Namespace) -> int:
    _check_bf16(args)
    end = _deadline(args)
    if args.threads:
        torch.set_num_threads(args.threads)
    cache = args.cache or args.out / 'cache'
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        seeds = salad_seeds('train', args.drives, args.first_drive)
    except ValueError as exc:
        raise ConfigError(f'--drives / --first-drive: {exc}') from None
    variant = drive_variant(args)
    model, state, camera = _start(args)  # its camera decides how the images are resampled
    build_cache(cache, seeds, args.frames, camera, args.workers,
                None if end is None else args.render_share * 60.0 * args.minutes, variant)
    build_datasets(cache, args, camera)
    try:
        samples = ShardSamples(finished_shards(cache), camera)
    except ValueError as exc:
        raise ConfigError(f'{exc}: another --cache') from None
    if not len(samples):
        raise ConfigError(f'no training images in {cache}')
    if model is None:
        cfg = measure_rows(samples, SaladConfig(camera=camera))
        cfg.validate()
        model = SaladNet(cfg).to(args.device)
    if args.lane_depth_weight is not None:  # recorded in the weights' config
        model.cfg = dataclasses.replace(model.cfg, lane_depth_weight=args.lane_depth_weight)
        model.cfg.validate('--lane-depth-weight')
    optimiser = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    if 'optimiser' in state:
        optimiser.load_state_dict(state['optimiser'])
    # what salad.pt records besides its step count: the same for every save of this slice
    meta = {'images': len(samples), 'drives': args.drives, 'frames': args.frames,
            'datasets': dataset_sources(cache),
            **({'first_drive': args.first_drive} if args.first_drive else {}),
            **({'minutes': args.minutes} if args.minutes else {}),
            **variant.meta(),
            **({'bf16': True} if args.bf16 else {}),
            **{key: state[key] for key in ('init', 'init_steps') if key in state}}
    train_s = None if end is None else end - time.monotonic() - SAVE_MARGIN_S
    if train_s is not None and train_s <= 0:
        raise ConfigError(f'--minutes {args.minutes:g}: no time left to train after the '
                          'rendering and packing')
    _train(args, model, optimiser, samples, state, meta, Schedule(args.steps, train_s))
    return 0


def _train(args: argparse.Namespace, model: SaladNet, optimiser: torch.optim.Optimizer,
           samples: ShardSamples, state: dict, meta: dict, schedule: Schedule) -> None:
    """One slice: from state's step to --steps, --slice-steps later, or the schedule's end."""
    criterion = SaladCriterion(model.cfg).to(args.device)
    on_gpu = args.device != 'cpu'
    # on a GPU the batch is zoomed and recoloured there, off the loader (augment.py)
    dataset = SaladDataset(samples, model.cfg.camera, SaladAugment(), defer_images=on_gpu)
    step = state['step']
    stop = min(args.steps or sys.maxsize, step + (args.slice_steps or sys.maxsize))
    print(f'{len(samples)} images; steps {step}..{stop if stop < sys.maxsize else "the end"}'
          + (f' of {args.steps}' if args.steps else '')
          + (f', the schedule ending in {schedule.seconds:.0f} s' if schedule.seconds else ''),
          file=sys.stderr)
    if step >= stop:
        return
    try:
        batches = EpochBatches(len(dataset), args.batch, step)
    except ValueError as exc:
        raise ConfigError(f'--batch: {exc}') from None
    loader = DataLoader(dataset, batch_sampler=batches, num_workers=args.workers,
                        pin_memory=on_gpu)
    model.train()
    for batch in loader:
        lr = learning_rate(step, schedule.progress(step), args.lr)
        for group in optimiser.param_groups:
            group['lr'] = lr
        batch = {k: v.to(args.device) for k, v in batch.items()}
        images = (augment_images(batch['image'], batch['augment'], model.cfg.camera)
                  if dataset.defer_images else batch['image'])
        with torch.autocast(images.device.type, torch.bfloat16, enabled=args.bf16):
            seg, spatial = model(images)
        losses = criterion(seg.float(), spatial.float(), batch)
        optimiser.zero_grad(set_to_none=True)
        losses['loss'].backward()
        optimiser.step()
        step += 1
        done = step >= stop or schedule.progress(step) >= 1.0
        if step % 50 == 0 or done:
            print(f'step {step} ' + ' '.join(f'{k} {float(v.detach()):.4f}' for k, v in
                                             losses.items())
                  + f' lr {lr:.2e} time {time.monotonic() - schedule.start:.1f}',
                  file=sys.stderr, flush=True)
        if step % args.save_every == 0 or done:
            _save(args, model, optimiser, state, step, meta)
        if done:
            break


def _save(args: argparse.Namespace, model: SaladNet, optimiser: torch.optim.Optimizer,
          state: dict, step: int, meta: dict) -> None:
    state.update(step=step, model=model.state_dict(), optimiser=optimiser.state_dict(),
                 config=dataclasses.asdict(model.cfg))
    tmp = args.out / '.state.pt.tmp'
    torch.save(state, tmp)
    tmp.replace(args.out / 'state.pt')
    save_salad(args.out / 'salad.pt', model, state['command'], {'steps': step, **meta})
