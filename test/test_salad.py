"""SALAD's geometry and learning pieces: the virtual camera, augmentation that keeps image and
3D labels consistent, targets that decode back to their lanes, and a model that learns."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.camera.lens import Lens
from fhld_ros.errors import ConfigError
from fhld_ros.salad.augment import SaladAugment, augment_images, draw, flip
from fhld_ros.salad.checkpoint import SaladCheckpointError, load_salad, save_salad
from fhld_ros.salad.config import STRIDE, SaladConfig, uncalibrated
from fhld_ros.salad.decode import decode, extend_to_row_edge
from fhld_ros.salad.detector import SaladDetector
from fhld_ros.salad.evaluate import score
from fhld_ros.salad.losses import SaladCriterion
from fhld_ros.salad.model import SaladNet
from fhld_ros.salad.perfect_maps import HEADS, PerfectMaps
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.targets import lane_targets, row_statistics
from fhld_ros.salad.virtual_camera import VirtualCamera
from msg_adapters.camera import camera_info_msg, tf_static_msg
from msg_adapters.family import rosbags_family

CAMERA = VirtualCamera()


def _project(k: np.ndarray, point: np.ndarray) -> np.ndarray:
    return (k @ point)[:2] / point[2]


def _dot(size: tuple[int, int], uv: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    """A bright Gaussian dot centred at pixel coordinates uv on black."""
    w, h = size
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    blob = np.exp(-((u - uv[0]) ** 2 + (v - uv[1]) ** 2) / (2 * sigma ** 2))
    return np.repeat((blob * 255).astype(np.uint8)[..., None], 3, axis=2)


def _peak(image: np.ndarray) -> np.ndarray:
    """Sub-pixel centroid of the bright dot."""
    weight = image[..., 0].astype(np.float64)
    weight[weight < 0.3 * weight.max()] = 0
    v, u = np.nonzero(weight)
    return np.array([np.average(u, weights=weight[v, u]), np.average(v, weights=weight[v, u])])


def test_a_point_lands_where_the_virtual_camera_sees_it_whatever_the_source_camera():
    point = np.array([1.3, 1.5, 12.0])
    for k, size in ((np.array([[600.0, 0, 470], [0, 600, 290], [0, 0, 1]]), (960, 600)),
                    (np.array([[1200.0, 0, 980], [0, 1180, 610], [0, 0, 1]]), (1920, 1280)),
                    (np.array([[250.0, 0, 160], [0, 250, 100], [0, 0, 1]]), (320, 200))):
        warped = CAMERA.warp(_dot(size, _project(k, point), sigma=0.01 * k[0, 0]), k)
        assert warped.shape == (CAMERA.height, CAMERA.width, 3)
        np.testing.assert_allclose(_peak(warped), _project(CAMERA.intrinsics, point), atol=0.5)


def test_a_distorted_camera_s_point_lands_where_a_pinhole_virtual_camera_sees_it():
    """plumb_bob distortion removed in the warp: points seen through a barrel lens (drawn where
    the distortion puts them) land where the virtual pinhole camera sees them."""
    k = np.array([[1050.0, 0, 955], [0, 1040, 580], [0, 0, 1]])
    size = (1920, 1200)
    for d in (np.array([-0.108, 0.139, -0.0038, -0.0048, 0.0]),  # the PJLab camera's
              np.array([-0.30, 0.10, 0.0, 0.0])):  # a wide lens's, k1 k2 p1 p2 only
        calib = CameraCalibration(*size, k, np.append(d, np.zeros(5))[:5], np.eye(4))
        for point in ([-2.0, 1.5, 10.0], [3.0, 1.5, 6.0], [0.5, 1.2, 30.0]):
            uv, _, inside = calib.project_camera(np.array([point]))
            assert inside[0]
            image = _dot(size, uv[0], sigma=0.01 * k[0, 0])
            want = _project(CAMERA.intrinsics, np.array(point))
            np.testing.assert_allclose(_peak(CAMERA.warp(image, k, d)), want, atol=0.1)
            if point[0] == 3.0:  # 30 deg off the axis: ignoring the lens misses it
                assert np.abs(_peak(CAMERA.warp(image, k)) - want).max() > 2.0
    # beyond a narrow lens's image the virtual camera sees black, as without distortion
    dark = CAMERA.warp(np.full((200, 320, 3), 255, np.uint8), np.array(
        [[600.0, 0, 160], [0, 600, 100], [0, 0, 1]]), np.array([-0.2, 0.05, 0, 0, 0]))
    assert dark[0, 0].max() == 0 and dark[CAMERA.height // 2, CAMERA.width // 2].min() == 255


@pytest.mark.parametrize('lens, k, size', [
    # a 190-degree fisheye (OpenCV's fisheye model; ROS calls it equidistant)
    (Lens('equidistant', (-0.013, 0.021, -0.011, 0.002)),
     np.array([[330.0, 0, 641], [0, 330, 398], [0, 0, 1]]), (1280, 800)),
    # a wide lens calibrated with OpenCV's rational model (k4..k6 in the denominator)
    (Lens('rational_polynomial', (0.8, 0.2, 0.001, -0.001, 0.01, 1.2, 0.4, 0.03)),
     np.array([[720.0, 0, 962], [0, 720, 538], [0, 0, 1]]), (1920, 1080))])
def test_a_fisheye_or_rational_lens_s_point_lands_where_the_pinhole_virtual_camera_sees_it(
        lens: Lens, k: np.ndarray, size: tuple[int, int]):
    points = np.array([[-2.0, 1.5, 10.0], [3.0, 1.5, 6.0], [0.5, 1.2, 30.0], [-6.0, 1.6, 8.0]])
    x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
    xd, yd = lens.distort(x, y)
    back = np.column_stack(lens.undistort(xd, yd))
    np.testing.assert_allclose(back, np.column_stack([x, y]), atol=1e-6)  # < 0.001 px
    pixels = np.column_stack([k[0, 0] * xd + k[0, 2], k[1, 1] * yd + k[1, 2]])
    for point, uv in zip(points, pixels):
        image = _dot(size, uv, sigma=0.006 * k[0, 0])
        want = _project(CAMERA.intrinsics, point)
        np.testing.assert_allclose(_peak(CAMERA.warp(image, k, lens)), want, atol=0.3)
        if point[0] == 3.0:  # 27 deg off the axis: a pinhole's K alone misses it
            assert np.abs(_peak(CAMERA.warp(image, k)) - want).max() > 5.0


def test_a_fisheye_s_pixels_undistort_to_rays_up_to_its_edge_and_autolabel_takes_it(tmp_path):
    lens = Lens('equidistant', (-0.013, 0.021, -0.011, 0.002))
    # 85 degrees off the axis: a pinhole's normalised radius of 11.4, still one-to-one
    theta = np.radians([10.0, 45.0, 85.0])
    xd, _ = lens.distort(np.tan(theta), np.zeros(3))
    np.testing.assert_allclose(lens.undistort(xd, np.zeros(3))[0], np.tan(theta), rtol=1e-9)
    assert lens.unfolded(np.tan(theta), np.zeros(3), 1.0).all()
    # a lens whose radius turns back at ~40 degrees is cut there, not folded into the image
    folding = Lens('equidistant', (-1.0, 0.0, 0.0, 0.0))
    assert list(folding.unfolded(np.tan(np.radians([30.0, 45.0])), np.zeros(2), 1.0)) == \
        [True, False]
    info = camera_info_msg(rosbags_family(), rosbags_family().header(0, 'camera'), 1280, 800,
                           np.array([[330.0, 0, 641], [0, 330, 398], [0, 0, 1]]),
                           np.array(lens.coefficients), 'equidistant')
    tf = tf_static_msg(rosbags_family(), 0, 'lidar', 'camera', np.eye(4))
    # autolabel's camera from a bag's camera_info, and through its --calib YAML
    calib = CameraCalibration.from_messages(info, [tf], 'lidar')
    calib.to_yaml(tmp_path / 'fisheye.yaml')
    for c in (calib, CameraCalibration.from_yaml(tmp_path / 'fisheye.yaml')):
        assert c.lens == lens
        points = np.array([[-8.0, 1.5, 4.0], [0.5, 1.2, 30.0], [9.0, -1.0, 1.0]])  # 66 deg off
        uv, _, inside = c.project(points)
        assert inside.all()
        rays = c.pixel_rays(uv)
        np.testing.assert_allclose(rays, points / np.linalg.norm(points, axis=1)[:, None],
                                   atol=1e-6)
    with pytest.raises(ConfigError, match="distortion_model 'fov' is not one of plumb_bob"):
        CameraCalibration(1280, 800, calib.K, np.array([0.9]), np.eye(4), distortion_model='fov')


def test_flip_and_zoom_move_the_image_and_the_3d_lane_alike():
    point = np.array([-2.0, 1.6, 15.0])
    image = _dot((CAMERA.width, CAMERA.height), _project(CAMERA.intrinsics, point))
    rng = np.random.default_rng(0)
    for s in (0.85, 1.0, 1.25):
        fixed = SaladAugment(flip=0.0, zoom=(s, s), brightness=0.0, contrast=0.0, colour=0.0)
        same, (moved,), params = draw(image, [point[None]], rng, fixed)
        np.testing.assert_allclose(moved[0], [-2.0, 1.6, 15.0 / s])
        np.testing.assert_allclose(params, [s, 1, 1, 1, 1, 1], rtol=1e-6)
        zoomed = augment_images(torch.from_numpy(same).permute(2, 0, 1)[None],
                                torch.from_numpy(params)[None], CAMERA)[0]
        np.testing.assert_allclose(_peak(zoomed.permute(1, 2, 0).numpy()),
                                   _project(CAMERA.intrinsics, moved[0]), atol=0.3)
    flipped, (mirrored,) = flip(image, [point[None]])
    np.testing.assert_allclose(_peak(flipped), _project(CAMERA.intrinsics, mirrored[0]),
                               atol=0.3)


def test_the_photometric_change_is_made_per_image_of_a_batch():
    images = torch.full((2, 3, 8, 8), 100, dtype=torch.uint8)
    images[1, :, :4] = 50  # mean 75
    params = torch.tensor([[1.0, 1.0, 1.2, 1.0, 1.0, 3.0],   # brightness, blue clipped
                           [1.0, 2.0, 1.0, 1.0, 0.5, 1.0]])  # contrast about 75, green gain
    out = augment_images(images, params, CAMERA)
    assert out.dtype == torch.float32
    np.testing.assert_allclose(out[0, :, 0, 0], [120, 120, 255])
    np.testing.assert_allclose(out[1, :, 0, 0], [25, 12.5, 25])
    np.testing.assert_allclose(out[1, :, 7, 7], [125, 62.5, 125])


def _road(curvature: float = 0.0) -> list[np.ndarray]:
    z = np.linspace(3.0, 70.0, 1000)
    return [np.column_stack([x0 + curvature * z ** 2, 1.6 + 0.01 * z, z])
            for x0 in (-5.25, -1.75, 1.75, 5.25)]


def _config_for(depths: np.ndarray, masks: np.ndarray) -> SaladConfig:
    shift, scale = row_statistics(depths, masks)
    return dataclasses.replace(SaladConfig(camera=CAMERA), row_shift=tuple(shift),
                               row_scale=tuple(scale))


def test_perfect_maps_decode_to_the_lanes_they_were_made_from():
    lanes = _road()
    targets = lane_targets(lanes, CAMERA)
    cfg = _config_for(targets.depth[None], targets.depth_mask[None])
    decoded, scores = decode(targets.seg * 0.9, np.concatenate(
        [targets.offsets, cfg.depth_residual(targets.depth)[None]]), cfg)
    assert len(decoded) == 4 and np.allclose(scores, 0.9)
    trees = [cKDTree(lane) for lane in lanes]
    for lane in decoded:
        error = min(tree.query(lane)[0].mean() for tree in trees)
        assert error < 0.05, error
        assert lane[0, 2] < 10 and lane[-1, 2] > 50  # near to far, up to the range


@pytest.mark.parametrize('height', [1.2, 1.5])
def test_side_lanes_that_touch_in_the_image_are_decoded_apart(height):
    # seen from a low camera, the lines of the outer lanes lie almost along the image rows and
    # touch near the horizon, at other depths: one point per run of cells lay between them
    z = np.linspace(3.0, 70.0, 1000)
    lanes = [np.column_stack([np.full_like(z, x0), np.full_like(z, height), z])
             for x0 in (-12.25, -8.75, -5.25, -1.75, 1.75)]
    targets = lane_targets(lanes, CAMERA)
    cfg = _config_for(targets.depth[None], targets.depth_mask[None])
    decoded, _ = decode(targets.seg * 0.9, np.concatenate(
        [targets.offsets, cfg.depth_residual(targets.depth)[None]]), cfg)
    assert len(decoded) == len(lanes)
    trees = [cKDTree(lane) for lane in lanes]
    nearest = [min(range(len(lanes)), key=lambda i: trees[i].query(lane)[0].mean())
               for lane in decoded]
    assert sorted(nearest) == list(range(len(lanes)))
    for lane, i in zip(decoded, nearest):
        assert trees[i].query(lane)[0].mean() < 0.05


def test_a_far_side_line_that_runs_along_the_image_rows_is_decoded():
    # a line 12 m to the side seen from 30 m on lies almost along the image rows: a few cell
    # rows hold all of it, and one point per row was too few to make a lane of it
    z = np.linspace(3.0, 70.0, 1000)
    lanes = [np.column_stack([np.full_like(z, x0), np.full_like(z, 1.5), z])
             for x0 in (-1.75, 1.75)]
    far = z >= 30.0
    lanes.append(np.column_stack([np.full(far.sum(), 12.0), np.full(far.sum(), 1.5), z[far]]))
    targets = lane_targets(lanes, CAMERA)
    cfg = _config_for(targets.depth[None], targets.depth_mask[None])
    decoded, _ = decode(targets.seg * 0.9, np.concatenate(
        [targets.offsets, cfg.depth_residual(targets.depth)[None]]), cfg)
    side = [lane for lane in decoded if np.median(lane[:, 0]) > 6.0]
    assert len(decoded) == 3 and len(side) == 1
    assert np.abs(side[0][:, 0] - 12.0).max() < 0.3
    assert side[0][0, 2] < 36.0 and side[0][-1, 2] > 55.0


def test_a_lane_continues_to_the_far_edge_of_its_top_cell_row_and_no_further():
    cfg = SaladConfig(camera=CAMERA)
    z = np.arange(5.0, 30.01, 0.5)
    lane = np.column_stack([1.75 + 0.02 * z, np.full_like(z, 1.6), z])
    top_row = np.floor((CAMERA.focal * 1.6 / 30.0 + CAMERA.cy + 0.5) / STRIDE)
    far_edge_z = CAMERA.focal * 1.6 / (top_row * STRIDE - 0.5 - CAMERA.cy)
    extended = extend_to_row_edge(lane, top_row, cfg)
    assert 30.0 < extended[-1, 2] <= far_edge_z < extended[-1, 2] + 0.5
    np.testing.assert_allclose(extended[:, 0], 1.75 + 0.02 * extended[:, 2])
    np.testing.assert_array_equal(extended[:len(lane)], lane)
    # a lane seen up to the horizon's row reaches the decoder's range, not the horizon
    near_horizon = extend_to_row_edge(lane, np.floor(CAMERA.cy / STRIDE), cfg)
    assert near_horizon[-1, 2] == pytest.approx(cfg.max_depth_m)


def test_dense_depth_fills_between_the_lanes_as_the_ground_does():
    targets = lane_targets(_road(), CAMERA)
    rows, cols = np.nonzero(targets.depth_mask & (targets.seg == 0))
    # a plane 1.6 m below the camera, rising 1 cm per metre: z = f h / (v - cy - 0.01 f) at
    # the cell centre; a cell row spans 4 px, so the lane points it took its depth from lie up
    # to 2 px off (10 % of the depth at 20 m)
    v = (rows + 0.5) * 4 - 0.5
    near = targets.depth[rows, cols] < 20
    expected = CAMERA.focal * 1.6 / (v - CAMERA.cy - CAMERA.focal * 0.01)
    assert near.sum() > 1000
    np.testing.assert_allclose(targets.depth[rows, cols][near], expected[near], rtol=0.1)


def test_the_model_learns_a_road():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    lanes = _road(0.001)
    targets = lane_targets(lanes, CAMERA)
    cfg = _config_for(targets.depth[None], targets.depth_mask[None])
    # lane paint drawn where the targets say, on grey noise: learnable in a few steps
    image = rng.integers(60, 90, (CAMERA.height, CAMERA.width, 3)).astype(np.uint8)
    image[np.repeat(np.repeat(targets.seg > 0, 4, axis=0), 4, axis=1)] = 230
    batch = {'seg': torch.from_numpy(targets.seg)[None],
             'offsets': torch.from_numpy(targets.offsets)[None],
             'depth': torch.from_numpy(targets.depth)[None],
             'depth_mask': torch.from_numpy(targets.depth_mask)[None]}
    model, criterion = SaladNet(cfg), SaladCriterion(cfg)
    optimiser = torch.optim.AdamW(model.parameters(), lr=3e-3)
    x = torch.from_numpy(image).permute(2, 0, 1)[None]
    first = None
    for _ in range(25):
        losses = criterion(*model(x), batch)
        optimiser.zero_grad()
        losses['loss'].backward()
        optimiser.step()
        first = first if first is not None else float(losses['loss'].detach())
    last = float(losses['loss'].detach())
    assert np.isfinite(last) and last < 0.5 * first, (first, last)


def test_the_lane_depth_term_weighs_the_lane_cells_alone():
    targets = lane_targets(_road(), CAMERA)
    cfg = _config_for(targets.depth[None], targets.depth_mask[None])
    batch = {'seg': torch.from_numpy(targets.seg)[None],
             'offsets': torch.from_numpy(targets.offsets)[None],
             'depth': torch.from_numpy(targets.depth)[None],
             'depth_mask': torch.from_numpy(targets.depth_mask)[None]}
    seg_logits, spatial = torch.zeros((1, 1, *targets.seg.shape)), torch.zeros(
        (1, 3, *targets.seg.shape))
    paper = SaladCriterion(cfg)(seg_logits, spatial, batch)
    assert 'lane_depth' not in paper  # off by default: the paper's loss
    criterion = SaladCriterion(dataclasses.replace(cfg, lane_depth_weight=0.5))
    losses = criterion(seg_logits, spatial, batch)
    assert float(losses['loss']) == pytest.approx(
        float(paper['loss']) + 0.5 * float(losses['lane_depth']), rel=1e-6)
    lane = targets.seg > 0.5
    road = targets.depth_mask & ~lane
    assert lane.any() and road.any()
    off_lanes = spatial.clone()
    off_lanes[0, 2][torch.from_numpy(road)] += 3.0  # the depth wrong between the lanes only
    moved = criterion(seg_logits, off_lanes, batch)
    assert float(moved['lane_depth']) == pytest.approx(float(losses['lane_depth']))
    assert float(moved['depth']) > float(losses['depth'])
    on_lanes = spatial.clone()
    on_lanes[0, 2][torch.from_numpy(lane)] += 3.0
    assert float(criterion(seg_logits, on_lanes, batch)['lane_depth']) > float(
        losses['lane_depth'])


def test_checkpoints_round_trip_with_weights_only_and_refuse_other_files(tmp_path):
    targets = lane_targets(_road(), CAMERA)
    model = SaladNet(_config_for(targets.depth[None], targets.depth_mask[None])).eval()
    save_salad(tmp_path / 'salad.pt', model, 'test', {'steps': 0})
    loaded, info = load_salad(tmp_path / 'salad.pt')
    assert loaded.cfg == model.cfg and info['train_command'] == 'test'
    x = torch.zeros(1, 3, CAMERA.height, CAMERA.width, dtype=torch.uint8)
    with torch.inference_mode():
        torch.testing.assert_close(loaded(x)[1], model(x)[1])
    (tmp_path / 'bad.pt').write_bytes(b'not a checkpoint')
    for path, message in ((tmp_path / 'bad.pt', 'cannot be read'),
                          (tmp_path / 'none.pt', 'does not exist')):
        with pytest.raises(SaladCheckpointError, match=message):
            load_salad(path)
    torch.save({'format': 'salad-checkpoint', 'format_version': 1, 'config': {'camera': {}},
                'state_dict': {}}, tmp_path / 'empty.pt')
    with pytest.raises(SaladCheckpointError, match='does not fit'):
        load_salad(tmp_path / 'empty.pt')


def test_detector_and_scoring_run_on_any_camera(tmp_path):
    targets = lane_targets(_road(), CAMERA)
    save_salad(tmp_path / 'salad.pt',
               SaladNet(_config_for(targets.depth[None], targets.depth_mask[None])), 'test')
    detector = SaladDetector(tmp_path / 'salad.pt')
    k = np.array([[1000.0, 0, 800], [0, 1000, 450], [0, 0, 1]])
    image = np.full((900, 1600, 3), 90, dtype=np.uint8)
    lanes, scores = detector(image, k)
    assert len(lanes) == len(scores) and set(detector.timings_ms) == {
        'warp_ms', 'model_ms', 'decode_ms'}
    rows = score(detector, [CameraLaneSample(image, k, _road(), 'grey')])
    assert set(rows) == {'tau_0.15', 'tau_0.30', 'tau_0.50', 'official', 'by_range'}
    if not lanes:  # nothing compared: no error, and valid JSON (no NaN)
        assert all(r['median_m'] is None for r in rows['by_range'].values())
        json.dumps(rows, allow_nan=False)
    assert rows['tau_0.30']['gt'] == 4 and rows['tau_0.30']['images'] == 1


def test_perfect_maps_score_what_the_decoding_makes_of_the_targets(tmp_path):
    # an untrained network finds nothing; with its heads replaced by the GT lanes' targets the
    # same images score what the decoding alone allows, each head's share one at a time
    lanes = [lane[(lane[:, 2] >= 10.0) & (lane[:, 2] <= 55.0)] for lane in _road()]  # in view
    targets = lane_targets(lanes, CAMERA)
    save_salad(tmp_path / 'salad.pt',
               SaladNet(_config_for(targets.depth[None], targets.depth_mask[None])), 'test')
    # a grey image shows no paint: the paint check would drop every lane (it is tested apart)
    detector = SaladDetector(tmp_path / 'salad.pt', min_paint_contrast=0.0)
    image = np.full((CAMERA.height, CAMERA.width, 3), 90, dtype=np.uint8)
    samples = [CameraLaneSample(image, CAMERA.intrinsics, lanes, 'grey')]
    every = PerfectMaps(detector, HEADS)
    assert score(every, every.over(samples))['tau_0.15']['F1'] == 100.0
    no_depth = PerfectMaps(detector, ['seg', 'offsets'])
    assert score(no_depth, no_depth.over(samples))['tau_0.15']['F1'] < 100.0
    checked = SaladDetector(tmp_path / 'salad.pt')  # the check on: the grey road shows none
    every = PerfectMaps(checked, HEADS)
    assert score(every, every.over(samples))['tau_0.30']['F1'] == 0.0
    assert checked.lanes_unpainted == len(lanes)  # counted for the node's diagnostics
    with pytest.raises(ValueError, match='unknown heads'):
        PerfectMaps(detector, ['depth', 'colour'])


def test_the_error_by_range_is_where_the_lanes_are_off():
    gt = _road()
    off_far = [lane + np.where(lane[:, 2:] > 40.0, [0.4, 0.0, 0.0], 0.0) for lane in gt]
    image = np.zeros((CAMERA.height, CAMERA.width, 3), dtype=np.uint8)
    rows = score(lambda image, k, road=None, distortion=None: (off_far, np.ones(4)),
                 [CameraLaneSample(image, CAMERA.intrinsics, gt, 'shifted')])
    by_range = rows['by_range']
    assert [by_range[b]['median_m'] for b in ('0-10m', '10-20m', '20-30m', '30-40m')] == \
        pytest.approx([0.0] * 4, abs=0.01)
    assert by_range['50-60m']['median_m'] == pytest.approx(0.4, abs=0.01)
    # the lanes still pass tau_CD 0.3 (the far third moves their mean): the F1 hides it
    assert rows['tau_0.30']['F1'] == 100.0


def test_labels_are_scored_within_the_range_salad_decodes():
    # real labels run to 67-122 m (OpenLane's), SALAD decodes to 60 m: scored whole, each
    # label's last 60 m would count against the lane in the chamfer distance
    z = np.linspace(3.0, 120.0, 400)
    labels = [np.column_stack([np.full_like(z, x), np.full_like(z, 1.6), z])
              for x in (-1.75, 1.75)]
    beyond = labels[0][z > 70.0] + [3.5, 0.0, 0.0]  # seen only past the top view compared
    decoded = [lane[lane[:, 2] <= 60.0] for lane in labels]
    image = np.zeros((CAMERA.height, CAMERA.width, 3), dtype=np.uint8)
    rows = score(lambda image, k, road=None, distortion=None: (decoded, np.ones(2)),
                 [CameraLaneSample(image, CAMERA.intrinsics, [*labels, beyond], 'long')])
    for row in ('tau_0.15', 'official'):
        assert rows[row]['gt'] == 2 and rows[row]['F1'] == 100.0, rows[row]


def test_config_values_are_checked_where_declared():
    SaladConfig().validate()
    for bad, message in (({'seg_threshold': 1.5}, 'seg_threshold must be'),
                         ({'widths': (16, 32)}, 'widths must be'),
                         ({'row_shift': (1.0,), 'row_scale': (1.0,)}, 'one per output row'),
                         ({'camera': VirtualCamera(width=500)}, 'multiple of 32'),
                         ({'camera': VirtualCamera(focal=-1.0)}, 'camera.focal must be')):
        with pytest.raises(ConfigError, match=message):
            dataclasses.replace(SaladConfig(), **bad).validate()


def test_the_shipped_weights_find_the_lanes_of_a_held_out_simulated_image():
    from fhld_ros.salad.figure import project
    from fhld_ros.salad.sim_source import salad_seeds, simulated_samples

    detector = SaladDetector()  # fhld_ros/checkpoints/salad.pt, weights_only
    assert detector.info['meta']['steps'] > 0
    sample = next(simulated_samples(salad_seeds('test', 1)[0], 1))
    lanes, scores = detector(sample.image, sample.intrinsics)
    gt = cKDTree(np.concatenate([project(lane, sample.intrinsics) for lane in sample.lanes]))
    # in the image the lanes lie on the GT lines (their depth is the weak part, salad.md)
    on_gt = [np.median(gt.query(project(lane, sample.intrinsics))[0]) < 3.0 for lane in lanes]
    assert len(lanes) >= 4 and sum(on_gt) >= 4, (len(lanes), on_gt)


def test_the_wide_mount_weights_place_a_tall_cameras_near_lanes():
    from fhld_ros.salad.sim_source import DriveVariant, salad_seeds, simulated_samples

    # by name: the shipped file, wherever the package is installed
    detector = SaladDetector('salad_wide_mount')
    assert detector.info['meta']['camera_heights_m'] == [1.2, 3.0]
    sample = next(simulated_samples(salad_seeds('test', 1)[0], 1,
                                    variant=DriveVariant((2.7, 2.7))))
    lanes, _ = detector(sample.image, sample.intrinsics)
    points = np.concatenate(lanes)
    near = points[(points[:, 2] > 5) & (points[:, 2] < 25)]  # optical frame: z forward
    gap = cKDTree(np.concatenate(sample.lanes)).query(near)[0]
    # the 1.2-2.0 m weights put these lanes a median 1.26 m off (salad.md)
    assert len(lanes) >= 4 and np.median(gap) < 0.3, (len(lanes), np.median(gap))


def test_shipped_weights_load_by_name_and_a_users_file_comes_first(tmp_path, monkeypatch):
    from fhld_ros.salad.checkpoint import SHIPPED_DIR, resolve_salad_checkpoint

    for name in ('salad', 'salad.pt', 'salad_wide_mount', 'salad_wide_mount.pt'):
        assert resolve_salad_checkpoint(name) == SHIPPED_DIR / f'{name.removesuffix(".pt")}.pt'
    monkeypatch.chdir(tmp_path)
    (tmp_path / 'salad.pt').write_bytes(b'a file of the same name')
    assert resolve_salad_checkpoint('salad.pt') == Path('salad.pt')
    assert resolve_salad_checkpoint('sub/salad.pt') == Path('sub/salad.pt')
    with pytest.raises(SaladCheckpointError, match='by name: salad, salad_wide_mount'):
        load_salad('salad_tall')


def test_an_autolabel_once_json_gives_a_real_image_its_lanes(tmp_path):
    from fhld_ros.salad.real_images import with_lanes

    path = tmp_path / 'lanes.json'
    path.write_text('{"lanes": [[[0.1, 1.8, 6.0], [0.3, 1.8, 19.0]]], "calibration": []}')
    image = np.zeros((4, 4, 3), dtype=np.uint8)
    sample = with_lanes(CameraLaneSample(image, np.eye(3), [], 'pjlab'), path)
    assert sample.name == 'pjlab' and len(sample.lanes) == 1
    np.testing.assert_allclose(sample.lanes[0][-1], [0.3, 1.8, 19.0])


def test_salad_real_scores_each_image_against_its_own_lifted_labels(tmp_path, capsys):
    import json

    from PIL import Image

    from fhld_ros.cli import main

    k = [[800.0, 0.0, 320.0], [0.0, 800.0, 180.0], [0.0, 0.0, 1.0]]
    nuscenes, pjlab = tmp_path / 'nuscenes_camera_lidar', tmp_path / 'pjlab_camera_lidar_pair'
    nuscenes.mkdir()
    pjlab.mkdir()
    image = Image.fromarray(np.full((360, 640, 3), 90, dtype=np.uint8))
    image.save(nuscenes / 'n015__CAM_FRONT__1.jpg')
    image.save(pjlab / '0.png')
    (nuscenes / 'calib.json').write_text(json.dumps(
        {'cams': {'CAM_FRONT': {'cam2img': [row + [0.0] for row in k] + [[0, 0, 0, 1.0]]}}}))
    (pjlab / 'center_camera-intrinsic.json').write_text(json.dumps(
        {'center_camera-intrinsic': {'param': {'cam_K': {'data': k}, 'cam_dist': {
            'data': [[-0.1, 0.1, 0.0, 0.0]]}}}}))
    line = [[0.0, 1.5, 6.0], [0.0, 1.5, 16.0]]
    gts = {}
    for name, lanes in (('nus', [line, line]), ('pj', [line])):
        gts[name] = tmp_path / f'{name}.json'
        gts[name].write_text(json.dumps({'lanes': lanes}))
    assert main(['salad-real', str(tmp_path), '--nuscenes-gt', str(gts['nus']),
                 '--pjlab-gt', str(gts['pj']), '--json']) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result['nuscenes']['tau_0.30']['gt'] == 2 and result['pjlab']['tau_0.30']['gt'] == 1
    assert result['nuscenes']['tau_0.30']['images'] == 1 == result['pjlab']['tau_0.30']['images']
    assert set(result['lanes']) == {'nuscenes_cam_front', 'pjlab_center_camera'}


def test_the_commands_decode_as_the_node_unless_told_otherwise():
    import argparse

    from fhld_ros.salad.detector import add_decoding_arguments, decoding_options
    from fhld_ros.salad.parameters import CameraParams

    parser = argparse.ArgumentParser()
    add_decoding_arguments(parser)
    node = CameraParams()
    assert decoding_options(parser.parse_args([])) == {
        'min_paint_contrast': node.min_paint_contrast, 'double_lines': node.double_lines}
    assert decoding_options(parser.parse_args(['--no-double-lines', '--min-paint-contrast', '0'])
                            ) == {'min_paint_contrast': 0.0, 'double_lines': False}


def test_training_can_start_from_shipped_weights(tmp_path):
    from fhld_ros.cli import main
    from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT

    out = tmp_path / 'run'
    assert main(['salad-train', str(out), '--drives', '1', '--frames', '1', '--steps', '2',
                 '--batch', '1', '--workers', '1', '--threads', '1',
                 '--init', str(DEFAULT_SALAD_CHECKPOINT), '--lane-depth-weight', '0.25']) == 0
    tuned, info = load_salad(out / 'salad.pt')
    shipped, _ = load_salad(DEFAULT_SALAD_CHECKPOINT)
    # its row depth statistics, not this one image's; the loss it was tuned with recorded; the
    # shipped weights' depth calibration left behind (measured on them, not the tuned ones)
    assert shipped.cfg.depth_calibration_m
    assert tuned.cfg == dataclasses.replace(uncalibrated(shipped.cfg), lane_depth_weight=0.25)
    assert info['meta']['init'] == str(DEFAULT_SALAD_CHECKPOINT) and info['meta']['steps'] == 2
    assert info['meta']['init_steps'] == load_salad(DEFAULT_SALAD_CHECKPOINT)[1]['meta']['steps']
    moved = [not torch.equal(a, b) for a, b in zip(tuned.state_dict().values(),
                                                   shipped.state_dict().values())]
    assert any(moved)  # it trained from there


@pytest.mark.parametrize('runtime', ['onnxruntime', 'torchscript'])
def test_the_served_network_matches_eager_torch(runtime):
    from fhld_ros.model.inference import OnnxGraph, TracedGraph

    detector = SaladDetector(threads=1, runtime=runtime, flip_average=True)
    assert isinstance(detector.network, {'onnxruntime': OnnxGraph, 'torchscript': TracedGraph}[
        runtime])
    camera = detector.cfg.camera  # a batch of two, as with flip_average: the image, its mirror
    x = torch.randint(0, 256, (2, 3, camera.height, camera.width), dtype=torch.uint8,
                      generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        eager = detector.model(x)
    for served, want in zip(detector.network(x), eager):
        torch.testing.assert_close(served, want, rtol=1e-4, atol=1e-4)
    assert isinstance(SaladDetector(threads=1).network, OnnxGraph)  # 'auto': a dependency
    with pytest.raises(ConfigError, match='model_runtime'):
        from fhld_ros.salad.parameters import CameraParams
        CameraParams(model_runtime='tensorrt')


def test_the_flip_average_sees_an_image_and_its_mirror_alike():
    image = np.random.default_rng(0).integers(0, 256, (CAMERA.height, CAMERA.width, 3),
                                              dtype=np.uint8)
    for flip_average in (True, False):
        detector = SaladDetector(threads=1, flip_average=flip_average)
        prob, spatial = detector.maps(image, CAMERA.intrinsics)
        prob_m, spatial_m = detector.maps(np.ascontiguousarray(image[:, ::-1]),
                                          CAMERA.intrinsics)
        mirrored = spatial[:, :, ::-1] * np.array([-1.0, 1.0, 1.0])[:, None, None]
        same = (np.allclose(prob_m, prob[:, ::-1], atol=1e-5)
                and np.allclose(spatial_m, mirrored, atol=1e-5))
        assert same == flip_average  # one pass alone is not mirror-symmetric


def test_images_augmented_on_the_training_device_match_the_loaders(tmp_path):
    from fhld_ros.salad.dataset import SaladDataset, ShardSamples, write_shard
    from fhld_ros.salad.sample import CameraLaneSample

    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (CAMERA.height, CAMERA.width, 3), dtype=np.uint8)
    lane = np.column_stack([np.full(40, -1.8), np.full(40, 1.5), np.linspace(5, 45, 40)])
    write_shard(tmp_path / 'a.npz', [CameraLaneSample(image, CAMERA.intrinsics, [lane], 'a')],
                CAMERA)
    samples = ShardSamples([tmp_path / 'a.npz'])
    loader = SaladDataset(samples, CAMERA, SaladAugment())
    deferred = SaladDataset(samples, CAMERA, SaladAugment(), defer_images=True)
    for epoch in range(4):  # the draws differ by epoch: flips and zooms in and out
        done, later = loader[(epoch, 0)], deferred[(epoch, 0)]
        assert done['augment'].tolist() == [1.0] * 6 and later['augment'][0] != 1.0
        for key in ('seg', 'offsets', 'depth', 'depth_mask'):
            assert torch.equal(done[key], later[key])
        batch = augment_images(later['image'][None], later['augment'][None], CAMERA)[0]
        assert (batch - done['image'].float()).abs().max() <= 0.5 + 1e-3


def test_epoch_batches_resume_where_they_stopped():
    from itertools import islice

    from fhld_ros.salad.dataset import EpochBatches

    run = list(islice(EpochBatches(10, 3), 9))  # 3 batches an epoch, the 10th image dropped
    assert [len(b) for b in run] == [3] * 9
    assert [{e for e, _ in b} for b in run] == [{0}] * 3 + [{1}] * 3 + [{2}] * 3
    first = [i for b in run[:3] for _, i in b]
    assert len(set(first)) == 9 and first != sorted(first)
    assert list(islice(EpochBatches(10, 3, first=4), 5)) == run[4:]
    with pytest.raises(ValueError, match='a batch of 11 needs at least 11 training images'):
        EpochBatches(10, 11)
