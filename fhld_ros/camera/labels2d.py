"""2D lane labels of camera images: one JSON per image, `<stamp_ns>.json` (docs/annotation.md).

    {"format": "fhld-lanes2d-1", "stamp_ns": 1700000000100000000, "frame_id": "camera",
     "image_size": [960, 600], "lanes": [{"id": 3, "uv": [[412.5, 599.0], ...]}, ...]}

Each lane is one visible piece of a line as pixel coordinates (OpenCV convention, u right,
v down), ordered from the image bottom (near) to the far end; an occluded line is several
pieces with the same id. Per-image polylines as in CULane, a JSON per image as in ONCE-3DLanes.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fhld_ros.errors import ConfigError

FORMAT = 'fhld-lanes2d-1'


@dataclass
class LaneLabel2D:
    id: int
    uv: np.ndarray  # (K, 2) pixels


@dataclass
class ImageLabels:
    stamp_ns: int
    frame_id: str
    image_size: tuple[int, int]  # (width, height)
    lanes: list[LaneLabel2D] = field(default_factory=list)


def label_path(directory: str | Path, stamp_ns: int) -> Path:
    return Path(directory) / f'{int(stamp_ns)}.json'


def write_labels(path: str | Path, labels: ImageLabels) -> None:
    data = {'format': FORMAT, 'stamp_ns': int(labels.stamp_ns), 'frame_id': labels.frame_id,
            'image_size': [int(v) for v in labels.image_size],
            'lanes': [{'id': int(lane.id),
                       'uv': np.round(np.asarray(lane.uv, dtype=np.float64), 2).tolist()}
                      for lane in labels.lanes]}
    Path(path).write_text(json.dumps(data, separators=(',', ':')) + '\n')


def read_labels(path: str | Path) -> ImageLabels:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f'2D labels {path}: cannot read it ({exc})') from exc
    try:
        if data.get('format') != FORMAT:
            raise ValueError(f'format is {data.get("format")!r}, expected {FORMAT!r}')
        width, height = (int(v) for v in data['image_size'])
        lanes = []
        for k, lane in enumerate(data['lanes']):
            uv = np.asarray(lane['uv'], dtype=np.float64)
            if uv.ndim != 2 or uv.shape[1] != 2 or not np.all(np.isfinite(uv)):
                raise ValueError(f'lane {k}: uv must be a list of finite [u, v] pairs')
            lanes.append(LaneLabel2D(int(lane['id']), uv))
        return ImageLabels(int(data['stamp_ns']), str(data.get('frame_id', 'camera')),
                           (width, height), lanes)
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        what = f'missing key {exc}' if isinstance(exc, KeyError) else str(exc)
        raise ConfigError(f'2D labels {path}: {what}') from exc


def read_label_dir(directory: str | Path) -> dict[int, ImageLabels]:
    """stamp_ns -> labels of every `*.json` in the directory."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ConfigError(f'--labels2d {directory}: not a directory')
    files = sorted(directory.glob('*.json'))
    if not files:
        raise ConfigError(f'--labels2d {directory}: no *.json label files in it')
    out: dict[int, ImageLabels] = {}
    for path in files:
        labels = read_labels(path)
        if labels.stamp_ns in out:
            raise ConfigError(f'--labels2d {directory}: two files label the image at '
                              f'stamp {labels.stamp_ns} ({path.name})')
        out[labels.stamp_ns] = labels
    return out
