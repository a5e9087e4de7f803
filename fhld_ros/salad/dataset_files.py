"""What the dataset readers (ONCE-3DLanes, OpenLane) share: label JSON and images read with
errors that name the file, arrays checked for shape and finiteness, images written as JPEG."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

JPEG_QUALITY = 95


def load_json(path: Path) -> dict:
    """A label file's JSON object; ValueError naming the file when it cannot be read or is
    not a JSON object."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f'{path}: not a readable JSON file ({exc})') from exc
    if not isinstance(data, dict):
        raise ValueError(f'{path}: expected a JSON object, got {type(data).__name__}')
    return data


def field(data: dict, key: str, path: Path) -> object:
    """data[key]; ValueError naming the file and the key when it is missing."""
    if key not in data:
        raise ValueError(f'{path}: no "{key}"')
    return data[key]


def float_array(value: object, what: str, path: Path, ndim: int | None = None) -> np.ndarray:
    """value as a finite float64 array (of ndim dimensions when given); ValueError naming the
    file and what the value is otherwise."""
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{path}: {what} is not an array of numbers ({exc})') from exc
    if ndim is not None and array.ndim != ndim:
        raise ValueError(f'{path}: {what} must have {ndim} dimensions, got shape {array.shape}')
    if not np.isfinite(array).all():
        raise ValueError(f'{path}: {what} has values that are not finite')
    return array


def load_image(path: Path, label: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of the image a label file names; ValueError naming both when it is
    missing or unreadable."""
    if not path.is_file():
        raise ValueError(f'{label}: its image {path} does not exist')
    try:
        with Image.open(path) as picture:
            return np.asarray(picture.convert('RGB'), dtype=np.uint8).copy()
    except (OSError, ValueError) as exc:
        raise ValueError(f'{label}: its image {path} cannot be read ({exc})') from exc


def save_jpeg(path: Path, rgb: np.ndarray) -> None:
    """rgb as a JPEG (the datasets' format), folders made as needed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(rgb, dtype=np.uint8)).save(path, quality=JPEG_QUALITY)


def write_json(path: Path, data: dict) -> None:
    """One line of JSON (some loaders read only a label file's first line)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data) + '\n')


def near_first(lane: np.ndarray) -> np.ndarray:
    """An (N, 3) optical-frame polyline ordered near to far (by its ends' z)."""
    return lane[::-1].copy() if lane.shape[0] > 1 and lane[0, 2] > lane[-1, 2] else lane
