"""Intensity encodings: the contrast encoding reads paint against the sweep's own ground, so
sensor units and gain cancel; the ground it measures is local (any mount height or tilt)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fhld_ros.intensity import (
    ABSOLUTE,
    CONTRAST,
    GROUND_LEVEL,
    IntensityEncoder,
    ground_level,
    ground_mask,
)
from fhld_ros.pipeline import LanePipeline
from fhld_ros.ros.parameters import DetectorParams
from fhld_ros.sim.simulator import Simulator
from fhld_ros.training.cache import TEST_SEED_BASE, CacheSettings, build_cache, scenario_for_seed
from fhld_ros.training.samples import training_samples


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
