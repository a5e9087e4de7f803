"""BEV encoding: rasteriser channel formulas, window geometry and the rolling grid."""
from __future__ import annotations

import math
import multiprocessing

import numpy as np
import pytest

from fhld_ros import bev
from fhld_ros.bev import BevSpec, rasterize
from fhld_ros.commands import bench_stages
from fhld_ros.intensity import normalize_intensity
from fhld_ros.rolling_grid import RollingBevGrid

SPEC = BevSpec()
EMPTY = np.array([0.0, 0.0, 0.0, bev.EMPTY_MIN_HEIGHT], dtype=np.float32)


def pose(x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw: float = 0.0, roll: float = 0.0,
         pitch: float = 0.0) -> np.ndarray:
    """4x4 sensor->output transform, R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    T = np.eye(4)
    T[:3, :3] = (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
                 @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
                 @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))
    T[:3, 3] = (x, y, z)
    return T


def to_sensor(points_output: np.ndarray, T: np.ndarray) -> np.ndarray:
    return ((points_output - T[:3, 3]) @ T[:3, :3]).astype(np.float32)


def reference_raster(xyz: np.ndarray, inten: np.ndarray, spec: BevSpec) -> np.ndarray:
    """Straightforward per-cell implementation of the documented formulas (float64)."""
    cells: dict[tuple[int, int], list[tuple[float, float]]] = {}
    half = spec.length_m / 2
    for (x, y, z), i in zip(xyz.astype(np.float64), inten.astype(np.float64)):
        if not (np.isfinite([x, y, z, i]).all() and -half <= x < half and -half <= y < half):
            continue
        key = (int((y + half) // spec.resolution_m), int((x + half) // spec.resolution_m))
        cells.setdefault(key, []).append((z, i))
    out = np.tile(EMPTY.astype(np.float64)[:, None, None], (1, spec.size_px, spec.size_px))
    for (row, col), values in cells.items():
        z, i = np.array(values).T
        out[0, row, col] = i.mean()
        out[1, row, col] = min(math.log1p(len(z)) / math.log1p(bev.DENSITY_REF_COUNT), 1.0)
        out[2, row, col] = min(z.var() / bev.HEIGHT_VAR_REF_M2, 1.0)
        out[3, row, col] = np.clip((z.min() - bev.MIN_HEIGHT_LOW_M)
                                   / (bev.MIN_HEIGHT_HIGH_M - bev.MIN_HEIGHT_LOW_M), 0, 1)
    return out


def assert_empty(raster: np.ndarray, spec: BevSpec = SPEC) -> None:
    assert raster.shape == (4, spec.size_px, spec.size_px) and raster.dtype == np.float32
    np.testing.assert_array_equal(raster, np.broadcast_to(EMPTY[:, None, None], raster.shape))


# --- geometry -------------------------------------------------------------------------------

def test_spec_conventions():
    assert SPEC.size_px == 640 and SPEC.resolution_m == 0.04
    assert SPEC.length_m == pytest.approx(25.6)
    np.testing.assert_allclose(SPEC.world_to_pixel([[-12.8, -12.8], [0.0, 0.0], [5.0, -2.0]]),
                               [[0, 0], [320, 320], [445, 270]], atol=1e-9)
    np.testing.assert_allclose(SPEC.pixel_to_world([[320.5, 0.5]]), [[0.02, -12.78]])
    pts = np.random.default_rng(1).uniform(-12.8, 12.8, (50, 2))
    np.testing.assert_allclose(SPEC.pixel_to_world(SPEC.world_to_pixel(pts)), pts, atol=1e-12)
    assert SPEC.world_to_pixel(np.zeros((3, 2), np.float32)).dtype == np.float32
    with pytest.raises(ValueError):
        BevSpec(size_px=0)


# --- intensity normalisation ----------------------------------------------------------------

@pytest.mark.parametrize('raw, scale', [
    (np.linspace(0.0, 1.0, 1000, dtype=np.float32), 1.0),  # 0-1 float sensor
    (np.linspace(0.0, 255.0, 1000, dtype=np.float32), 255.0),  # Velodyne-style float
    (np.arange(1000, dtype=np.uint16) % 256, 255.0),  # Ouster calibrated reflectivity
    (np.arange(1000, dtype=np.uint16) * 60, 65535.0),  # raw 16-bit signal
])
def test_normalize_intensity_picks_full_scale(raw, scale):
    out = normalize_intensity(raw)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, raw.astype(np.float64) / scale, rtol=1e-6, atol=1e-7)


def test_normalize_intensity_ignores_rare_outliers_and_bad_values():
    raw = np.full(10000, 0.5, dtype=np.float32)
    raw[:5] = 40.0  # 0.05 % retro-reflector spikes: scale stays 1, spikes clip to 1
    raw[5] = np.nan
    out = normalize_intensity(raw)
    assert out[:5].tolist() == [1.0] * 5 and out[5] == 0.0 and np.all(out[6:] == 0.5)
    np.testing.assert_allclose(normalize_intensity(np.array([10.0, 300.0]), scale=255.0),
                               [10 / 255, 1.0])
    assert normalize_intensity(np.zeros(0)).shape == (0,)
    with pytest.raises(ValueError):
        normalize_intensity(np.ones(3), scale=0.0)


# --- rasteriser -----------------------------------------------------------------------------

def test_channels_exact_on_hand_computed_cloud():
    # cell (row 320, col 320): three points; cell (445, 0): one high point; cell (0, 639): 20
    pts = np.array([[0.02, 0.01, -1.5], [0.03, 0.02, -1.9], [0.001, 0.039, -2.0],
                    [-12.78, 5.0, 2.0]] + [[12.79, -12.79, -5.0 + 0.1 * k] for k in range(20)])
    inten = np.array([0.2, 0.4, 0.9, 1.0] + [0.25] * 20)
    raster = rasterize(pts, inten)
    assert raster.shape == (4, 640, 640) and raster.dtype == np.float32
    assert raster.flags.c_contiguous
    a = raster[:, 320, 320]
    np.testing.assert_allclose(a, [0.5, math.log(4) / math.log(17), (0.14 / 3) / 0.1,
                                   (-2.0 + 3.0) / 4.0], rtol=1e-5, atol=1e-6)
    b = raster[:, 445, 0]  # x = -12.78 -> col 0, y = 5 -> row 445; z above the range -> 1
    np.testing.assert_allclose(b, [1.0, math.log(2) / math.log(17), 0.0, 1.0], atol=1e-6)
    c = raster[:, 0, 639]  # 20 points saturate density; var of 0.1 steps = 0.3325 -> 1
    np.testing.assert_allclose(c, [0.25, 1.0, 1.0, 0.0], atol=1e-6)
    occupied = raster[1] > 0
    assert occupied.sum() == 3
    np.testing.assert_array_equal(raster[:, ~occupied], np.repeat(EMPTY[:, None], 640 ** 2 - 3,
                                                                  axis=1))


def test_rasterize_matches_reference_on_random_clouds():
    spec = BevSpec(size_px=8, resolution_m=0.5)
    rng = np.random.default_rng(7)
    for _ in range(20):
        n = int(rng.integers(0, 300))
        xyz = np.column_stack([rng.uniform(-2.5, 2.5, (n, 2)),
                               rng.normal(-1.8, 0.7, n)]).astype(np.float32)
        xyz[:, :2] = np.round(xyz[:, :2] * 8) / 8 + 1 / 16  # keep off cell boundaries
        inten = rng.uniform(0, 1, n).astype(np.float32)
        np.testing.assert_allclose(rasterize(xyz, inten, spec),
                                   reference_raster(xyz, inten, spec), atol=2e-5)


def test_every_band_sums_its_cells_points_in_the_order_they_came():
    # float32 sums depend on the order of their terms: each thread's band of rows must add a
    # cell's points in the order of the sweeps and points, as one pass (and numpy's add.at) does
    spec = BevSpec(size_px=6, resolution_m=1.0)
    rng = np.random.default_rng(3)
    sweeps = []
    for _ in range(3):
        n = 2000
        xy = rng.uniform(-3.5, 3.5, (2, n)).astype(np.float32)  # some outside: border cells
        e = (rng.normal(0, 1, n) * 10.0 ** rng.integers(-4, 4, n)).astype(np.float32)
        affine = bev.window_affine(math.cos(0.3), math.sin(0.3), rng.uniform(-1, 1, 3), spec)
        sweeps.append((xy, affine, rng.uniform(0, 1, n).astype(np.float32), e))
    side = spec.size_px + 2
    sums, e_min = np.zeros((side * side, 4), np.float32), np.full(side * side, np.inf, np.float32)
    for xy, affine, inten, e in sweeps:
        pix = np.clip(bev.pixel_coords(xy, affine), 0, side - 1).astype(np.intp)
        cells = pix[1] * side + pix[0]
        for k, values in enumerate((np.ones_like(e), inten, e, e * e)):
            np.add.at(sums[:, k], cells, values)
        np.minimum.at(e_min, cells, e)
    rasters = []
    for threads in (1, 2, 3, bev.MAX_RASTER_THREADS):
        acc = bev.RasterAccumulator(spec, threads=threads)
        acc.add_all(sweeps)
        np.testing.assert_array_equal(acc.sums, sums)
        np.testing.assert_array_equal(acc.e_min, e_min)
        rasters.append(acc.encode(-1.8))
    for raster in rasters[1:]:
        np.testing.assert_array_equal(raster, rasters[0])


def test_non_finite_pixels_land_in_the_border_not_outside_the_arrays():
    # the grid drops non-finite points, but a finite coordinate near float32's limit still
    # overflows in the pixel mapping: inf - inf is NaN, which must not index memory
    spec = BevSpec(size_px=4, resolution_m=1.0)
    big = np.float32(3e38)
    xy = np.array([[np.nan, 1.0, np.inf, -np.inf, big, 0.5],
                   [0.0, np.nan, -np.inf, np.inf, big, 0.5]], dtype=np.float32)
    affine = bev.window_affine(math.cos(0.5), math.sin(0.5), np.zeros(3), spec)
    acc = bev.RasterAccumulator(spec)
    acc.add(xy, affine, np.full(6, 0.5, np.float32), np.zeros(6, np.float32))
    counts = acc.sums[:, 0].reshape(6, 6)
    assert counts.sum() == 6 and counts[1:-1, 1:-1].sum() == 1  # only the finite point inside


def test_raster_threads_are_bounded():
    for threads in (0, bev.MAX_RASTER_THREADS + 1):
        with pytest.raises(ValueError, match='threads must be 1'):
            bev.RasterAccumulator(SPEC, threads=threads)


def test_a_forked_child_rasters_with_threads_of_its_own():
    # the band threads of the parent do not exist in a fork (training's data workers): the
    # child must start its own instead of queueing its bands for threads that are gone
    grid = RollingBevGrid(SPEC)
    grid.insert(0, np.array([[1.0, 0.0, -1.8]]), np.array([0.5]), np.eye(4))
    expected = grid.window().raster
    ctx = multiprocessing.get_context('fork')
    with ctx.Pool(1) as pool:
        child = pool.apply_async(_window_raster, (grid,)).get(timeout=60)
    np.testing.assert_array_equal(child, expected)


def _window_raster(grid: RollingBevGrid) -> np.ndarray:
    return grid.window().raster


def test_points_outside_window_or_non_finite_are_ignored():
    h = SPEC.length_m / 2
    bad = np.array([[h, 0, -1.8], [-h - 0.01, 0, -1.8], [0, h, -1.8], [0, -h - 1e-3, -1.8],
                    [1e30, 0, 0], [np.nan, 0, -1.8], [0, np.inf, -1.8], [0, 0, np.nan],
                    [1.0, 1.0, -1.8]])
    inten = np.array([0.5] * 8 + [np.nan])
    assert_empty(rasterize(bad, inten))
    edge = rasterize(np.array([[-h, -h, -1.8], [h - 1e-4, h - 1e-4, -1.8]]), [0.5, 0.5])
    assert edge[1, 0, 0] > 0 and edge[1, 639, 639] > 0 and (edge[1] > 0).sum() == 2


def test_empty_inputs_give_valid_rasters():
    assert_empty(rasterize(np.zeros((0, 3)), np.zeros(0)))
    grid = RollingBevGrid()
    assert grid.window() is None and len(grid) == 0
    grid.insert(1, np.zeros((0, 3), np.float32), np.zeros(0), np.eye(4))
    win = grid.window()
    assert_empty(win.raster)
    assert win.points_window.shape == (0, 3) and win.intensity.shape == (0,)
    grid.insert(2, np.array([[100.0, 0, 0]], np.float32), [1.0], np.eye(4))  # all outside
    assert_empty(grid.window().raster)
    with pytest.raises(ValueError):
        rasterize(np.zeros((3, 3)), np.zeros(2))


# --- rolling grid ---------------------------------------------------------------------------

def trajectory(n: int, start=(3.0e5, -2.0e5, 50.0)) -> list[np.ndarray]:
    """Poses driving and turning far from the odometry origin, with some roll/pitch/climb."""
    return [pose(start[0] + 1.5 * k * math.cos(0.1 * k), start[1] + 1.5 * k * math.sin(0.1 * k),
                 start[2] + 0.3 * k, yaw=0.8 + 0.15 * k, roll=0.02 * math.sin(k),
                 pitch=-0.03 * math.cos(k)) for k in range(n)]


def yaw_frame(T: np.ndarray) -> np.ndarray:
    """The expected window frame of a sensor pose: its position, heading only."""
    W = pose(*T[:3, 3], yaw=math.atan2(T[1, 0], T[0, 0]))
    return W


def test_world_fixed_points_stay_put_as_ego_moves_and_turns():
    poses = trajectory(10)
    ego_window = yaw_frame(poses[-1])
    rng = np.random.default_rng(3)
    # 30 distinct cells of the final window; world points at their centres, about road height
    flat = rng.choice(np.arange(40, 600) * 640 + 300, 30, replace=False) \
        + rng.integers(-250, 250, 30)
    cells = np.column_stack([flat // 640, flat % 640])  # (row, col)
    local = np.column_stack([SPEC.pixel_to_world(cells[:, ::-1] + 0.5),
                             rng.uniform(-2, -1.6, 30)])
    world = local @ ego_window[:3, :3].T + ego_window[:3, 3]
    grid = RollingBevGrid(accumulate_sec=10.0, max_sweeps=10)
    for k, T in enumerate(poses):
        assert grid.insert(k * 100_000_000, to_sensor(world, T), np.full(30, 100.0), T) is False
    assert len(grid) == 10
    win = grid.window()
    assert win.stamp_ns == 900_000_000
    np.testing.assert_allclose(win.window_to_output, ego_window, atol=1e-12)
    np.testing.assert_allclose(win.to_window(world), local, atol=1e-9)
    # every sweep put each world point into its cell: 30 cells with 10 points each
    raster = win.raster
    occupied = raster[1] > 0
    assert {tuple(c) for c in np.argwhere(occupied)} == {tuple(c) for c in cells}
    rows, cols = cells.T
    np.testing.assert_allclose(raster[1, rows, cols], math.log(11) / math.log(17), rtol=1e-6)
    np.testing.assert_allclose(raster[0, rows, cols], 100 / 255, rtol=1e-6)
    # float32 sums: variance is exact to ~1e-6 m^2 (1e-5 here) for heights near the road
    np.testing.assert_allclose(raster[2, rows, cols], 0.0, atol=1e-4)
    np.testing.assert_allclose(raster[3, rows, cols], (local[:, 2] + 3.0) / 4.0, atol=1e-5)
    # the accumulated points: all 300 inside, each on its world point (sub-millimetre)
    pts = win.to_output(win.points_window)
    assert pts.shape == (300, 3) and win.intensity.shape == (300,)
    assert np.linalg.norm(pts[:, None] - world[None], axis=2).min(axis=1).max() < 1e-3


def test_window_outline_and_frame_transforms():
    T = pose(10.0, -4.0, 1.5, yaw=math.pi / 2, roll=0.1)
    grid = RollingBevGrid()
    local = np.array([[5.02, 0.02, -1.8]])  # on the road 5 m ahead along the heading
    world = local @ yaw_frame(T)[:3, :3].T + T[:3, 3]
    grid.insert(0, to_sensor(world, T), [0.5], T)
    win = grid.window()
    np.testing.assert_allclose(win.to_window(world), local, atol=1e-9)
    assert np.argwhere(win.raster[1] > 0).tolist() == [[320, 445]]  # x -> column, y -> row
    np.testing.assert_allclose(win.outline[0], win.outline[-1])  # closed
    np.testing.assert_allclose(win.outline[:4], [[22.8, -16.8, 1.5], [22.8, 8.8, 1.5],
                                                 [-2.8, 8.8, 1.5], [-2.8, -16.8, 1.5]],
                               atol=1e-9)
    p = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_allclose(win.to_window(win.to_output(p)), p, atol=1e-12)


def test_window_raster_matches_rasterize_of_its_points():
    rng = np.random.default_rng(5)
    grid = RollingBevGrid()
    for k, T in enumerate(trajectory(4, start=(20.0, 5.0, 0.0))):
        pts = rng.uniform(-15, 15, (3000, 3)).astype(np.float32)
        pts[:, 2] = rng.normal(-1.8, 0.4, 3000)
        grid.insert(k * 50_000_000, pts, rng.uniform(0, 255, 3000), T)
    win = grid.window()
    again = rasterize(win.points_window, win.intensity)
    differ = np.abs(again - win.raster).max(axis=0) > 1e-4
    assert (win.raster[1] > 0).sum() > 5000
    assert differ.sum() <= 10  # only points within float rounding of a cell boundary


def insert_marker_sweeps(grid: RollingBevGrid, stamps_s: list[float]) -> None:
    """Sweep k holds one point at x = k + 0.5 m (cell column 320 + 25 k + 12)."""
    for k, t in enumerate(stamps_s):
        grid.insert(round(t * 1e9), np.array([[k + 0.5, 0.0, -1.8]], np.float32), [0.5],
                    np.eye(4))


def marker_columns(grid: RollingBevGrid) -> list[int]:
    return sorted(int(c) for c in np.nonzero(grid.window().raster[1, 320])[0])


def test_eviction_by_age_and_count():
    grid = RollingBevGrid(accumulate_sec=0.3, max_sweeps=10)
    insert_marker_sweeps(grid, [0.0, 0.1, 0.2, 0.3, 0.4, 0.45])
    assert len(grid) == 4  # ages 0.25, 0.15, 0.05 and 0 s are < 0.3 s
    assert marker_columns(grid) == [320 + 25 * k + 12 for k in (2, 3, 4, 5)]
    grid = RollingBevGrid(accumulate_sec=0.3, max_sweeps=10)
    insert_marker_sweeps(grid, [0.0, 0.1, 0.2, 0.3])
    assert len(grid) == 3  # age exactly 0.3 s: evicted
    grid = RollingBevGrid(accumulate_sec=100.0, max_sweeps=3)
    insert_marker_sweeps(grid, [0.0, 0.1, 0.2, 0.3, 0.4, 0.5])
    assert len(grid) == 3
    assert marker_columns(grid) == [320 + 25 * k + 12 for k in (3, 4, 5)]


def test_time_going_backwards_resets():
    grid = RollingBevGrid(accumulate_sec=10.0)
    insert_marker_sweeps(grid, [5.0, 5.1, 5.2])
    assert grid.insert(round(5.2e9), np.zeros((1, 3), np.float32), [0.5], np.eye(4)) is False
    assert len(grid) == 4  # equal stamp: not a jump
    assert grid.insert(round(1e9), np.array([[2.5, 0, -1.8]], np.float32), [0.5],
                       np.eye(4)) is True  # bag loop
    assert len(grid) == 1 and grid.window().stamp_ns == round(1e9)
    assert marker_columns(grid) == [320 + 62]
    assert grid.insert(round(50e9), np.zeros((0, 3), np.float32), [], np.eye(4)) is False
    assert len(grid) == 1  # a forward jump just ages everything out
    grid.reset()
    assert len(grid) == 0 and grid.window() is None


def test_insert_drops_non_finite_and_validates():
    grid = RollingBevGrid()
    pts = np.array([[1.0, 0, -1.8], [np.nan, 0, -1.8], [2.0, np.inf, -1.8], [3.0, 0, -1.8]],
                   np.float32)
    grid.insert(0, pts, np.array([0.5, 0.5, 0.5, np.nan]), np.eye(4))
    assert grid.window().points_window.shape == (1, 3)
    with pytest.raises(ValueError):
        grid.insert(1, pts, np.zeros(3), np.eye(4))
    with pytest.raises(ValueError):
        grid.insert(1, pts, np.zeros(4), np.eye(3))
    with pytest.raises(ValueError):
        RollingBevGrid(max_sweeps=0)


def test_intensity_scales_give_comparable_rasters():
    pts = np.array([[1.0, 1.0, -1.8], [2.0, 1.0, -1.8]], np.float32)
    rasters = []
    for raw in (np.array([0.2, 0.6], np.float32), np.array([51.0, 153.0], np.float32),
                np.array([51, 153], np.uint16)):
        grid = RollingBevGrid()
        grid.insert(0, pts, raw, np.eye(4))
        rasters.append(grid.window().raster)
    np.testing.assert_allclose(rasters[1], rasters[0], atol=1e-6)
    np.testing.assert_allclose(rasters[2], rasters[0], atol=1e-6)


def test_heights_survive_large_climbs():
    # the sensor climbs 270 m over the held sweeps (the grid re-bases its height reference);
    # two world points 10 cm apart in height, seen by every sweep: exact variance and min
    grid = RollingBevGrid(accumulate_sec=100.0, max_sweeps=10)
    world = np.array([[2.0, 0.02, 269.0], [2.01, 0.02, 269.1]])
    for k in range(10):
        T = pose(0.1 * k, 0.0, 30.0 * k, pitch=0.01 * k)
        grid.insert(k, to_sensor(world, T), [1.0, 1.0], T)
    win = grid.window()
    assert np.argwhere(win.raster[1] > 0).tolist() == [[320, 347]]  # window x = 1.1 m
    np.testing.assert_allclose(win.raster[:, 320, 347],
                               [1.0, 1.0, 0.05 ** 2 / 0.1, (-1.0 + 3.0) / 4.0], atol=1e-5)
    np.testing.assert_allclose(win.points_window, [[1.1, 0.02, -1.0], [1.11, 0.02, -0.9]] * 10,
                               atol=1e-4)


def test_bench_reports_timings():
    result = bench_stages.bench_bev()
    assert {'grid_insert_ms', 'raster_ms', 'raster_points'} <= set(result)
    assert all(isinstance(v, float) and v > 0 for v in result.values())
