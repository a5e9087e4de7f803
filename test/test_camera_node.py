"""camera_lane_detector and `fhld replay --detector salad`: one CameraPipeline behind both.

The node runs in a real DDS graph (loopback) fed a simulated 960x540 camera drive (`fhld
simulate --camera`) re-recorded with one malformed image and one uncalibrated camera_info, one
message at a time, each once it has handled the last, so that it computes what a replay
computes: the /lanes contract, byte for byte the replay's messages, the bad messages dropped and
counted while the node goes on. The weights are an untrained SALAD whose lane logit is pushed
up, so that it decodes a lane in every image (model_fixtures.lane_everywhere_salad; the shipped
salad.pt is not needed). The pipeline
itself (frames, ego lanes, outline, rate, refusals) is checked without DDS on a fake detector.
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rclpy
import torch
from model_fixtures import lane_everywhere_salad
from rclpy.parameter import Parameter
from ros_helpers import RawLaneOutputs, feed, spinning, wait_until
from sensor_msgs.msg import CameraInfo, Image

from fhld_ros.bagio import BagWriter, read_raw
from fhld_ros.camera.calibration import distort
from fhld_ros.camera.lens import Lens
from fhld_ros.commands.replay_camera import CAMERA_INFO_TOPIC, IMAGE_TOPIC, replay_camera
from fhld_ros.lane_output import LANE_TOPICS
from fhld_ros.salad.camera_pipeline import (
    OPTICAL_TO_FLU,
    CameraIntrinsics,
    CameraPipeline,
    distortion_notice,
    seen_region,
)
from fhld_ros.salad.config import SaladConfig
from fhld_ros.salad.parameters import CameraParams
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.virtual_camera import VirtualCamera
from msg_adapters.camera import camera_info_msg, compressed_image_msg, image_to_msg, msg_to_image
from msg_adapters.family import rosbags_family
from msg_adapters.lanes import DELETEALL, LINE_STRIP
from msg_adapters.odometry import euler_to_matrix

pytestmark = [pytest.mark.ros]

IMAGES = 5
MALFORMED_AFTER = 2  # a truncated image after this one
UNCALIBRATED_AFTER = 3  # a camera_info with K all zero after this image
K = np.array([[685.0, 0.0, 479.5], [0.0, 685.0, 269.5], [0.0, 0.0, 1.0]])
FAMILY = rosbags_family()


def _user_bag(sim: Path, out: Path) -> None:
    """The simulated camera re-recorded with the bad messages of the module doc."""
    store = FAMILY.typestore
    with BagWriter(out) as writer:
        images = 0
        for topic, msgtype, stamp, raw in read_raw(sim, [CAMERA_INFO_TOPIC, IMAGE_TOPIC]):
            writer.write(topic, msgtype, stamp, raw)
            if topic != IMAGE_TOPIC:
                continue
            images += 1
            if images == MALFORMED_AFTER:
                image = store.deserialize_cdr(raw, msgtype)
                image.data = image.data[:-7]
                image.header.stamp = FAMILY.stamp(stamp + 50_000_000)
                writer.write(topic, msgtype, stamp + 50_000_000, image)
            if images == UNCALIBRATED_AFTER:
                writer.write(CAMERA_INFO_TOPIC, 'sensor_msgs/msg/CameraInfo', stamp + 1,
                             camera_info_msg(FAMILY, FAMILY.header(stamp + 1, 'camera'),
                                             960, 540, np.zeros((3, 3))))


@pytest.fixture(scope='module')
def drive(tmp_path_factory) -> tuple[Path, Path]:
    """(the user bag, the checkpoint)."""
    root = tmp_path_factory.mktemp('camera')
    done = subprocess.run([sys.executable, '-m', 'fhld_ros.cli', 'simulate', str(root / 'sim'),
                           '--seed', '3', '--sweeps', str(IMAGES), '--camera', '--camera-size',
                           '960x540', '--quiet'], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    _user_bag(root / 'sim', root / 'user')
    return root / 'user', lane_everywhere_salad(root / 'salad.pt')


class Probe(RawLaneOutputs):
    """Publishes images and camera_info; keeps the node's lane topics as serialized messages
    and its newest /diagnostics values."""

    def __init__(self, context: rclpy.Context) -> None:
        super().__init__(context, 'camera_probe')
        self.image = self.node.create_publisher(Image, 'camera/image_raw', self.qos)
        self.info = self.node.create_publisher(CameraInfo, 'camera/camera_info', self.qos)
        self.start()


def _handled(node) -> tuple[int, int]:
    """(camera_info messages, images) the node's pipeline has taken, bad ones included."""
    with node.lock:
        c = node.pipeline.counters
        return c['camera_infos'] + c['bad_camera_info'], c['images'] + c['bad_images']


def _check_contract(raw: bytes, frame: str) -> int:
    """The /lanes contract (docs/design.md §3); returns the number of lanes."""
    msg = FAMILY.typestore.deserialize_cdr(raw, 'visualization_msgs/msg/MarkerArray')
    first, *rest = msg.markers
    assert first.action == DELETEALL and first.ns == 'lanes'
    assert rest[-1].ns == 'bev_window' and len(rest[-1].points) == 5
    assert all(m.ns == 'lanes' and m.type == LINE_STRIP for m in rest[:-1])
    assert all(m.header.frame_id == frame for m in msg.markers)
    return len(rest) - 1


@pytest.mark.slow
def test_node_publishes_the_contract_and_the_replays_messages(drive, tmp_path, rclpy_context,
                                                              one_torch_thread):
    from fhld_ros.ros.camera_node import CameraLaneDetectorNode
    bag, checkpoint = drive
    params = CameraParams(checkpoint=str(checkpoint))
    stats = replay_camera(bag, tmp_path / 'replayed', params, progress=False)
    assert (stats['images'], stats['dropped'], stats['bad_camera_info']) == (IMAGES + 1, 1, 1)
    assert stats['detections'] == IMAGES
    replayed = {suffix: [raw for *_, raw in read_raw(tmp_path / 'replayed', ['/lanes' + suffix])]
                for suffix in LANE_TOPICS}
    assert all(_check_contract(raw, 'camera') >= 1 for raw in replayed[''])

    node = CameraLaneDetectorNode(context=rclpy_context, parameter_overrides=[
        Parameter('checkpoint', value=str(checkpoint))])
    probe = Probe(rclpy_context)
    with spinning(node, probe):
        assert wait_until(lambda: probe.image.get_subscription_count() >= 1
                          and probe.info.get_subscription_count() >= 1
                          and all(node.count_subscribers('lanes' + suffix) >= 1
                                  for suffix in LANE_TOPICS), 30), 'discovery never completed'
        feed(node, probe, bag, {CAMERA_INFO_TOPIC: (probe.info, 0),
                                IMAGE_TOPIC: (probe.image, 1)}, _handled, 30)
        for suffix in LANE_TOPICS:
            assert probe.got[suffix] == replayed[suffix], f'/lanes{suffix} differs'
        counters = node.pipeline.counters
        assert (counters['bad_images'], counters['bad_camera_info']) == (1, 1)
        assert counters['images_overtaken'] == 0  # fed at its pace
        assert wait_until(lambda: probe.diagnostics.get('detections') == str(IMAGES), 5)
        values = probe.diagnostics
        assert (values['bad_images'], values['bad_camera_info']) == ('1', '1')
        assert values['last_error'].startswith('bad_camera_info: ')
        assert float(values['latency_ms_p95']) >= float(values['latency_ms_p50']) > 0
        assert {'stage_warp_ms_p50', 'stage_model_ms_p50', 'stage_decode_ms_p50'} <= set(values)


def _compressed_bag(bag: Path, out: Path) -> None:
    """The user bag with its images as PNG CompressedImages on /camera/image_raw/compressed,
    as a recorder keeps them; its malformed image a PNG cut short."""
    store = FAMILY.typestore
    with BagWriter(out) as writer:
        for topic, msgtype, stamp, raw in read_raw(bag, [CAMERA_INFO_TOPIC, IMAGE_TOPIC]):
            if topic == CAMERA_INFO_TOPIC:
                writer.write(topic, msgtype, stamp, raw)
                continue
            image = store.deserialize_cdr(raw, msgtype)
            try:
                rgb = msg_to_image(image)
            except ValueError:  # the malformed one
                rgb = None
            msg = compressed_image_msg(FAMILY, image.header, np.zeros((540, 960, 3), np.uint8)
                                       if rgb is None else rgb, 'png')
            if rgb is None:
                msg.data = msg.data[:len(msg.data) // 2]
            writer.write(IMAGE_TOPIC + '/compressed', 'sensor_msgs/msg/CompressedImage', stamp,
                         msg)


def test_replay_reads_a_bags_compressed_images(drive, tmp_path):
    bag, checkpoint = drive
    params = CameraParams(checkpoint=str(checkpoint))
    _compressed_bag(bag, tmp_path / 'compressed')
    stats = {name: replay_camera(tmp_path / name if name == 'compressed' else bag,
                                 tmp_path / f'{name}_lanes', params, progress=False)
             for name in ('raw', 'compressed')}
    assert stats['compressed'] == stats['raw']
    assert (stats['raw']['dropped'], stats['raw']['detections']) == (1, IMAGES)
    for suffix in LANE_TOPICS:  # PNG is lossless: the lanes of the raw images, byte for byte
        lanes = [[raw for *_, raw in read_raw(tmp_path / f'{name}_lanes', ['/lanes' + suffix])]
                 for name in ('raw', 'compressed')]
        assert lanes[0] == lanes[1] and len(lanes[0]) == IMAGES


def test_replay_warns_of_a_lens_on_images_that_look_rectified(tmp_path, capsys):
    with BagWriter(tmp_path / 'rect') as writer:
        info = _info(d=np.array([-0.1, 0.01, 0.0, 0.0, 0.0]))
        writer.write('/front/camera_info', 'sensor_msgs/msg/CameraInfo', 0, info)
        writer.write('/front/image_rect', 'sensor_msgs/msg/Image', 1, _image(1))
    stats = replay_camera(tmp_path / 'rect', tmp_path / 'lanes', CameraParams(),
                          '/front/image_rect', '/front/camera_info', progress=False)
    assert stats['detections'] == 1
    err = capsys.readouterr().err
    assert '/front/image_rect looks rectified already' in err and 'image_rectified:=true' in err


def _node_error(*ros_args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'fhld_ros.ros.camera_lane_detector',
                           '--ros-args', *ros_args], capture_output=True, text=True, timeout=120)


@pytest.mark.slow
def test_a_missing_checkpoint_or_a_bad_parameter_is_one_line_and_exit_2(tmp_path):
    missing = _node_error('-p', f'checkpoint:={tmp_path / "none.pt"}')
    assert missing.returncode == 2, missing.stderr
    assert missing.stderr.strip() == (f'camera_lane_detector: error: SALAD checkpoint '
                                      f'{tmp_path / "none.pt"} does not exist (the shipped '
                                      'weights by name: salad, salad_wide_mount)')
    bad = _node_error('-p', 'rate_hz:=fast')
    assert bad.returncode == 2, bad.stderr
    assert bad.stderr.strip() == ('camera_lane_detector: error: rate_hz must be a number with '
                                  'a decimal point (e.g. 10.0), not string fast')


# -- the pipeline without DDS --------------------------------------------------------------

class RoadDetector:
    """Four straight lanes 1.5 m below a level camera, 4-50 m ahead; the last scores 0.3."""

    cfg = SaladConfig()
    timings_ms = {'warp_ms': 1.0}
    lanes_unpainted = 2  # and two more, without paint beside them

    def __init__(self) -> None:
        self.roads: list[RoadPlane | None] = []
        self.distortions: list[np.ndarray | None] = []

    def __call__(self, image: np.ndarray, k: np.ndarray, road: RoadPlane | None = None,
                 distortion: np.ndarray | None = None) -> tuple[list[np.ndarray], np.ndarray]:
        self.roads.append(road)
        self.distortions.append(distortion)
        z = np.linspace(4.0, 50.0, 47)
        return ([np.column_stack([np.full_like(z, x), np.full_like(z, 1.5), z])
                 for x in (-5.25, -1.75, 1.75, 5.25)], np.array([0.9, 0.8, 0.7, 0.3]))


def _image(stamp_ns: int, width: int = 960, height: int = 540, frame: str = 'camera'):
    return image_to_msg(FAMILY, FAMILY.header(stamp_ns, frame),
                        np.zeros((height, width, 3), np.uint8))


def _info(k: np.ndarray = K, width: int = 960, height: int = 540,
          d: np.ndarray | None = None, model: str = 'plumb_bob'):
    return camera_info_msg(FAMILY, FAMILY.header(0, 'camera'), width, height, k, d, model)


def test_with_the_images_pitch_the_outline_lies_on_the_road_the_lanes_span():
    # the mount says 3 degrees down; the lanes (RoadDetector's) lie level under the camera
    pose = (0.0, 0.0, 1.5, -np.pi / 2 - np.radians(3.0), 0.0, -np.pi / 2)
    outs = []
    for pitch in ('mount', 'image'):
        pipeline = CameraPipeline(CameraParams(output_frame='base_footprint',
                                               camera_to_output=pose, road_plane_m=20.0,
                                               road_plane_pitch=pitch), RoadDetector())
        assert pipeline.receive_camera_info(_info()) is None
        assert pipeline.receive_image(_image(0)).due
        outs.append(pipeline.detect())
    mount, image = outs
    np.testing.assert_allclose(mount.outline[:, 2], 0.0, atol=1e-9)  # the mount's road
    points = np.concatenate(image.lanes)
    fit = np.column_stack([points[:, :2], np.ones(len(points))])
    coef, *_ = np.linalg.lstsq(fit, points[:, 2], rcond=None)
    outline = np.column_stack([image.outline[:, :2], np.ones(5)]) @ coef
    np.testing.assert_allclose(image.outline[:, 2], outline, atol=1e-6)
    assert np.ptp(image.outline[:, 2]) > 1.0  # tilted 3 degrees against base_footprint
    assert image.lanes_pitch_deg == pytest.approx(0.0, abs=1e-6)  # level to the camera


def test_a_distorted_camera_s_distortion_reaches_the_detector():
    pipeline = CameraPipeline(CameraParams(), RoadDetector())
    d = np.array([-0.108, 0.139, -0.0038, -0.0048, 0.0])  # the PJLab camera's
    for info in (_info(), _info(d=d)):
        assert pipeline.receive_camera_info(info) is None
        assert pipeline.receive_image(_image(len(pipeline.detector.distortions) * 10**8)).due
        assert pipeline.detect() is not None
    undistorted, distorted = pipeline.detector.distortions
    assert undistorted is None and distorted == Lens('plumb_bob', tuple(d))


def test_lanes_come_out_in_the_output_frame_with_ego_lanes_and_the_seen_ground():
    pose = (1.0, 0.2, 1.5, -np.pi / 2, 0.0, -np.pi / 2)  # level, 1.5 m over base_link
    outs, roads = [], []
    for params in (CameraParams(), CameraParams(output_frame='base_link', camera_to_output=pose,
                                                road_plane_m=30.0)):
        pipeline = CameraPipeline(params, RoadDetector())
        assert pipeline.receive_camera_info(_info()) is None
        assert pipeline.receive_image(_image(0)).due
        outs.append(pipeline.detect())
        roads += pipeline.detector.roads
    camera, base = outs
    # with road_plane_m the detector gets base_link's ground: 1.5 m below the level camera
    assert roads[0] is None and roads[1] == RoadPlane.from_extrinsic(euler_to_matrix(*pose), 30.0)
    np.testing.assert_allclose(roads[1].normal, [0.0, 1.0, 0.0], atol=1e-6)
    assert (camera.frame_id, base.frame_id) == ('camera', 'base_link')
    assert len(camera.lanes) == 3 and np.allclose(camera.confidences, [0.9, 0.8, 0.7])
    T = euler_to_matrix(*pose)
    for a, b in zip(camera.lanes + [camera.outline], base.lanes + [base.outline]):
        np.testing.assert_allclose(b, a @ T[:3, :3].T + T[:3, 3], atol=1e-9)
    # optical x -1.75 is left of the camera, +1.75 right
    assert camera.ego_left[0, 0] == -1.75 and camera.ego_right[0, 0] == 1.75
    np.testing.assert_allclose(base.ego_left[0], [5.0, 1.95, 0.0], atol=1e-9)
    # the outline: on the road the lanes span (1.5 m below), from where the model's view meets
    # it (the virtual camera's lower edge, 22.5 deg down) to the decoder's 60 m
    flu = camera.outline @ OPTICAL_TO_FLU.T
    np.testing.assert_allclose(flu[:, 2], -1.5, atol=1e-9)
    assert camera.lanes_plane_height_m == pytest.approx(1.5)  # reported on /diagnostics
    assert camera.lanes_pitch_deg == pytest.approx(0.0, abs=1e-6)  # the level camera's
    assert flu[0, 0] == pytest.approx(1.5 / np.tan(np.arctan(165.5 / 400)), rel=0.05)
    assert flu[1, 0] == pytest.approx(60.0) and flu[0, 1] < 0 < flu[3, 1]
    np.testing.assert_array_equal(flu[0], flu[4])


def test_a_fisheye_or_rational_lens_reaches_the_detector_and_other_models_are_named():
    pipeline = CameraPipeline(CameraParams(), RoadDetector())
    for model, d in (('equidistant', [-0.05, 0.01, 0.002, -0.001]),
                     ('rational_polynomial', [0.8, 0.2, 0.001, -0.001, 0.01, 1.2, 0.4, 0.03])):
        assert pipeline.receive_camera_info(_info(d=np.array(d), model=model)) is None
        assert pipeline.receive_image(_image(len(pipeline.detector.distortions) * 10**8)).due
        assert pipeline.detect() is not None
        assert pipeline.detector.distortions[-1] == Lens(model, tuple(d))
    text, _ = distortion_notice('camera/image_raw', 'camera/camera_info', Lens(model, tuple(d)))
    assert 'rational_polynomial 0.8, 0.2' in text
    problems = [str(pipeline.receive_camera_info(_info(d=np.array(d), model=model)))
                for model, d in (('fov', [0.9]), ('equidistant', [0.1, 0.0, 0.0, 0.0, 0.2]),
                                 ('plumb_bob', [0.1, np.nan, 0.0, 0.0]))]
    assert "distortion_model 'fov' is not supported (supported: plumb_bob, " in problems[0]
    assert 'distortion_model equidistant takes 4 coefficients in d, got 5' in problems[1]
    assert 'is not finite' in problems[2]
    assert pipeline.camera is None and pipeline.counters['bad_camera_info'] == 3


def test_rectified_images_take_p_and_no_distortion():
    # image_proc's image_rect comes with the raw camera's camera_info: a fisheye's K and D, and
    # P, the intrinsics of the rectified images
    info = _info(d=np.array([-0.05, 0.01, 0.002, -0.001]), model='equidistant')
    P = np.array([[520.0, 0.0, 470.0, 0.0], [0.0, 520.0, 265.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    info.p = P.ravel()
    raw = CameraPipeline(CameraParams(), RoadDetector())
    assert raw.receive_camera_info(info) is None and raw.camera.lens.model == 'equidistant'
    rect = CameraPipeline(CameraParams(image_topic='camera/image_rect', image_rectified=True),
                          RoadDetector())
    assert rect.receive_camera_info(info) is None
    np.testing.assert_array_equal(rect.camera.K, P[:, :3])
    assert rect.camera.lens is None
    assert rect.receive_image(_image(0)).due and rect.detect() is not None
    assert rect.detector.distortions == [None]
    info.p = np.zeros(12)  # a driver that never filled P
    assert 'camera_info P is all zero' in str(rect.receive_camera_info(info))


@pytest.mark.parametrize('topic, level', [
    ('camera/image_raw', 'info'), ('/front/image_rect_color', 'warning'),
    ('/front/image_rect/compressed', 'warning'), ('/front/rect_image', 'warning'),
    ('/front/image_rectangle', 'info')])
def test_distortion_on_a_rectified_looking_topic_is_warned_about(topic: str, level: str):
    text, said = distortion_notice(topic, '/front/camera_info',
                                   Lens.plumb_bob(np.array([-0.1, 0.01, 0, 0, 0])))
    assert said == level and 'image_rectified:=true' in text and '-0.1, 0.01' in text


def test_a_binned_or_cropped_camera_s_images_take_their_own_intrinsics():
    # camera_info describes the full 1920x1080 sensor; the images are binned 2x2 (960x540), or
    # an 800x400 region of interest at (300, 200)
    full = np.array([[1370.0, 0.0, 959.5], [0.0, 1370.0, 539.5], [0.0, 0.0, 1.0]])
    point = np.array([1.7, 0.4, 12.0])  # where the sensor sees it: (u, v) full-resolution
    seen = (full @ point)[:2] / point[2]
    for binning, roi, size, pixel in ((2, (0, 0, 0, 0), (960, 540), (seen - 0.5) / 2),
                                      (1, (300, 200, 800, 400), (800, 400), seen - [300, 200])):
        info = _info(full, 1920, 1080)
        info.binning_x = info.binning_y = binning
        info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = roi
        pipeline = CameraPipeline(CameraParams(), RoadDetector())
        assert pipeline.receive_camera_info(info) is None
        assert pipeline.receive_image(_image(0, *size)).due  # the images' own size
        K = pipeline.camera.K
        np.testing.assert_allclose((K @ point)[:2] / point[2], pixel, atol=1e-9)
    info.roi.x_offset = 1300  # 800 px from 1300 of 1920
    assert 'roi 800x400 at (1300, 200) lies outside' in str(pipeline.receive_camera_info(info))


def test_the_seen_region_of_a_barrel_lens_is_wider_and_inside_its_image():
    # a camera narrower than the virtual one: its own border bounds the region the model sees
    K = np.array([[700.0, 0.0, 320.0], [0.0, 700.0, 180.0], [0.0, 0.0, 1.0]])
    boxes = []
    for D in (np.zeros(5), np.array([-0.3, 0.1, 0.001, -0.002, 0.0])):
        region = seen_region(CameraIntrinsics(640, 360, K, D, 'camera'), VirtualCamera())
        k = region.K
        low = -k[:2, 2] / np.diag(k)[:2]
        high = low + np.array([region.width, region.height]) / np.diag(k)[:2]
        x, y = np.meshgrid(np.linspace(low[0], high[0], 9), np.linspace(low[1], high[1], 9))
        u, v = distort(x.ravel(), y.ravel(), D)
        u, v = 700.0 * u + 320.0, 700.0 * v + 180.0
        assert np.all((u > -0.5) & (u < 640.5) & (v > -0.5) & (v < 360.5))  # all in the image
        assert min(u.min(), 640 - u.max(), v.min(), 360 - v.max()) < 0.5  # and up to its edge
        boxes.append(high - low)
    pinhole, barrel = boxes
    # between the corners a barrel lens shows more than a pinhole with the same K (above, the
    # virtual camera's own edge bounds both)
    assert barrel[0] > 1.05 * pinhole[0] and barrel[1] > pinhole[1], (barrel, pinhole)


class TrainedOn(RoadDetector):
    """RoadDetector with a checkpoint's meta: simulated drives with cameras `heights` up."""

    def __init__(self, heights: list[float] | None = None, datasets: tuple = ()) -> None:
        super().__init__()
        self.info = {'meta': {'drives': 896, 'datasets': list(datasets),
                              **({'camera_heights_m': heights} if heights else {})}}


@pytest.mark.parametrize('detector, height, advice', [
    (TrainedOn(), 1.5, None), (TrainedOn(), 2.05, None),  # within 1.2-2.0 m, or just above
    (TrainedOn(), 2.6, 'use checkpoint:=salad_wide_mount'),
    (TrainedOn([1.2, 3.0]), 2.6, None),
    (TrainedOn([1.2, 3.0]), 3.5, '--camera-height 3.3 3.7'),
    (TrainedOn(), 0.8, '--camera-height 0.6 1.0'),
    (TrainedOn(datasets=['once: /data']), 2.6, None),  # a dataset's mounts are unknown
    (RoadDetector(), 2.6, None)])  # weights that say nothing
def test_a_mount_beyond_the_trained_heights_is_warned_about(detector, height, advice):
    pose = (0.0, 0.0, height, -np.pi / 2 - np.radians(2.0), 0.0, -np.pi / 2)
    params = CameraParams(output_frame='base_footprint', camera_to_output=pose,
                          road_plane_m=40.0)
    warning = CameraPipeline(params, detector).mount_warning
    if advice is None:
        assert warning is None
    else:
        assert f'the camera {height:.2f} m above the road' in warning and advice in warning
    # without road_plane_m the output frame's z = 0 need not be the road: nothing to say
    no_plane = dataclasses.replace(params, road_plane_m=0.0)
    assert CameraPipeline(no_plane, detector).mount_warning is None


class NoLanes(RoadDetector):
    """Finds no lane."""

    def __call__(self, image: np.ndarray, k: np.ndarray, road: RoadPlane | None = None,
                 distortion: np.ndarray | None = None) -> tuple[list[np.ndarray], np.ndarray]:
        return [], np.zeros(0)


def test_with_a_known_mount_the_outline_lies_on_its_road():
    # no lanes to span a plane: the outline lay on a level road camera_height_m (1.5) below
    pose = (0.0, 0.0, 2.0, -np.pi / 2 - np.radians(2.0), 0.0, -np.pi / 2)  # 2 m up, 2 deg down
    outlines = []
    for road_plane_m in (0.0, 40.0):
        params = CameraParams(output_frame='base_footprint', camera_to_output=pose,
                              road_plane_m=road_plane_m)
        pipeline = CameraPipeline(params, NoLanes())
        pipeline.receive_camera_info(_info())
        pipeline.receive_image(_image(0))
        out = pipeline.detect()
        outlines.append(out.outline)
        assert out.lanes_plane_height_m is None  # no lanes, no plane of theirs to report
    level, mount = outlines  # in base_footprint: the road is z = 0 there
    assert np.ptp(level[:, 2]) > 0.1  # the level road 1.5 m below a camera pitched down
    np.testing.assert_allclose(mount[:, 2], 0.0, atol=1e-6)


def test_images_are_detected_at_rate_hz_on_their_stamps():
    pipeline = CameraPipeline(CameraParams(rate_hz=10.0), RoadDetector())
    pipeline.receive_camera_info(_info())
    detected = []
    for k in range(9):  # 30 Hz
        pipeline.receive_image(_image(k * 33_333_333))
        out = pipeline.detect()
        if out is not None:
            detected.append(k)
    assert detected == [0, 3, 6]
    assert pipeline.counters['images_skipped'] == 6
    assert pipeline.counters['lanes_unpainted'] == 3 * RoadDetector.lanes_unpainted
    # two due images before a detection: the newer wins, the older is overtaken (a drop)
    assert pipeline.receive_image(_image(400_000_000)).due
    intake = pipeline.receive_image(_image(500_000_000))
    assert intake.due and intake.replaced
    assert pipeline.detect().stamp_ns == 500_000_000
    assert pipeline.counters['images_overtaken'] == 1


def test_bad_input_is_refused_naming_the_problem_and_counted():
    pipeline = CameraPipeline(CameraParams(), RoadDetector())
    assert 'no camera_info received yet' in str(pipeline.receive_image(_image(0)).dropped)
    assert pipeline.receive_camera_info(_info()) is None
    wrong_size = pipeline.receive_image(_image(0, 640, 360)).dropped
    assert str(wrong_size) == 'image is 640x360, its camera_info says 960x540'
    encoded = _image(0)
    encoded.encoding = '16UC1'
    assert "encoding '16UC1' is not supported" in str(pipeline.receive_image(encoded).dropped)
    truncated = _image(0)
    truncated.data = truncated.data[:-3]
    assert 'do not hold it' in str(pipeline.receive_image(truncated).dropped)
    assert pipeline.receive_image(_image(0, frame='')).due  # in the camera_info's frame
    assert pipeline.detect().frame_id == 'camera'
    no_frame = camera_info_msg(FAMILY, FAMILY.header(0, ''), 960, 540, K)
    assert pipeline.receive_camera_info(no_frame) is None
    assert 'empty frame_id' in str(pipeline.receive_image(_image(1, frame='')).dropped)
    assert 'K is all zero' in str(pipeline.receive_camera_info(_info(np.zeros((3, 3)))))
    assert 'newest camera_info is bad: camera_info K is all zero' in str(
        pipeline.receive_image(_image(0)).dropped)
    skewed = K.copy()
    skewed[0, 1] = 5.0
    assert 'without skew' in str(pipeline.receive_camera_info(_info(skewed)))
    assert pipeline.counters['bad_images'] == 6 and pipeline.counters['bad_camera_info'] == 2
    assert pipeline.counters['images'] == 1 and pipeline.detect() is None


@pytest.mark.slow
def test_bench_camera_reports_each_stage(monkeypatch):
    from fhld_ros.commands import bench_camera
    monkeypatch.setattr(bench_camera, 'REPEATS', 3)
    threads = torch.get_num_threads()
    result = bench_camera.bench_camera()
    assert torch.get_num_threads() == threads
    for key in ('camera_warp_ms', 'camera_model_ms', 'camera_decode_ms',
                'camera_decode_network_ms', 'camera_e2e_ms_p50', 'camera_e2e_ms_p95'):
        assert result[key] > 0, key
    assert result['camera_decode_lanes'] >= 2 and result['camera_image'] == '960x540'
    assert result['camera_weights'] in ('shipped', 'untrained (salad.pt absent)')


def test_replay_names_a_missing_camera_topic(drive, tmp_path):
    from fhld_ros.errors import ConfigError
    bag, checkpoint = drive
    with pytest.raises(ConfigError, match=f'^bag {bag} has no topic /front/image '):
        replay_camera(bag, tmp_path / 'out', CameraParams(checkpoint=str(checkpoint)),
                      image_topic='/front/image', progress=False)
    assert not (tmp_path / 'out').exists()


def test_diagnostics_level_follows_the_last_window():
    from diagnostic_msgs.msg import DiagnosticStatus

    from fhld_ros.ros.camera_diagnostics import CameraStats
    stats = CameraStats(now=0.0)
    level, message, _ = stats.assess(1.0)
    assert (level, message) == (DiagnosticStatus.WARN, 'no images received yet')
    for k in range(10):  # 10 Hz, each detected in 40 ms
        now = 1.0 + 0.1 * k
        stats.image_received(now)
        stats.image_due(k, now, 0.1)
        stats.detection_done(k, now, {'model_ms': 30.0}, now + 0.04, 0.2,
                             None if k == 9 else 1.5 + 0.1 * (k % 3),
                             None if k > 6 else 2.0 + k)
    assert stats.assess(2.0)[:2] == (DiagnosticStatus.OK, 'running')
    assert stats.assess(2.0)[2]['window_lanes_plane_height_m'] == '1.60'  # lane-less: left out
    assert stats.assess(2.0)[2]['window_lanes_pitch_deg'] == '5.00'  # the median of 2-8
    stats.image_received(2.0)
    stats.error('bad_images', ValueError('image is 640x360, its camera_info says 960x540'), 2.0)
    level, message, window = stats.assess(2.05)
    assert level == DiagnosticStatus.WARN
    assert message == 'dropped 1 of 11 images in 2 s (1 bad; 9% > 0%)', message
    assert window['window_images_dropped'] == '1'
    assert stats.assess(8.0)[:2] == (DiagnosticStatus.WARN,
                                     'input stale: no images for 6.0 s (> 2 s)')
    assert stats.assess(13.0)[0] == DiagnosticStatus.ERROR
    assert 'window_lanes_plane_height_m' not in stats.assess(13.0)[2]  # none in the window
    assert 'window_lanes_pitch_deg' not in stats.assess(13.0)[2]
    status = stats.status({'images': 10}, 'RELIABLE', 'node', 2.05)
    values = {kv.key: kv.value for kv in status.values}
    assert values['latency_ms_p50'] == '40.0' and values['stage_model_ms_p50'] == '30.0'
    assert values['last_error'].startswith('bad_images: image is 640x360')
