"""One process or several under torchrun: rank, device and the few collectives training needs.

``torchrun --nproc-per-node=N $(which fhld) train ...`` sets WORLD_SIZE > 1; each process then
joins one process group (nccl on CUDA, gloo on CPU) and trains a DDP replica. Without it the
helpers here cost nothing.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as torch_dist


@dataclass
class Dist:
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device('cpu')

    @property
    def main(self) -> bool:
        return self.rank == 0


def setup_distributed(device: str = 'auto') -> Dist:
    """Rank and device of this process; under torchrun (WORLD_SIZE > 1) one process group."""
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


def any_rank(flag: bool, dist: Dist) -> bool:
    """True on every rank if any rank says so (all ranks stop at the same iteration)."""
    if dist.world == 1:
        return flag
    t = torch.tensor([float(flag)], device=dist.device)
    torch_dist.all_reduce(t, op=torch_dist.ReduceOp.MAX)
    return bool(t.item())


def barrier(dist: Dist) -> None:
    if dist.world > 1:
        torch_dist.barrier()


def all_gather(obj: Any, dist: Dist) -> list[Any]:
    """Every rank's obj, in rank order (a collective call under DDP)."""
    if dist.world == 1:
        return [obj]
    gathered: list[Any] = [None] * dist.world
    torch_dist.all_gather_object(gathered, obj)
    return gathered


def shutdown() -> None:
    """Leave the process group, if this process joined one."""
    if torch_dist.is_available() and torch_dist.is_initialized():
        torch_dist.destroy_process_group()
