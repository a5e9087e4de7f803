"""`fhld train --config CONFIG [--resume] [--out DIR]`: FHLD training on cached simulator windows.

Data: the training cache (larger rasters, augmented and cropped to the model's input) and a
held-out test cache of other seeds at the model's exact raster (data/cache.py); missing
shards are simulated first (single process; under torchrun the cache must exist, build it with
``--cache-only``). ``data.bags`` adds the windows of labelled bags, drawn beside the simulator's
by weight (data/bag_source.py, cached by the same step). The loop, evaluation and
checkpoints are training/loop.py: best.pt by F1@10 on the test cache, last.pt with optimizer
and RNG state besides. Both are fhld_ros.model.checkpoint files (torch.load(weights_only=True))
with the training config and command line inside; best.pt loads with load_checkpoint like the
shipped weights.

Resume is exact (training/resume.py). ``--max-minutes`` (or SIGINT/SIGTERM) stops after the
current iteration with a checkpoint. Multi-GPU / multi-machine:
``torchrun --nproc-per-node=N $(which fhld) train --config C`` (DDP, nccl on CUDA, gloo on CPU;
the batch size is per process; only rank 0 writes and evaluates). docs/training.md tells how
the shipped weights were trained.
"""
from __future__ import annotations

import argparse
import os
import shlex
import time
from pathlib import Path

from fhld_ros.errors import ConfigError
from fhld_ros.training.config import TrainConfig, load_config
from fhld_ros.training.distributed import shutdown
from fhld_ros.training.loop import ensure_caches, train


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
    path = Path(args.config)
    cfg = _read_config(path, args.max_minutes)
    out_dir = Path(args.out) if args.out else Path('out/train') / path.stem
    try:
        if args.cache_only:
            deadline = (time.monotonic() + 60 * args.max_minutes
                        if args.max_minutes is not None else None)
            done = ensure_caches(cfg, deadline, args.workers, not args.quiet)
            print('cache complete' if done else 'cache incomplete (time budget); run again')
            return 0
        summary = train(cfg, out_dir, args.resume, args.max_minutes, args.device,
                        not args.quiet, command_line(args))
    finally:  # user errors are ConfigErrors (one line); anything else shows its traceback
        shutdown()
    if int(os.environ.get('RANK', '0')) == 0:
        how = f'stopped ({summary["stopped"]})' if summary['stopped'] else 'done'
        print(f'{how} at iteration {summary["iteration"]}/{cfg.train.iterations}, best F1@10 '
              f'{summary.get("best_f1", -1):.1f}; {out_dir}' +
              (' (continue with --resume)' if summary['stopped'] else ''))
    return 130 if summary['stopped'] == 'signal' else 0


def _read_config(path: Path, max_minutes: float | None) -> TrainConfig:
    """The checked config, or one ConfigError line."""
    if not path.is_file():
        raise ConfigError(f'config not found: {path}')
    if max_minutes is not None and max_minutes < 0:
        raise ConfigError(f'--max-minutes must be >= 0, got {max_minutes:g}')
    try:
        return load_config(path)
    except ConfigError as exc:
        raise ConfigError(f'bad config {path}: {exc}') from exc


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
