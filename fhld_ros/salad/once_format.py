"""ONCE-3DLanes files <-> CameraLaneSample.

The release (github.com/once-3dlanes/once_3dlanes_benchmark; the loaders of PersFormer and LATR
map a label file to its image the same way) lays a split out as

    <root>/<split>/<sequence>/cam01/<frame>.json    labels, split: train, val, test
    <root>/data/<sequence>/cam01/<frame>.jpg        the ONCE front camera's images

and each label file is one JSON object: "lanes", a list of lanes, each a list of [x, y, z]
points in metres in the camera frame (x right, y down, z forward: the optical frame, no
conversion), and "calibration", the 3x4 projection [K | 0] (3x3 accepted). Images are also
looked for under raw_data/ and raw_data/data/ (how some copies unpack ONCE). Some label files
of the release are empty: they are skipped, as those loaders skip them.

Predictions for the official evaluation (eval.py there) are not the same shape: per frame
<pred_dir>/<sequence>/cam01/<frame>.json with "lanes": [{"points": [[x, y, z], ...],
"score": s}, ...]; write_once_predictions writes them.
"""
from __future__ import annotations

import re
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from fhld_ros.salad.dataset_files import (
    field,
    float_array,
    load_image,
    load_json,
    near_first,
    save_jpeg,
    write_json,
)
from fhld_ros.salad.sample import CameraLaneSample

CAMERA = 'cam01'  # the front camera, the only one ONCE-3DLanes labels
IMAGE_DIRS = ('data', 'raw_data', 'raw_data/data')  # under the root, first found wins
SPLITS = ('train', 'val', 'test')
NAME = re.compile(rf'^([^/\s]+)/{CAMERA}/([^/\s]+)$')  # a sample's name: <sequence>/cam01/<frame>
DEFAULT_SEQUENCE = '000000'


def read_once(root: str | Path, split: str) -> Iterator[CameraLaneSample]:
    """The samples of one split, in sorted sequence and frame order; named
    '<sequence>/cam01/<frame>'. ValueError naming the file on a malformed label or a missing
    image."""
    folder = Path(root) / split
    if not folder.is_dir():
        raise ValueError(f'{folder}: no such ONCE-3DLanes split directory (the splits are '
                         f'{", ".join(SPLITS)})')
    for label in sorted(folder.glob(f'*/{CAMERA}/*.json')):
        if label.stat().st_size > 0:
            yield read_once_frame(root, label)


def read_once_frame(root: str | Path, label: str | Path) -> CameraLaneSample:
    """One label file (and its image under root) as a sample."""
    label = Path(label)
    data = load_json(label)
    sequence, frame = label.parent.parent.name, label.stem
    calibration = float_array(field(data, 'calibration', label), '"calibration"', label, ndim=2)
    if calibration.shape not in ((3, 3), (3, 4)):
        raise ValueError(f'{label}: "calibration" must be 3x3 or 3x4, got {calibration.shape}')
    if calibration.shape == (3, 4) and np.abs(calibration[:, 3]).max() > 1e-9:
        raise ValueError(f'{label}: "calibration" has a non-zero 4th column: the lanes would '
                         'not be in the camera frame')
    raw = field(data, 'lanes', label)
    if not isinstance(raw, list):
        raise ValueError(f'{label}: "lanes" must be a list of lanes')
    lanes = [_lane(points, i, label) for i, points in enumerate(raw)]
    # the official evaluation drops lanes of fewer than 2 points too
    lanes = [near_first(lane) for lane in lanes if lane.shape[0] >= 2]
    image = load_image(_image_path(Path(root), sequence, frame), label)
    try:
        return CameraLaneSample(image, calibration[:, :3], lanes, f'{sequence}/{CAMERA}/{frame}')
    except ValueError as exc:  # e.g. a K with a focal length <= 0
        raise ValueError(f'{label}: {exc}') from exc


def _lane(points: object, i: int, label: Path) -> np.ndarray:
    if not isinstance(points, list):
        raise ValueError(f'{label}: lane {i} must be a list of [x, y, z] points')
    if not points:
        return np.empty((0, 3))
    lane = float_array(points, f'lane {i}', label, ndim=2)
    if lane.shape[1] != 3:
        raise ValueError(f'{label}: lane {i} must be a list of [x, y, z], got shape '
                         f'{lane.shape}')
    return lane


def _image_path(root: Path, sequence: str, frame: str) -> Path:
    candidates = [root / d / sequence / CAMERA / f'{frame}.jpg' for d in IMAGE_DIRS]
    return next((p for p in candidates if p.is_file()), candidates[0])


def sample_key(sample: CameraLaneSample, index: int, sequence: str = DEFAULT_SEQUENCE
               ) -> tuple[str, str]:
    """(sequence, frame) of a sample: from its name when that is '<sequence>/cam01/<frame>'
    (what read_once gives), else the given sequence and the index as the frame."""
    match = NAME.match(sample.name)
    return (match.group(1), match.group(2)) if match else (sequence, f'{index:06d}')


def write_once(root: str | Path, split: str, samples: Iterable[CameraLaneSample],
               sequence: str = DEFAULT_SEQUENCE) -> list[Path]:
    """Samples as ONCE-3DLanes label files and JPEG images under root (see sample_key for the
    names); returns the label files."""
    root, written = Path(root), []
    for i, sample in enumerate(samples):
        seq, frame = sample_key(sample, i, sequence)
        label = root / split / seq / CAMERA / f'{frame}.json'
        calibration = np.hstack([sample.intrinsics, np.zeros((3, 1))])
        write_json(label, {'lanes': [lane.tolist() for lane in sample.lanes],
                           'calibration': calibration.tolist()})
        save_jpeg(root / IMAGE_DIRS[0] / seq / CAMERA / f'{frame}.jpg', sample.image)
        written.append(label)
    return written


def write_once_predictions(pred_root: str | Path,
                           predictions: Iterable[tuple[str, Sequence[np.ndarray],
                                                       Sequence[float]]]) -> list[Path]:
    """(name '<sequence>/cam01/<frame>', lanes (N, 3) optical frame, scores) per frame as the
    official evaluation's prediction files; returns them."""
    written = []
    for name, lanes, scores in predictions:
        match = NAME.match(name)
        if match is None:
            raise ValueError(f'prediction name must be <sequence>/{CAMERA}/<frame>, got {name!r}')
        if len(lanes) != len(scores):
            raise ValueError(f'{name}: {len(lanes)} lanes but {len(scores)} scores')
        path = Path(pred_root) / match.group(1) / CAMERA / f'{match.group(2)}.json'
        write_json(path, {'lanes': [
            {'points': np.asarray(lane, dtype=np.float64).reshape(-1, 3).tolist(),
             'score': float(score)} for lane, score in zip(lanes, scores)]})
        written.append(path)
    return written
