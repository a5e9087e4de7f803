"""The simulated front camera and its 2D lane labels: the image shows the sky, the road and its
paint where the GT lines project, a vehicle ahead hides the lines behind it, the labels never
lie on nearer things, and `fhld simulate --camera --labels2d` writes /tf_static, camera_info,
images and label files that read back through msg_adapters/camera.py and the calibration."""
from __future__ import annotations

import array
import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree

from fhld_ros.bagio import read_messages
from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.camera.labels2d import read_label_dir, read_labels, write_labels
from fhld_ros.cli import main
from fhld_ros.geometry import resample_polyline
from fhld_ros.sim.camera import RENDER_RANGE_M, SimCamera, mount_extrinsic, sweep_stamp_ns
from fhld_ros.sim.gt_lines import crop_to_disc
from fhld_ros.sim.labels2d_gt import LABEL_STEP_M, sim_image_labels
from fhld_ros.sim.markings import NONE as NO_PAINT
from fhld_ros.sim.simulator import Simulator
from msg_adapters.camera import (
    camera_info_msg,
    camera_info_values,
    compressed_image_msg,
    image_to_msg,
    msg_to_image,
    tf_static_msg,
    tf_transforms,
)
from msg_adapters.family import rclpy_family, rosbags_family
from msg_adapters.lanes import marker_array_to_lanes
from msg_adapters.odometry import euler_to_matrix

TRUCK = (3, 5)  # seed, sweep: an urban street with a van 7 m ahead in the ego lane


@pytest.fixture(scope='module')
def truck_scene():
    seed, k = TRUCK
    sim = Simulator(seed, sweeps=k + 1)
    camera = SimCamera(sim)
    image = camera.render(k)
    return sim, camera, image, sim_image_labels(sim, camera.calibration(), image)[0]


def gt_points(sim: Simulator, calib: CameraCalibration, image) -> tuple[np.ndarray, ...]:
    """Every GT line point (resampled) in the image within 60 m: world xyz, uv, depth."""
    pieces, _ = crop_to_disc(sim.scene.lane_lines, image.camera_to_odom[:2, 3], 70.0)
    # as sim_image_labels does
    pts = np.concatenate([resample_polyline(piece, LABEL_STEP_M) for piece in pieces])
    to_cloud = np.linalg.inv(sim.true_poses[image.index])
    uv, depth, inside = calib.project(pts @ to_cloud[:3, :3].T + to_cloud[:3, 3])
    keep = inside & (depth <= 60.0)
    return pts[keep], uv[keep], depth[keep]


def nearer_everywhere(depth_image: np.ndarray, uv: np.ndarray, depth: np.ndarray
                      ) -> np.ndarray:
    """Points whose 3x3 pixel neighbourhood is all much nearer than they are."""
    h, w = depth_image.shape
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    reach = np.full(len(uv), -np.inf)
    for du in (-1, 0, 1):
        for dv in (-1, 0, 1):
            reach = np.maximum(reach, depth_image[np.clip(v + dv, 0, h - 1),
                                                  np.clip(u + du, 0, w - 1)])
    return reach < depth - np.maximum(0.5, 0.1 * depth)


def luminance(rgb: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = rgb.shape[:2]
    u = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    return rgb[v, u].astype(float) @ np.array([0.299, 0.587, 0.114])


@pytest.mark.slow
def test_image_shows_sky_on_top_and_paint_where_gt_lines_project(truck_scene) -> None:
    sim, camera, image, _ = truck_scene
    assert image.rgb.shape == (600, 960, 3) and image.rgb.dtype == np.uint8
    assert image.depth.shape == (600, 960) and image.depth.dtype == np.float32
    assert image.stamp_ns == sweep_stamp_ns(TRUCK[1])
    top = image.rgb[:40, 380:580].reshape(-1, 3).astype(int)  # above the van
    assert np.isinf(image.depth[:40, 380:580]).all()
    assert (top[:, 2] > top[:, 0] + 40).all()  # blue sky
    assert np.isfinite(image.depth[-100:]).all()  # road at the bottom
    # painted GT points within 25 m against the road half a metre to either side
    pts, uv, depth = gt_points(sim, camera.calibration(), image)
    s, d = sim.scene.ref.project(pts[:, :2])
    kind, contrast, _ = sim.scene.paint.lookup(s, d)
    sel = (kind != NO_PAINT) & (contrast > 0.6) & (depth < 25.0) & (
        np.abs(image.depth[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)] -
               depth) < 0.5)  # not behind the van
    assert sel.sum() > 50
    shift = np.zeros((sel.sum(), 2))
    shift[:, 0] = camera.K[0, 0] * 0.5 / depth[sel]
    paint = luminance(image.rgb, uv[sel])
    road = np.minimum(luminance(image.rgb, uv[sel] - shift), luminance(image.rgb, uv[sel] + shift))
    assert np.median(paint - road) > 50 and np.mean(paint > road + 20) > 0.9


@pytest.mark.slow
def test_a_vehicle_ahead_cuts_the_labels_and_no_label_lies_on_nearer_things(truck_scene
                                                                             ) -> None:
    sim, camera, image, labels = truck_scene
    _, uv, depth = gt_points(sim, camera.calibration(), image)
    h, w = image.depth.shape
    rendered = image.depth[np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1),
                           np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)]
    hidden = rendered < depth - np.maximum(0.5, 0.1 * depth)
    assert hidden.sum() > 40  # the van hides part of the lines in the image
    assert labels.lanes and all(lane.uv.shape[0] >= 2 for lane in labels.lanes)
    vertices = np.concatenate([lane.uv for lane in labels.lanes])
    dist, nearest = cKDTree(uv).query(vertices)
    assert dist.max() < 1e-6  # every label vertex is a projected GT point
    # ... none on a nearer thing: within a pixel of each vertex the rendered depth reaches it
    # (where an occluder's edge lies inside a pixel is not known)
    assert nearer_everywhere(image.depth, vertices, depth[nearest]).sum() == 0
    assert hidden[nearest].sum() <= 0.05 * hidden.sum()  # at the van's edge at most
    # lines passing under the van are cut there: a label ends next to the hidden points
    far_ends = np.array([lane.uv[-1] for lane in labels.lanes])
    assert cKDTree(uv[hidden]).query(far_ends)[0].min() < 6.0
    for lane in labels.lanes:  # near end first (image bottom)
        assert lane.uv[0, 1] >= lane.uv[-1, 1]
    assert {lane.id for lane in labels.lanes} <= set(range(len(sim.scene.lane_lines)))


@pytest.mark.slow
@pytest.mark.parametrize('seed, k', [(9, 30), (5, 50), (1, 20)])
def test_labels_never_lie_on_nearer_things(seed: int, k: int) -> None:
    """Highway traffic and urban streets: every label vertex can be seen from the camera."""
    sim = Simulator(seed, sweeps=k + 1)
    camera = SimCamera(sim, 480, 300)
    calib = camera.calibration()
    image = camera.render(k)
    labels, _ = sim_image_labels(sim, calib, image)
    assert len(labels.lanes) >= 2
    _, uv, depth = gt_points(sim, calib, image)
    vertices = np.concatenate([lane.uv for lane in labels.lanes])
    dist, nearest = cKDTree(uv).query(vertices)
    assert dist.max() < 1e-6
    assert nearer_everywhere(image.depth, vertices, depth[nearest]).sum() == 0


def test_obstacle_culling_matches_testing_every_pixel() -> None:
    sim = Simulator(1, sweeps=21)
    camera = SimCamera(sim, 320, 200)
    pose = camera.pose(20)
    dirs = camera.world_dirs(pose)
    culled, _ = camera.cast_obstacles(20, pose[:3, 3], dirs)
    full, _ = camera.cast_obstacles(20, pose[:3, 3], dirs, cull=False)
    assert np.isfinite(full.t).sum() > 5000
    assert np.array_equal(culled.t, full.t)


@pytest.mark.parametrize('hfov_deg, roll_deg, pitch_deg', [(70.0, 0.0, 3.0), (90.0, 12.0, -1.0),
                                                            (50.0, -8.0, 8.0)])
def test_ground_tiles_built_cover_every_ray(hfov_deg: float, roll_deg: float,
                                           pitch_deg: float) -> None:
    # the camera builds only the ground tiles under the sector it sees; each ray's points out
    # to the render range, and the cells beside them, must lie in built tiles, whichever way
    # the camera looks (the sector's edges cross tile corners at some headings)
    sim = Simulator(3, sweeps=1)
    roll = np.deg2rad(roll_deg)
    about_axis = np.eye(4)
    about_axis[:2, :2] = [[np.cos(roll), -np.sin(roll)], [np.sin(roll), np.cos(roll)]]
    camera = SimCamera(sim, 160, 100, hfov_deg,
                       T_cloud_camera=mount_extrinsic(pitch_deg=pitch_deg) @ about_axis)
    reach = RENDER_RANGE_M + 5.0
    t = np.arange(0.0, RENDER_RANGE_M + 1.0, 1.0)
    for yaw in np.deg2rad(np.arange(0.0, 360.0, 10.0)):
        heading = np.eye(4)
        heading[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        pose = heading @ camera.pose(0)
        origin, dirs = pose[:3, 3], camera.world_dirs(pose)
        seen = camera._seen_tiles(origin, dirs, reach)
        corners = np.floor((origin[:2] + [[-reach], [reach]]) / camera.grid.tile_m)
        assert seen and len(seen) < 0.6 * np.prod(corners[1] - corners[0] + 1)  # of the square
        # the image's edges (where the sector's are) and every 8th ray inside
        rays = np.concatenate([dirs[[0, -1]].reshape(-1, 3), dirs[:, [0, -1]].reshape(-1, 3),
                               dirs[::8, ::8].reshape(-1, 3)])
        points = origin[:2] + t[:, None, None] * rays[None, :, :2]
        assert camera.grid.tiles_near(points, 2 * camera.grid.RES) <= seen, np.rad2deg(yaw)


def test_ground_block_builds_a_tile_left_out_once_a_ray_needs_it() -> None:
    sim = Simulator(3, sweeps=1)
    grid = SimCamera(sim, 160, 100).grid
    xy, reach = np.array([10.0, 3.0]), 100.0
    ahead = grid.tiles_near(xy[None] + [[60.0, 0.0]], 1.0)
    behind = grid.tiles_near(xy[None] - [[60.0, 0.0]], 1.0)

    def heights(tiles: set) -> np.ndarray:  # at 8 x 8 points over each tile
        inside = (np.arange(8) + 0.5) * grid.tile_m / 8
        x, y = (np.concatenate([(key + inside[:, None]) for key in np.array(list(tiles))[:, k]
                                * grid.tile_m]) for k in (0, 1))
        return grid.nearest_h(*np.meshgrid(x, y))

    grid.ensure(xy, reach, ahead)
    assert np.isfinite(heights(ahead)).all() and np.isneginf(heights(behind)).all()
    z_ahead = grid.z_range
    grid.ensure(xy, reach, ahead)  # the same block serves
    grid.ensure(xy, reach, behind)  # a tile left out is built
    assert np.isfinite(heights(ahead | behind)).all()
    grid.ensure(xy, reach)  # everything: the LiDAR's block
    assert np.isfinite(grid.h).all()
    assert grid.z_range[0] <= z_ahead[0] and grid.z_range[1] >= z_ahead[1]


def test_labels_round_trip_through_json(truck_scene, tmp_path: Path) -> None:
    *_, labels = truck_scene
    path = tmp_path / f'{labels.stamp_ns}.json'
    write_labels(path, labels)
    back = read_labels(path)
    assert (back.stamp_ns, back.frame_id, back.image_size) == (labels.stamp_ns, 'camera',
                                                                (960, 600))
    assert [lane.id for lane in back.lanes] == [lane.id for lane in labels.lanes]
    for a, b in zip(back.lanes, labels.lanes):
        assert np.allclose(a.uv, b.uv, atol=0.006)


@pytest.mark.parametrize('family', [rosbags_family(), rclpy_family()], ids=lambda f: f.name)
def test_image_and_camera_info_messages_round_trip(family) -> None:
    rgb = np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    header = family.header(1_700_000_000_100_000_000, 'camera')
    msg = image_to_msg(family, header, rgb)
    assert (msg.encoding, msg.step, msg.height, msg.width) == ('rgb8', 21, 5, 7)
    assert np.array_equal(msg_to_image(msg), rgb)
    K = np.array([[700.0, 0.0, 479.5], [0.0, 700.0, 299.5], [0.0, 0.0, 1.0]])
    D = np.array([-0.1, 0.01, 0.001, -0.002, 0.0])
    info = camera_info_msg(family, header, 960, 600, K, D)
    assert info.distortion_model == 'plumb_bob'
    assert np.allclose(np.asarray(info.p).reshape(3, 4)[:, :3], K)
    assert np.allclose(np.asarray(info.r), np.eye(3).ravel())
    width, height, K2, model, D2, frame = camera_info_values(info)
    assert (width, height, model, frame) == (960, 600, 'plumb_bob', 'camera')
    assert np.allclose(K2, K) and np.allclose(D2, D)


def test_tf_static_round_trips_through_cdr() -> None:
    family = rosbags_family()
    T = euler_to_matrix(1.2, -0.1, -0.3, 0.01, 0.05, -0.02)
    msg = tf_static_msg(family, 1_700_000_000_000_000_000, 'lidar', 'camera', T)
    store = family.typestore
    back = store.deserialize_cdr(store.serialize_cdr(msg, 'tf2_msgs/msg/TFMessage'),
                                 'tf2_msgs/msg/TFMessage')
    ((parent, child, T2),) = tf_transforms(back)
    assert (parent, child) == ('lidar', 'camera') and np.allclose(T2, T)
    bgr = image_to_msg(family, family.header(0, 'camera'), np.zeros((2, 2, 3), np.uint8))
    bgr.encoding = 'bayer_rggb16'
    with pytest.raises(ValueError, match="'bayer_rggb16' is not supported"):
        msg_to_image(bgr)


def _with_data(family, msg, data: bytes):
    """msg with its data field replaced by `data`, as the family holds uint8[]."""
    msg.data = np.frombuffer(data, np.uint8) if family.name == 'rosbags' else array.array(
        'B', data)
    return msg


@pytest.mark.parametrize('family', [rosbags_family(), rclpy_family()], ids=lambda f: f.name)
def test_compressed_images_read_as_image_transport_writes_them(family) -> None:
    header = family.header(0, 'camera')
    y, x = np.mgrid[0:60, 0:80]
    rgb = np.stack([x * 3, y * 4, 255 - x * 2], axis=-1).astype(np.uint8)  # smooth: JPEG-able
    png = compressed_image_msg(family, header, rgb, 'png')
    assert png.format == 'rgb8; png compressed bgr8'
    assert np.array_equal(msg_to_image(png), rgb)  # lossless
    jpeg = compressed_image_msg(family, header, rgb, 'jpeg')
    assert np.abs(msg_to_image(jpeg).astype(int) - rgb).mean() < 2.0
    grey = io.BytesIO()
    Image.fromarray(rgb[..., 1]).save(grey, format='JPEG')
    back = msg_to_image(_with_data(family, jpeg, grey.getvalue()))
    assert back.shape == (60, 80, 3) and np.array_equal(back[..., 0], back[..., 2])
    cut = compressed_image_msg(family, header, rgb, 'png')
    cut = _with_data(family, cut, bytes(cut.data)[:len(cut.data) // 2])
    with pytest.raises(ValueError, match=r"format 'rgb8; png compressed bgr8', \d+ bytes\) "
                       'does not decode'):
        msg_to_image(cut)
    depth = compressed_image_msg(family, header, rgb, 'png')
    depth.format = '16UC1; compressedDepth png'
    with pytest.raises(ValueError, match='is a depth image'):
        msg_to_image(depth)
    wide = io.BytesIO()
    Image.fromarray((x * 800).astype(np.uint16)).save(wide, format='PNG')  # mono16
    depth.format = 'mono16; png compressed mono16'
    with pytest.raises(ValueError, match='not 8-bit channels'):
        msg_to_image(_with_data(family, depth, wide.getvalue()))


def _yuv_video_range(rgb: np.ndarray) -> np.ndarray:
    """RGB -> BT.601 video-range Y, Cb, Cr (uint8), as a camera's YUV output holds them."""
    r, g, b = np.moveaxis(rgb.astype(np.float64), -1, 0)
    y = 16 + 219 / 255 * (0.299 * r + 0.587 * g + 0.114 * b)
    cb = 128 + 224 / 255 * (-0.168736 * r - 0.331264 * g + 0.5 * b)
    cr = 128 + 224 / 255 * (0.5 * r - 0.418688 * g - 0.081312 * b)
    return np.rint(np.stack([y, cb, cr], axis=-1)).astype(np.uint8)


@pytest.mark.parametrize('encoding, order', [('yuv422', 'uyvy'), ('uyvy', 'uyvy'),
                                             ('yuv422_yuy2', 'yuyv'), ('yuyv', 'yuyv')])
def test_yuv422_images_read_as_rgb(encoding, order) -> None:
    rng = np.random.default_rng(1)
    pairs = rng.integers(0, 256, (4, 3, 3), dtype=np.uint8)  # one colour per pixel pair:
    rgb = np.repeat(pairs, 2, axis=1)  # then 4:2:2 loses nothing
    rgb[0, :2] = (255, 255, 255)
    rgb[0, 2:4] = 0
    yuv = _yuv_video_range(rgb)
    y, cb, cr = yuv[:, 0::2, 0], yuv[:, 0::2, 1], yuv[:, 0::2, 2]
    y1 = yuv[:, 1::2, 0]
    quads = np.stack([cb, y, cr, y1] if order == 'uyvy' else [y, cb, y1, cr], axis=-1)
    step = 6 * 2 + 4  # rows padded by 4 bytes
    data = np.zeros((4, step), np.uint8)
    data[:, :12] = quads.reshape(4, 12)
    family = rosbags_family()
    msg = image_to_msg(family, family.header(0, 'camera'), np.zeros((4, 6, 3), np.uint8))
    msg.encoding, msg.step, msg.data = encoding, step, data.ravel()
    back = msg_to_image(msg)
    assert np.abs(back.astype(int) - rgb).max() <= 2  # Y, Cb, Cr quantised to whole steps
    assert (back[0, 0] == 255).all() and (back[0, 2] == 0).all()  # video range: 235 / 16
    msg.width = 5  # two pixels a quad: an odd width does not fit
    with pytest.raises(ValueError, match='do not hold it'):
        msg_to_image(msg)


@pytest.mark.parametrize('encoding', ['bayer_rggb8', 'bayer_bggr8', 'bayer_gbrg8',
                                      'bayer_grbg8'])
def test_bayer_images_read_as_rgb(encoding) -> None:
    # a smooth scene, as a sensor's mosaic samples it (each pixel one colour of its 2x2 tile)
    v, u = np.mgrid[0:41, 0:60].astype(np.float64)  # odd rows: a tile cut at the border
    rgb = np.rint(np.stack([40 + 3 * u, 200 - 2 * v, 120 + 60 * np.sin(u / 9 + v / 7)],
                           axis=-1)).astype(np.uint8)
    colour = {'r': 0, 'g': 1, 'b': 2}
    tile = [colour[c] for c in encoding[6:10]]  # e.g. 'rggb': row 0 r g, row 1 g b
    family = rosbags_family()
    msg = image_to_msg(family, family.header(0, 'camera'), rgb, encoding)
    mosaic = np.frombuffer(bytes(msg.data), np.uint8).reshape(41, 60)
    for i, c in enumerate(tile):  # what the sensor records
        assert np.array_equal(mosaic[i // 2::2, i % 2::2], rgb[i // 2::2, i % 2::2, c])
    step = 60 + 4  # rows padded by 4 bytes
    data = np.zeros((41, step), np.uint8)
    data[:, :60] = mosaic
    msg.step, msg.data = step, data.ravel()
    back = msg_to_image(msg).astype(int)
    for i, c in enumerate(tile):  # each pixel keeps its own sample
        assert np.array_equal(back[i // 2::2, i % 2::2, c], mosaic[i // 2::2, i % 2::2])
    # the others are the mean of their neighbours: exact on a linear ramp (but at the border,
    # mirrored: one ramp step off), close on the sine
    ramp = np.abs(back[..., :2] - rgb[..., :2])
    assert ramp[1:-1, 1:-1].max() <= 1 and ramp.max() <= 3
    assert np.abs(back[..., 2] - rgb[..., 2]).mean() < 1.5
    with pytest.raises(ValueError, match="rgb8 or bayer_rggb8, .* not 'bgr8'"):
        image_to_msg(family, msg.header, rgb, 'bgr8')


@pytest.mark.slow
def test_simulate_camera_writes_images_calibration_and_labels(tmp_path: Path) -> None:
    bag, labels_dir = tmp_path / 'drive', tmp_path / 'labels'
    args = ['simulate', str(bag), '--seed', '3', '--sweeps', '3', '--sensor', 'os1-32',
            '--columns', '256', '--camera', '--camera-size', '320x200', '--labels2d',
            str(labels_dir), '--quiet']
    assert main(args) == 0
    msgs: dict[str, list] = {}
    for topic, stamp, msg in read_messages(bag):
        msgs.setdefault(topic, []).append((stamp, msg))
    assert {t: len(m) for t, m in msgs.items()} == {
        '/points': 3, '/odom': 3, '/lanes_gt': 1, '/tf_static': 1, '/camera/camera_info': 3,
        '/camera/image_raw': 3, '/camera/lanes_gt': 3}
    stamps = [s for s, _ in msgs['/points']]
    assert [s for s, _ in msgs['/camera/image_raw']] == stamps
    assert [s for s, _ in msgs['/camera/camera_info']] == stamps
    assert msgs['/tf_static'][0][0] == stamps[0]
    for (stamp, info), (_, img) in zip(msgs['/camera/camera_info'], msgs['/camera/image_raw']):
        assert info.header.stamp == img.header.stamp and stamp == sweep_stamp_ns(
            stamps.index(stamp))
        assert info.header.frame_id == img.header.frame_id == 'camera'
        assert msg_to_image(img).shape == (200, 320, 3)
    tf = msgs['/tf_static'][0][1]
    ((parent, child, T),) = tf_transforms(tf)
    assert (parent, child) == ('lidar', 'camera') and np.allclose(T, mount_extrinsic())
    sim = Simulator(3, sweeps=3, sensor='os1-32', columns=256)
    camera = SimCamera(sim, 320, 200)
    calib = CameraCalibration.from_messages(msgs['/camera/camera_info'][0][1], [tf], 'lidar')
    assert np.allclose(calib.K, camera.K) and np.allclose(calib.D, 0)
    assert np.allclose(calib.T_camera_cloud, np.linalg.inv(camera.T_cloud_camera))
    image = camera.render(2)  # deterministic: the bag's last image again
    assert np.array_equal(msg_to_image(msgs['/camera/image_raw'][2][1]), image.rgb)
    labels = read_label_dir(labels_dir)
    assert sorted(labels) == stamps
    expected, pieces = sim_image_labels(sim, calib, image)
    assert [lane.id for lane in labels[stamps[2]].lanes] == [lane.id for lane in expected.lanes]
    visible = marker_array_to_lanes(msgs['/camera/lanes_gt'][2][1])  # the 3D GT of the labels
    assert visible.frame_id == 'odom' and len(visible.lanes) == len(pieces) > 0
    assert all(np.allclose(a, b) for a, b in zip(visible.lanes, pieces))
    # the rule for DIR: refused when not empty, --overwrite replaces only this run's files
    (labels_dir / 'mine.txt').write_text('keep')
    assert main([*args, '--overwrite']) == 0
    assert (labels_dir / 'mine.txt').read_text() == 'keep'
    assert len(list(labels_dir.glob('*.json'))) == 3


@pytest.mark.parametrize('extra, text', [
    (['--labels2d', 'labels'], '--labels2d needs --camera'),
    (['--camera', '--camera-size', '10x10'], '--camera-size'),
    (['--camera', '--camera-size', 'big'], '--camera-size'),
    (['--camera', '--frame-id', 'camera'], '--frame-id'),
])
def test_bad_camera_arguments_give_one_line(tmp_path: Path, capsys: pytest.CaptureFixture,
                                            extra: list[str], text: str) -> None:
    out = tmp_path / 'bag'
    extra = [str(tmp_path / e) if e == 'labels' else e for e in extra]
    assert main(['simulate', str(out), '--sweeps', '1', '--quiet', *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('fhld simulate: error:') and text in err[0]
    assert list(tmp_path.iterdir()) == []


def test_labels_dir_that_is_not_empty_is_refused(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture) -> None:
    labels = tmp_path / 'labels'
    labels.mkdir()
    (labels / 'other.json').write_text('{}')
    assert main(['simulate', str(tmp_path / 'bag'), '--sweeps', '1', '--quiet', '--camera',
                 '--labels2d', str(labels)]) == 2
    assert 'not empty' in capsys.readouterr().err
    assert not (tmp_path / 'bag').exists()
