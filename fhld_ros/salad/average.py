"""`fhld salad-average`: the mean of the weights of SALAD checkpoints fine-tuned from one
another (a "model soup"). Two CPU fine-tunes of the same weights on different drives err
differently: their mean scored above either on the validation drives, though not above the
first on the test drives (docs/salad.md, "Two fine-tunes averaged").

The files must build the same network and decode alike: every config field equal but the loss
weights, which only training reads, and a depth calibration (calibrate.py), which was measured
on one file's weights and is left out; the result keeps the last file's config otherwise, so
its loss weights are what `fhld salad-train --init` inherits.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import torch

from fhld_ros.bagio import check_file_output
from fhld_ros.salad.checkpoint import (
    SaladCheckpointError,
    load_salad,
    resolve_salad_checkpoint,
    save_salad,
)
from fhld_ros.salad.config import CALIBRATION_FIELDS, LOSS_FIELDS, uncalibrated
from fhld_ros.salad.model import SaladNet


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('out', type=Path, help='the averaged checkpoint to write')
    parser.add_argument('checkpoints', nargs='+', type=Path, metavar='CHECKPOINT',
                        help='two or more SALAD checkpoints of one network (paths or shipped '
                             'names); the last one\'s config is kept')
    parser.add_argument('--overwrite', action='store_true', help='overwrite OUT if it exists')


def average_salad(paths: list[str | os.PathLike]) -> tuple[SaladNet, list[dict]]:
    """(the model with the mean of the files' weights, each file's provenance: path, train
    command and meta). Integer buffers (batch-norm step counts) are the last file's."""
    if len(paths) < 2:
        raise SaladCheckpointError('averaging needs two or more checkpoints')
    models, infos = zip(*(load_salad(path) for path in paths))
    last = models[-1]
    for path, model in zip(paths[:-1], models[:-1]):
        differ = [key for key, value in vars(model.cfg).items()
                  if key not in LOSS_FIELDS | CALIBRATION_FIELDS
                  and value != getattr(last.cfg, key)]
        if differ:
            raise SaladCheckpointError(f'{path} and {paths[-1]} build different networks or '
                                       f'decode differently: {", ".join(differ)}')
    states = [model.state_dict() for model in models]
    mean = {key: (torch.stack([state[key] for state in states]).mean(0)
                  if value.is_floating_point() else value)
            for key, value in states[-1].items()}
    last.load_state_dict(mean)
    last.cfg = uncalibrated(last.cfg)
    provenance = [{'path': str(path), 'train_command': info.get('train_command', ''),
                   'meta': info.get('meta', {})} for path, info in zip(paths, infos)]
    return last, provenance


def run(args: argparse.Namespace) -> int:
    inputs = {f'CHECKPOINT {i + 1}': resolve_salad_checkpoint(path)
              for i, path in enumerate(args.checkpoints)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    check_file_output(args.out, args.overwrite, inputs, 'OUT')  # never over an input
    model, provenance = average_salad(args.checkpoints)
    save_salad(args.out, model, ' '.join(sys.argv), {'averaged': provenance})
    print(f'wrote {args.out}: the mean of {len(provenance)} checkpoints')
    return 0
