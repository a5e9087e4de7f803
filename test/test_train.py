"""Training infrastructure: window cache, dataset + augmentation, `fhld train` (resume, DDP)."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from model_fixtures import small_config
from scipy.spatial import cKDTree

from fhld_ros.bev import EMPTY_MIN_HEIGHT, BevSpec
from fhld_ros.cli import main as fhld
from fhld_ros.data.cache import (
    ALL_SENSORS,
    ALL_TOPOLOGIES,
    CacheSettings,
    build_cache,
    read_meta,
    scenario_for_seed,
    shard_path,
)
from fhld_ros.data.samples import training_samples
from fhld_ros.data.variation import SHARES
from fhld_ros.errors import ConfigError
from fhld_ros.evaluation import real_scans
from fhld_ros.model.checkpoint import load_checkpoint, save_checkpoint
from fhld_ros.model.detector import FhldDetector
from fhld_ros.sim.simulator import Simulator
from fhld_ros.training.augment import (
    AugmentParams,
    Similarity,
    augment,
    centre_crop,
    warp_lanes,
    warp_raster,
    warp_rasters,
)
from fhld_ros.training.config import TrainSection, cache_settings, load_config, read_yaml
from fhld_ros.training.dataset import CacheDataset, collate
from fhld_ros.training.loop import init_weights

pytestmark = pytest.mark.usefixtures('one_torch_thread')

REPO = Path(__file__).resolve().parent.parent
MODEL = small_config(lsm_warmup=1)  # 128 px at 20 cm: tiny rasters, a narrow network
RES = MODEL.resolution_m
# training windows cached at 160 px (the model's 128 px cut out after augmentation)
TINY = CacheSettings(windows_per_seed=2, size_px=160, resolution_m=RES, sweeps_per_sample=2,
                     stride=2, sensors=('vlp16',))
TINY_TEST = dataclasses.replace(TINY, size_px=MODEL.size_px)  # held out: the model's raster
TRAIN_SEEDS = (0, 2)
TEST_SEED = 1_000_000


def build_tiny_caches(root: Path) -> Path:
    """Training and test cache of the TINY settings in root/train, root/test (built inline;
    the pool has its own test)."""
    build_cache(root / 'train', range(*TRAIN_SEEDS), TINY, workers=1, progress=False)
    build_cache(root / 'test', [TEST_SEED], TINY_TEST, workers=1, progress=False)
    return root


@pytest.fixture(scope='module')
def caches(tmp_path_factory) -> Path:
    return build_tiny_caches(tmp_path_factory.mktemp('cache'))


def write_config(path: Path, caches: Path, **train) -> Path:
    """A training config over the `caches` fixture; `train` overrides the train section."""
    cfg = {'seed': 3, 'model': MODEL.to_dict(),
           'data': {'train_cache': str(caches / 'train'), 'test_cache': str(caches / 'test'),
                    'train_seeds': list(TRAIN_SEEDS), 'test_seeds': [TEST_SEED, TEST_SEED + 1],
                    'train_windows_per_seed': TINY.windows_per_seed,
                    'test_windows_per_seed': TINY_TEST.windows_per_seed,
                    'train_size_px': TINY.size_px, 'sweeps_per_sample': TINY.sweeps_per_sample,
                    'stride': TINY.stride, 'sensors': list(TINY.sensors), 'cache_workers': 1},
           'train': {'iterations': 3, 'batch_size': 2, 'eval_every': 100, 'ckpt_every': 100,
                     'log_every': 1, 'eval_windows': 1, 'eval_batch_size': 1, **train}}
    path.write_text(json.dumps(cfg))  # JSON is YAML
    return path


def train_argv(cfg: Path, out: Path) -> list[str]:
    return ['train', '--config', str(cfg), '--out', str(out), '--quiet']


def load_payload(path: Path) -> dict:
    return torch.load(path, map_location='cpu', weights_only=True)


# --- (a) cache ----------------------------------------------------------------------------

def test_cache_round_trip_matches_the_simulator(caches):
    meta = read_meta(shard_path(caches / 'train', 1))
    assert meta['seed'] == 1 and meta['windows'] == 2 and meta['size_px'] == 160
    assert meta['scenario'] == scenario_for_seed(1, TINY)
    data = CacheDataset(caches / 'train')
    assert len(data) == 4 and data.size_px == 160 and data.resolution_m == RES
    sim = Simulator(1, sweeps=TINY.sweeps_per_seed, **meta['scenario'])
    samples = list(training_samples(sim, 2, sweeps_per_sample=2, stride=2,
                                    spec=BevSpec(160, RES),
                                    intensity_encoding=TINY.intensity_encoding))
    for k, sample in enumerate(samples):
        item = data[2 + k]
        assert (item['seed'], item['window']) == (1, k)
        np.testing.assert_allclose(item['raster'].numpy(), sample.raster, atol=1e-3)
        assert len(item['lanes']) == len(sample.lanes)
        for got, want in zip(item['lanes'], sample.lanes):
            np.testing.assert_allclose(got, want, atol=1e-5)
    batch = collate([data[0], data[3]])
    assert batch['raster'].shape == (2, 4, 160, 160) and len(batch['lanes']) == 2
    # centre crop to the model's 128 px, as for evaluation
    crop = CacheDataset(caches / 'train', out_size=128)[3]
    assert crop['raster'].shape == (4, 128, 128)
    assert all(np.abs(lane[:, :2]).max() <= 128 * RES / 2 + 1e-9 for lane in crop['lanes'])


@pytest.mark.slow
def test_cache_pool_builds_the_same_shards(caches, tmp_path):
    """The spawned worker pool writes what the inline build wrote."""
    report = build_cache(tmp_path, range(*TRAIN_SEEDS), TINY, workers=2, progress=False)
    assert sorted(report.built) == [0, 1] and report.windows == 4 and report.complete
    for seed in range(*TRAIN_SEEDS):
        with (np.load(shard_path(tmp_path, seed)) as pool,
              np.load(shard_path(caches / 'train', seed)) as inline):
            assert sorted(pool.files) == sorted(inline.files)
            for name in pool.files:
                np.testing.assert_array_equal(pool[name], inline[name], err_msg=name)


def test_cache_build_resumes_and_refuses_other_settings(caches):
    again = build_cache(caches / 'train', range(*TRAIN_SEEDS), TINY, workers=2, progress=False)
    assert again.built == [] and sorted(again.skipped) == [0, 1]
    assert not list((caches / 'train').glob('.*tmp*'))  # atomic writes leave nothing behind
    for other in (dataclasses.replace(TINY, windows_per_seed=3),
                  dataclasses.replace(TINY, bare_curbs=True)):
        with pytest.raises(ValueError, match='other settings'):
            build_cache(caches / 'train', [5], other, workers=1, progress=False)


TRAINING_CONFIGS = sorted(p for p in (REPO / 'config').rglob('*.yaml')
                          if p.name not in ('lane_detector.yaml', 'pjlab_camera_calib.yaml'))


def test_experiments_are_apart_from_the_shipped_recipe_and_the_starting_points():
    assert {p.relative_to(REPO / 'config').as_posix() for p in TRAINING_CONFIGS
            if p.parent.name != 'experiments'} == {
        'distill_stem5.yaml', 'train_cpu.yaml', 'train_gpu.yaml'}


@pytest.mark.parametrize('path', TRAINING_CONFIGS, ids=lambda p: p.name)
def test_every_training_config_loads(path, tmp_path, monkeypatch):
    bags = (read_yaml(path).get('data') or {}).get('bags') or []  # base: chain merged
    real_bags = sorted({Path(b['path']).name for b in bags if 'out/realbags/' in b['path']})
    if real_bags:  # hand-labelled real sweeps as bags: `fhld realscans --write-bags`
        if not real_scans.DEFAULT_DIR.is_dir():
            pytest.skip(f'{path.name} trains on real sweeps in ../shared/real_scans (absent)')
        monkeypatch.chdir(tmp_path)
        names = [f'{stem}.bin' for stem in real_bags]
        real_scans.write_labelled_bags(real_scans.DEFAULT_DIR, tmp_path / 'out' / 'realbags',
                                       names)
    cfg = load_config(path)
    # the shipped file changes with each release: a recipe names the file it starts from
    assert 'fhld_ros/checkpoints' not in cfg.train.teacher + cfg.train.init


def test_the_shipped_recipe_is_self_contained_and_its_teacher_checked():
    path = REPO / 'config' / 'distill_stem5.yaml'
    assert 'base:' not in path.read_text() and 'git show' not in path.read_text()
    t = load_config(path).train
    assert (t.teacher, t.distill) == ('config/teachers/fhld_no_lane_stem7.pt', 'stem')
    assert (REPO / t.teacher).is_file() and not t.init
    assert dataclasses.replace(t, teacher=str(REPO / t.teacher)).verified('teacher')
    assert load_checkpoint(REPO / t.teacher).config.stem_kernel == 7
    assert load_config(path).model['stem_kernel'] == 5


@pytest.mark.parametrize('path', [p for p in TRAINING_CONFIGS if p.name.startswith('train_')],
                         ids=lambda p: p.name)
def test_shipped_training_configs_load(path):
    cfg = load_config(path)
    train, test = cache_settings(cfg, 'train'), cache_settings(cfg, 'test')
    assert not (test.sensor_variation or test.road_look or test.bare_curbs)  # held out as is
    reshared = ('train_cpu_unmarked.yaml', 'train_cpu_sparse_bright.yaml', 'train_cpu_b1.yaml')
    assert train.bare_curbs == (path.name in ('train_cpu_barecurbs.yaml', *reshared))
    assert (train.no_markings_share != test.no_markings_share) == (path.name in reshared)
    assert test == dataclasses.replace(test, **SHARES)  # the test cache keeps the defaults


def test_a_config_states_what_it_changes_over_its_base(tmp_path):
    (tmp_path / 'exp').mkdir()
    (tmp_path / 'base.yaml').write_text(
        'seed: 4\nmodel: {stem_kernel: 7, lsm_warmup: 10}\n'
        'data: {sensors: [vlp16, hdl64e], train_seeds: [0, 8], road_look: true}\n'
        'train: {iterations: 50, lr: 1.0e-3}\n')
    child = tmp_path / 'exp' / 'child.yaml'
    child.write_text('base: ../base.yaml\nmodel: {lsm_warmup: 0}\ndata: {sensors: [vlp16]}\n'
                     'augment:\ntrain: {iterations: 60}\n')
    cfg = load_config(child)
    assert cfg.seed == 4 and cfg.model == {'stem_kernel': 7, 'lsm_warmup': 0}
    assert (cfg.data.cache.sensors, cfg.data.train_seeds, cfg.data.cache.road_look) == (
        ('vlp16',), (0, 8), True)  # a list replaces the base's list
    assert (cfg.train.iterations, cfg.train.lr) == (60, 1e-3)
    assert cfg.augment == AugmentParams()  # an empty section keeps the base's (none here)


@pytest.mark.parametrize('files, message', [
    ({'a.yaml': 'base: b.yaml\n', 'b.yaml': 'base: a.yaml\n'}, 'base chain is a cycle'),
    ({'a.yaml': 'base: a.yaml\n'}, 'base chain is a cycle'),
    ({'a.yaml': 'base: missing.yaml\n'}, 'its base missing.yaml does not exist'),
    ({'a.yaml': 'base: [b.yaml]\n'}, r"base must name a YAML file, not \['b.yaml'\]"),
    ({'a.yaml': 'base: b.yaml\n', 'b.yaml': 'trian: {}\n'}, r'unknown section\(s\) trian'),
    ({'a.yaml': 'data: {windows_per_seed: 3}\n'}, r'unknown key\(s\) windows_per_seed in '
     'section data'),
    ({'a.yaml': 'train: {teacher_sha256: abc}\n'}, 'train.teacher_sha256 must be 64'),
    ({'a.yaml': f'train: {{init_sha256: {"a" * 64}}}\n'}, 'init_sha256 is given without'),
])
def test_a_bad_base_or_key_is_a_config_error(tmp_path, files, message):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config(tmp_path / 'a.yaml')


def test_training_refuses_a_teacher_or_init_of_another_checksum(tmp_path):
    path = tmp_path / 'teacher.pt'
    path.write_bytes(b'weights')
    right = hashlib.sha256(b'weights').hexdigest()
    section = TrainSection(teacher=str(path), teacher_sha256=right)
    assert section.verified('teacher') == str(path) == TrainSection(teacher=str(path)).verified(
        'teacher')
    with pytest.raises(ConfigError, match=f'train.teacher {path} has sha256 {right}, the '
                       f'config asks for {"0" * 64}'):
        dataclasses.replace(section, teacher_sha256='0' * 64).verified('teacher')
    with pytest.raises(ConfigError, match='train.init .*missing.pt: cannot read it'):
        TrainSection(init=str(tmp_path / 'missing.pt'), init_sha256=right).verified('init')


def test_the_data_section_holds_the_training_caches_settings(tmp_path):
    path = tmp_path / 'c.yaml'
    path.write_text('model: {resolution_m: 0.08, intensity_encoding: absolute}\n'
                    'data: {train_size_px: 400, train_windows_per_seed: 3, stride: 5,\n'
                    '       topologies: [none, split], sensor_variation: true}\n')
    cfg = load_config(path)
    assert cache_settings(cfg, 'train') == cfg.data.cache == CacheSettings(
        windows_per_seed=3, size_px=400, resolution_m=0.08, stride=5,
        intensity_encoding='absolute', topologies=(None, 'split'), sensor_variation=True)
    assert cache_settings(cfg, 'test') == dataclasses.replace(
        cfg.data.cache, windows_per_seed=5, size_px=640, sensor_variation=False)


def test_scenarios_cover_every_sensor_and_topology():
    settings = CacheSettings()
    pairs = {(s['sensor'], s['topology'])
             for s in (scenario_for_seed(k, settings) for k in range(56))}
    assert len(pairs) == len(ALL_SENSORS) * len(ALL_TOPOLOGIES) == 56
    test_split = [scenario_for_seed(1_000_000 + k, settings) for k in range(8)]
    assert {s['sensor'] for s in test_split} == set(ALL_SENSORS)
    assert {s['topology'] for s in test_split} == set(ALL_TOPOLOGIES)


# --- (b) augmentation -----------------------------------------------------------------------

def painted(size: int, res: float) -> tuple[torch.Tensor, list[np.ndarray]]:
    """An empty raster with two bright curved lines painted densely, and their polylines."""
    half = size * res / 2
    x = np.linspace(-half, half, 4000)
    lanes = [np.stack([x, y0 + 0.004 * x ** 2 + 0.1 * x, 0.01 * x - 1.8], 1)
             for y0 in (-3.0, 2.5)]
    raster = torch.zeros(4, size, size)
    raster[3] = EMPTY_MIN_HEIGHT
    spec = BevSpec(size, res)
    for lane in lanes:
        col, row = np.floor(spec.world_to_pixel(lane)).astype(int).T
        ok = (col >= 0) & (col < size) & (row >= 0) & (row < size)
        raster[:, row[ok], col[ok]] = torch.tensor([1.0, 0.5, 0.2, 0.3])[:, None]
    return raster, lanes


def test_identity_flip_and_crop_are_exact():
    raster, lanes = painted(160, RES)
    for transform, want in ((Similarity(), raster), (Similarity(flip=True), raster.flip(-2))):
        got = warp_raster(raster, transform, 160, RES)
        assert torch.equal(got[1] > 0, want[1] > 0)
        torch.testing.assert_close(got, want, atol=1e-6, rtol=0)  # float32 grid coordinates
    flipped = warp_lanes(lanes, Similarity(flip=True), 160, RES)
    mirrored = warp_lanes([lane * [1, -1, 1] for lane in lanes], Similarity(), 160, RES)
    for a, b in zip(flipped, mirrored, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)
    crop, crop_lanes = centre_crop(raster, lanes, 128, RES)
    torch.testing.assert_close(warp_raster(raster, Similarity(), 128, RES), crop, atol=1e-6,
                               rtol=0)
    assert torch.equal(crop, raster[:, 16:144, 16:144]) and len(crop_lanes) == 2
    np.testing.assert_allclose(Similarity(angle=math.pi / 2).apply(np.array([[1.0, 0, 5]])),
                               [[0.0, 1.0, 5.0]], atol=1e-12)


@pytest.mark.parametrize('seed', range(6))
def test_augmented_lanes_land_on_the_painted_pixels(seed):
    raster, lanes = painted(160, RES)
    rng = np.random.default_rng(seed)
    params = AugmentParams(shift_m=2.0, rotate_deg=25.0, flip_prob=0.5, scale_min=0.8,
                           scale_max=1.2)
    out, out_lanes = augment(raster, lanes, rng, params, out_size=128, resolution_m=RES)
    assert out.shape == (4, 128, 128) and len(out_lanes) >= 2
    occupied = out[1] > 0
    # empty cells stay exactly empty; occupied cells keep exactly the painted values (no
    # blending with empty neighbours)
    assert torch.all(out[:3, ~occupied] == 0)
    assert torch.all(out[3, ~occupied] == EMPTY_MIN_HEIGHT)
    values = out[:, occupied]
    torch.testing.assert_close(values, torch.tensor([1.0, 0.5, 0.2, 0.3])[:, None].expand_as(
        values))
    # GT -> pixels: (almost) every GT sample falls on a bright pixel or right next to it
    spec = BevSpec(128, RES)
    pts = np.concatenate(out_lanes)
    col, row = np.clip(np.floor(spec.world_to_pixel(pts)).astype(int), 0, 127).T  # edge: 128
    near = torch.nn.functional.max_pool2d(occupied[None, None].float(), 3, 1, 1)[0, 0] > 0
    assert near.numpy()[row, col].mean() > 0.97
    # and every bright pixel lies on a transformed GT lane (within 1.5 px)
    rows, cols = np.nonzero(occupied.numpy())
    centres = spec.pixel_to_world(np.stack([cols, rows], 1) + 0.5)
    dense = np.concatenate([np.linspace(a[:2], b[:2], 20) for lane in out_lanes
                            for a, b in zip(lane[:-1], lane[1:])])
    dist, _ = cKDTree(dense).query(centres)
    assert dist.max() < 1.5 * RES * 1.25  # sqrt(2) source px, times the largest scale
    assert all(np.abs(lane[:, :2]).max() < 128 * RES / 2 + 1e-9 for lane in out_lanes)


def test_dataset_augmentation_is_keyed_by_seed_epoch_index(caches):
    data = CacheDataset(caches / 'train', out_size=128, augment=AugmentParams(), seed=1)
    items = [data[1], data[2]]  # seed 0 window 1, seed 1 window 0
    assert items[0]['raster'].shape == (4, 128, 128)
    assert torch.equal(items[1]['raster'], data[2]['raster'])
    data.set_epoch(1)
    assert not torch.equal(items[1]['raster'], data[2]['raster'])
    # the GPU path: raw float16 windows + thetas, warped per batch, give the same items
    deferred = CacheDataset(caches / 'train', out_size=128, augment=AugmentParams(), seed=1,
                            defer_warp=True)
    batch = collate([deferred[1], deferred[2]])
    assert batch['raster'].dtype == torch.float16 and batch['theta'].shape == (2, 2, 3)
    warped = warp_rasters(batch['raster'], batch['theta'], 128)
    for k, item in enumerate(items):
        torch.testing.assert_close(warped[k], item['raster'], atol=2e-3, rtol=0)  # float16
        assert len(batch['lanes'][k]) == len(item['lanes'])
        for x, y in zip(batch['lanes'][k], item['lanes']):
            np.testing.assert_array_equal(x, y)
    assert len(items[1]['lanes']) > 0


# --- (c) training, checkpoints, resume --------------------------------------------------------

@pytest.mark.slow
def test_train_stops_on_budget_and_resumes_exactly(caches, tmp_path):
    cfg = write_config(tmp_path / 'tiny.yaml', caches)
    assert fhld(train_argv(cfg, tmp_path / 'a')) == 0
    straight = load_payload(tmp_path / 'a' / 'last.pt')
    assert straight['meta']['iteration'] == 3
    assert '--config' in straight['train_command']
    best = load_checkpoint(tmp_path / 'a' / 'best.pt')
    assert best.meta['train_config']['train']['iterations'] == 3
    assert set(best.meta['eval']) >= {'P@10', 'R@10', 'F1@10', 'F1@30'}
    log = [json.loads(line) for line in (tmp_path / 'a' / 'log.jsonl').read_text().splitlines()]
    assert [r['iteration'] for r in log if 'loss' in r] == [1, 2, 3]

    run_b = train_argv(cfg, tmp_path / 'b')
    assert fhld([*run_b, '--max-minutes', '0']) == 0  # budget spent: one iteration, then stop
    stopped = load_payload(tmp_path / 'b' / 'last.pt')
    assert stopped['meta']['iteration'] == 1 and 'optimizer' in stopped['meta']['train_state']
    assert fhld(run_b) == 2  # refuses to overwrite a run without --resume
    assert fhld([*run_b, '--resume']) == 0
    resumed = load_payload(tmp_path / 'b' / 'last.pt')
    assert resumed['meta']['iteration'] == 3 and len(resumed['meta']['commands']) == 2
    for key, value in straight['state_dict'].items():
        assert torch.equal(value, resumed['state_dict'][key]), key


def test_bad_config_is_one_clear_error(tmp_path, capsys):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('train: {iterations: 3, batchsize: 2}\n')
    assert fhld(['train', '--config', str(bad)]) == 2
    assert 'batchsize' in capsys.readouterr().err
    bad.write_text('data: {train_seeds: [0, 10], test_seeds: [5, 20]}\n')
    assert fhld(['train', '--config', str(bad)]) == 2
    assert 'overlap' in capsys.readouterr().err


# --- (d) DDP --------------------------------------------------------------------------------

@pytest.mark.slow
def test_ddp_gloo_two_processes(caches, tmp_path):
    cfg = write_config(tmp_path / 'ddp.yaml', caches, iterations=2, batch_size=1)
    env = {**os.environ, 'OMP_NUM_THREADS': '1', 'PYTHONPATH': str(REPO)}
    env.pop('WORLD_SIZE', None)
    proc = subprocess.run(
        [sys.executable, '-m', 'torch.distributed.run', '--standalone', '--nproc-per-node=2',
         '-m', 'fhld_ros.cli', 'train', '--config', str(cfg), '--out', str(tmp_path / 'run'),
         '--device', 'cpu', '--quiet'],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    payload = load_payload(tmp_path / 'run' / 'last.pt')
    meta = payload['meta']
    assert meta['iteration'] == 2 and meta['world_size'] == 2
    assert len(meta['train_state']['rng']) == 2
    assert payload['train_command'].startswith('torchrun --nproc-per-node=2')


def test_train_init_starts_from_another_checkpoints_weights(tmp_path):
    source = FhldDetector(MODEL)
    path = save_checkpoint(tmp_path / 'init.pt', source, 'x')
    module = FhldDetector(MODEL)
    init_weights(module, str(path))
    for key, value in source.state_dict().items():
        assert torch.equal(value, module.state_dict()[key]), key
    with pytest.raises(ValueError, match='its layers differ from the model section'):
        init_weights(FhldDetector(dataclasses.replace(MODEL, local_hidden=16)), str(path))


def test_freeze_batchnorm_keeps_the_running_statistics(caches, tmp_path):
    """At small batches on a CPU a fine-tune normalises as the node will (running statistics)
    and leaves them as they were; the weights still learn."""
    for name, freeze in (('free', False), ('frozen', True)):
        cfg = write_config(tmp_path / f'{name}.yaml', caches, freeze_batchnorm=freeze)
        assert fhld(train_argv(cfg, tmp_path / name)) == 0
    fresh = FhldDetector(MODEL).state_dict()  # the seed's initialisation, as both runs start
    for name, freeze in (('free', False), ('frozen', True)):
        state = load_payload(tmp_path / name / 'last.pt')['state_dict']
        stats = [k for k in state if k.endswith(('running_mean', 'running_var'))]
        assert stats and all(torch.equal(state[k], fresh[k]) for k in stats) == freeze, name
        assert any(not torch.equal(state[k], fresh[k]) for k in state
                   if k.endswith('conv.weight'))
