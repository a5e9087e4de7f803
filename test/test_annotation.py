"""The annotation pipeline's parts on scenes whose answer is known: calibration files and
projection, the 2D label format, ground segmentation, lane regions and lane recovery."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fhld_ros.annotation.ground import segment_ground
from fhld_ros.annotation.lane_regions import lane_members
from fhld_ros.annotation.recovery import recover_lane
from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.camera.labels2d import (
    ImageLabels,
    LaneLabel2D,
    read_label_dir,
    read_labels,
    write_labels,
)
from fhld_ros.errors import ConfigError

# camera 1.5 m above a flat road, looking along +x of the cloud frame (optical z = cloud x)
T_CAMERA_CLOUD = np.array([[0.0, -1.0, 0.0, 0.0],
                           [0.0, 0.0, -1.0, 0.0],
                           [1.0, 0.0, 0.0, 0.0],
                           [0.0, 0.0, 0.0, 1.0]])
K = np.array([[700.0, 0.0, 480.0], [0.0, 700.0, 300.0], [0.0, 0.0, 1.0]])


def camera(D=(0, 0, 0, 0, 0)) -> CameraCalibration:
    return CameraCalibration(960, 600, K, np.asarray(D, dtype=float), T_CAMERA_CLOUD)


def test_projection_is_the_pinhole_model_and_distortion_is_opencvs():
    xyz = np.array([[10.0, 1.0, -1.5], [20.0, -3.0, -1.5], [-5.0, 0.0, 0.0]])
    uv, depth, inside = camera().project(xyz)
    assert np.allclose(uv[0], [480 - 70, 300 + 105]) and depth[0] == 10
    assert inside.tolist() == [True, True, False]  # the last is behind the camera
    D = (-0.1, 0.05, 0.001, -0.002, 0.0)
    uv_d, _, _ = camera(D).project(xyz[:2])
    x, y = -xyz[:2, 1] / xyz[:2, 0], 1.5 / xyz[:2, 0]
    r2 = x * x + y * y
    radial = 1 + D[0] * r2 + D[1] * r2 * r2
    xd = x * radial + 2 * D[2] * x * y + D[3] * (r2 + 2 * x * x)
    yd = y * radial + D[2] * (r2 + 2 * y * y) + 2 * D[3] * x * y
    assert np.allclose(uv_d, np.column_stack([700 * xd + 480, 700 * yd + 300]))


def test_calibration_yaml_round_trip_and_one_line_errors(tmp_path):
    path = tmp_path / 'calib.yaml'
    camera((-0.1, 0.05, 0, 0, 0)).to_yaml(path)
    back = CameraCalibration.from_yaml(path)
    assert np.allclose(back.K, K) and np.allclose(back.T_camera_cloud, T_CAMERA_CLOUD)
    assert np.allclose(back.D, [-0.1, 0.05, 0, 0, 0])
    cases = {'width: 10\n': 'missing height, K, T_camera_cloud',
             'width: 1\nheight: 1\nK: [1,0,0,0,1,0,0,0,1]\nT_camera_cloud: [[2,0,0,0],[0,1,0,0],'
             '[0,0,1,0],[0,0,0,1]]\n': 'not a rigid transform',
             'width: 1\nheight: 1\nK: [1,2,3]\nT_camera_cloud: 1\n': 'cannot reshape',
             'width: 1\nheight: 1\nK: [1,0,0,0,1,0,0,0,1]\nT_camera_cloud: [[1,0,0,0],[0,1,0,0],'
             '[0,0,1,0],[0,0,0,1]]\nD: [1, 2]\n': 'plumb_bob takes 4 to 5 coefficients',
             'width: 1\nheight: 1\nK: [1,0,0,0,1,0,0,0,1]\nT_camera_cloud: [[1,0,0,0],[0,1,0,0],'
             '[0,0,1,0],[0,0,0,1]]\nfx: 3\n': "unknown key 'fx'",
             ': [': 'cannot read it'}
    for text, message in cases.items():
        path.write_text(text)
        with pytest.raises(ConfigError, match=message) as info:
            CameraCalibration.from_yaml(path)
        assert '\n' not in str(info.value) and str(path) in str(info.value)


def test_labels_round_trip_and_bad_files_name_themselves(tmp_path):
    labels = ImageLabels(1_700_000_000_100_000_000, 'camera', (960, 600),
                         [LaneLabel2D(3, np.array([[100.25, 599.0], [300.0, 350.5]]))])
    write_labels(tmp_path / f'{labels.stamp_ns}.json', labels)
    back = read_label_dir(tmp_path)[labels.stamp_ns]
    assert back.image_size == (960, 600) and back.lanes[0].id == 3
    assert np.allclose(back.lanes[0].uv, labels.lanes[0].uv)
    bad = tmp_path / 'bad.json'
    for content, message in ((json.dumps({'format': 'x'}), "format is 'x'"),
                             ('{', 'cannot read it'),
                             (json.dumps({'format': 'fhld-lanes2d-1', 'stamp_ns': 1,
                                          'image_size': [2, 2],
                                          'lanes': [{'id': 0, 'uv': [[1, 2, 3]]}]}),
                              'lane 0: uv must be')):
        bad.write_text(content)
        with pytest.raises(ConfigError, match=message):
            read_labels(bad)
    with pytest.raises(ConfigError, match='no \\*.json'):
        read_label_dir(tmp_path / 'empty' if (tmp_path / 'empty').mkdir() is None else None)


def test_ground_is_the_road_and_kerb_not_the_car_or_wall():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-20, 20, (40000, 2))
    z = 0.02 * xy[:, 0] + np.where(xy[:, 1] > 6, 0.15, 0.0)  # a slope and a kerb at y = 6
    road = np.column_stack([xy, z])
    car = np.column_stack([rng.uniform(8, 12.5, 3000), rng.uniform(-1, 1, 3000),
                           rng.uniform(0.45, 1.5, 3000)])  # body only, bumpers up
    wall = np.column_stack([rng.uniform(-20, 20, 3000), np.full(3000, -15.0),
                            rng.uniform(0.5, 3, 3000)])
    hidden = (xy[:, 0] > 8) & (xy[:, 0] < 12.5) & (np.abs(xy[:, 1]) < 1)
    pts = np.vstack([road[~hidden], car, wall])
    mask = segment_ground(pts, np.array([5.0, 0.0]))
    n_road = int((~hidden).sum())
    assert mask[:n_road].mean() > 0.97
    assert mask[n_road:].mean() < 0.02


def test_lane_region_width_follows_depth_and_recovery_finds_the_paint():
    """A straight painted line 1.75 m left of the camera; its label is drawn 3 px off to the
    right. The region holds the returns around it, and recovery centres on the paint."""
    cam = camera()
    rng = np.random.default_rng(1)
    radius, azimuth = np.meshgrid(np.arange(4.0, 40.0, 0.4), np.arange(-0.2, 0.8, 0.002))
    x, y = (radius * np.cos(azimuth)).ravel(), (radius * np.sin(azimuth)).ravel()
    x, y = x[(y > -0.2) & (y < 3.6)], y[(y > -0.2) & (y < 3.6)]  # one sweep's rings
    xyz = np.column_stack([x, y, np.full_like(x, -1.5)])
    paint = np.abs(y - 1.75) < 0.075
    contrast = np.where(paint, 6.0, 1.0) * rng.uniform(0.8, 1.2, x.size)
    line_x = np.linspace(4, 40, 50)
    line_uv, _, _ = cam.project(np.column_stack([line_x, np.full(50, 1.75), np.full(50, -1.5)]))
    uv, depth, inside = cam.project(xyz)
    members = lane_members(uv, depth, line_uv + [3.0, 0.0], 700.0)
    got = xyz[members.index]
    # near the camera the region is ~2 x 0.3 m wide on the road; far away it keeps >= 1.5 px
    near = got[got[:, 0] < 8]
    assert 0.4 < np.ptp(near[:, 1]) < 0.8
    lanes = recover_lane(got, members.t, contrast[members.index], np.zeros(len(got), int))
    assert len(lanes) == 1
    lane = lanes[0]
    assert lane[0, 0] < 6 and lane[-1, 0] > 35
    assert np.abs(lane[:, 1] - 1.75).max() < 0.05, np.abs(lane[:, 1] - 1.75).max()
    assert np.abs(lane[:, 2] + 1.5).max() < 1e-6
