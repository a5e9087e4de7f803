"""Intensity encodings: the contrast encoding reads paint against the sweep's own ground, so
sensor units and gain cancel; the ground it measures is local (any mount height or tilt)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numpy.lib import recfunctions

from fhld_ros.data.cache import TEST_SEED_BASE, CacheSettings, build_cache, scenario_for_seed
from fhld_ros.data.samples import training_samples
from fhld_ros.intensity import (
    ABSOLUTE,
    CONTRAST,
    CONTRAST_RINGS,
    GROUND_LEVEL,
    IntensityEncoder,
    ground_level,
    ground_mask,
    normalize_intensity,
)
from fhld_ros.intensity_rings import (
    RING_GAIN_RANGE,
    RING_GAP_DEG,
    RING_MAX_WIDTH_DEG,
    RING_MIN_POINTS,
    RING_MIN_RINGS,
    RING_MIN_SECTORS,
    RING_MIN_SHARE,
    RING_SAMPLE,
    RING_SECTORS,
    ring_gains,
)
from fhld_ros.parameters import DetectorParams
from fhld_ros.pipeline import LanePipeline
from fhld_ros.rolling_grid import RollingBevGrid
from fhld_ros.sim.simulator import Simulator
from msg_adapters.family import rosbags_family
from msg_adapters.pointcloud2 import create_cloud, read_xyzi, read_xyzir


def road_scene(rng: np.random.Generator, mount_z: float = 1.9, pitch_deg: float = 0.0
               ) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame points: a road plane (2 % of it paint, 6x brighter) seen from mount_z,
    pitched, plus a wall and a car roof that are brighter than the road."""
    xy = rng.uniform(-20, 20, (20000, 2))
    road = np.column_stack([xy, np.full(len(xy), -mount_z)])
    wall = np.column_stack([np.full(3000, 8.0), rng.uniform(-10, 10, 3000),
                            rng.uniform(-mount_z, 3.0, 3000)])
    roof = np.column_stack([rng.uniform(4, 8, (2000, 2)), np.full(2000, -mount_z + 1.5)])
    xyz = np.concatenate([road, wall, roof])
    p = np.deg2rad(pitch_deg)
    rot = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    xyz = (xyz @ rot.T).astype(np.float32)
    value = np.concatenate([rng.normal(10.0, 1.0, len(road)), np.full(3000, 40.0),
                            np.full(2000, 50.0)])
    value[:len(road) // 50] = 60.0  # paint
    return xyz, value


@pytest.mark.parametrize('mount_z,pitch_deg', [(1.4, 0.0), (1.9, 3.0), (2.5, -3.0)])
def test_ground_is_the_road_at_any_mount_height_and_tilt(mount_z, pitch_deg):
    xyz, value = road_scene(np.random.default_rng(0), mount_z, pitch_deg)
    mask = ground_mask(xyz)
    road = np.arange(len(xyz)) < 20000
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    assert mask[road & (r > 3) & (r < 19)].mean() > 0.97
    assert mask[~road].mean() < 0.03  # wall (bar its foot) and roof stay out
    assert ground_level(value[mask]) == pytest.approx(10.0, abs=0.6)  # paint stays out


def test_ground_level_of_few_dark_or_coarse_values():
    assert ground_level(np.ones(10)) is None  # too few
    assert ground_level(np.zeros(1000)) is None  # no intensity at all
    coarse = np.zeros(1000)
    coarse[::10] = 1.0  # a dark road in integer counts: 90 % zeros
    assert ground_level(coarse) == pytest.approx(0.1)


def test_contrast_encoding_is_the_same_at_any_gain_and_units():
    xyz, value = road_scene(np.random.default_rng(1))
    ref = IntensityEncoder(CONTRAST)(xyz, value)
    assert np.median(ref[:20000]) == pytest.approx(GROUND_LEVEL, rel=0.1)
    for gain in (0.25, 4.0, 1 / 255.0, 65535 / 255.0):
        np.testing.assert_allclose(IntensityEncoder(CONTRAST)(xyz, value * gain), ref,
                                   rtol=1e-4, atol=1e-6)
    counts = np.round(value).astype(np.uint16)  # integer counts: equal up to rounding
    np.testing.assert_allclose(IntensityEncoder(CONTRAST)(xyz, counts), ref, atol=0.01)
    absolute = IntensityEncoder(ABSOLUTE)
    assert not np.allclose(absolute(xyz, value * 4.0), absolute(xyz, value))


def test_a_sweep_without_ground_keeps_the_last_level():
    encoder = IntensityEncoder(CONTRAST)
    xyz, value = road_scene(np.random.default_rng(2))
    encoder(xyz, value)
    wall = xyz[20000:23000]
    out = encoder(wall, np.full(len(wall), 20.0))  # twice the road's level
    np.testing.assert_allclose(out, 2 * GROUND_LEVEL, rtol=0.1)
    with pytest.raises(ValueError, match='unknown intensity encoding'):
        IntensityEncoder('relative')


def test_simulated_windows_match_across_gain_and_units_in_contrast_encoding():
    def window(gain: float, units: str | None) -> np.ndarray:
        sim = Simulator(2_000_010, sweeps=2, sensor='hdl32e', intensity=units)
        sample = next(training_samples(sim, 1, sweeps_per_sample=2, intensity_gain=gain,
                                       intensity_encoding=CONTRAST))
        return sample.raster[0]
    base = window(1.0, 'float')
    np.testing.assert_allclose(window(3.0, 'float'), base, atol=1e-5)
    np.testing.assert_allclose(window(0.3, 'u8'), base, atol=0.02)
    assert abs(float(window(1.0, 'reflectivity').mean()) - float(base.mean())) < 0.2 * float(
        base.mean())


def test_pipeline_encodes_as_its_detector_asks():
    class ContrastDetector:
        intensity_encoding = CONTRAST

        def __call__(self, window):
            return [], np.zeros(0)
    params = DetectorParams(size_px=64, resolution_m=0.5)
    assert LanePipeline(params, ContrastDetector()).grid.encode_intensity.encoding == CONTRAST
    plain = LanePipeline(params, lambda window: ([], np.zeros(0)))
    assert plain.grid.encode_intensity.encoding == ABSOLUTE


def test_sensor_variation_draws_for_training_seeds_only():
    varied = CacheSettings(sensor_variation=True)
    scenarios = [scenario_for_seed(seed, varied) for seed in range(200)]
    assert scenarios == [scenario_for_seed(seed, varied) for seed in range(200)]  # seeded
    worn = [s['paint_contrast'] for s in scenarios if s['paint_contrast'] is not None]
    assert 0.45 < len(worn) / 200 < 0.75 and 1.6 <= min(worn) and max(worn) <= 8.0
    assert 0.1 < sum(s["single_sweep"] for s in scenarios) / 200 < 0.3
    assert {s['intensity'] for s in scenarios} == {None, 'reflectivity', 'float', 'u8'}
    assert any(not s['markings'] for s in scenarios)
    gains = [s['intensity_gain'] for s in scenarios]
    assert min(gains) < 0.5 and max(gains) > 2.0
    mounts = [s['mount_z'] for s in scenarios if s['mount_z'] is not None]
    assert 1.4 <= min(mounts) and max(mounts) <= 2.5
    # the same drift and distortion as without variation; the test set never varies
    plain = [scenario_for_seed(seed) for seed in range(200)]
    assert all(plain[k].items() <= scenarios[k].items() for k in range(200))
    for seed in range(TEST_SEED_BASE, TEST_SEED_BASE + 56):
        assert scenario_for_seed(seed, varied) == scenario_for_seed(seed)


def test_road_look_adds_pavements_and_tilt_to_the_same_draws():
    varied = CacheSettings(sensor_variation=True)
    looks = CacheSettings(sensor_variation=True, road_look=True)
    for seed in range(100):
        base, more = scenario_for_seed(seed, varied), scenario_for_seed(seed, looks)
        assert base.items() <= more.items()  # the older draws stay put
        assert set(more) - set(base) == {'asphalt_rho', 'gutter_ratio', 'seams',
                                         'mount_pitch_deg', 'mount_roll_deg'}
    scenarios = [scenario_for_seed(seed, looks) for seed in range(300)]
    for key in ('asphalt_rho', 'gutter_ratio', 'seams'):
        assert 0.2 < sum(bool(s[key]) for s in scenarios) / 300 < 0.5
    tilts = np.array([[s['mount_pitch_deg'], s['mount_roll_deg']] for s in scenarios])
    assert np.abs(tilts).max() <= 3.0 and 0.3 < np.mean(tilts[:, 0] != 0) < 0.7
    assert scenario_for_seed(TEST_SEED_BASE, looks) == scenario_for_seed(TEST_SEED_BASE)


def test_bare_curbs_draws_roads_without_edge_lines_and_leaves_the_rest():
    looks = CacheSettings(sensor_variation=True, road_look=True)
    bare = CacheSettings(sensor_variation=True, road_look=True, bare_curbs=True)
    scenarios = [scenario_for_seed(seed, bare) for seed in range(300)]
    for seed, more in enumerate(scenarios[:100]):
        base = scenario_for_seed(seed, looks)
        assert base.items() <= more.items() and set(more) - set(base) == {'edge_lines'}
    assert 0.4 < np.mean([not s['edge_lines'] for s in scenarios]) < 0.6
    assert scenario_for_seed(TEST_SEED_BASE, bare) == scenario_for_seed(TEST_SEED_BASE)


# each share: the key it sets, what it turns the key into, the default share's fraction
SHARE_KEYS = {'no_markings_share': ('markings', False, 0.2),
              'single_sweep_share': ('single_sweep', True, 0.2),
              'bright_asphalt_share': ('asphalt_rho', 'set', 0.35)}


@pytest.mark.parametrize('share', sorted(SHARE_KEYS))
def test_a_larger_share_changes_more_of_the_same_seeds_and_nothing_else(share, tmp_path):
    key, changed, default = SHARE_KEYS[share]
    bare = CacheSettings(sensor_variation=True, road_look=True, bare_curbs=True)
    more = dataclasses.replace(bare, **{share: 0.6})

    def hit(scenario: dict) -> bool:
        return scenario[key] is not None if changed == 'set' else scenario[key] == changed
    before = [scenario_for_seed(seed, bare) for seed in range(300)]
    after = [scenario_for_seed(seed, more) for seed in range(300)]
    for old, new in zip(before, after):  # only the share's key changes, and only towards it
        assert {k: v for k, v in old.items() if k != key} == \
            {k: v for k, v in new.items() if k != key}
        assert hit(new) >= hit(old)
        if changed == 'set' and hit(old):  # the value drawn stays put
            assert new[key] == old[key]
    assert default - 0.1 < np.mean([hit(s) for s in before]) < default + 0.1
    assert 0.5 < np.mean([hit(s) for s in after]) < 0.7
    assert scenario_for_seed(TEST_SEED_BASE, more) == scenario_for_seed(TEST_SEED_BASE)
    build_cache(tmp_path, [], bare, workers=1, progress=False)  # the index records the share
    with pytest.raises(ValueError, match='other settings'):
        build_cache(tmp_path, [], more, workers=1, progress=False)
    with pytest.raises(ValueError, match=share):
        dataclasses.replace(bare, **{share: 1.5}).validate()


def test_worn_paint_share_and_max_change_only_the_paint(tmp_path):
    base = CacheSettings(sensor_variation=True, road_look=True, bare_curbs=True)
    worn = dataclasses.replace(base, worn_paint_share=0.9, worn_paint_max=3.0)
    before = [scenario_for_seed(seed, base) for seed in range(300)]
    after = [scenario_for_seed(seed, worn) for seed in range(300)]
    for old, new in zip(before, after):
        assert {k: v for k, v in old.items() if k != 'paint_contrast'} == \
            {k: v for k, v in new.items() if k != 'paint_contrast'}
        if old['paint_contrast'] is not None:  # worn before: worn after, no brighter
            assert 1.6 <= new['paint_contrast'] <= min(old['paint_contrast'], 3.0) + 1e-3
    contrasts = [s['paint_contrast'] for s in after if s['paint_contrast'] is not None]
    assert 0.8 < len(contrasts) / 300 and max(contrasts) <= 3.0
    assert 0.5 < np.mean([s['paint_contrast'] is not None for s in before]) < 0.7
    assert scenario_for_seed(TEST_SEED_BASE, worn) == scenario_for_seed(TEST_SEED_BASE)
    build_cache(tmp_path, [], base, workers=1, progress=False)
    with pytest.raises(ValueError, match='other settings'):
        build_cache(tmp_path, [], worn, workers=1, progress=False)
    with pytest.raises(ValueError, match='worn_paint_max'):
        dataclasses.replace(base, worn_paint_max=1.0).validate()


def _sim_sweep(sensor: str, sigma: float | None, seed: int = 2_000_777
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensor-frame xyz, raw intensity and true ring of one simulated sweep (returns only)."""
    pts = next(Simulator(seed, sweeps=1, sensor=sensor, laser_gain_sigma=sigma).sweeps()).points
    field = 'intensity' if 'intensity' in pts.dtype.names else 'reflectivity'
    xyz = np.stack([pts['x'], pts['y'], pts['z']], -1).reshape(-1, 3).astype(np.float32)
    keep = np.abs(xyz).sum(axis=1) > 0  # organised layouts: zero no-returns
    return xyz[keep], pts[field].reshape(-1)[keep].astype(np.float32), pts['ring'].reshape(-1)[
        keep]


@pytest.mark.parametrize('sensor', ['hdl64e', 'hdl32e', 'vlp16', 'os1-128', 'os2-128'])
def test_rings_from_elevation_are_the_sensors_lasers(sensor):
    xyz, raw, ring = _sim_sweep(sensor, None)
    ground = ground_mask(xyz)
    gains = ring_gains(xyz, xyz[ground], raw[ground])
    assert gains is not None
    seen = [k for k in np.unique(ring[ground]) if np.count_nonzero(ground & (ring == k)) >= 200]
    assert len(seen) >= 6
    # one gain per laser, and no two lasers share one (each its own ring); a ring left out
    # (too few ground returns for its own level) keeps gain 1
    per_ring = [np.unique(gains[ring == k]) for k in seen]
    assert all(g.size == 1 for g in per_ring)
    own = np.concatenate(per_ring)
    assert np.count_nonzero(own == 1.0) <= 3
    assert len(np.unique(own[own != 1.0])) == np.count_nonzero(own != 1.0)


@pytest.mark.parametrize('sensor', ['hdl64e', 'hdl32e', 'os1-64'])
def test_contrast_rings_takes_out_per_laser_gain(sensor):
    xyz, calibrated, _ = _sim_sweep(sensor, 0.0)  # every laser at gain 1
    _, spread, _ = _sim_sweep(sensor, 0.3)  # the same drive, gains log-normal sigma 0.3
    ground = ground_mask(xyz) & (np.hypot(xyz[:, 0], xyz[:, 1]) < 12.8)
    ref = IntensityEncoder(CONTRAST_RINGS)(xyz, calibrated)[ground]
    # per ground return: |log| error of the encoding against the calibrated sweep
    def error(encoding: str) -> float:
        out = IntensityEncoder(encoding)(xyz, spread)[ground]
        both = (out > 0) & (ref > 0)
        return float(np.median(np.abs(np.log(out[both] / ref[both]))))
    rings, sweep = error(CONTRAST_RINGS), error(CONTRAST)
    assert rings < 0.12 and sweep > 1.5 * rings, (rings, sweep)


def test_contrast_rings_falls_back_without_separable_rings():
    xyz, value = road_scene(np.random.default_rng(3))  # points anywhere: no rings
    encoder = IntensityEncoder(CONTRAST_RINGS)
    np.testing.assert_allclose(encoder(xyz, value), IntensityEncoder(CONTRAST)(xyz, value))
    assert not encoder.rings_found
    ground = ground_mask(xyz)
    assert ring_gains(xyz, xyz[ground], value[ground]) is None
    # a simulated sweep accumulated while driving: each laser smeared over degrees
    sim = Simulator(2_000_778, sweeps=5, sensor='hdl32e')
    clouds = [s.points for s in sim.sweeps()]
    poses = sim.true_poses
    newest = np.linalg.inv(poses[-1])
    parts = []
    for pts, pose in zip(clouds, poses):
        local = np.stack([pts['x'], pts['y'], pts['z'], np.ones(len(pts))], -1)
        parts.append((local @ (newest @ pose).T)[:, :3])
    xyz = np.concatenate(parts).astype(np.float32)
    raw = np.concatenate([p['intensity'] for p in clouds]).astype(np.float32)
    ground = ground_mask(xyz)
    gains = ring_gains(xyz, xyz[ground], raw[ground])
    assert gains is None or np.all(gains == 1.0)


def test_laser_gain_spread_is_off_by_default_and_leaves_the_drive():
    base = Simulator(2_000_779, sweeps=1, sensor='hdl64e')
    spread = Simulator(2_000_779, sweeps=1, sensor='hdl64e', laser_gain_sigma=0.3)
    assert base.gains.std() < 0.2 and 0.15 < np.log(spread.gains).std() < 0.45
    a, b = next(base.sweeps()).points, next(spread.sweeps()).points
    np.testing.assert_array_equal(a['x'], b['x'])  # the same drive, only the gains differ
    laser = CacheSettings(sensor_variation=True, laser_gains=True)
    drawn = [scenario_for_seed(seed, laser)['laser_gain_sigma'] for seed in range(100)]
    assert 0.3 < np.mean([d is not None for d in drawn]) < 0.7
    assert 'laser_gain_sigma' not in scenario_for_seed(TEST_SEED_BASE, laser)
    assert 'laser_gain_sigma' not in scenario_for_seed(0, CacheSettings(sensor_variation=True))


def _reference_ring_gains(xyz_sensor, ground_xyz, ground_values):
    """ring_gains as first written, in plain numpy (sort, bincount, per-row sort, searchsorted):
    the compiled one must give the same float32 gains."""
    v = np.asarray(ground_values, dtype=np.float64).reshape(-1)
    step = max(1, v.size // RING_SAMPLE)
    g = np.asarray(ground_xyz, dtype=np.float32).reshape(-1, 3)[::step]
    v = v[::step]
    g, v = g[np.isfinite(v)], v[np.isfinite(v)]
    if v.size < RING_MIN_POINTS * RING_MIN_RINGS:
        return None
    el = np.degrees(np.arctan2(g[:, 2], np.hypot(g[:, 0], g[:, 1])))
    order = np.argsort(el)
    el, v, g = el[order], v[order], g[order]
    split = np.flatnonzero(np.diff(el) > RING_GAP_DEG) + 1
    starts, ends = np.concatenate([[0], split]), np.concatenate([split, [el.size]])
    count = ends - starts
    big = count[count >= RING_MIN_POINTS]
    ok = ((count >= max(RING_MIN_POINTS, RING_MIN_SHARE * np.median(big) if big.size else 0))
          & (el[ends - 1] - el[starts] <= RING_MAX_WIDTH_DEG))
    if ok.sum() < RING_MIN_RINGS:
        return None
    rings = int(ok.sum())
    member = np.repeat(np.where(ok, np.cumsum(ok) - 1, -1), count)
    keep = member >= 0
    azimuth = np.arctan2(g[keep, 1], g[keep, 0])
    sector = ((azimuth + np.pi) * (RING_SECTORS / (2 * np.pi))).astype(np.int64) % RING_SECTORS
    cell = member[keep] * RING_SECTORS + sector
    n = np.bincount(cell, minlength=rings * RING_SECTORS)
    total = np.bincount(cell, v[keep], rings * RING_SECTORS)
    with np.errstate(divide='ignore', invalid='ignore'):
        log_mean = np.log(total / n).reshape(rings, RING_SECTORS)
    log_mean[(n < 2).reshape(rings, RING_SECTORS) | ~np.isfinite(log_mean)] = np.nan
    ratio = log_mean[1:] - log_mean[:-1]
    seen = np.isfinite(ratio)
    matched = seen.sum(axis=1) >= RING_MIN_SECTORS
    if matched.sum() < RING_MIN_RINGS - 1:
        return None
    ratio[~seen] = np.inf
    ratio.sort(axis=1)
    counts, rows = seen.sum(axis=1), np.arange(rings - 1)
    lo_mid, hi_mid = np.maximum(counts - 1, 0) // 2, counts // 2
    step = 0.5 * (ratio[rows, lo_mid] + ratio[rows, np.minimum(hi_mid, RING_SECTORS - 1)])
    profile = np.concatenate([[0.0], np.cumsum(np.where(matched, step, 0.0))])
    centre = 0.5 * (el[starts] + el[ends - 1])[ok]
    fit = np.ones(rings, dtype=bool)
    for _ in range(2):
        smooth = np.polyval(np.polyfit(centre[fit], profile[fit], 2), centre)
        off = np.abs(profile - smooth)
        fit = off <= max(3.0 * np.median(off), 1e-6)
    gain = np.ones(starts.size + 2, dtype=np.float32)
    gain[1:-1][ok] = np.clip(np.exp(-(profile - smooth)), *RING_GAIN_RANGE)
    lo, hi = el[starts], el[ends - 1]
    gaps = lo[1:] - hi[:-1]
    edges = np.concatenate([[lo[0] - gaps[0] / 2], (lo[1:] + hi[:-1]) / 2,
                            [hi[-1] + gaps[-1] / 2]])
    tan_edges = np.tan(np.radians(edges)).astype(np.float32)
    x, y, z = np.asarray(xyz_sensor, dtype=np.float32).reshape(-1, 3).T
    with np.errstate(divide='ignore', invalid='ignore'):
        t = z / np.sqrt(x * x + y * y)
    k = np.searchsorted(tan_edges, t, 'right')
    k[~np.isfinite(t)] = np.where(z[~np.isfinite(t)] < 0, 0, tan_edges.size)
    return gain[k]


def _reference_encoding(xyz, raw):
    """contrast_rings from _reference_ring_gains, as the encoder first did it."""
    ground = ground_mask(xyz)
    level = ground_level(raw[ground])
    gains = _reference_ring_gains(xyz, xyz[ground], raw[ground])
    return normalize_intensity(raw.astype(np.float32) * gains, level / GROUND_LEVEL)


@pytest.mark.parametrize('sensor,sigma', [('hdl64e', 0.3), ('os1-64', None), ('vlp16', 0.3)])
def test_compiled_ring_gains_equal_the_numpy_reference(sensor, sigma):
    xyz, raw, _ = _sim_sweep(sensor, sigma, seed=2_000_780)
    assert len(raw) < 65536 * 2  # one ground sample step: the reference takes every return
    ground = ground_mask(xyz)
    reference = _reference_ring_gains(xyz, xyz[ground], raw[ground])
    assert reference is not None and len(np.unique(reference)) > 6
    np.testing.assert_array_equal(ring_gains(xyz, xyz[ground], raw[ground]), reference)
    encoder = IntensityEncoder(CONTRAST_RINGS)
    np.testing.assert_array_equal(encoder(xyz, raw), _reference_encoding(xyz, raw))
    assert encoder.rings_found


@pytest.mark.parametrize('sensor', ['hdl64e', 'hdl32e', 'os1-64'])
def test_ring_field_takes_out_per_laser_gain_at_least_as_well(sensor):
    xyz, calibrated, ring = _sim_sweep(sensor, 0.0)
    _, spread, _ = _sim_sweep(sensor, 0.3)
    ground = ground_mask(xyz) & (np.hypot(xyz[:, 0], xyz[:, 1]) < 12.8)

    def error(with_ring: bool) -> float:
        """median |log| error on the ground against the calibrated sweep, encoded alike"""
        ref = IntensityEncoder(CONTRAST_RINGS)(xyz, calibrated, ring=ring if with_ring else None)
        encoder = IntensityEncoder(CONTRAST_RINGS)
        out = encoder(xyz, spread, ring=ring if with_ring else None)
        assert encoder.rings_found
        both = (out[ground] > 0) & (ref[ground] > 0)
        return float(np.median(np.abs(np.log(out[ground][both] / ref[ground][both]))))
    by_ring, by_elevation = error(True), error(False)
    assert by_ring < 0.12 and by_ring <= by_elevation + 0.01, (by_ring, by_elevation)
    # one gain per laser, and the ring path is not the elevation path in disguise
    gains = ring_gains(xyz, xyz[ground], spread[ground], ring, ring[ground])
    assert all(np.unique(gains[ring == k]).size == 1 for k in np.unique(ring))
    assert not np.array_equal(gains, ring_gains(xyz, xyz[ground], spread[ground]))


def test_a_malformed_ring_field_falls_back_to_elevation_rings():
    xyz, raw, ring = _sim_sweep('hdl32e', 0.3)
    encoder = IntensityEncoder(CONTRAST_RINGS)
    by_elevation = encoder(xyz, raw)
    fractional = ring.astype(np.float32) + 0.5
    not_finite = ring.astype(np.float64)
    not_finite[7] = np.nan
    negative = -1 - ring.astype(np.int32)
    for bad in (ring[:-1], ring.reshape(1, -1)[:, :10], fractional, not_finite, negative,
                np.zeros_like(ring), np.full(len(ring), 70000), np.array(['a'] * len(ring))):
        np.testing.assert_array_equal(encoder(xyz, raw, ring=bad), by_elevation)
        assert encoder.rings_found
    as_float = encoder(xyz, raw, ring=ring.astype(np.float32))  # nuScenes: float ring ids
    np.testing.assert_array_equal(as_float, encoder(xyz, raw, ring=ring))
    assert not np.array_equal(as_float, by_elevation)


def test_the_ring_field_goes_from_the_cloud_into_the_encoder():
    sim = Simulator(2_000_781, sweeps=1, sensor='hdl32e', laser_gain_sigma=0.3)
    pts = next(sim.sweeps()).points.copy()
    pts['x'][:3] = 0.0  # no-returns: dropped with their ring
    pts['y'][:3] = pts['z'][:3] = 0.0
    pts['z'][5] = np.nan
    family = rosbags_family()
    msg = create_cloud(family.cls('sensor_msgs/msg/PointCloud2'), family.header(1, 'lidar'), pts)
    xyz, raw, ring = read_xyzir(msg)
    plain = read_xyzi(msg)
    np.testing.assert_array_equal(plain[0], xyz)
    np.testing.assert_array_equal(ring, np.delete(pts['ring'], [0, 1, 2, 5]))
    without = recfunctions.drop_fields(pts, 'ring', usemask=False)
    assert read_xyzir(create_cloud(family.cls('sensor_msgs/msg/PointCloud2'),
                                   family.header(1, 'lidar'), without))[2] is None
    # the grid drops a non-finite intensity with its ring; the encoder then sees the rest
    raw[9] = np.inf
    grid = RollingBevGrid(intensity_encoding=CONTRAST_RINGS)
    grid.insert(0, xyz, raw, np.eye(4), ring=ring)
    keep = np.arange(len(raw)) != 9
    expected = IntensityEncoder(CONTRAST_RINGS)(xyz[keep], raw[keep], ring=ring[keep])
    np.testing.assert_array_equal(grid._sweeps[-1].intensity01, expected)
    assert not np.array_equal(expected, IntensityEncoder(CONTRAST_RINGS)(xyz[keep], raw[keep]))
