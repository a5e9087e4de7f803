"""Checkpoint files: weights + the config that built them + code version + training command.

Only plain containers, numbers, strings and tensors are stored, so loading goes through
``torch.load(weights_only=True)`` (no arbitrary unpickling). Every way a file can be unusable
(missing, truncated/corrupt, not ours, newer format, weights that do not fit the config or
the code, a raster other than the caller's) raises CheckpointError with one clear line.
"""
from __future__ import annotations

import os
import re
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from fhld_ros import __version__
from fhld_ros.errors import ConfigError
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.detector import FhldDetector

FORMAT = 'fhld-checkpoint'
FORMAT_VERSION = 1
# Config fields added after checkpoints existed, with the value those checkpoints were built
# with (inference-only fields such as local_refine_steps take the current default instead).
LEGACY_CONFIG_DEFAULTS: dict[str, Any] = {'stem_kernel': 7, 'intensity_encoding': 'absolute'}
# torch's weights_only refusal of a pickled class or callable; its wording varies between
# releases ('Unsupported global: GLOBAL x.Y', 'unsupported GLOBAL posix.system whose ...').
_UNSAFE_GLOBAL = re.compile(r'unsupported global:?\s*(?:global\s+)?([\w.]+)', re.IGNORECASE)
DEFAULT_CHECKPOINT = Path(__file__).resolve().parent.parent / 'checkpoints' / 'fhld.pt'


class CheckpointError(ConfigError):
    """A checkpoint that cannot be used; the message names the file and the problem."""


@dataclass
class LoadedCheckpoint:
    model: FhldDetector
    config: FhldConfig
    code_version: str
    train_command: str
    meta: dict[str, Any] = field(default_factory=dict)


def code_version() -> str:
    """Package version plus the git commit of the source tree when there is one."""
    try:
        commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'],
                                cwd=Path(__file__).parent, capture_output=True, text=True,
                                timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ''
    return f'{__version__}+g{commit}' if commit else __version__


def save_checkpoint(path: str | os.PathLike, model: FhldDetector, train_command: str,
                    meta: dict[str, Any] | None = None, half: bool = False) -> Path:
    """Write atomically (temp file + rename). half=True stores float tensors as float16."""
    # CPU tensors: weights trained on a GPU load where there is none
    state = {k: (v.half() if half and v.is_floating_point() else v).detach().cpu().contiguous()
             for k, v in model.state_dict().items()}
    payload = {'format': FORMAT, 'format_version': FORMAT_VERSION,
               'config': model.cfg.to_dict(), 'code_version': code_version(),
               'train_command': train_command, 'meta': dict(meta or {}), 'state_dict': state}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f'.{path.name}.', suffix='.tmp')
    try:
        with os.fdopen(fd, 'wb') as f:
            torch.save(payload, f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | os.PathLike, expect: FhldConfig | None = None,
                    map_location: str | torch.device = 'cpu') -> LoadedCheckpoint:
    """Load a checkpoint; with ``expect``, its raster spec must equal the stored one."""
    path = Path(path)
    if not path.is_file():  # a directory or a device (/dev/zero) exists but is no checkpoint
        raise CheckpointError(f'checkpoint {path} is not a regular file' if path.exists()
                              else f'checkpoint not found: {path}')
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # zip, pickle and tensor errors all mean the same to the user
        unsafe = _UNSAFE_GLOBAL.search(str(exc))
        if unsafe:  # a class or function (os.system, ...) weights_only would have to import
            raise CheckpointError(
                f'checkpoint {path} holds Python objects ({unsafe.group(1)}), not plain data: '
                'an unsafe pickle that could run code; refusing to unpickle it '
                '(weights_only=True)') from exc
        first = next((line.strip() for line in str(exc).splitlines() if line.strip()), '')
        if first.startswith('Weights only load failed'):  # torch's preamble, not the cause
            first = 'invalid pickle data'
        detail = f'{type(exc).__name__}: {first[:160]}' if first else type(exc).__name__
        raise CheckpointError(f'checkpoint {path} is corrupt or not a torch file ({detail})'
                              ) from exc
    if not isinstance(payload, dict) or payload.get('format') != FORMAT:
        raise CheckpointError(f'{path} is not an FHLD checkpoint (no "{FORMAT}" header)')
    if payload.get('format_version') != FORMAT_VERSION:
        raise CheckpointError(f'checkpoint {path} has format version '
                              f'{payload.get("format_version")}, this code reads {FORMAT_VERSION}')
    try:
        config = FhldConfig.from_dict({**LEGACY_CONFIG_DEFAULTS, **payload['config']})
        config.validate()
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f'checkpoint {path} has an unusable config: {exc}') from exc
    if expect is not None:
        stored = (config.size_px, config.resolution_m, config.in_channels)
        wanted = (expect.size_px, expect.resolution_m, expect.in_channels)
        if stored != wanted:
            raise CheckpointError(
                f'checkpoint {path} expects a {stored[0]} px raster at {stored[1]} m with '
                f'{stored[2]} channels, the input (parameters size_px, resolution_m) is '
                f'{wanted[0]} px at {wanted[1]} m with {wanted[2]} channels')
    model = FhldDetector(config)
    try:
        model.load_state_dict(payload['state_dict'], strict=True)
    except (KeyError, RuntimeError) as exc:
        detail = ' '.join(str(exc).split())[:300]
        raise CheckpointError(f'checkpoint {path} does not fit the model built from its '
                              f'config (code {code_version()}, file {payload.get("code_version")}'
                              f'): {detail}') from exc
    model.eval()
    return LoadedCheckpoint(model, config, str(payload.get('code_version', '')),
                            str(payload.get('train_command', '')), dict(payload.get('meta', {})))


def interpolate_checkpoints(start: str | os.PathLike, tuned: str | os.PathLike,
                            weight: float, out: str | os.PathLike) -> Path:
    """Write (1 - weight) * start + weight * tuned, the weights of a fine-tuned model moved back
    towards those it started from (WiSE-FT, Wortsman et al. 2022: more robust under a change of
    data than either end). Both must share one config; the meta keeps tuned's, plus both
    sources."""
    if not 0.0 <= weight <= 1.0:
        raise ConfigError(f'weight must be within 0..1, got {weight:g}')
    a, b = load_checkpoint(start), load_checkpoint(tuned)
    if a.config != b.config:
        raise CheckpointError(f'{start} and {tuned} have different model configs')
    sa, sb = a.model.state_dict(), b.model.state_dict()
    b.model.load_state_dict({
        k: (sa[k].float() * (1.0 - weight) + sb[k].float() * weight).to(sb[k].dtype)
        if sb[k].is_floating_point() else sb[k] for k in sb})
    meta = {k: v for k, v in b.meta.items() if k != 'train_state'}
    meta['interpolated'] = {'start': str(start), 'start_code_version': a.code_version,
                            'tuned': str(tuned), 'tuned_code_version': b.code_version,
                            'tuned_weight': weight}
    return save_checkpoint(out, b.model, b.train_command, meta)


def build_default_detector() -> FhldDetector:
    """The shipped weights when present, else a randomly initialised default model."""
    if DEFAULT_CHECKPOINT.exists():
        return load_checkpoint(DEFAULT_CHECKPOINT).model
    with torch.random.fork_rng():  # reproducible weights without touching the caller's RNG
        torch.manual_seed(0)
        return FhldDetector(FhldConfig())
