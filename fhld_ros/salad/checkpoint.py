"""SALAD checkpoint files: weights, the SaladConfig that built them and their provenance, as
plain containers and tensors, so they load with torch.load(weights_only=True)."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fhld_ros.dataclass_dict import to_plain
from fhld_ros.errors import ConfigError
from fhld_ros.model.checkpoint import code_version
from fhld_ros.salad.config import SaladConfig
from fhld_ros.salad.model import SaladNet
from fhld_ros.salad.virtual_camera import VirtualCamera

FORMAT = 'salad-checkpoint'
FORMAT_VERSION = 1
SHIPPED_DIR = Path(__file__).resolve().parent.parent / 'checkpoints'
DEFAULT_SALAD_CHECKPOINT = SHIPPED_DIR / 'salad.pt'


class SaladCheckpointError(ConfigError):
    """A file that is not a usable SALAD checkpoint; the message names it and why."""


def config_from_plain(data: dict[str, Any]) -> SaladConfig:
    data = dict(data)
    camera = VirtualCamera(**data.pop('camera'))
    fields = {f.name for f in dataclasses.fields(SaladConfig)}
    unknown = sorted(set(data) - fields)
    if unknown:
        raise ValueError(f'unknown config keys {", ".join(unknown)}')
    return SaladConfig(camera=camera, **{k: tuple(v) if isinstance(v, list) else v
                                         for k, v in data.items()})


def _builtin(value: Any) -> Any:
    """numpy scalars as Python numbers (weights_only loading refuses numpy objects)."""
    if isinstance(value, dict):
        return {key: _builtin(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_builtin(item) for item in value]
    return value.item() if isinstance(value, np.generic) else value


def save_salad(path: str | os.PathLike, model: SaladNet, train_command: str,
               meta: dict[str, Any] | None = None) -> None:
    """Write atomically (a temporary file renamed over path)."""
    path = Path(path)
    # CPU tensors: weights trained on a GPU load where there is none
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    payload = {'format': FORMAT, 'format_version': FORMAT_VERSION,
               'config': _builtin(to_plain(model.cfg)), 'state_dict': state,
               'code_version': code_version(), 'train_command': train_command,
               'meta': _builtin(to_plain(meta or {}))}
    tmp = path.with_name(f'.{path.name}.tmp')
    torch.save(payload, tmp)
    os.replace(tmp, path)


def shipped_names() -> list[str]:
    return sorted(path.stem for path in SHIPPED_DIR.glob('salad*.pt'))


def resolve_salad_checkpoint(path: str | os.PathLike) -> Path:
    """path as given; where no such file exists and it names no folder, the shipped weights of
    that name (`salad_wide_mount` or `salad_wide_mount.pt`), so a user need not know where the
    package is installed."""
    path = Path(path)
    if path.is_file() or path.parent != Path('.'):
        return path
    shipped = SHIPPED_DIR / f'{path.name.removesuffix(".pt")}.pt'
    return shipped if shipped.is_file() else path


def load_salad(path: str | os.PathLike, device: str = 'cpu') -> tuple[SaladNet, dict[str, Any]]:
    """(model in eval mode, the file's payload without its weights); path as
    resolve_salad_checkpoint takes it."""
    path = resolve_salad_checkpoint(path)
    if not path.is_file():
        raise SaladCheckpointError(f'SALAD checkpoint {path} does not exist (the shipped '
                                   f'weights by name: {", ".join(shipped_names())})')
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # truncated, not a torch file, or an object weights_only refuses
        raise SaladCheckpointError(f'SALAD checkpoint {path} cannot be read: {exc}') from exc
    if not isinstance(payload, dict) or payload.get('format') != FORMAT:
        raise SaladCheckpointError(f'{path} is not a SALAD checkpoint')
    if payload.get('format_version') != FORMAT_VERSION:
        raise SaladCheckpointError(f'{path} has format version {payload.get("format_version")}'
                                   f', this code reads {FORMAT_VERSION}')
    try:
        cfg = config_from_plain(payload['config'])
        cfg.validate()
        model = SaladNet(cfg)
        model.load_state_dict(payload['state_dict'])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise SaladCheckpointError(f'SALAD checkpoint {path} does not fit this code: '
                                   f'{exc}') from exc
    return model.to(device).eval(), {k: v for k, v in payload.items() if k != 'state_dict'}
