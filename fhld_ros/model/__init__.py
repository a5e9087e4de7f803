"""FHLD detector (Guan et al., AAAI 2023): backbone, global curves, dynamic anchors, local
segments. See detector.py for the entry points and config.py for the coordinate conventions.

Names are imported lazily: fhld_ros.matcher and fhld_ros.losses import submodules of this
package, and the detector imports the matcher.
"""
from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    'DEFAULT_CHECKPOINT': 'checkpoint', 'CheckpointError': 'checkpoint',
    'load_checkpoint': 'checkpoint', 'save_checkpoint': 'checkpoint',
    'FhldConfig': 'config', 'Detections': 'detector', 'FhldDetector': 'detector',
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    return getattr(importlib.import_module(f'{__name__}.{_EXPORTS[name]}'), name)
