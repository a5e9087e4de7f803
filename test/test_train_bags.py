"""Labelled bags as training data (data/bag_source.py): windows, weighted draws, training."""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch
from test_train import (
    MODEL,
    TINY,
    build_tiny_caches,
    load_payload,
    train_argv,
    write_config,
)

from fhld_ros.bagio import BagWriter
from fhld_ros.bev import BevSpec
from fhld_ros.cli import main as fhld
from fhld_ros.data.bag_source import LabelledBag, bag_key, bag_samples, build_bag_cache
from fhld_ros.data.samples import training_samples
from fhld_ros.sim.simulator import Simulator
from fhld_ros.training.config import load_config
from fhld_ros.training.dataset import (
    CacheDataset,
    SourcesDataset,
    WeightedSourceSampler,
    training_set,
)
from msg_adapters.lanes import lanes_to_marker_array
from msg_adapters.odometry import make_odometry
from msg_adapters.pointcloud2 import create_cloud

pytestmark = pytest.mark.usefixtures('one_torch_thread')

BAG_SEED, BAG_SWEEPS = 7, 30  # 15 windows of TINY's 2 sweeps, one every 2 sweeps


@pytest.fixture(scope='module')
def caches(tmp_path_factory) -> Path:
    """The TINY simulator caches of test_train, and a simulated 30-sweep bag beside them."""
    root = build_tiny_caches(tmp_path_factory.mktemp('cache'))
    assert fhld(['simulate', str(root / 'drive'), '--seed', str(BAG_SEED), '--sweeps',
                 str(BAG_SWEEPS), '--sensor', 'vlp16', '--quiet']) == 0
    return root


def bag_config(path: Path, caches: Path, bags: list, **data) -> Path:
    """test_train's tiny config with data.bags (and other data keys) set."""
    cfg = json.loads(write_config(path, caches).read_text())
    cfg['data'].update(bags=bags, **data)
    path.write_text(json.dumps(cfg))
    return path


def test_bag_windows_are_the_simulators_windows(caches, tmp_path):
    """The bag's sweeps through the node's pipeline with its /odom, and its /lanes_gt taken into
    the window frame, give the windows the simulator cache makes of the same drive."""
    bag = LabelledBag(str(caches / 'drive'))
    sim = Simulator(BAG_SEED, sweeps=BAG_SWEEPS, sensor='vlp16')
    want = list(training_samples(sim, sweeps_per_sample=TINY.sweeps_per_sample,
                                 stride=TINY.stride, spec=BevSpec(TINY.size_px, TINY.resolution_m),
                                 intensity_encoding=TINY.intensity_encoding))
    stats = Counter()
    got = list(bag_samples(bag, TINY, stats))
    assert stats == {'sweeps': 30, 'windows': 15} and len(want) == 15
    lanes_seen = 0
    for g, w in zip(got, want):
        assert g.meta['sweep'] == w.meta['sweep'] and g.meta['stamp_ns'] == w.meta['stamp_ns']
        np.testing.assert_allclose(g.window_to_odom, w.window_to_odom, atol=1e-9)
        np.testing.assert_allclose(g.raster, w.raster, atol=1e-5)
        # /lanes_gt marker ids are the scene's line indices (+1000 for a second piece)
        assert [i % 1000 for i in g.meta['line_ids']] == w.meta['line_ids']
        for a, b in zip(g.lanes, w.lanes, strict=True):
            np.testing.assert_allclose(a, b, atol=1e-9)
        lanes_seen += len(g.lanes)
    assert lanes_seen >= 30  # GT in every window, not a vacuous comparison

    # stored as simulator shards: the dataset reads them back as it reads the cache
    index = build_bag_cache(bag, TINY, tmp_path / 'train')
    assert Path(index['dir']).parent == tmp_path / 'bags' and index['stats']['windows'] == 15
    data = CacheDataset(index['dir'])
    assert len(data) == 15 and data.size_px == TINY.size_px
    for k in (0, 7, 14):
        raster, lanes = data.load(k)
        np.testing.assert_allclose(raster.numpy(), want[k].raster, atol=1e-3)  # float16
        for a, b in zip(lanes, want[k].lanes, strict=True):
            np.testing.assert_allclose(a, b, atol=1e-5)  # float32


def test_bag_key_follows_content_and_settings(caches, tmp_path):
    bag = LabelledBag(str(caches / 'drive'))
    key = bag_key(bag, TINY)
    copy = tmp_path / 'drive'
    shutil.copytree(caches / 'drive', copy)  # copy2: same names, sizes, times
    assert bag_key(LabelledBag(str(copy)), TINY) == key
    assert bag_key(bag, dataclasses.replace(TINY, stride=3)) != key
    assert bag_key(dataclasses.replace(bag, lanes_topic='/lanes'), TINY) != key
    os.utime(copy / 'metadata.yaml', ns=(1, 1))
    assert bag_key(LabelledBag(str(copy)), TINY) != key


def test_weighted_draws_follow_the_weights():
    sizes, weights = [40, 7, 13], [1.0, 0.5, 0.25]
    sampler = WeightedSourceSampler(sizes, weights, seed=5)
    source = np.repeat(np.arange(3), sizes)
    draws = []
    for epoch in range(200):
        sampler.set_epoch(epoch)
        draws += list(sampler)
    assert len(draws) == 200 * 60
    shares = np.bincount(source[draws], minlength=3) / len(draws)
    np.testing.assert_allclose(shares, np.array(weights) / sum(weights), atol=0.015)
    # every window of the small sources is drawn, uniformly within its source
    small = np.bincount(draws, minlength=60)[40:47]
    assert small.min() > 0.6 * small.mean()
    # a function of (seed, epoch): the same again, another epoch differs, ranks split the draws
    sampler.set_epoch(3)
    again = WeightedSourceSampler(sizes, weights, seed=5)
    again.set_epoch(3)
    assert list(sampler) == list(again) == draws[180:240]
    ranks = [WeightedSourceSampler(sizes, weights, 2, rank, seed=5) for rank in (0, 1)]
    for r in ranks:
        r.set_epoch(3)
    assert list(ranks[0]) == draws[180:240:2] and list(ranks[1]) == draws[181:240:2]


def test_training_set_draws_from_the_sources(caches, tmp_path):
    bags = [{'path': str(caches / 'drive'), 'weight': 0.5}]
    cfg = load_config(bag_config(tmp_path / 'c.yaml', caches, bags))
    data = training_set(cfg, MODEL.size_px, build=True)
    assert isinstance(data, SourcesDataset) and data.sizes == [4, 15]
    assert data.weights == [1.0, 0.5]
    assert data.provenance[0]['windows'] == 15 and data.provenance[0]['weight'] == 0.5
    assert data.datasets[1].key_offset == 4  # its augmentation keys follow the simulator's
    item = data[4 + 3]  # bag window 3, augmented and cut to the model's raster
    assert item['raster'].shape == (4, MODEL.size_px, MODEL.size_px) and item['lanes']
    only = load_config(bag_config(tmp_path / 'b.yaml', caches, bags, sim_weight=0))
    assert training_set(only, MODEL.size_px).sizes == [15]  # bags only


@pytest.mark.slow
def test_train_on_cache_and_bag_resumes_exactly(caches, tmp_path):
    bags = [{'path': str(caches / 'drive'), 'weight': 0.5}]
    cfg = bag_config(tmp_path / 'tiny.yaml', caches, bags)
    assert fhld(['train', '--config', str(cfg), '--cache-only', '--quiet']) == 0
    built = list((caches / 'bags').glob('drive-*/bag.json'))
    assert len(built) == 1
    assert fhld(train_argv(cfg, tmp_path / 'a')) == 0
    straight = load_payload(tmp_path / 'a' / 'last.pt')
    assert straight['meta']['iteration'] == 3
    [source] = straight['meta']['bag_sources']
    assert source['path'] == str(caches / 'drive') and source['weight'] == 0.5
    assert source['windows'] == 15 and built[0].parent.name.endswith(source['key'])
    assert straight['meta']['train_config']['data']['bags'][0]['weight'] == 0.5

    run_b = train_argv(cfg, tmp_path / 'b')
    assert fhld([*run_b, '--max-minutes', '0']) == 0
    assert fhld([*run_b, '--resume']) == 0
    resumed = load_payload(tmp_path / 'b' / 'last.pt')
    assert resumed['meta']['iteration'] == 3
    assert resumed['meta']['bag_sources'] == straight['meta']['bag_sources']
    for key, value in straight['state_dict'].items():
        assert torch.equal(value, resumed['state_dict'][key]), key


def write_bag(path: Path, label_stamp_ns: int, label_frame: str = 'odom',
              topics: tuple[str, ...] = ('/points', '/odom', '/lanes_gt')) -> Path:
    """Two 3-point sweeps with odometry at 0.1 s and 0.2 s, and one label of one lane."""
    with BagWriter(path) as bag:
        fam = bag.family
        points = np.zeros(3, dtype=[(n, np.float32) for n in ('x', 'y', 'z', 'intensity')])
        points['x'] = [1.0, 2.0, 3.0]
        lane = np.array([[-5.0, 1.5, 0.0], [5.0, 1.5, 0.0]])
        if '/lanes_gt' in topics:
            bag.write('/lanes_gt', 'visualization_msgs/msg/MarkerArray', label_stamp_ns,
                      lanes_to_marker_array(fam, fam.header(label_stamp_ns, label_frame),
                                            [lane], [1.0], [0]))
        for stamp in (100_000_000, 200_000_000):
            if '/odom' in topics:
                bag.write('/odom', 'nav_msgs/msg/Odometry', stamp,
                          make_odometry(fam, fam.header(stamp, 'odom'), 'lidar', np.eye(4)))
            if '/points' in topics:
                bag.write('/points', 'sensor_msgs/msg/PointCloud2', stamp,
                          create_cloud(fam.cls('sensor_msgs/msg/PointCloud2'),
                                       fam.header(stamp, 'lidar'), points))
    return path


def test_windows_without_a_usable_label_are_counted_not_trained_on(tmp_path):
    good = LabelledBag(str(write_bag(tmp_path / 'good', 50_000_000)))
    stats = Counter()
    [window] = bag_samples(good, TINY, stats)
    assert stats == {'sweeps': 2, 'windows': 1} and len(window.lanes) == 1
    np.testing.assert_allclose(window.lanes[0][[0, -1], :2], [[-5.0, 1.5], [5.0, 1.5]])
    late = LabelledBag(str(write_bag(tmp_path / 'late', 900_000_000)))
    with pytest.raises(ValueError, match=r'no training window \(sweeps 2, unlabelled 1\)'):
        list(bag_samples(late, TINY))
    other = LabelledBag(str(write_bag(tmp_path / 'map', 50_000_000, 'map')))
    with pytest.raises(ValueError, match="other_frame 1.*/lanes_gt in 'map', windows in 'odom'"):
        list(bag_samples(other, TINY))


def test_bad_bag_entries_are_one_clear_error(caches, tmp_path, capsys):
    drive = str(caches / 'drive')
    no_gt = write_bag(tmp_path / 'no_gt', 0, topics=('/points', '/odom'))
    no_points = write_bag(tmp_path / 'no_points', 0, topics=('/odom', '/lanes_gt'))
    cases = [([{'path': str(tmp_path / 'missing')}], {}, 'missing does not exist'),
             ([{'path': drive, 'weight': 0}], {}, 'data.bags[0].weight must be a number > 0'),
             ([{'path': drive, 'weight': -1.0}], {}, 'weight must be a number > 0, not -1.0'),
             ([{'path': drive, 'wieght': 1}], {}, 'unknown key(s) wieght in data.bags[0]'),
             ([{'weight': 1}], {}, 'data.bags[0].path must name a bag'),
             ([{'path': str(no_gt)}], {}, 'no_gt has no topic /lanes_gt'),
             ([{'path': drive}, {'path': str(no_points)}], {},
              'data.bags[1]: bag ' + str(no_points) + ' has no topic /points'),
             ('drive', {}, 'data.bags must be a list'),
             ([{'path': drive}], {'sim_weight': -1}, 'data.sim_weight must be a number >= 0'),
             ([], {'sim_weight': 0}, 'nothing to train on')]
    for k, (bags, data, message) in enumerate(cases):
        cfg = bag_config(tmp_path / f'bad{k}.yaml', caches, bags, **data)
        assert fhld(['train', '--config', str(cfg)]) == 2, message
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err


def test_a_labelled_real_sweep_is_one_training_window(tmp_path):
    """fhld realscans --write-bags: a sweep and its hand labels as a bag without /odom, which
    gives one window per sweep in the sensor frame with the labelled lines as GT."""
    from fhld_ros.evaluation.real_scans import write_labelled_bags
    rng = np.random.default_rng(0)
    sweep = np.column_stack([rng.uniform(-3, 3, (500, 2)), np.full(500, -1.7),
                             rng.uniform(0, 0.3, 500)]).astype('<f4')
    (tmp_path / 'scan_0.bin').write_bytes(sweep.tobytes())
    line = [[-3.0, 1.0, -1.7], [3.0, 1.0, -1.7]]
    labels = tmp_path / 'labels.json'
    labels.write_text(json.dumps({'scans': [{'file': 'scan_0.bin', 'sensor': 'test', 'lines': [
        {'id': 'left', 'kind': 'solid', 'points': line}]}]}))
    [bag] = write_labelled_bags(tmp_path, tmp_path / 'bags', ['scan_0.bin'], labels)
    stats = Counter()
    [window] = bag_samples(LabelledBag(str(bag)), TINY, stats)
    assert stats == {'sweeps': 1, 'windows': 1}
    np.testing.assert_allclose(window.lanes[0][[0, -1]], line, atol=1e-6)
    np.testing.assert_allclose(window.window_to_odom, np.eye(4))  # the sensor frame
    with pytest.raises(ValueError, match='not in .*labels.json: other.bin'):
        write_labelled_bags(tmp_path, tmp_path / 'more', ['other.bin'], labels)
    with pytest.raises(ValueError, match='exists'):  # never over a bag already there
        write_labelled_bags(tmp_path, tmp_path / 'bags', ['scan_0.bin'], labels)
