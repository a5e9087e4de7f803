"""What a training run reports: the progress bar, OUT/log.jsonl and the mean losses in it.

log.jsonl has one JSON object per line: {iteration, lr, s_per_it, skipped, loss, loss_cls, ...}
every log_every iterations (means over them) and {iteration, eval} after each evaluation.
"""
from __future__ import annotations

import json
from pathlib import Path

from torch import Tensor
from tqdm import tqdm


class LossMeter:
    """Loss tensors summed on the device: one host sync per log line."""

    def __init__(self) -> None:
        self.sums: dict[str, Tensor] = {}
        self.count = 0

    def add(self, losses: dict[str, Tensor]) -> None:
        for k, v in losses.items():
            self.sums[k] = self.sums[k] + v.detach() if k in self.sums else v.detach()
        self.count += 1

    def means(self) -> dict[str, float]:
        """Means since the last call; starts a new sum."""
        means = {k: float(v) / self.count for k, v in self.sums.items()}
        self.sums, self.count = {}, 0
        return means


class RunLog:
    """The progress bar and OUT/log.jsonl (rank 0; path None elsewhere)."""

    def __init__(self, path: Path | None, total: int, initial: int, show: bool) -> None:
        self.file = path.open('a') if path is not None else None
        self.bar = tqdm(total=total, initial=initial, disable=not show, unit='it',
                        dynamic_ncols=True, desc='train')

    def losses(self, iteration: int, lr: float, s_per_it: float, skipped: int,
               means: dict[str, float]) -> None:
        self.bar.set_postfix(loss=f'{means["loss"]:.3f}', cls=f'{means["loss_cls"]:.3f}',
                             curve=f'{means["loss_curve"]:.4f}',
                             lsm=f'{means.get("loss_lsm", 0.0):.3f}', lr=f'{lr:.1e}')
        self._write({'iteration': iteration, 'lr': lr, 's_per_it': s_per_it,
                     'skipped': skipped, **means})

    def evaluation(self, iteration: int, scores: dict[str, float]) -> None:
        self.bar.write(f'eval @ {iteration}: ' + ' '.join(
            f'{k}={v:.1f}' for k, v in scores.items() if '@' in k))
        self._write({'iteration': iteration, 'eval': scores})

    def _write(self, record: dict) -> None:
        if self.file is not None:
            self.file.write(json.dumps(record) + '\n')
            self.file.flush()

    def __enter__(self) -> RunLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.bar.close()
        if self.file is not None:
            self.file.close()
