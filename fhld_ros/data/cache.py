"""Training-window cache: simulator windows rasterised once, stored as compressed shards.

Ray casting costs seconds per window, so windows are generated once (in parallel processes) and
reused by every training run (docs/design.md §5). One shard per simulator seed,
``shard_<seed>.npz`` (np.savez_compressed, no pickled objects):

* ``raster_<i>``    (4, S, S) float16, window i (one zip member each, so a reader decompresses
                    only the window it needs)
* ``lane_points``   (P, 3) float32 GT points of every lane of every window, window frame
* ``lane_offsets``  (L + 1,) int64: lane j is lane_points[lane_offsets[j]:lane_offsets[j + 1]]
* ``window_lanes``  (n + 1,) int64: window i owns lanes window_lanes[i]:window_lanes[i + 1]
* ``lane_ids``      (L,) int64 scene line index of each lane
* ``window_to_odom`` (n, 4, 4) float64, ``stamps_ns`` (n,) int64, ``sweeps`` (n,) int64
* ``meta``          JSON string: seed, scenario (sensor, topology, ...), road class, raster spec
                    (shards of labelled bags, data/bag_source.py: the bag and shard index)

Shards are written to a temporary file and renamed, so a shard either exists complete or not at
all; a build skips existing shards and so resumes after an interruption. The directory's
``cache.json`` records the build settings; a build with other settings refuses to mix in.

Split convention: training seeds and held-out test seeds come from disjoint ranges, test seeds
from TEST_SEED_BASE up. The scenario of a seed (scenario_for_seed) cycles through the sensor
presets and topologies so that any run of consecutive seeds covers all of them.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fhld_ros.bev import BevSpec
from fhld_ros.data.samples import TrainingSample, training_samples
from fhld_ros.data.variation import SHARES, sensor_variation, variation_record
from fhld_ros.dataclass_dict import check_fields, documented, to_plain
from fhld_ros.errors import ConfigError
from fhld_ros.intensity import CONTRAST, INTENSITY_ENCODINGS
from fhld_ros.sim.layout import TOPOLOGIES
from fhld_ros.sim.lidar import SENSORS, SPINNING
from fhld_ros.sim.simulator import Simulator

SHARD_FORMAT = 1
SAMPLE_OPTIONS = ('intensity_gain', 'single_sweep')  # scenario keys that are not Simulator's
TEST_SEED_BASE = 1_000_000
ALL_SENSORS: tuple[str, ...] = SPINNING
ALL_TOPOLOGIES: tuple[str | None, ...] = (None, *TOPOLOGIES)  # None: the layout's own events
INDEX_NAME = 'cache.json'


@dataclass(frozen=True)
class CacheSettings:
    """Everything that determines a shard's content besides its seed."""

    windows_per_seed: int = documented(8, 'windows cut from each seed\'s drive', range='[1, inf)')
    size_px: int = documented(640, 'raster side, cells', range='[1, inf)')
    resolution_m: float = documented(0.04, 'raster cell size, m', range='(0, inf)')
    sweeps_per_sample: int = documented(10, 'sweeps accumulated per window (1 s at 10 Hz)',
                                        range='[1, inf)')
    stride: int = documented(10, 'sweeps between windows (== sweeps_per_sample: no sweep is '
                             'reused)', range='[1, inf)')
    sensors: tuple[str, ...] = documented(ALL_SENSORS, 'sensor presets the seeds cycle through',
                                          choices=SENSORS, length='[1, inf)')
    topologies: tuple[str | None, ...] = documented(
        ALL_TOPOLOGIES, "road topologies the seeds cycle through (None: the layout's own)",
        choices=ALL_TOPOLOGIES, length='[1, inf)')
    odom_noise_max: float = documented(1.0, 'half the seeds drive with drift U(0, max), half '
                                       'exact', range='[0, inf)')
    motion_distortion_prob: float = documented(0.25, 'share of the seeds whose sweeps are '
                                               'motion-distorted', range='[0, 1]')
    intensity_encoding: str = documented(CONTRAST, "the model's (FhldConfig.intensity_encoding)",
                                         choices=INTENSITY_ENCODINGS)
    sensor_variation: bool = documented(False, 'training seeds only: sensor_variation() drawn '
                                        'per seed')
    road_look: bool = documented(False, 'sensor_variation also draws pavements and mount tilt')
    bare_curbs: bool = documented(False, 'sensor_variation also draws roads without lines along '
                                  'the curbs')
    laser_gains: bool = documented(False, 'sensor_variation also draws per-laser gain spread '
                                   '(variation.py)')
    # sensor_variation's shares of the seeds (variation.py)
    no_markings_share: float = documented(SHARES['no_markings_share'], 'roads without any '
                                          'paint', range='[0, 1]')
    single_sweep_share: float = documented(SHARES['single_sweep_share'], 'windows of one sweep '
                                           'without odometry', range='[0, 1]')
    bright_asphalt_share: float = documented(SHARES['bright_asphalt_share'], 'KITTI-like bright '
                                             'pavement (with road_look)', range='[0, 1]')
    worn_paint_share: float = documented(SHARES['worn_paint_share'], 'roads with worn paint',
                                         range='[0, 1]')
    worn_paint_max: float = documented(SHARES['worn_paint_max'], "worn paint's reflectance at "
                                       'most, x the asphalt (variation.py)', range='[1.6, inf)')

    def validate(self, where: str = '', names: dict[str, str] | None = None) -> None:
        """ConfigError naming every unusable setting (as `where.name`, or the name `names`
        gives it)."""
        check_fields(self, where, names)

    @property
    def sweeps_per_seed(self) -> int:
        return self.sweeps_per_sample + (self.windows_per_seed - 1) * self.stride


def scenario_for_seed(seed: int, settings: CacheSettings = CacheSettings()) -> dict:
    """Simulator options of a seed: sensor = seed mod #sensors, topology = (seed + seed //
    #sensors) mod #topologies, so n consecutive seeds cover min(n, #sensors) sensors and, when
    #sensors >= #topologies, every topology; with gcd(#sensors + 1, #topologies) = 1 (8
    sensors, 7 topologies by default) #sensors * #topologies consecutive seeds cover every pair.
    Odometry drift and motion distortion are drawn from the seed; with
    settings.sensor_variation, and below TEST_SEED_BASE only (the test set stays what it is),
    also what real sensors and roads vary (sensor_variation). SAMPLE_OPTIONS are for
    training_samples, every other key a Simulator option."""
    ns, nt = len(settings.sensors), len(settings.topologies)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5CE7A]))
    drift = float(rng.uniform(0.0, settings.odom_noise_max)) if rng.random() < 0.5 else 0.0
    scenario = {'sensor': settings.sensors[seed % ns],
                'topology': settings.topologies[(seed + seed // ns) % nt],
                'odom_noise': round(drift, 3),
                'motion_distortion': bool(rng.random() < settings.motion_distortion_prob)}
    if settings.sensor_variation and seed < TEST_SEED_BASE:
        scenario.update(sensor_variation(seed, settings))
    return scenario


def single_sweep_windows(settings: CacheSettings) -> dict:
    """training_samples options for windows of one sweep without odometry (the node without
    /odom, the cloud frame) that end where the settings' accumulated windows end."""
    return dict(sweeps_per_sample=1, stride=settings.stride,
                start=settings.sweeps_per_sample - 1, odometry=False)


def shard_path(out_dir: str | os.PathLike, seed: int) -> Path:
    return Path(out_dir) / f'shard_{seed:07d}.npz'


def make_shard(seed: int, settings: CacheSettings) -> dict[str, np.ndarray]:
    """Simulate one seed's windows and pack them into the shard arrays."""
    scenario = scenario_for_seed(seed, settings)
    options = {k: v for k, v in scenario.items() if k not in SAMPLE_OPTIONS}
    sim = Simulator(seed, sweeps=settings.sweeps_per_seed, **options)
    spec = BevSpec(settings.size_px, settings.resolution_m)
    how = (single_sweep_windows(settings) if scenario.get('single_sweep') else
           dict(sweeps_per_sample=settings.sweeps_per_sample, stride=settings.stride))
    samples = list(training_samples(sim, settings.windows_per_seed, spec=spec,
                                    intensity_gain=scenario.get('intensity_gain', 1.0),
                                    intensity_encoding=settings.intensity_encoding, **how))
    return pack_samples(samples, {
        'format': SHARD_FORMAT, 'seed': seed, 'windows': len(samples),
        'road_class': sim.scene.road_class, 'scenario': scenario,
        'size_px': settings.size_px, 'resolution_m': settings.resolution_m,
        'sweeps_per_sample': settings.sweeps_per_sample, 'stride': settings.stride})


def pack_samples(samples: list[TrainingSample], meta: dict) -> dict[str, np.ndarray]:
    """The shard arrays of windows (the module doc's layout; meta as its JSON string).
    Each sample's meta holds 'line_ids', 'stamp_ns' and 'sweep'."""
    lanes = [lane for s in samples for lane in s.lanes]
    counts = [len(s.lanes) for s in samples]
    arrays = {f'raster_{i:04d}': s.raster.astype(np.float16) for i, s in enumerate(samples)}
    arrays.update(
        lane_points=(np.concatenate(lanes).astype(np.float32) if lanes
                     else np.zeros((0, 3), np.float32)),
        lane_offsets=np.concatenate([[0], np.cumsum([len(lane) for lane in lanes])]).astype(
            np.int64),
        window_lanes=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        lane_ids=np.array([i for s in samples for i in s.meta['line_ids']], dtype=np.int64),
        window_to_odom=np.stack([s.window_to_odom for s in samples]),
        stamps_ns=np.array([s.meta['stamp_ns'] for s in samples], dtype=np.int64),
        sweeps=np.array([s.meta['sweep'] for s in samples], dtype=np.int64),
        meta=np.array(json.dumps(meta)))
    return arrays


def write_shard(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Atomic: a temporary file in the same directory, renamed into place."""
    tmp = path.with_name(f'.{path.stem}.{os.getpid()}.tmp.npz')  # savez keeps a .npz suffix
    try:
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_meta(path: str | os.PathLike) -> dict:
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z['meta']))
    return meta


_ONE_THREAD = {name: '1' for name in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS',
                                       'MKL_NUM_THREADS')}


def _init_worker() -> None:
    """One thread per worker process: `workers` processes share the cores. BLAS (and torch,
    should anything import it) read the spawn environment (_ONE_THREAD); importing torch just to
    call set_num_threads would cost seconds per worker, so only an already loaded one is set."""
    torch = sys.modules.get('torch')
    if torch is not None:
        torch.set_num_threads(1)


@contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    """os.environ with values set (inherited by processes spawned meanwhile), then restored."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _build_one(job: tuple[str, int, CacheSettings]) -> tuple[int, int, float]:
    out_dir, seed, settings = job
    start = time.perf_counter()
    path = shard_path(out_dir, seed)
    arrays = make_shard(seed, settings)
    write_shard(path, arrays)
    return seed, int(arrays['window_lanes'].shape[0] - 1), time.perf_counter() - start


def _check_index(out_dir: Path, settings: CacheSettings) -> None:
    """cache.json must match the requested settings (written on the first build)."""
    index = out_dir / INDEX_NAME
    wanted = {'format': SHARD_FORMAT, 'settings': to_plain(settings)}
    # caches from before an option stay valid
    for option in ('road_look', 'bare_curbs', 'laser_gains'):
        if not getattr(settings, option):
            del wanted['settings'][option]
    for name in SHARES:  # recorded under 'variation'
        del wanted['settings'][name]
    if settings.sensor_variation:  # its constants shape the shards too
        wanted['variation'] = variation_record(settings)
    if index.exists():
        stored = json.loads(index.read_text())
        if stored != wanted:
            diff = {k: (stored.get('settings', {}).get(k), v)
                    for k, v in wanted['settings'].items()
                    if stored.get('settings', {}).get(k) != v}
            raise ConfigError(f'cache {out_dir} was built with other settings '
                             f'(stored, requested): {diff or stored}; use another directory')
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = index.with_name(f'.{INDEX_NAME}.{os.getpid()}.tmp')
    tmp.write_text(json.dumps(wanted, indent=1))
    os.replace(tmp, index)


@dataclass
class CacheReport:
    built: list[int] = field(default_factory=list)  # seeds simulated by this call
    skipped: list[int] = field(default_factory=list)  # shards that already existed
    missing: list[int] = field(default_factory=list)  # left for later (deadline reached)
    windows: int = 0  # windows simulated by this call
    seconds: float = 0.0

    @property
    def windows_per_hour(self) -> float:
        return 3600.0 * self.windows / self.seconds if self.seconds > 0 else math.nan

    @property
    def complete(self) -> bool:
        return not self.missing


def build_cache(out_dir: str | os.PathLike, seeds: Iterable[int],
                settings: CacheSettings = CacheSettings(), workers: int = 2,
                deadline: float | None = None, progress: bool = True) -> CacheReport:
    """Simulate the shards of `seeds` missing from out_dir with `workers` processes.

    Workers are spawned (safe whatever the parent holds: threads, torch, CUDA) and run one
    torch thread each. `deadline` (time.monotonic()) stops handing out new seeds; shards in
    flight are finished. Concurrent builds into one directory are not supported.
    """
    settings.validate()
    out_dir = Path(out_dir)
    _check_index(out_dir, settings)
    for stale in out_dir.glob('.shard_*.tmp.npz'):  # left by a killed build
        stale.unlink(missing_ok=True)
    seeds = list(dict.fromkeys(int(s) for s in seeds))
    report = CacheReport(skipped=[s for s in seeds if shard_path(out_dir, s).exists()])
    todo = [s for s in seeds if not shard_path(out_dir, s).exists()]
    start = time.perf_counter()
    bar = tqdm(total=len(todo) * settings.windows_per_seed, unit='win', disable=not progress,
               desc=f'cache {out_dir.name}', dynamic_ncols=True)
    jobs = iter(todo)

    def past_deadline() -> bool:
        return deadline is not None and time.monotonic() >= deadline

    def done(seed: int, windows: int) -> None:
        report.built.append(seed)
        report.windows += windows
        bar.update(windows)

    try:
        if workers <= 1:
            for seed in jobs:
                if past_deadline():
                    break
                done(*_build_one((str(out_dir), seed, settings))[:2])
        else:
            with _environment(_ONE_THREAD), ProcessPoolExecutor(
                    workers, mp_context=get_context('spawn'), initializer=_init_worker) as pool:
                pending: set = set()
                while True:
                    while len(pending) < workers and not past_deadline():
                        seed = next(jobs, None)
                        if seed is None:
                            break
                        pending.add(pool.submit(_build_one, (str(out_dir), seed, settings)))
                    if not pending:
                        break
                    finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in finished:
                        done(*fut.result()[:2])
    finally:
        bar.close()
        report.seconds = time.perf_counter() - start
        report.missing = [s for s in todo if s not in set(report.built)]
    return report


def cache_seeds(out_dir: str | os.PathLike) -> list[int]:
    """Seeds of the complete shards in a cache directory, sorted."""
    return sorted(int(p.stem.split('_')[1]) for p in Path(out_dir).glob('shard_*.npz'))

