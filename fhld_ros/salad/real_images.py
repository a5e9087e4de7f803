"""`fhld salad-real [DIR]`: SALAD on the real camera images of the development set
(../shared/real_scans, README there): the two OpenLane frames, scored against their 3D GT, and
the nuScenes CAM_FRONT and PJLab front images, which have no lane GT; --draw writes each image
with its lanes (red; OpenLane GT green). The PJLab camera's lens distortion (its calibration's
k1 k2 p1 p2) is removed as the camera node removes camera_info's; nuScenes and OpenLane images
come without."""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image

from fhld_ros.errors import ConfigError
from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT
from fhld_ros.salad.detector import SaladDetector, add_decoding_arguments, decoding_options
from fhld_ros.salad.evaluate import score
from fhld_ros.salad.figure import draw_lanes
from fhld_ros.salad.openlane_format import read_openlane
from fhld_ros.salad.sample import CameraLaneSample

DEFAULT_DIR = Path(__file__).resolve().parents[2].parent / 'shared' / 'real_scans'


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('dir', nargs='?', type=Path, default=DEFAULT_DIR,
                        help='the real_scans folder (default ../shared/real_scans)')
    parser.add_argument('--checkpoint', type=Path, default=DEFAULT_SALAD_CHECKPOINT)
    add_decoding_arguments(parser)
    parser.add_argument('--draw', type=Path, metavar='DIR', help='write <name>.jpg per image')
    parser.add_argument('--pjlab-gt', type=Path, metavar='JSON',
                        help="the PJLab image's lanes from its hand 2D labels lifted by `fhld "
                        "autolabel --once-json` (docs/salad.md): scores that image too")
    parser.add_argument('--nuscenes-gt', type=Path, metavar='JSON',
                        help="the same for the nuScenes CAM_FRONT image")
    parser.add_argument('--json', action='store_true')


def with_lanes(sample: CameraLaneSample, once_json: Path) -> CameraLaneSample:
    """The sample with the 3D lanes of an ONCE-style JSON ({"lanes": [[[x, y, z], ...]]})."""
    lanes = [np.asarray(lane, dtype=np.float64) for lane in
             json.loads(once_json.read_text())['lanes']]
    return dataclasses.replace(sample, lanes=lanes)


def unlabelled_images(root: Path) -> Iterator[CameraLaneSample]:
    """The nuScenes CAM_FRONT and PJLab front images with their intrinsics (no lanes)."""
    nuscenes = root / 'nuscenes_camera_lidar'
    if (nuscenes / 'calib.json').is_file():
        cam = json.loads((nuscenes / 'calib.json').read_text())['cams']['CAM_FRONT']
        image = next(nuscenes.glob('*__CAM_FRONT__*.jpg'))
        yield CameraLaneSample(np.asarray(Image.open(image).convert('RGB')),
                               np.asarray(cam['cam2img'], dtype=np.float64)[:3, :3], [],
                               'nuscenes_cam_front')
    pjlab = root / 'pjlab_camera_lidar_pair'
    if (pjlab / 'center_camera-intrinsic.json').is_file():
        param = json.loads((pjlab / 'center_camera-intrinsic.json').read_text())[
            'center_camera-intrinsic']['param']
        distortion = param.get('cam_dist', {}).get('data')
        yield CameraLaneSample(np.asarray(Image.open(pjlab / '0.png').convert('RGB')),
                               np.asarray(param['cam_K']['data'], dtype=np.float64), [],
                               'pjlab_center_camera', distortion=None if distortion is None
                               else np.asarray(distortion, dtype=np.float64).ravel())


def run(args: argparse.Namespace) -> int:
    if not args.dir.is_dir():
        raise ConfigError(f'no real_scans folder at {args.dir}')
    detector = SaladDetector(args.checkpoint, **decoding_options(args))
    openlane = list(read_openlane(args.dir / 'openlane_examples')) \
        if (args.dir / 'openlane_examples').is_dir() else []
    results: dict = {}
    if openlane:
        results['openlane'] = score(detector, openlane)
        row = results['openlane']['tau_0.30']
        print(f'OpenLane, {row["images"]} images, {row["gt"]} GT lanes: F1 {row["F1"]:.1f} '
              f'P {row["P"]:.1f} R {row["R"]:.1f} CD {row["CD"]:.3f} m (tau_CD 0.3)')
    others = list(unlabelled_images(args.dir))
    for key, title, name, gt in (('pjlab', 'PJLab', 'pjlab_center_camera', args.pjlab_gt),
                                 ('nuscenes', 'nuScenes', 'nuscenes_cam_front',
                                  args.nuscenes_gt)):
        if gt is None:
            continue
        others = [with_lanes(s, gt) if s.name == name else s for s in others]
        results[key] = score(detector, [s for s in others if s.name == name])
        row = results[key]['tau_0.30']
        print(f'{title}, {row["gt"]} lifted hand-labelled lanes: F1 {row["F1"]:.1f} '
              f'P {row["P"]:.1f} R {row["R"]:.1f} CD {row["CD"]:.3f} m (tau_CD 0.3)')
    if args.draw:
        args.draw.mkdir(parents=True, exist_ok=True)
    for sample in [*openlane, *others]:
        lanes, scores = detector(sample.image, sample.intrinsics, distortion=sample.distortion)
        name = sample.name.replace('/', '_')
        results.setdefault('lanes', {})[name] = len(lanes)
        print(f'{name}: {len(lanes)} lanes ({", ".join(f"{s:.2f}" for s in scores)})')
        if args.draw:
            draw_lanes(sample.image, sample.intrinsics, lanes, sample.lanes or None,
                       args.draw / f'{name}.jpg', distortion=sample.distortion)
    if args.json:
        json.dump(results, sys.stdout)
        print()
    return 0
