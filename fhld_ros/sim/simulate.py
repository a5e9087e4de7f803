"""`fhld simulate OUT_BAG`: a simulated drive as a rosbag2 MCAP bag (docs/design.md §4).

Topics: /points (sensor_msgs/PointCloud2 in the sensor frame), /odom (nav_msgs/Odometry:
header.frame_id `odom`, child_frame_id = the cloud's frame, pose = sensor pose, so replay needs
no extrinsic) and /lanes_gt (visualization_msgs/MarkerArray): every GT lane line of the scene
at the first sweep, then once a second the lines within GT_RADIUS_M of the ego. OUT_BAG and
--preview follow bagio's output rule: refused when they exist unless --overwrite, which replaces
only a bag folder (OUT_BAG) or a regular file (--preview).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fhld_ros.bagio import BagWriter, check_file_output, check_output, write_file_atomically
from fhld_ros.errors import CliError
from fhld_ros.intensity import normalize_intensity
from fhld_ros.sim.layout import ROAD_CLASSES, TOPOLOGIES
from fhld_ros.sim.lidar import DEFAULT_SENSOR, INTENSITY_SCALES, LAYOUTS, SENSORS
from fhld_ros.sim.preview import BevPreview
from fhld_ros.sim.simulator import MAX_SWEEPS, Simulator
from msg_adapters.lanes import lanes_to_marker_array
from msg_adapters.odometry import make_odometry
from msg_adapters.pointcloud2 import create_cloud

GT_RADIUS_M = 80.0
GT_EVERY = 10  # sweeps between /lanes_gt messages


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
    parser.add_argument('--overwrite', action='store_true',
                        help='replace an existing OUT_BAG (only a rosbag2 bag folder) and '
                        '--preview PNG (only a regular file)')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')


def _check(args: argparse.Namespace) -> None:
    check_output(args.out_bag, args.overwrite)
    if not 1 <= args.sweeps <= MAX_SWEEPS:
        raise CliError(f'--sweeps must be in 1..{MAX_SWEEPS}, got {args.sweeps}')
    if args.seed < 0:
        raise CliError(f'--seed must be >= 0, got {args.seed}')
    if args.columns is not None and not 64 <= args.columns <= 4096:
        raise CliError(f'--columns must be in 64..4096, got {args.columns}')
    if args.speed is not None and not 0.0 <= args.speed <= 30.0:
        raise CliError(f'--speed must be within 0..30 m/s, got {args.speed:g}')
    if not 0.0 <= args.odom_noise <= 10.0:
        raise CliError(f'--odom-noise must be within 0..10, got {args.odom_noise:g}')
    if args.preview is not None:
        preview = Path(args.preview)
        if preview.suffix.lower() != '.png':
            raise CliError(f'--preview must name a .png file, got {preview}')
        check_file_output(preview, args.overwrite, {'OUT_BAG': args.out_bag}, '--preview')
    if not args.frame_id or args.frame_id == 'odom' or any(c.isspace() for c in args.frame_id):
        raise CliError(f'--frame-id must be a non-empty name other than odom, got '
                       f'{args.frame_id!r}')


def run(args: argparse.Namespace) -> int:
    _check(args)
    try:
        sim = Simulator(args.seed, args.sweeps, args.sensor, columns=args.columns,
                        layout=args.layout, intensity=args.intensity, no_return=args.no_return,
                        road=args.road, topology=args.topology, speed=args.speed,
                        odom_noise=args.odom_noise, motion_distortion=args.motion_distortion,
                        noise=not args.no_noise)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    sim.frame_id = args.frame_id
    preview = None
    if args.preview:
        preview = BevPreview(sim.odom_poses[:, :2, 3], sim.mount.z)

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
                ids = _unique_ids(ids)
                bag.write('/lanes_gt', 'visualization_msgs/msg/MarkerArray', stamp,
                          lanes_to_marker_array(fam, fam.header(stamp, 'odom'), lanes,
                                                np.ones(len(lanes)), ids, None))
            bag.write('/odom', 'nav_msgs/msg/Odometry', stamp,
                      make_odometry(fam, fam.header(stamp, 'odom'), sim.frame_id,
                                    sweep.odom_pose, sweep.linear, sweep.angular))
            bag.write('/points', 'sensor_msgs/msg/PointCloud2', stamp,
                      create_cloud(cloud_cls, fam.header(stamp, sim.frame_id), sweep.points,
                                   height=sweep.height))
            if preview is not None:
                xyz = np.stack([sweep.points[a] for a in 'xyz'], axis=1)
                field = 'intensity' if 'intensity' in sweep.points.dtype.names else \
                    'reflectivity'
                preview.add(xyz, normalize_intensity(sweep.points[field]), sweep.odom_pose)
            bar.update()
        bar.close()
    if preview is not None:
        scene = sim.scene
        events = ', '.join(e.kind for e in scene.events) or 'no topology event'
        title = (f'fhld simulate --seed {args.seed} --sweeps {args.sweeps} '
                 f'--sensor {args.sensor}: {scene.road_class}, {events}; '
                 f'{len(scene.lane_lines)} GT lines')
        write_file_atomically(args.preview, lambda tmp: preview.save(
            tmp, scene.lane_lines, sim.odom_poses[:, :2, 3], title))
    return 0


def _unique_ids(ids: list[int]) -> list[int]:
    """Marker ids stay the line's id; a second piece of the same line gets id + 1000 * k."""
    seen: dict[int, int] = {}
    out = []
    for i in ids:
        k = seen.get(i, 0)
        seen[i] = k + 1
        out.append(i + 1000 * k)
    return out
