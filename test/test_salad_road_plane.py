"""A known camera mount: the road plane gives SALAD's near lanes their depth (road_plane.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fhld_ros.errors import ConfigError
from fhld_ros.salad.config import SaladConfig
from fhld_ros.salad.decode import decode
from fhld_ros.salad.evaluate import score
from fhld_ros.salad.parameters import CameraParams
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.sim_source import (
    HEIGHT_RANGE_M,
    DriveVariant,
    camera_for_seed,
    salad_seeds,
    simulated_samples,
)
from fhld_ros.salad.targets import lane_targets, row_statistics
from fhld_ros.salad.virtual_camera import VirtualCamera
from msg_adapters.odometry import euler_to_matrix

CAMERA = VirtualCamera()
HEIGHT, PITCH = 1.5, np.radians(3.0)


def _level_road() -> list[np.ndarray]:
    """Four straight lanes on a level road HEIGHT below a camera pitched down by PITCH."""
    z = np.linspace(3.0, 70.0, 1000)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(PITCH), -np.sin(PITCH)],
                     [0.0, np.sin(PITCH), np.cos(PITCH)]])  # level frame -> pitched optical
    return [np.column_stack([np.full_like(z, x0), np.full_like(z, HEIGHT), z]) @ turn.T
            for x0 in (-5.25, -1.75, 1.75, 5.25)]


def test_the_output_frames_ground_is_the_plane_of_a_level_mount():
    # optical -> base_footprint: 1.5 m up, pitched 3 degrees down (ROS RPY of an optical frame)
    T = euler_to_matrix(0.4, -0.1, HEIGHT, -np.pi / 2 - PITCH, 0.0, -np.pi / 2)
    road = RoadPlane.from_extrinsic(T)
    level = RoadPlane.level(HEIGHT, PITCH)
    np.testing.assert_allclose(road.normal, level.normal, atol=1e-9)
    assert road.height_m == pytest.approx(HEIGHT) and road.until_m == 20.0
    # a level camera: the row 100 px below the centre sees the road at f h / 100
    flat = RoadPlane.level(HEIGHT, 0.0)
    assert flat.depth(np.array([CAMERA.cx]), np.array([CAMERA.cy + 100.0]), CAMERA)[0] == \
        pytest.approx(CAMERA.focal * HEIGHT / 100.0)
    assert np.isinf(flat.depth(np.array([0.0]), np.array([CAMERA.cy - 5.0]), CAMERA)[0])
    with pytest.raises(ValueError, match='above the road'):
        RoadPlane.from_extrinsic(euler_to_matrix(0, 0, -1.0, -np.pi / 2, 0, -np.pi / 2))


def test_near_lanes_take_the_roads_depth_and_far_ones_the_networks():
    lanes = _level_road()
    targets = lane_targets(lanes, CAMERA)
    shift, scale = row_statistics(targets.depth[None], targets.depth_mask[None])
    cfg = dataclasses.replace(SaladConfig(camera=CAMERA), row_shift=tuple(shift),
                              row_scale=tuple(scale))
    far_off = cfg.depth_residual(targets.depth * 1.1)  # a network 10 % too far everywhere
    maps = targets.seg * 0.9, np.concatenate([targets.offsets, far_off[None]])
    trees = [cKDTree(lane) for lane in lanes]

    def error(decoded: list[np.ndarray], near: bool) -> float:
        points = np.concatenate(decoded)
        points = points[(points[:, 2] < 18.0) if near else (points[:, 2] > 32.0)]
        return float(np.median([min(t.query(p)[0] for t in trees) for p in points]))

    network, _ = decode(*maps, cfg)
    # the plane up to 20 m, blending into the network's depth by 30 m
    with_road, _ = decode(*maps, cfg, RoadPlane.level(HEIGHT, PITCH, until_m=20.0))
    assert len(network) == len(with_road) == 4
    assert error(network, near=True) > 0.15  # 10 % of the lanes' 1.75 and 5.25 m sideways
    assert error(with_road, near=True) < 0.03
    assert error(with_road, near=False) == pytest.approx(error(network, near=False), rel=0.2)


def test_a_road_plane_needs_the_camera_above_the_output_frames_ground():
    with pytest.raises(ConfigError, match='road_plane_m 40 needs camera_to_output'):
        CameraParams(road_plane_m=40.0)
    CameraParams(road_plane_m=40.0, output_frame='base_footprint',
                 camera_to_output=(0.0, 0.0, HEIGHT, -np.pi / 2, 0.0, -np.pi / 2))


class _Recorder:
    """A detector that returns no lanes and keeps the road plane it was given."""

    def __init__(self) -> None:
        self.roads: list[RoadPlane | None] = []

    def __call__(self, image: np.ndarray, k: np.ndarray, road: RoadPlane | None = None,
                 distortion: np.ndarray | None = None) -> tuple[list[np.ndarray], np.ndarray]:
        self.roads.append(road)
        return [], np.zeros(0)


def test_simulated_drives_know_their_mount_and_scoring_uses_it_when_asked():
    sample = next(iter(simulated_samples(4_000_000, 1)))
    assert sample.road is not None and 1.2 <= sample.road.height_m <= 2.0
    # the GT lanes near the car lie on it
    near = np.concatenate(sample.lanes)
    near = near[near[:, 2] < 15.0]
    assert np.abs(near @ np.asarray(sample.road.normal) - sample.road.height_m).max() < 0.05
    plain = CameraLaneSample(sample.image, sample.intrinsics, sample.lanes, 'no mount')
    recorder = _Recorder()
    score(recorder, [sample, plain])
    score(recorder, [sample, plain], road_until_m=30.0)
    assert recorder.roads[:2] == [None, None]
    assert recorder.roads[2] == dataclasses.replace(sample.road, until_m=30.0)
    assert recorder.roads[3] is None


def test_a_drives_camera_moves_to_a_given_height_and_keeps_its_pitch_and_lens():
    own = next(iter(simulated_samples(4_000_000, 1, (320, 180))))
    tall = next(iter(simulated_samples(4_000_000, 1, (320, 180),
                                       variant=DriveVariant((2.6, 2.6)))))
    assert tall.road.height_m == pytest.approx(2.6)
    np.testing.assert_allclose(tall.road.normal, own.road.normal, atol=1e-9)  # same pitch
    np.testing.assert_array_equal(tall.intrinsics, own.intrinsics)
    near = np.concatenate(tall.lanes)
    near = near[near[:, 2] < 15.0]
    assert np.abs(near @ np.asarray(tall.road.normal) - 2.6).max() < 0.05  # the road below
    assert np.abs(tall.image.astype(int) - own.image).mean() > 5  # it sees more road
    # a range: each seed at the same place in it as in the seeds' own range
    seeds = salad_seeds('train', 20)
    own_h = np.array([camera_for_seed(s).height_m for s in seeds])
    tall = DriveVariant((2.4, 2.8))
    tall_h = np.array([camera_for_seed(s, variant=tall).height_m for s in seeds])
    lo, hi = HEIGHT_RANGE_M
    np.testing.assert_allclose(tall_h, 2.4 + (own_h - lo) / (hi - lo) * 0.4, atol=1e-9)
    with pytest.raises(ValueError, match='0 < low <= high'):
        DriveVariant((2.0, 1.9))
    from fhld_ros.cli import main
    for bad in (['-1'], ['2', '1'], ['1', '2', '3']):
        assert main(['salad-eval', '--drives', '1', '--camera-height', *bad]) == 2
    assert main(['salad-eval', '--drives', '1', '--first-drive', '-1']) == 2
    assert main(['salad-eval', '--drives', '1', '--workers', '0']) == 2


def test_a_drives_camera_moves_sideways_and_a_line_runs_under_it():
    seeds = salad_seeds('train', 40)
    own = [camera_for_seed(s) for s in seeds]
    side = [camera_for_seed(s, variant=DriveVariant(side_m=1.8)) for s in seeds]
    left = np.array([d.left_m for d in side])
    assert np.abs(left).max() <= 1.8 and left.min() < -1.0 and left.max() > 1.0
    assert all(o == dataclasses.replace(d, left_m=0.0) for o, d in zip(own, side))
    assert {d.left_m for d in own} == {0.0}
    seed = int(seeds[int(np.argmax(left))])  # furthest left: the lanes move right in the image
    a = next(iter(simulated_samples(seed, 1, (320, 180))))
    b = next(iter(simulated_samples(seed, 1, (320, 180), variant=DriveVariant(side_m=1.8))))
    assert b.road.height_m == pytest.approx(a.road.height_m)
    near = [lane[lane[:, 2] < 12.0] for lane in a.lanes]
    moved = [lane[lane[:, 2] < 12.0] for lane in b.lanes]
    xs_a = sorted(float(np.median(p[:, 0])) for p in near if len(p))
    xs_b = sorted(float(np.median(p[:, 0])) for p in moved if len(p))
    shifted = [x + left.max() for x in xs_a]
    assert sum(min(abs(x - y) for x in xs_b) < 0.1 for y in shifted) >= 2, (xs_b, shifted)
    assert min(abs(x) for x in xs_b) < 0.3 < min(abs(x) for x in xs_a)  # now under the camera
    with pytest.raises(ValueError, match='side offset'):
        DriveVariant(side_m=-0.5)
    assert DriveVariant((2.6, 2.6), 1.5).tag() == '_h2.60-2.60_s1.50'
    assert DriveVariant().tag() == '' and DriveVariant(road_look=True).tag() == '_look'
    from fhld_ros.cli import main
    assert main(['salad-eval', '--drives', '1', '--camera-side', '9']) == 2


def test_the_road_look_paints_no_lines_along_half_the_kerbs_and_varies_the_pavement():
    from fhld_ros.data.variation import road_variation
    seeds = salad_seeds('train', 200)
    draws = [road_variation(s) for s in seeds]
    assert draws == [road_variation(s) for s in seeds]  # the seed's own, every time
    for key, share in (('edge_lines', 0.5), ('seams', 0.35)):
        assert abs(np.mean([d[key] for d in draws]) - share) < 0.1, key
    for key in ('gutter_ratio', 'asphalt_rho'):
        assert abs(np.mean([d[key] is not None for d in draws]) - 0.35) < 0.1, key
    look = DriveVariant(road_look=True)
    assert look.meta() == {'road_look': True} and DriveVariant().road(seeds[0]) == {}
    seed = next(s for s, d in zip(seeds, draws) if not d['edge_lines'])
    own = next(iter(simulated_samples(seed, 1, (320, 180))))
    bare = next(iter(simulated_samples(seed, 1, (320, 180), variant=look)))
    # the same camera and lanes, less the two edge lines just inside the kerbs
    np.testing.assert_array_equal(bare.intrinsics, own.intrinsics)
    assert bare.road == own.road
    near = lambda sample: sorted(float(np.median(lane[lane[:, 2] < 20.0, 0]))  # noqa: E731
                                 for lane in sample.lanes if (lane[:, 2] < 20.0).sum() > 3)
    kept, before = near(bare), near(own)
    assert len(kept) < len(before) and all(min(abs(x - y) for y in before) < 0.05
                                           for x in kept), (kept, before)
    assert np.abs(bare.image.astype(int) - own.image).mean() > 0.5
    from fhld_ros.cli import main
    assert main(['salad-eval', '--drives', '1', '--road-look', '--camera-side', '9']) == 2


def test_held_out_drives_start_where_asked():
    # a second set of validation drives, to confirm a choice made on the first
    from fhld_ros.salad.evaluate import held_out_drives
    sample = next(held_out_drives(1, 1, 'val', first=60))
    assert sample.name == f'sim seed {salad_seeds("val", 1, 60)[0]} sweep 0'


def test_held_out_drives_rendered_in_processes_are_the_same_images_in_order():
    from fhld_ros.salad.evaluate import held_out_drives
    serial = list(held_out_drives(3, 1, 'val', first=7))
    pooled = list(held_out_drives(3, 1, 'val', first=7, workers=2))
    assert [s.name for s in pooled] == [s.name for s in serial]
    for a, b in zip(serial, pooled):
        assert np.array_equal(a.image, b.image) and len(a.lanes) == len(b.lanes)
        assert all(np.array_equal(x, y) for x, y in zip(a.lanes, b.lanes))
