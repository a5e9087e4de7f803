"""Lane heights refined from the raster's measured surface (model/heights.py)."""
import numpy as np
import pytest

from fhld_ros.bev import BevSpec, min_height_m, rasterize
from fhld_ros.model.heights import refine_lane_heights, surface_heights

SPEC = BevSpec(size_px=200, resolution_m=0.04)  # 8 m window


def road_raster(z_of_x, rng, half=3.5, step=0.02, noise=0.0, extra=None):
    """A densely sampled road surface z(x) over the window, optionally plus extra points."""
    g = np.arange(-half, half, step)
    x, y = np.meshgrid(g, g)
    xyz = np.stack([x.ravel(), y.ravel(), z_of_x(x.ravel())], axis=1)
    xyz[:, 2] += rng.normal(0, noise, len(xyz)) if noise else 0.0
    if extra is not None:
        xyz = np.concatenate([xyz, extra])
    return rasterize(xyz, np.full(len(xyz), 0.5), SPEC)


def lane_along_x(z, y=1.0, n=60):
    x = np.linspace(-3.0, 3.0, n)
    return np.stack([x, np.full(n, y), np.full(n, z)], axis=1)


def test_min_height_decodes_the_channel_and_marks_empty_cells():
    xyz = np.array([[0.01, 0.01, -1.7], [0.02, 0.03, -1.9], [1.01, 1.01, -0.5]])
    surface = min_height_m(rasterize(xyz, np.zeros(3), SPEC))
    (c0, r0), (c1, r1) = np.floor(SPEC.world_to_pixel(xyz[[0, 2]])).astype(int)
    assert surface[r0, c0] == pytest.approx(-1.9, abs=1e-5)
    assert surface[r1, c1] == pytest.approx(-0.5, abs=1e-5)
    assert np.isnan(surface).sum() == surface.size - 2


def test_surface_heights_take_the_patch_median_and_nan_when_empty():
    xyz = [[0.01 + 0.04 * i, 0.01 + 0.04 * j, -1.8] for i in range(3) for j in range(3)]
    xyz[0][2] = 0.5  # one outlier cell does not move a median
    raster = rasterize(np.array(xyz), np.zeros(len(xyz)), SPEC)
    got = surface_heights(raster, np.array([[0.05, 0.05], [-3.0, -3.0]]), SPEC.resolution_m)
    assert got[0] == pytest.approx(-1.8, abs=1e-5)
    assert np.isnan(got[1])


def test_heights_follow_a_sloped_road_through_noise():
    rng = np.random.default_rng(0)
    slope = lambda x: -1.8 + 0.05 * x  # noqa: E731
    raster = road_raster(slope, rng, noise=0.01)
    lane = lane_along_x(-1.8 + 0.15)  # model heights 15 cm off and flat
    (out,) = refine_lane_heights([lane], raster, SPEC.resolution_m)
    np.testing.assert_array_equal(out[:, :2], lane[:, :2])
    # min of ~4 noisy points per cell sits ~1 sigma low; well inside a centimetre or two
    assert np.abs(out[:, 2] - slope(lane[:, 0])).max() < 0.025


def test_obstacles_far_from_the_predicted_height_are_gated_out():
    rng = np.random.default_rng(1)
    g = np.arange(0.0, 2.0, 0.02)
    car = np.stack(np.meshgrid(g, np.arange(0.5, 1.5, 0.02)), -1).reshape(-1, 2)
    # a car body 0.5 m above the road covers a third of the lane; its cells' minimum is the car
    car = np.concatenate([car, np.full((len(car), 1), -1.3)], axis=1)
    raster = road_raster(lambda x: np.full_like(x, -1.8), rng)
    raster_car = rasterize(car, np.zeros(len(car)), SPEC)
    raster[:, raster_car[1] > 0] = raster_car[:, raster_car[1] > 0]
    lane = lane_along_x(-1.75)
    (out,) = refine_lane_heights([lane], raster, SPEC.resolution_m)
    assert np.abs(out[:, 2] + 1.8).max() < 0.01


def test_lanes_without_surface_keep_the_model_heights():
    raster = rasterize(np.zeros((0, 3)), np.zeros(0), SPEC)
    lane = lane_along_x(-1.6)
    (out,) = refine_lane_heights([lane], raster, SPEC.resolution_m)
    np.testing.assert_array_equal(out, lane)
    assert refine_lane_heights([], raster, SPEC.resolution_m) == []
