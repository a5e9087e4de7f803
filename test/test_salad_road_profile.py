"""One road depth per image row, shared by the lanes (road_profile.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from fhld_ros.salad.config import SaladConfig
from fhld_ros.salad.decode import decode
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.road_profile import MIN_CELLS, shared_row_depth
from fhld_ros.salad.targets import lane_targets, row_statistics
from fhld_ros.salad.virtual_camera import VirtualCamera

CAMERA = VirtualCamera()
HEIGHT, PITCH = 1.5, np.radians(2.0)
LANE_X = (-5.25, -1.75, 1.75, 5.25)
# each lane's depth off by its own share, as the network's; with no trend across the image (a
# trend is what a road's cross slope looks like, and the profile keeps it)
SCATTER = (1.07, 0.94, 0.95, 1.06)


def _lanes(z: np.ndarray) -> list[np.ndarray]:
    """Four straight lanes, at depths z, on a level road HEIGHT below a camera pitched down by
    PITCH (optical frame)."""
    turn = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(PITCH), -np.sin(PITCH)],
                     [0.0, np.sin(PITCH), np.cos(PITCH)]])  # level frame -> pitched optical
    return [np.column_stack([np.full_like(z, x0), np.full_like(z, HEIGHT), z]) @ turn.T
            for x0 in LANE_X]


def _cells(road: RoadPlane, rows: int = 40) -> tuple[np.ndarray, ...]:
    """Pixels (u, v) of the four lanes from 4 to 50 m, their depth on `road`, their lane."""
    points = np.concatenate(_lanes(np.geomspace(4.0, 50.0, rows)))
    u = CAMERA.focal * points[:, 0] / points[:, 2] + CAMERA.cx
    v = CAMERA.focal * points[:, 1] / points[:, 2] + CAMERA.cy
    return u, v, road.depth(u, v, CAMERA), np.repeat(np.arange(len(LANE_X)), rows)


def test_lanes_of_one_row_meet_half_way_and_true_depths_stay():
    level = RoadPlane.level(HEIGHT, PITCH)
    u, v, truth, lane = _cells(level)
    weight = np.full(len(u), 0.9)
    np.testing.assert_allclose(shared_row_depth(truth, u, v, weight, CAMERA), truth, rtol=1e-6)
    # a road sloping sideways (crossfall, or a camera rolled): depth changes along the row
    tilted = RoadPlane(tuple(np.array([0.05, 0.998, 0.035]) / np.linalg.norm(
        [0.05, 0.998, 0.035])), HEIGHT)
    tilted_truth = tilted.depth(u, v, CAMERA)
    np.testing.assert_allclose(shared_row_depth(tilted_truth, u, v, weight, CAMERA),
                               tilted_truth, rtol=1e-6)

    scattered = truth * np.asarray(SCATTER)[lane]
    pulled = shared_row_depth(scattered, u, v, weight, CAMERA)
    before, after = np.abs(scattered / truth - 1), np.abs(pulled / truth - 1)
    assert np.median(before) > 0.05
    assert np.median(after) < 0.6 * np.median(before)
    for i in range(len(LANE_X)):  # half way to the mean of the row's lanes
        np.testing.assert_allclose(pulled[lane == i] / truth[lane == i],
                                   0.5 * (SCATTER[i] + np.mean(SCATTER)), atol=0.01)


def test_too_few_cells_or_only_far_ones_keep_their_depths():
    u, v, truth, lane = _cells(RoadPlane.level(HEIGHT, PITCH), rows=6)
    scattered = truth * np.asarray(SCATTER)[lane]
    weight = np.full(len(u), 0.9)
    assert len(u) < MIN_CELLS
    np.testing.assert_array_equal(shared_row_depth(scattered, u, v, weight, CAMERA), scattered)
    far = np.full(40, 70.0)  # beyond the depths a profile is fitted to
    np.testing.assert_array_equal(
        shared_row_depth(far, np.full(40, CAMERA.cx), CAMERA.cy + np.arange(40.0), np.ones(40),
                         CAMERA), far)


def test_decoded_lanes_lie_nearer_their_true_place_with_the_profile():
    lanes = _lanes(np.linspace(3.0, 60.0, 1000))
    targets = lane_targets(lanes, CAMERA)
    shift, scale = row_statistics(targets.depth[None], targets.depth_mask[None])
    cfg = dataclasses.replace(SaladConfig(camera=CAMERA), row_shift=tuple(shift),
                              row_scale=tuple(scale))
    depth = targets.depth.copy()  # each lane's cells off by the lane's own share
    for lane, share in zip(lanes, SCATTER):
        own = lane_targets([lane], CAMERA)
        depth = np.where(own.seg > 0, own.depth * share, depth)
    maps = targets.seg * 0.9, np.concatenate([targets.offsets, cfg.depth_residual(depth)[None]])
    trees = [cKDTree(lane) for lane in lanes]

    def error(decoded: list[np.ndarray]) -> float:
        points = np.concatenate(decoded)
        return float(np.mean([min(t.query(p)[0] for t in trees) for p in points]))

    raw, _ = decode(*maps, cfg, road_profile=False)
    pulled, _ = decode(*maps, cfg)
    assert len(raw) == len(pulled) == 4
    assert error(pulled) < 0.7 * error(raw)  # 0.15 against 0.24 m when written
