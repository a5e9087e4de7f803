"""The road's pitch read off an image: where its lanes' image lines meet (lanes_road.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fhld_ros.errors import ConfigError
from fhld_ros.salad.camera_pipeline import CameraPipeline
from fhld_ros.salad.config import SaladConfig
from fhld_ros.salad.decode import decode
from fhld_ros.salad.evaluate import score
from fhld_ros.salad.lanes_road import horizon_row, image_road, lane_lines, lanes_pitch
from fhld_ros.salad.parameters import CameraParams
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.targets import lane_targets, row_statistics
from fhld_ros.salad.virtual_camera import VirtualCamera

CAMERA = VirtualCamera()
HEIGHT = 2.6


def _road(pitch_rad: float, heading_rad: float = 0.0, roll_rad: float = 0.0,
          offsets: tuple[float, ...] = (-5.25, -1.75, 1.75, 5.25)) -> list[np.ndarray]:
    """Straight lanes on a level road HEIGHT below a camera pitched down by pitch_rad and
    rolled by roll_rad, the lanes heading_rad to the right of its view."""
    t = np.linspace(0.0, 70.0, 800)
    c, s = np.cos(pitch_rad), np.sin(pitch_rad)
    pitch = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    lanes = []
    for x0 in offsets:
        level = np.column_stack([x0 + t * np.sin(heading_rad), np.full_like(t, HEIGHT),
                                 3.0 + t * np.cos(heading_rad)])
        lanes.append(level @ pitch.T @ roll.T)
    return lanes


@pytest.mark.parametrize('pitch_deg, heading_deg', [(3.0, 0.0), (0.0, 4.0), (-1.5, -6.0),
                                                    (8.0, 2.0)])
def test_straight_lanes_meet_on_the_horizon_of_the_cameras_pitch(pitch_deg, heading_deg):
    lanes = _road(np.radians(pitch_deg), np.radians(heading_deg))
    assert len(lane_lines(lanes, CAMERA)) == 4
    assert np.degrees(lanes_pitch(lanes, CAMERA)) == pytest.approx(pitch_deg, abs=0.01)


def test_no_pitch_without_two_lanes_that_meet():
    one = _road(np.radians(3.0), offsets=(1.75,))
    assert lanes_pitch(one, CAMERA) is None
    far = [lane[lane[:, 2] > 30.0] for lane in _road(np.radians(3.0))]  # no near part
    assert len(lane_lines(far, CAMERA)) == 0 and lanes_pitch(far, CAMERA) is None
    # two lines of the same slope in the image never meet
    assert horizon_row(np.array([[100.0, 0.5], [200.0, 0.55]])) is None
    assert horizon_row(np.array([[100.0, 0.5], [300.0, -0.5]])) == pytest.approx(200.0)


def test_a_mount_off_in_pitch_gets_the_images_own_and_keeps_its_height_and_roll():
    pitch, roll = np.radians(2.0), np.radians(1.0)
    mount = RoadPlane((float(np.sin(roll)), float(np.cos(roll)), 0.0), HEIGHT)  # level, rolled
    turned = mount.with_pitch(pitch)
    assert turned.pitch_rad == pytest.approx(pitch) and turned.height_m == HEIGHT
    assert turned.normal[0] == mount.normal[0] and not turned.pitch_from_image
    assert np.linalg.norm(turned.normal) == pytest.approx(1.0)


def test_near_lanes_take_the_depth_of_the_road_at_the_images_pitch():
    true_pitch = np.radians(2.5)
    lanes = _road(true_pitch, np.radians(2.0))
    targets = lane_targets(lanes, CAMERA)
    shift, scale = row_statistics(targets.depth[None], targets.depth_mask[None])
    cfg = dataclasses.replace(SaladConfig(camera=CAMERA), row_shift=tuple(shift),
                              row_scale=tuple(scale))
    # the network's depth 20 % short, as for a camera mounted above the heights it learnt
    short = cfg.depth_residual(targets.depth * 0.8)
    maps = targets.seg * 0.9, np.concatenate([targets.offsets, short[None]])

    def near_error(road: RoadPlane | None) -> float:
        points = np.concatenate(decode(*maps, cfg, road)[0])
        points = points[points[:, 2] < 18.0]
        return float(np.median(cKDTree(np.concatenate(lanes)).query(points)[0]))

    assert len(decode(*maps, cfg)[0]) == 4
    off = RoadPlane.level(HEIGHT, true_pitch - np.radians(1.5))  # the mount 1.5 degrees off
    exact = near_error(RoadPlane.level(HEIGHT, true_pitch))  # the mount as it is
    assert exact < 0.1 and near_error(None) > 0.3 and near_error(off) > 2 * exact
    assert near_error(dataclasses.replace(off, pitch_from_image=True)) == \
        pytest.approx(exact, abs=0.002)
    # a network that reads the road at the mount's height keeps its depths (the mount's pitch
    # is not to be trusted), as where the lanes span no plane (one lane)
    right = targets.seg * 0.9, np.concatenate([targets.offsets,
                                               cfg.depth_residual(targets.depth)[None]])
    one = lane_targets(_road(true_pitch, offsets=(1.75,)), CAMERA)
    one = one.seg * 0.9, np.concatenate([one.offsets, cfg.depth_residual(one.depth)[None]])
    for m in (right, one):
        np.testing.assert_array_equal(
            np.concatenate(decode(*m, cfg, dataclasses.replace(off, pitch_from_image=True))[0]),
            np.concatenate(decode(*m, cfg)[0]))
    # no two lanes meet (one lane far out, the other short): the mount's pitch
    assert image_road(off, [lanes[0][:3], lanes[3] * 0.8], CAMERA) == \
        dataclasses.replace(off, pitch_from_image=False)


def test_the_node_and_the_scoring_take_the_pitch_from_the_image_when_asked():
    pose = (0.0, 0.0, HEIGHT, -np.pi / 2 - 0.05, 0.0, -np.pi / 2)  # 2.6 m up, ~3 deg down
    mount = dict(output_frame='base_footprint', camera_to_output=pose, road_plane_m=20.0)
    assert not CameraPipeline(CameraParams(**mount), object()).road.pitch_from_image
    road = CameraPipeline(CameraParams(**mount, road_plane_pitch='image'), object()).road
    assert road.pitch_from_image and road.height_m == pytest.approx(HEIGHT)
    assert road.pitch_rad == pytest.approx(0.05)  # the mount's, until an image gives its own
    with pytest.raises(ConfigError, match='road_plane_pitch'):
        CameraParams(**mount, road_plane_pitch='lidar')
    # fhld salad-eval --road-plane 20 --road-pitch image
    seen = []

    def detector(image, k, road=None, distortion=None):
        seen.append(road)
        return [], np.zeros(0)

    sample = CameraLaneSample(np.zeros((8, 8, 3), np.uint8), np.eye(3), [], 'level',
                              RoadPlane.level(HEIGHT, 0.05))
    score(detector, [sample], 20.0, pitch_from_image=True)
    score(detector, [sample], 20.0)
    assert [r.pitch_from_image for r in seen] == [True, False]
