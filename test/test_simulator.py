"""Simulator core: determinism, GT on the surface, paint on the GT lines, topology coverage,
lines per window, ego motion, worn and missing paint, and training samples through the node's
input path."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fhld_ros.bev import BevSpec
from fhld_ros.data.samples import paint_contrast, training_samples
from fhld_ros.intensity import normalize_intensity
from fhld_ros.sim.layout import MAX_LINES_PER_WINDOW, TOPOLOGIES, max_lines_per_window
from fhld_ros.sim.scene import GROUND_MATERIALS, PAINT
from fhld_ros.sim.simulator import Simulator


def world_points(sweep) -> tuple[np.ndarray, np.ndarray]:
    """Returned points of a (not motion-distorted) sweep in the odom frame, and their mask."""
    p = sweep.points
    xyz = np.stack([p[a] for a in 'xyz'], axis=1).astype(np.float64)
    ok = np.isfinite(xyz).all(axis=1) & (np.abs(xyz).sum(axis=1) > 0)
    pose = sweep.sensor_to_odom
    return xyz @ pose[:3, :3].T + pose[:3, 3], ok


def intensity01(sweep) -> np.ndarray:
    p = sweep.points
    return normalize_intensity(p['intensity' if 'intensity' in p.dtype.names else 'reflectivity'])


def dense(lines: list[np.ndarray], step: float = 0.02) -> np.ndarray:
    """Polylines resampled every `step` metres (for nearest-point queries)."""
    out = []
    for line in lines:
        seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
        for a, b, n in zip(line[:-1], line[1:], np.maximum(1, np.ceil(seg / step).astype(int))):
            out.append(a + np.linspace(0, 1, n, endpoint=False)[:, None] * (b - a))
        out.append(line[-1:])
    return np.concatenate(out)


def test_same_seed_same_run_in_any_order() -> None:
    a = Simulator(5, sweeps=3, sensor='os1-32', columns=256)
    b = Simulator(5, sweeps=8, sensor='os1-32', columns=256)  # a longer run starts the same
    late = a.sweep(2)  # random access first: must not depend on what was generated before
    seq = [b.sweep(k) for k in range(3)]
    assert late.points.tobytes() == seq[2].points.tobytes()
    assert a.sweep(0).points.tobytes() == seq[0].points.tobytes()
    assert np.array_equal(late.labels, seq[2].labels)
    assert all(np.array_equal(x, y) for x, y in zip(a.scene.lane_lines, b.scene.lane_lines))
    assert np.array_equal(a.true_poses, b.true_poses[:3])
    c = Simulator(6, sweeps=3, sensor='os1-32', columns=256)
    assert c.sweep(0).points.tobytes() != seq[0].points.tobytes()


def test_gt_lies_on_the_simulated_surface() -> None:
    sim = Simulator(2, sweeps=2, sensor='os1-64', columns=512, noise=False)
    scene = sim.scene
    assert scene.lane_lines
    gt = np.concatenate(scene.lane_lines)
    s, d = scene.ref.project(gt[:, :2])
    assert np.median(np.abs(gt[:, 2] - scene.surface.height(s, d))) < 0.01
    # the ray-cast ground under the lines is at the GT height
    samples = dense(scene.lane_lines)
    tree = cKDTree(samples[:, :2])
    dz = []
    for k in range(2):
        sweep = sim.sweep(k)
        world, ok = world_points(sweep)
        ground = world[ok & np.isin(sweep.labels, GROUND_MATERIALS)]
        dist, idx = tree.query(ground[:, :2])
        near = dist < 0.05
        dz.append(ground[near, 2] - samples[idx[near], 2])
    dz = np.concatenate(dz)
    assert dz.size > 200
    assert np.median(np.abs(dz)) < 0.01


@pytest.mark.slow
def test_bright_ground_points_concentrate_on_gt_lines() -> None:
    """>= 80 % of paint returns (high intensity, on the ground) within 10 cm of a GT line,
    over several scenes with noise on; crosswalks, arrows and text are the rest."""
    bright_in = bright_all = paint_in = paint_all = 0
    for seed in range(6):
        sim = Simulator(seed, sweeps=12, sensor='os1-64', columns=512)
        if not sim.scene.lane_lines:  # unmarked road
            continue
        tree = cKDTree(dense(sim.scene.lane_lines))
        for k in (0, 11):
            sweep = sim.sweep(k)
            world, ok = world_points(sweep)
            s, d = sim.scene.ref.project(world[:, :2])
            on_ground = np.abs(world[:, 2] - sim.scene.surface.height(s, d)) < 0.1
            bright = ok & on_ground & (intensity01(sweep) > 0.35)
            dist, _ = tree.query(world[bright])
            bright_in += int((dist < 0.1).sum())
            bright_all += int(bright.sum())
            dist, _ = tree.query(world[sweep.labels == PAINT])
            paint_in += int((dist < 0.1).sum())
            paint_all += int(dist.size)
    assert bright_all > 800 and paint_all > 800
    assert bright_in / bright_all >= 0.8
    assert paint_in / paint_all >= 0.8


def _lines_at(layout, s: float) -> int:
    row = int(layout.row(s))
    return sum(line.i0 <= row <= line.i1 for line in layout.lines)


@pytest.mark.slow
def test_every_topology_appears_across_seeds() -> None:
    seen: dict[str, int] = {}
    for seed in range(40):
        layout = Simulator(seed, sweeps=100).scene.layout
        assert max_lines_per_window(layout) <= MAX_LINES_PER_WINDOW
        first_s, last_s = layout.s[0] + 10, layout.s[-1] - 10
        for event in layout.events:
            seen[event.kind] = seen.get(event.kind, 0) + 1
            before, after = event.s_start - 5.0, event.s_end + 5.0
            if before < first_s or after > last_s or not layout.style.marked:
                continue
            change = _lines_at(layout, after) - _lines_at(layout, before)
            if event.kind in ('split', 'lane_added'):
                assert change == 1, (seed, event)
            elif event.kind in ('merge', 'lane_dropped'):
                assert change == -1, (seed, event)
            else:  # ramps: two more lines (gore edges) while the ramp is beside the road
                mid = max(_lines_at(layout, s) for s in np.linspace(before, after, 40))
                assert change == 0 and mid >= _lines_at(layout, before) + 1, (seed, event)
    assert set(seen) == set(TOPOLOGIES)


def test_forced_topology_and_unmarked_roads() -> None:
    sim = Simulator(1, sweeps=50, topology='exit_ramp')
    assert sim.scene.road_class == 'highway'
    assert sim.scene.events[0].kind == 'exit_ramp'
    unmarked = [seed for seed in range(30)
                if not Simulator(seed, sweeps=10, road='rural').scene.lane_lines]
    assert unmarked  # some rural roads carry no paint: windows with 0 lines


def test_ego_motion_and_odometry_drift() -> None:
    changes = 0
    for seed in range(6):
        sim = Simulator(seed, sweeps=200, sensor='os1-32', columns=256)
        speed = np.diff(sim.plan.s) / np.diff(sim.plan.times)
        assert speed.min() >= -1e-9 and speed.max() <= 30.0 + 1e-6
        changes += len(sim.plan.lane_changes)
        assert np.array_equal(sim.odom_poses, sim.true_poses)  # no drift unless asked
    assert changes > 0
    stopped = Simulator(3, sweeps=20, speed=0.0)
    assert np.allclose(stopped.true_poses[0], stopped.true_poses[-1])
    drift = Simulator(3, sweeps=100, odom_noise=1.0, speed=20.0)
    err = np.linalg.norm(drift.odom_poses[:, :3, 3] - drift.true_poses[:, :3, 3], axis=1)
    assert err[0] == 0.0 and 0.01 < err[-1] < 10.0
    again = Simulator(3, sweeps=100, odom_noise=1.0, speed=20.0)
    assert np.array_equal(drift.odom_poses, again.odom_poses)


def test_training_samples_follow_the_node_input_path() -> None:
    spec = BevSpec()
    sim = Simulator(3, sweeps=10, sensor='os1-64', columns=512, noise=False)
    samples = list(training_samples(sim, 2))
    assert len(samples) == 1  # 10 sweeps make one 1 s window
    sample = samples[0]
    assert sample.raster.shape == (4, spec.size_px, spec.size_px)
    assert sample.raster.dtype == np.float32
    assert 0.0 <= sample.raster.min() and sample.raster.max() <= 1.0
    assert sample.meta['sweeps'] == 10
    pose = sim.true_poses[9]
    assert np.allclose(sample.window_to_odom[:3, 3], pose[:3, 3])
    assert 1 <= len(sample.lanes) <= MAX_LINES_PER_WINDOW
    half = spec.length_m / 2
    for lane in sample.lanes:
        assert np.all(np.abs(lane[:, :2]) <= half + 1e-6)
        assert np.all(np.abs(lane[:, 2] + sim.mount.z) < 1.0)  # road below the sensor
    # bright cells of the raster lie on the GT lines
    rows, cols = np.nonzero((sample.raster[0] > 0.35) & (sample.raster[1] > 0))
    centres = spec.pixel_to_world(np.stack([cols + 0.5, rows + 0.5], axis=1))
    dist, _ = cKDTree(dense(sample.lanes)[:, :2]).query(centres)
    assert centres.shape[0] > 100
    assert np.mean(dist < 0.15) > 0.8


@pytest.mark.parametrize('sensor', ['os1-64', 'vlp32c'])  # uint16 reflectivity, raw 0-255
def test_worn_paint_is_the_same_scene_with_paint_at_most_its_contrast(sensor: str) -> None:
    fresh = Simulator(4, sweeps=1, sensor=sensor, columns=512)
    worn = Simulator(4, sweeps=1, sensor=sensor, columns=512, paint_contrast=2.5)
    assert all(np.array_equal(a, b) for a, b in zip(fresh.scene.lane_lines,
                                                    worn.scene.lane_lines))
    assert len(worn.scene.lane_lines) == len(fresh.scene.lane_lines) > 0
    f, w = fresh.sweep(0), worn.sweep(0)
    assert np.mean(w.labels == PAINT) > 0.5 * np.mean(f.labels == PAINT) > 0
    # median paint / median asphalt of the ground returns: ~10-30x fresh, <= 2.5x worn
    assert paint_contrast(f.points, f.labels) > 8.0
    assert 1.2 < paint_contrast(w.points, w.labels) <= 2.5


def test_no_markings_is_the_same_road_without_paint_or_gt() -> None:
    marked = Simulator(6, sweeps=10, sensor='os1-64', columns=512)
    bare = Simulator(6, sweeps=10, sensor='os1-64', columns=512, markings=False)
    assert marked.scene.lane_lines and marked.scene.paint.markings
    assert bare.scene.lane_lines == [] and bare.scene.paint.markings == []
    assert not bare.scene.layout.style.marked
    assert np.array_equal(bare.scene.layout.offsets, marked.scene.layout.offsets)
    assert np.array_equal(bare.true_poses, marked.true_poses)
    sweep = bare.sweep(9)
    assert not np.any(sweep.labels == PAINT) and np.any(marked.sweep(9).labels == PAINT)
    sample = next(training_samples(bare, 1))
    assert sample.lanes == [] and sample.meta['line_ids'] == []
    assert np.isnan(sample.meta['paint_contrast'])


def test_roads_without_edge_lines_keep_every_other_line() -> None:
    marked = Simulator(7, sweeps=1, sensor='os1-64', columns=512, road='urban')
    bare = Simulator(7, sweeps=1, sensor='os1-64', columns=512, road='urban', edge_lines=False)
    kinds = [ln.kind for ln in marked.scene.layout.lines]
    assert 'edge' in kinds and 'edge' not in [ln.kind for ln in bare.scene.layout.lines]
    inner = [k for k, kind in enumerate(kinds) if kind != 'edge']
    assert len(bare.scene.lane_lines) == len(inner) > 0
    assert all(np.array_equal(bare.scene.lane_lines[i], marked.scene.lane_lines[k])
               for i, k in enumerate(inner))
    assert np.array_equal(bare.true_poses, marked.true_poses)


def test_road_look_changes_the_pavement_only_where_asked() -> None:
    base = Simulator(7, sweeps=1, sensor='os1-64', columns=512, road='urban')
    look = Simulator(7, sweeps=1, sensor='os1-64', columns=512, road='urban', asphalt_rho=0.25,
                     gutter_ratio=2.0, seams=True)
    assert np.array_equal(base.true_poses, look.true_poses)
    assert all(np.array_equal(a, b) for a, b in zip(base.scene.lane_lines,
                                                    look.scene.lane_lines))
    d = np.arange(-15.0, 15.0, 0.01)
    s = np.full(d.shape, 40.0)
    mat0, rho0 = base.scene.surface.material(s, d)
    mat1, rho1 = look.scene.surface.material(s, d)
    assert np.array_equal(mat0, mat1)
    paved = np.flatnonzero(mat1 == 1)
    ratio = rho1[paved] / rho0[paved] * base.scene.surface.asphalt / 0.25
    width, _ = look.scene.surface.gutter
    edge = np.minimum(d[paved].max() - d[paved], d[paved] - d[paved].min())
    assert np.allclose(ratio[edge > width + 0.05].max(), 1.0)  # the pavement, brighter
    assert np.median(ratio[edge < width - 0.05]) == pytest.approx(2.0)  # gutters
    assert 0.002 < np.mean(ratio < 0.8) < 0.1  # seams: narrow dark stripes
    assert np.array_equal(rho0[mat0 != 1], rho1[mat1 != 1])  # sidewalks, terrain: the same


def test_tilted_mount_tilts_the_ground_in_the_sensor_frame() -> None:
    def ground_slopes(sim: Simulator) -> np.ndarray:
        sweep = sim.sweep(0)
        p = sweep.points
        xyz = np.stack([p[a] for a in 'xyz'], axis=1).astype(np.float64)
        near = (sweep.labels == 1) & (np.hypot(xyz[:, 0], xyz[:, 1]) < 15.0)
        a = np.c_[xyz[near, :2], np.ones(near.sum())]
        return np.linalg.lstsq(a, xyz[near, 2], rcond=None)[0][:2]  # dz/dx, dz/dy
    flat = ground_slopes(Simulator(3, sweeps=1, sensor='os1-64', columns=512, road='highway'))
    tilted = Simulator(3, sweeps=1, sensor='os1-64', columns=512, road='highway',
                       mount_pitch_deg=3.0, mount_roll_deg=-2.0)
    slope = ground_slopes(tilted) - flat
    assert slope == pytest.approx([np.tan(np.deg2rad(3.0)), np.tan(np.deg2rad(2.0))], abs=0.01)
    gt = tilted.scene.lane_lines  # GT stays in the world, the pose carries the tilt
    assert all(np.array_equal(a, b) for a, b in zip(gt, Simulator(
        3, sweeps=1, sensor='os1-64', columns=512, road='highway').scene.lane_lines))


def test_bad_options_raise_clear_errors() -> None:
    for kwargs, text in (({'sensor': 'bogus'}, 'unknown sensor'), ({'speed': 40.0}, 'speed'),
                         ({'columns': 8}, 'columns'), ({'topology': 'loop'}, 'topology'),
                         ({'intensity': 'dB'}, 'intensity'),
                         ({'paint_contrast': 0.5}, 'paint_contrast'),
                         ({'mount_roll_deg': 8.0}, 'pitch and roll'),
                         ({'asphalt_rho': 0.9}, 'asphalt_rho'), ({'gutter_ratio': 9}, 'gutter')):
        with pytest.raises(ValueError, match=text):
            Simulator(0, sweeps=1, **kwargs)
    with pytest.raises(ValueError, match='sweeps'):
        Simulator(0, sweeps=0)


def test_clip_to_square_cuts_exactly_and_splits_on_reentry() -> None:
    from fhld_ros.sim.gt_lines import clip_to_square
    # a zig-zag that leaves through y = +5 and comes back in
    line = np.array([[-8.0, 0.0, 0.0], [0.0, 8.0, 0.0], [8.0, 0.0, 1.0], [20.0, 0.0, 1.0]])
    pieces, src = clip_to_square([line, line[:1]], 5.0)
    assert src == [0, 0] and len(pieces) == 2
    a, b = pieces
    assert np.allclose(a[0], [-5.0, 3.0, 0.0]) and np.allclose(a[-1], [-3.0, 5.0, 0.0])
    assert np.allclose(b[0], [3.0, 5.0, 0.375]) and np.allclose(b[-1], [5.0, 3.0, 0.625])
    assert clip_to_square([line + [0.0, 30.0, 0.0]], 5.0) == ([], [])
