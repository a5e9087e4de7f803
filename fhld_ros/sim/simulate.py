"""`fhld simulate OUT_BAG`: a simulated drive as a rosbag2 MCAP bag (docs/design.md §4).

Topics: /points (sensor_msgs/PointCloud2 in the sensor frame), /odom (nav_msgs/Odometry:
header.frame_id `odom`, child_frame_id = the cloud's frame, pose = sensor pose, so replay needs
no extrinsic) and /lanes_gt (visualization_msgs/MarkerArray): every GT lane line of the scene
at the first sweep, then once a second the lines within GT_RADIUS_M of the ego. With --camera
also a front camera (sim/camera.py): /tf_static (tf2_msgs/TFMessage, once, the camera's pose
in the cloud frame), and per sweep at its stamp /camera/camera_info and /camera/image_raw (rgb8);
--labels2d DIR writes each image's 2D lane labels as DIR/<stamp_ns>.json (sim/labels2d_gt.py)
and, per image, /camera/lanes_gt (MarkerArray, odom frame): the 3D GT of what the labels show,
so `fhld eval --gt-topic /camera/lanes_gt` scores `fhld autolabel` on exactly that.
OUT_BAG and --preview follow bagio's output rule: refused when they exist unless --overwrite,
which replaces only a bag folder (OUT_BAG) or a regular file (--preview); --labels2d refuses a
non-empty DIR unless --overwrite, which replaces only the label files of this run.
"""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fhld_ros.bagio import BagWriter, check_file_output, check_output, write_file_atomically
from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.camera.camera_topics import write_camera
from fhld_ros.camera.labels2d import ImageLabels, label_path, write_labels
from fhld_ros.errors import ConfigError
from fhld_ros.intensity import normalize_intensity
from fhld_ros.sim.camera import CAMERA_FRAME, SimCamera, sweep_stamp_ns
from fhld_ros.sim.labels2d_gt import sim_image_labels
from fhld_ros.sim.layout import ROAD_CLASSES, TOPOLOGIES
from fhld_ros.sim.lidar import DEFAULT_SENSOR, INTENSITY_SCALES, LAYOUTS, SENSORS
from fhld_ros.sim.preview import BevPreview
from fhld_ros.sim.simulator import MAX_SWEEPS, Simulator
from msg_adapters.lanes import lanes_to_marker_array, unique_marker_ids
from msg_adapters.odometry import make_odometry
from msg_adapters.pointcloud2 import create_cloud

GT_RADIUS_M = 80.0
GT_EVERY = 10  # sweeps between /lanes_gt messages
VISIBLE_GT_TOPIC = '/camera/lanes_gt'  # per labelled image: the 3D GT its labels show
CAMERA_SIZE_RANGE = (64, 4096)  # px, each side


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('out_bag', metavar='OUT_BAG', help='bag directory to write')
    parser.add_argument('--seed', type=int, default=0, help='scene seed (default 0)')
    parser.add_argument('--sweeps', type=int, default=100,
                        help=f'number of 10 Hz sweeps, 1..{MAX_SWEEPS} (default 100)')
    parser.add_argument('--sensor', default=DEFAULT_SENSOR, choices=list(SENSORS),
                        help=f'LiDAR preset (default {DEFAULT_SENSOR})')
    parser.add_argument('--columns', type=int, help='columns per revolution (default: preset)')
    parser.add_argument('--layout', choices=LAYOUTS,
                        help='driver point layout (default: the preset\'s)')
    parser.add_argument('--intensity', choices=INTENSITY_SCALES,
                        help='intensity field: reflectivity (uint16 calibrated), float (0-1), '
                        'u8 (0-255 float); default: the preset\'s')
    parser.add_argument('--no-return', choices=('zero', 'nan'), default='zero',
                        help='organised layout: no-return points all-zero or NaN')
    parser.add_argument('--road', choices=('auto', *ROAD_CLASSES), default='auto',
                        help='road class (default auto: drawn from the seed)')
    parser.add_argument('--topology', choices=TOPOLOGIES,
                        help='force a topology event near the start')
    parser.add_argument('--speed', type=float, help='ego speed in m/s, 0..30 (default: random)')
    parser.add_argument('--odom-noise', type=float, default=0.0,
                        help='odometry drift level, 0 = exact, 1 = typical (default 0)')
    parser.add_argument('--motion-distortion', action='store_true',
                        help='points in each column\'s own frame, as raw drivers publish')
    parser.add_argument('--no-noise', action='store_true',
                        help='no range/intensity noise and no random dropouts')
    parser.add_argument('--frame-id', default='lidar', help='cloud frame (default lidar)')
    parser.add_argument('--preview', metavar='PNG', help='also draw a bird\'s-eye picture')
    parser.add_argument('--camera', action='store_true',
                        help='also a front camera: /camera/image_raw, /camera/camera_info and '
                        '/tf_static (docs/annotation.md)')
    parser.add_argument('--camera-size', metavar='WxH', default='960x600',
                        help='camera image size in pixels (default 960x600)')
    parser.add_argument('--labels2d', metavar='DIR',
                        help='with --camera: write each image\'s 2D lane labels as '
                        'DIR/<stamp_ns>.json')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace an existing OUT_BAG (only a rosbag2 bag folder), '
                        '--preview PNG (only a regular file) and the label files of this run '
                        'in a non-empty --labels2d DIR')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')


def _check(args: argparse.Namespace) -> None:
    check_output(args.out_bag, args.overwrite)
    if not 1 <= args.sweeps <= MAX_SWEEPS:
        raise ConfigError(f'--sweeps must be in 1..{MAX_SWEEPS}, got {args.sweeps}')
    if args.seed < 0:
        raise ConfigError(f'--seed must be >= 0, got {args.seed}')
    if args.columns is not None and not 64 <= args.columns <= 4096:
        raise ConfigError(f'--columns must be in 64..4096, got {args.columns}')
    if args.speed is not None and not 0.0 <= args.speed <= 30.0:
        raise ConfigError(f'--speed must be within 0..30 m/s, got {args.speed:g}')
    if not 0.0 <= args.odom_noise <= 10.0:
        raise ConfigError(f'--odom-noise must be within 0..10, got {args.odom_noise:g}')
    if args.preview is not None:
        preview = Path(args.preview)
        if preview.suffix.lower() != '.png':
            raise ConfigError(f'--preview must name a .png file, got {preview}')
        check_file_output(preview, args.overwrite, {'OUT_BAG': args.out_bag}, '--preview')
    if not args.frame_id or args.frame_id == 'odom' or any(c.isspace() for c in args.frame_id):
        raise ConfigError(f'--frame-id must be a non-empty name other than odom, got '
                       f'{args.frame_id!r}')
    if args.camera and args.frame_id == CAMERA_FRAME:
        raise ConfigError(f'--frame-id {CAMERA_FRAME} is the camera\'s frame with --camera: '
                       'name the cloud frame otherwise')
    args.camera_wh = _camera_size(args.camera_size)
    if args.labels2d is not None:
        if not args.camera:
            raise ConfigError('--labels2d needs --camera (the labels are of the camera images)')
        _check_labels_dir(Path(args.labels2d), args)


def _camera_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r'(\d+)x(\d+)', text.strip())
    lo, hi = CAMERA_SIZE_RANGE
    if match is None or not all(lo <= int(v) <= hi for v in match.groups()):
        raise ConfigError(f'--camera-size must be WxH with both within {lo}..{hi} px, '
                          f'got {text!r}')
    return int(match.group(1)), int(match.group(2))


def _label_paths(directory: Path, sweeps: int) -> list[Path]:
    """The files this run writes: one per sweep, named by its stamp (the simulator's clock)."""
    return [label_path(directory, sweep_stamp_ns(k)) for k in range(sweeps)]


def _check_labels_dir(directory: Path, args: argparse.Namespace) -> None:
    """--labels2d follows the output rule: a new or empty directory, or with --overwrite a
    directory whose files of this run's names are regular files (nothing else is touched)."""
    name = f'--labels2d {directory}'
    out_r, bag_r = directory.resolve(), Path(args.out_bag).resolve()
    if out_r == bag_r or bag_r in out_r.parents or out_r in bag_r.parents:
        raise ConfigError(f'{name} overlaps OUT_BAG {args.out_bag}: write it elsewhere')
    if args.preview is not None and Path(args.preview).resolve() == out_r:
        raise ConfigError(f'{name} is --preview {args.preview}: write it elsewhere')
    if directory.is_symlink() or (directory.exists() and not directory.is_dir()):
        raise ConfigError(f'{name} exists and is not a directory')
    if not directory.exists():
        if not out_r.parent.is_dir():
            raise ConfigError(f'cannot write {name}: directory {out_r.parent} does not exist')
        return
    if any(directory.iterdir()) and not args.overwrite:
        raise ConfigError(f'{name} exists and is not empty (use --overwrite to replace the label '
                       'files of this run)')
    for path in _label_paths(directory, args.sweeps):
        if path.is_symlink() or (path.exists() and not path.is_file()):
            raise ConfigError(f'{name}: {path.name} exists and is not a regular file: '
                              'not replaced')


def run(args: argparse.Namespace) -> int:
    _check(args)
    try:
        sim = Simulator(args.seed, args.sweeps, args.sensor, columns=args.columns,
                        layout=args.layout, intensity=args.intensity, no_return=args.no_return,
                        road=args.road, topology=args.topology, speed=args.speed,
                        odom_noise=args.odom_noise, motion_distortion=args.motion_distortion,
                        noise=not args.no_noise)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    sim.frame_id = args.frame_id
    preview = None
    if args.preview:
        preview = BevPreview(sim.odom_poses[:, :2, 3], sim.mount.z)
    camera = SimCamera(sim, *args.camera_wh) if args.camera else None
    calib = camera.calibration() if camera is not None else None
    labels: list[ImageLabels] = []

    with BagWriter(args.out_bag, overwrite=args.overwrite) as bag:
        fam = bag.family
        cloud_cls = fam.cls('sensor_msgs/msg/PointCloud2')
        bar = tqdm(total=sim.n_sweeps, unit='sweep', desc='simulate', disable=args.quiet)
        for sweep in sim.sweeps():
            stamp = sweep.stamp_ns
            if sweep.index % GT_EVERY == 0:
                if sweep.index == 0:
                    lanes, ids = sim.scene.lane_lines, list(range(len(sim.scene.lane_lines)))
                else:
                    lanes, ids = sim.lane_lines_near(sweep.sensor_to_odom[:2, 3], GT_RADIUS_M)
                ids = unique_marker_ids(ids)
                bag.write('/lanes_gt', 'visualization_msgs/msg/MarkerArray', stamp,
                          lanes_to_marker_array(fam, fam.header(stamp, 'odom'), lanes,
                                                np.ones(len(lanes)), ids, None))
            bag.write('/odom', 'nav_msgs/msg/Odometry', stamp,
                      make_odometry(fam, fam.header(stamp, 'odom'), sim.frame_id,
                                    sweep.odom_pose, sweep.linear, sweep.angular))
            bag.write('/points', 'sensor_msgs/msg/PointCloud2', stamp,
                      create_cloud(cloud_cls, fam.header(stamp, sim.frame_id), sweep.points,
                                   height=sweep.height))
            if camera is not None:
                labels += _write_camera(bag, camera, calib, sweep.index,
                                        args.labels2d is not None)
            if preview is not None:
                xyz = np.stack([sweep.points[a] for a in 'xyz'], axis=1)
                field = 'intensity' if 'intensity' in sweep.points.dtype.names else \
                    'reflectivity'
                preview.add(xyz, normalize_intensity(sweep.points[field]), sweep.odom_pose)
            bar.update()
        bar.close()
    if args.labels2d is not None:
        _write_labels(Path(args.labels2d), labels)
    if preview is not None:
        scene = sim.scene
        events = ', '.join(e.kind for e in scene.events) or 'no topology event'
        title = (f'fhld simulate --seed {args.seed} --sweeps {args.sweeps} '
                 f'--sensor {args.sensor}: {scene.road_class}, {events}; '
                 f'{len(scene.lane_lines)} GT lines')
        write_file_atomically(args.preview, lambda tmp: preview.save(
            tmp, scene.lane_lines, sim.odom_poses[:, :2, 3], title))
    return 0


def _write_camera(bag: BagWriter, camera: SimCamera, calib: CameraCalibration, k: int,
                  with_labels: bool) -> list[ImageLabels]:
    """The camera's messages of sweep k (/tf_static before the first image), and its labels."""
    image = camera.render(k)
    write_camera(bag, calib, camera.sim.frame_id, image.stamp_ns, image.rgb, first=k == 0)
    if not with_labels:
        return []
    labels, pieces = sim_image_labels(camera.sim, calib, image)
    fam = bag.family
    bag.write(VISIBLE_GT_TOPIC, 'visualization_msgs/msg/MarkerArray', image.stamp_ns,
              lanes_to_marker_array(fam, fam.header(image.stamp_ns, 'odom'), pieces,
                                    np.ones(len(pieces)),
                                    unique_marker_ids([lane.id for lane in labels.lanes])))
    return [labels]


def _write_labels(directory: Path, labels: list[ImageLabels]) -> None:
    """After the bag is in place: each file through a temporary name in the directory."""
    directory.mkdir(exist_ok=True)
    for item in labels:
        write_file_atomically(label_path(directory, item.stamp_ns),
                              lambda tmp, item=item: write_labels(tmp, item))
