"""What a run's checkpoints hold besides the weights, and an exact continuation from last.pt.

Weights go through fhld_ros.model.checkpoint like the shipped file; the meta adds the
iteration, the best F1@10 so far, the latest evaluation, every command that trained the run
and the training config (with labelled bags also ``bag_sources``: path, content key, weight and
windows of each; a distillation also ``teacher``: its path, code version and meta). last.pt
also carries ``train_state``: the Adam state and every rank's torch RNG state (anchor noise and
matching negatives draw from it). The data order and augmentation are functions of (seed,
epoch, index), so with these the resumed run takes the same steps as one that never stopped.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from fhld_ros.dataclass_dict import to_plain
from fhld_ros.errors import ConfigError
from fhld_ros.model.checkpoint import load_checkpoint, save_checkpoint
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.detector import FhldDetector
from fhld_ros.training.config import TrainConfig
from fhld_ros.training.distributed import Dist, all_gather


@dataclass
class RunState:
    """Progress that checkpoints carry from one slice of a run to the next."""

    iteration: int = 0  # iterations done
    best_f1: float = -1.0  # best F1@10 so far (best.pt)
    last_eval: dict | None = None
    commands: list[str] = field(default_factory=list)  # every command that trained the run
    # the labelled bags among the training sources: path, key, weight, windows (bag_source.py)
    bag_sources: list[dict] = field(default_factory=list)
    teacher: dict = field(default_factory=dict)  # train.teacher's provenance (distill.py)


def rank_seed(seed: int, dist: Dist) -> int:
    """Seed of the training draws after initialisation: anchor noise differs per rank."""
    return seed + 1 + dist.rank


def save_run(path: Path, module: FhldDetector, opt: torch.optim.Optimizer, state: RunState,
             cfg: TrainConfig, dist: Dist, with_state: bool) -> None:
    """best.pt (with_state=False, rank 0 only) or last.pt (collective: every rank calls it)."""
    train_state = _train_state(opt, dist) if with_state else None
    if not dist.main:
        return
    meta = {'iteration': state.iteration, 'best_f1': state.best_f1, 'eval': state.last_eval,
            'world_size': dist.world, 'commands': state.commands,
            'train_config': to_plain(cfg)}
    if state.bag_sources:
        meta['bag_sources'] = state.bag_sources
    if state.teacher:
        meta['teacher'] = state.teacher
    if train_state is not None:
        meta['train_state'] = train_state
    save_checkpoint(path, module, state.commands[-1], meta)  # the command running now


def resume_run(path: Path, module: FhldDetector, opt: torch.optim.Optimizer,
               model_cfg: FhldConfig, seed: int, dist: Dist) -> RunState:
    """Load last.pt into module and opt, restore this rank's RNG; the run's progress."""
    ckpt = load_checkpoint(path, map_location='cpu')
    if ckpt.config != model_cfg:
        raise ConfigError(f'{path} was trained with another model config; the config '
                         'file\'s model section must not change across a resume')
    module.load_state_dict(ckpt.model.state_dict())
    saved = ckpt.meta['train_state']
    opt.load_state_dict(saved['optimizer'])
    state = RunState(int(ckpt.meta['iteration']), float(ckpt.meta['best_f1']),
                     ckpt.meta.get('eval'), list(ckpt.meta.get('commands', [])))
    _restore_rng(saved['rng'], dist, rank_seed(seed, dist) + 7919 * state.iteration)
    return state


def _rng_state(dist: Dist) -> dict:
    state = {'cpu': torch.get_rng_state()}
    if dist.device.type == 'cuda':  # anchor noise on the GPU draws from the device generator
        state['cuda'] = torch.cuda.get_rng_state(dist.device)
    return state


def _train_state(opt: torch.optim.Optimizer, dist: Dist) -> dict:
    """Optimizer state and every rank's RNG state (a collective call under DDP)."""
    return {'optimizer': opt.state_dict(), 'rng': all_gather(_rng_state(dist), dist)}


def _restore_rng(states: list[dict], dist: Dist, reseed: int) -> None:
    if len(states) != dist.world:  # another process count: no exact continuation possible
        torch.manual_seed(reseed)
        return
    torch.set_rng_state(states[dist.rank]['cpu'])
    if 'cuda' in states[dist.rank] and dist.device.type == 'cuda':
        torch.cuda.set_rng_state(states[dist.rank]['cuda'], dist.device)
