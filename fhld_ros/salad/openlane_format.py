"""OpenLane (v1) lane3d files <-> CameraLaneSample.

A frame's label is one JSON object: "file_path" (the image, relative to the images folder:
'<split>/<segment>/<frame>.jpg'), "intrinsic" (3x3 K), "extrinsic" (4x4, the camera in the
vehicle frame), "lane_lines": [{"xyz": 3xN, "uv": 2xN, "visibility": N, "category",
"track_id", "attribute"}, ...]. The layouts read:

    <root>/images/<split>/<segment>/<frame>.jpg, <root>/lane3d_1000/<split>/<segment>/<frame>.json
    <root>/images/<segment>/<frame>.jpg, <root>/lane3d/annotations/<segment>/<frame>.json

(the release, and the examples of OpenLane's evaluation code, whose "file_path" keeps the
'validation/' the folder lacks).

"xyz" is in OpenLane's camera frame, x forward, y left, z up, camera-centred: K applied to
(-y, -z, x) gives "uv" exactly (the two examples: largest difference 5e-13 px over their
2,862 visible points; taken as vehicle-frame points through the inverse extrinsic first, the
lanes' median distances are 76-159 px), the conversion OpenLane's evaluation makes too (its
cam_representation). "uv" holds the visible points only, in order: visibility 0 marks the far
ends the image does not show (there beyond 67-122 m). A lane here is each run of visible
points in front of the camera, in the optical frame, near to far.
"""
from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
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
from fhld_ros.sim.gt_lines import runs

LABEL_DIRS = 'lane3d*'  # lane3d_1000, lane3d_300, lane3d (the examples)
WRITE_LABELS = 'lane3d_1000'
NAME = re.compile(r'^([^/\s]+)/([^/\s]+)$')  # a sample's name: <segment>/<frame>
DEFAULT_SEGMENT = 'segment-0'
# OpenLane camera (x forward, y left, z up) -> optical (x right, y down, z forward)
OPENLANE_TO_OPTICAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def read_openlane(root: str | Path, labels: str | Path | None = None
                  ) -> Iterator[CameraLaneSample]:
    """Every label file under root's lane3d* folders (or under `labels`, e.g.
    root/lane3d_1000/validation), in sorted order, named '<segment>/<frame>'. ValueError
    naming the file on a malformed label or a missing image."""
    root = Path(root)
    folders = [Path(labels)] if labels is not None else sorted(root.glob(LABEL_DIRS))
    if not any(folder.is_dir() for folder in folders):
        raise ValueError(f'{labels or root / LABEL_DIRS}: no OpenLane label folder')
    for folder in folders:
        for label in sorted(folder.rglob('*.json')):
            yield read_openlane_frame(root, label)


def read_openlane_frame(root: str | Path, label: str | Path) -> CameraLaneSample:
    """One label file (and its image under root/images) as a sample."""
    label = Path(label)
    data = load_json(label)
    K = float_array(field(data, 'intrinsic', label), '"intrinsic"', label, ndim=2)
    if K.shape != (3, 3):
        raise ValueError(f'{label}: "intrinsic" must be 3x3, got {K.shape}')
    file_path = field(data, 'file_path', label)
    if not isinstance(file_path, str) or not file_path:
        raise ValueError(f'{label}: "file_path" must name the image')
    raw = field(data, 'lane_lines', label)
    if not isinstance(raw, list):
        raise ValueError(f'{label}: "lane_lines" must be a list')
    lanes = [piece for i, line in enumerate(raw) for piece in _visible_pieces(line, i, label)]
    image = load_image(_image_path(Path(root), file_path), label)
    try:
        return CameraLaneSample(image, K, lanes, f'{label.parent.name}/{label.stem}')
    except ValueError as exc:  # e.g. a K with a focal length <= 0
        raise ValueError(f'{label}: {exc}') from exc


def _visible_pieces(line: object, i: int, label: Path) -> list[np.ndarray]:
    """The runs of visible points in front of the camera of lane_lines[i], optical frame."""
    if not isinstance(line, dict):
        raise ValueError(f'{label}: lane_lines[{i}] must be an object')
    xyz = float_array(field(line, 'xyz', label), f'lane_lines[{i}].xyz', label, ndim=2)
    if xyz.shape[0] != 3:
        raise ValueError(f'{label}: lane_lines[{i}].xyz must be 3xN, got {xyz.shape}')
    visibility = float_array(line.get('visibility', np.ones(xyz.shape[1])),
                             f'lane_lines[{i}].visibility', label, ndim=1)
    if visibility.shape != (xyz.shape[1],):
        raise ValueError(f'{label}: lane_lines[{i}].visibility has {visibility.size} values '
                         f'for {xyz.shape[1]} points')
    points = xyz.T @ OPENLANE_TO_OPTICAL.T
    keep = (visibility > 0.5) & (points[:, 2] > 0)
    return [near_first(points[a:b]) for a, b in runs(keep) if b - a >= 2]


def _image_path(root: Path, file_path: str) -> Path:
    """root/images/<file_path>, else without its first folder (the examples' layout)."""
    relative = Path(file_path)
    candidates = [root / 'images' / relative, root / 'images' / Path(*relative.parts[1:]),
                  root / relative]
    return next((p for p in candidates if p.is_file()), candidates[0])


def write_openlane(root: str | Path, samples: Iterable[CameraLaneSample],
                   split: str = 'validation', segment: str = DEFAULT_SEGMENT) -> list[Path]:
    """Samples in the release layout (images/<split>/..., lane3d_1000/<split>/...), named
    from a sample's '<segment>/<frame>' name or else the given segment and the index; every
    point visible, "uv" its projection, the extrinsic the identity (a sample has none).
    Returns the label files."""
    root, written = Path(root), []
    for i, sample in enumerate(samples):
        match = NAME.match(sample.name)
        seg, frame = (match.group(1), match.group(2)) if match else (segment, f'{i:06d}')
        file_path = f'{split}/{seg}/{frame}.jpg'
        lines = []
        for j, lane in enumerate(sample.lanes):
            uv = lane @ sample.intrinsics.T
            lines.append({'xyz': (lane @ OPENLANE_TO_OPTICAL).T.tolist(),
                          'uv': (uv[:, :2] / uv[:, 2:]).T.tolist(),
                          'visibility': [1.0] * lane.shape[0], 'category': 0,
                          'track_id': j + 1, 'attribute': 0})
        label = root / WRITE_LABELS / split / seg / f'{frame}.json'
        write_json(label, {'extrinsic': np.eye(4).tolist(),
                           'intrinsic': sample.intrinsics.tolist(), 'lane_lines': lines,
                           'file_path': file_path})
        save_jpeg(root / 'images' / file_path, sample.image)
        written.append(label)
    return written
