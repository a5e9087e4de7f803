"""SALAD's data sources: simulated drives (their lanes on the painted pixels, the camera drawn
per seed), ONCE-3DLanes and OpenLane files written and read back, the two real OpenLane
examples, and malformed files refused with the file named."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from fhld_ros.data.cache import TEST_SEED_BASE
from fhld_ros.salad.once_format import read_once, write_once, write_once_predictions
from fhld_ros.salad.openlane_format import read_openlane, write_openlane
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.sim_source import (
    HEIGHT_RANGE_M,
    HFOV_RANGE_DEG,
    PITCH_RANGE_DEG,
    PRINCIPAL_JITTER,
    camera_for_seed,
    drive_camera,
    salad_seeds,
    simulated_samples,
    visible_lanes,
)
from fhld_ros.sim.camera import HFOV_DEG, intrinsics

REAL = Path(__file__).resolve().parents[1].parent / 'shared' / 'real_scans'
OPENLANE_EXAMPLES = REAL / 'openlane_examples'


def _project(K: np.ndarray, points: np.ndarray) -> np.ndarray:
    p = points @ K.T
    return p[:, :2] / p[:, 2:]


def _paint_share(gray: np.ndarray, K: np.ndarray, lanes: list[np.ndarray]) -> float:
    """Share of the lane points within 30 m that are brighter (by 15 of 255) than the pixels
    0.6 m (at least 4 px) to either side: paint on asphalt."""
    h, w = gray.shape
    pts = np.concatenate(lanes)
    u, v = np.round(_project(K, pts)).astype(int).T
    d = np.maximum(4, np.round(K[0, 0] * 0.6 / pts[:, 2])).astype(int)
    ok = (pts[:, 2] < 30.0) & (u - d >= 0) & (u + d < w) & (v >= 0) & (v < h)
    u, v, d = u[ok], v[ok], d[ok]
    around = np.maximum(gray[v, u - d], gray[v, u + d])
    return float(np.mean(gray[v, u] > around + 15))


@pytest.mark.parametrize('seed', list(salad_seeds('test', 2, start=1)))
def test_simulated_lanes_lie_on_the_painted_pixels(seed):
    camera = drive_camera(seed, 1, (480, 270))
    image, lanes = visible_lanes(camera, 0)
    assert len(lanes) >= 3
    pts = np.concatenate(lanes)
    assert pts[:, 2].min() > 0.5  # in front of the camera
    assert all(lane[0, 2] < lane[-1, 2] for lane in lanes)  # near to far
    uv = _project(camera.K, pts)
    assert (uv > -1).all() and (uv[:, 0] < 481).all() and (uv[:, 1] < 271).all()
    # the rendered depth where they project is their z (ground between pixel rows: a few %)
    u, v = np.clip(np.round(uv).astype(int), 0, [479, 269]).T
    assert np.median(np.abs(image.depth[v, u] / pts[:, 2] - 1)) < 0.03
    gray = image.rgb.astype(np.float64).mean(axis=2)
    share = _paint_share(gray, camera.K, lanes)
    shifted = max(_paint_share(gray, camera.K, [lane + [dx, 0, 0] for lane in lanes])
                  for dx in (-0.8, 0.8))
    assert share > 0.25 and share > shifted + 0.15, (share, shifted)
    # the road plane through the near lane points is the drawn camera's height and pitch
    near = pts[pts[:, 2] < 20.0]
    centre = near.mean(axis=0)
    normal = np.linalg.svd(near - centre)[2][2]
    normal *= np.sign(normal[1])
    draw = camera_for_seed(seed)
    assert abs(normal @ centre - draw.height_m) < 0.1
    assert abs(np.rad2deg(np.arctan2(normal[2], normal[1])) - draw.pitch_deg) < 1.0


def test_the_camera_is_drawn_per_seed_and_deterministic():
    seeds = salad_seeds('train', 30)
    draws = [camera_for_seed(s) for s in seeds]
    assert camera_for_seed(seeds[3]) == draws[3]
    for values, (lo, hi) in (([d.height_m for d in draws], HEIGHT_RANGE_M),
                             ([d.pitch_deg for d in draws], PITCH_RANGE_DEG),
                             ([d.hfov_deg for d in draws], HFOV_RANGE_DEG)):
        assert lo <= min(values) and max(values) <= hi and len(set(values)) == len(values)
        assert max(values) - min(values) > 0.5 * (hi - lo)  # spread over the range
    offsets = np.array([d.principal_offset for d in draws])
    assert np.abs(offsets).max() <= PRINCIPAL_JITTER and np.abs(offsets).max() > 0.02
    a, b = drive_camera(seeds[0], 1, (320, 180)), drive_camera(seeds[1], 1, (320, 180))
    assert not np.allclose(a.K, b.K) and not np.allclose(a.T_cloud_camera, b.T_cloud_camera)
    np.testing.assert_allclose(a.K, draws[0].intrinsics((320, 180)))
    fixed = drive_camera(seeds[0], 1, (320, 180), randomise=False)
    np.testing.assert_allclose(fixed.K, intrinsics(320, 180, HFOV_DEG))
    # the splits apart from each other and from the LiDAR detector's seeds
    train, test, val = (salad_seeds(split, 10 ** 6) for split in ('train', 'test', 'val'))
    assert train.stop <= test.start and train.start >= TEST_SEED_BASE + 10 ** 6
    assert test.stop <= val.start
    with pytest.raises(ValueError):
        salad_seeds('validation', 1)


def test_simulated_samples_repeat_per_seed():
    seed = salad_seeds('train', 1, start=7)[0]
    first = list(simulated_samples(seed, 2, (160, 90)))
    again = list(simulated_samples(seed, 2, (160, 90)))
    assert [s.name for s in first] == [f'sim seed {seed} sweep {k}' for k in (0, 10)]
    for a, b in zip(first, again):
        assert a.size == (160, 90)
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.intrinsics, b.intrinsics)
        assert len(a.lanes) == len(b.lanes) > 0
        for la, lb in zip(a.lanes, b.lanes):
            np.testing.assert_array_equal(la, lb)
    np.testing.assert_allclose(first[0].intrinsics, camera_for_seed(seed).intrinsics((160, 90)))


def _samples() -> list[CameraLaneSample]:
    """Two small samples: smooth images (JPEG keeps them), lanes far to near in the first."""
    y, x = np.mgrid[0:48, 0:64]
    image = np.stack([x * 3, y * 4, (x + y) * 2], axis=-1).astype(np.uint8)
    K = np.array([[50.0, 0.0, 31.0], [0.0, 52.0, 24.5], [0.0, 0.0, 1.0]])
    z = np.linspace(3.0, 40.0, 12)
    lane_a = np.stack([np.full_like(z, -1.8), 1.5 - 0.01 * z, z], axis=1)
    lane_b = np.stack([1.7 + 0.001 * z ** 2, np.full_like(z, 1.4), z], axis=1)
    return [CameraLaneSample(image, K, [lane_a[::-1], lane_b], 'first'),
            CameraLaneSample(image[::-1].copy(), K * [[1.1], [1.1], [1]], [lane_b], 'second')]


def _assert_same(read: CameraLaneSample, wrote: CameraLaneSample) -> None:
    np.testing.assert_array_equal(read.intrinsics, wrote.intrinsics)
    assert np.abs(read.image.astype(int) - wrote.image).mean() < 3  # JPEG
    assert len(read.lanes) == len(wrote.lanes)
    for got, lane in zip(read.lanes, wrote.lanes):
        near_first = lane if lane[0, 2] < lane[-1, 2] else lane[::-1]
        np.testing.assert_allclose(got, near_first, rtol=0, atol=1e-12)


def test_once_round_trip(tmp_path):
    wrote = _samples()
    labels = write_once(tmp_path, 'val', wrote, sequence='000042')
    assert [p.relative_to(tmp_path).as_posix() for p in labels] == [
        'val/000042/cam01/000000.json', 'val/000042/cam01/000001.json']
    data = json.loads(labels[0].read_text())
    assert set(data) == {'lanes', 'calibration'} and np.shape(data['calibration']) == (3, 4)
    (tmp_path / 'val' / '000042' / 'cam01' / 'empty.json').write_text('')  # skipped
    read = list(read_once(tmp_path, 'val'))
    assert [s.name for s in read] == ['000042/cam01/000000', '000042/cam01/000001']
    for r, w in zip(read, wrote):
        _assert_same(r, w)
    # written again under their names; images also found under raw_data/
    write_once(tmp_path / 'again', 'train', read)
    (tmp_path / 'again' / 'data').rename(tmp_path / 'again' / 'raw_data')
    assert [s.name for s in read_once(tmp_path / 'again', 'train')] == [s.name for s in read]
    preds = write_once_predictions(tmp_path / 'pred', [(read[0].name, read[0].lanes, [0.9, 0.4])])
    pred = json.loads(preds[0].read_text())
    assert preds[0] == tmp_path / 'pred' / '000042' / 'cam01' / '000000.json'
    assert [lane['score'] for lane in pred['lanes']] == [0.9, 0.4]
    np.testing.assert_array_equal(pred['lanes'][1]['points'], read[0].lanes[1])


def test_once_malformed_files_name_the_file(tmp_path):
    label = write_once(tmp_path, 'train', _samples()[:1])[0]
    good = label.read_text()
    eye = np.eye(3).tolist()
    for text in ('{"lanes": [[[1, 2', '[]', json.dumps({'lanes': []}),
                 json.dumps({'lanes': [], 'calibration': [[1, 0, 0], [0, 1, 0]]}),
                 json.dumps({'lanes': [], 'calibration': np.ones((3, 4)).tolist()}),
                 json.dumps({'lanes': {}, 'calibration': eye}),
                 json.dumps({'lanes': [[[0, 0], [1, 2]]], 'calibration': eye}),
                 json.dumps({'lanes': [[[0, 1, 'x'], [0, 1, 2]]], 'calibration': eye})):
        label.write_text(text)
        with pytest.raises(ValueError, match=re.escape(str(label))):
            list(read_once(tmp_path, 'train'))
    label.write_text(good)
    next((tmp_path / 'data').rglob('*.jpg')).unlink()
    with pytest.raises(ValueError, match=re.escape(str(label)) + '.*does not exist'):
        list(read_once(tmp_path, 'train'))
    with pytest.raises(ValueError, match='split directory'):
        list(read_once(tmp_path, 'val'))


def test_openlane_round_trip_and_visibility(tmp_path):
    wrote = _samples()
    labels = write_openlane(tmp_path, wrote, segment='segment-7')
    read = list(read_openlane(tmp_path))
    assert [s.name for s in read] == ['segment-7/000000', 'segment-7/000001']
    for r, w in zip(read, wrote):
        _assert_same(r, w)
    data = json.loads(labels[0].read_text())
    assert data['file_path'] == 'validation/segment-7/000000.jpg'
    line = data['lane_lines'][1]
    np.testing.assert_allclose(np.array(line['uv']).T, _project(wrote[0].intrinsics,
                                                                wrote[0].lanes[1]))
    assert np.array(line['xyz'])[0].min() > 0  # OpenLane's x is forward
    # invisible points split a lane; points behind the camera are dropped
    line['visibility'][4:6] = [0.0, 0.0]
    line['xyz'][0][-1] = -1.0
    labels[0].write_text(json.dumps(data))
    pieces = next(read_openlane(tmp_path, tmp_path / 'lane3d_1000' / 'validation')).lanes[1:]
    assert [p.shape[0] for p in pieces] == [4, 5]
    np.testing.assert_allclose(np.concatenate(pieces), np.delete(wrote[0].lanes[1], [4, 5, 11],
                                                                 axis=0), atol=1e-12)


def test_openlane_malformed_files_name_the_file(tmp_path):
    label = write_openlane(tmp_path, _samples()[:1])[0]
    data = json.loads(label.read_text())
    bad_xyz = json.loads(label.read_text())
    bad_xyz['lane_lines'][0]['xyz'] = bad_xyz['lane_lines'][0]['xyz'][:2]
    bad_vis = json.loads(label.read_text())
    bad_vis['lane_lines'][0]['visibility'] = [1.0]
    for text in ('not json', json.dumps({**data, 'intrinsic': [[1, 0], [0, 1]]}),
                 json.dumps({k: v for k, v in data.items() if k != 'file_path'}),
                 json.dumps(bad_xyz), json.dumps(bad_vis)):
        label.write_text(text)
        with pytest.raises(ValueError, match=re.escape(str(label))):
            list(read_openlane(tmp_path))
    label.write_text(json.dumps(data))
    next((tmp_path / 'images').rglob('*.jpg')).unlink()
    with pytest.raises(ValueError, match=re.escape(str(label)) + '.*does not exist'):
        list(read_openlane(tmp_path))


def test_real_openlane_examples_project_onto_their_uv():
    if not OPENLANE_EXAMPLES.is_dir():
        pytest.skip(f'{OPENLANE_EXAMPLES} is absent')
    samples = list(read_openlane(OPENLANE_EXAMPLES))
    assert len(samples) == 2
    for sample in samples:
        assert sample.size == (1920, 1280) and len(sample.lanes) == 5
        label = next(OPENLANE_EXAMPLES.rglob(sample.name.split('/')[1] + '.json'))
        uv = np.concatenate([np.array(line['uv']).T
                             for line in json.loads(label.read_text())['lane_lines']])
        projected = np.concatenate([_project(sample.intrinsics, lane) for lane in sample.lanes])
        assert all(lane[:, 2].min() > 5 for lane in sample.lanes)
        gap = np.linalg.norm(uv[:, None] - projected[None], axis=2)
        assert gap.min(axis=1).max() < 2.0 and gap.min(axis=0).max() < 2.0


def test_salad_trains_on_a_users_once_and_openlane_data(tmp_path, capsys):
    from fhld_ros.cli import main
    from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT, load_salad
    from fhld_ros.salad.dataset import ShardSamples, to_virtual

    seed = salad_seeds('train', 1, start=7)[0]
    once = list(simulated_samples(seed, 3, (480, 270)))
    write_once(tmp_path / 'once', 'train', once, sequence='000101')
    write_once(tmp_path / 'once', 'val', once[:1], sequence='000102')  # another split: not read
    write_openlane(tmp_path / 'openlane', _samples(), split='training')
    out, cache = tmp_path / 'run', tmp_path / 'run' / 'cache'
    train = ['salad-train', str(out), '--drives', '0', '--batch', '1', '--workers', '0',
             '--threads', '1', '--init', str(DEFAULT_SALAD_CHECKPOINT)]
    assert main([*train, '--steps', '2', '--once', str(tmp_path / 'once'), '--openlane',
                 str(tmp_path / 'openlane'), '--openlane-labels',
                 str(tmp_path / 'openlane' / 'lane3d_1000' / 'training')]) == 0
    # every labelled image of the chosen split and folder, resampled to the virtual camera
    shards = sorted(cache.glob('*.npz'))
    assert [p.name.split('-')[0] for p in shards] == ['once', 'openlane']
    samples = ShardSamples(shards[:1])
    assert len(samples) == 3 and len(ShardSamples(shards)) == 5
    model, info = load_salad(out / 'salad.pt')
    camera = model.cfg.camera  # --init's view
    assert camera == load_salad(DEFAULT_SALAD_CHECKPOINT)[0].cfg.camera
    for i, sample in enumerate(read_once(tmp_path / 'once', 'train')):
        want = to_virtual(once[i], camera).image.astype(int)
        assert np.abs(samples.images[i] - want).mean() < 3  # JPEG
        kept = [lane for lane in sample.lanes if len(lane) >= 2]
        assert len(samples.lanes[i]) == len(kept) > 0
        for got, lane in zip(samples.lanes[i], kept):
            np.testing.assert_allclose(got, lane, atol=1e-5)  # float32 in the shard
    assert info['meta']['images'] == 5 and len(info['meta']['datasets']) == 2
    assert info['meta']['datasets'][0].endswith(f'{tmp_path / "once"} train')
    # a resumed run reuses the packed images: the shards are not written again, and the
    # temporary file of a shard whose writing was cut off is not read
    mtimes = [p.stat().st_mtime_ns for p in shards]
    (cache / '.sim_1.tmp.npz').write_bytes(b'PK cut off')
    assert main([*train[:-2], '--steps', '3', '--resume', '--once',
                 str(tmp_path / 'once')]) == 0
    assert [p.stat().st_mtime_ns for p in sorted(cache.glob('[!.]*.npz'))] == mtimes
    assert load_salad(out / 'salad.pt')[1]['meta']['steps'] == 3
    # bad input: one line naming the problem
    capsys.readouterr()
    train[1] = str(tmp_path / 'bad')
    assert main([*train, '--steps', '1', '--once', str(tmp_path / 'none')]) != 0
    assert 'no such ONCE-3DLanes split directory' in capsys.readouterr().err
    assert main([*train, '--steps', '1', '--openlane-labels', str(tmp_path)]) != 0
    assert '--openlane-labels needs --openlane' in capsys.readouterr().err
    train[1] = str(tmp_path / 'big')
    assert main([*train, '--steps', '1', '--batch', '6', '--cache', str(cache)]) != 0
    assert '--batch: a batch of 6 needs at least 6 training images; there are 5' in \
        capsys.readouterr().err
