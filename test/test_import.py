"""`fhld import`: PCD (ascii, binary, binary_compressed) and KITTI .bin sweeps into a bag that
reads back equal to the source, /odom from poses, stamps from rates or times, the LZF decoder,
one clear error per kind of bad input, and an imported bag replayed through the pipeline."""
from __future__ import annotations

import argparse
import struct
from pathlib import Path

import numpy as np
import pytest

from fhld_ros.bagio import read_messages, topic_counts
from fhld_ros.commands import import_scans
from fhld_ros.commands.replay import replay
from fhld_ros.errors import ConfigError
from fhld_ros.importing.pcd import XYZI_DTYPE, lzf_decompress, read_pcd
from fhld_ros.parameters import DetectorParams
from fhld_ros.sim.simulator import Simulator
from msg_adapters.family import stamp_to_ns
from msg_adapters.odometry import euler_to_matrix, odometry_to_matrix
from msg_adapters.pointcloud2 import read_points, read_xyzi

REAL_PCD = Path(__file__).resolve().parents[2] / 'shared/real_scans/pjlab_camera_lidar_pair/0.pcd'
START_NS = 1_700_000_000 * 1_000_000_000
_TYPE = {'f': 'F', 'i': 'I', 'u': 'U'}


def lzf_compress(data: bytes) -> bytes:
    """A tiny greedy LZF compressor (test side): literal runs and back-references, overlapping
    ones included, so the decoder is checked against a second implementation of the format."""
    out, literal, table, i = bytearray(), bytearray(), {}, 0

    def flush() -> None:
        while literal:
            out.append(min(len(literal), 32) - 1)
            out.extend(literal[:32])
            del literal[:32]

    while i < len(data):
        ref = table.get(data[i:i + 3]) if i + 3 <= len(data) else None
        table[data[i:i + 3]] = i
        if ref is not None and i - ref <= 8192:
            length = 0
            while length < min(264, len(data) - i) and data[ref + length] == data[i + length]:
                length += 1
            flush()
            code, offset = length - 2, i - ref - 1
            out.append((min(code, 7) << 5) | (offset >> 8))
            if code >= 7:
                out.append(code - 7)
            out.append(offset & 0xFF)
            i += length
            continue
        literal.append(data[i])
        i += 1
    flush()
    return bytes(out)


def pcd_bytes(points: np.ndarray, data: str, height: int = 1, **header: str) -> bytes:
    """A PCD file of a structured array; gaps between fields become `_` padding (garbage-filled).
    Keyword arguments replace header lines (e.g. TYPE='F F F X')."""
    fields, pos = [], 0
    for name in sorted(points.dtype.names, key=lambda n: points.dtype.fields[n][1]):
        ftype, offset = points.dtype.fields[name][:2]
        if offset > pos:
            fields.append(('_', np.dtype('u1'), offset - pos))
        fields.append((name, ftype.base, int(np.prod(ftype.shape))))
        pos = offset + ftype.itemsize
    if points.dtype.itemsize > pos:
        fields.append(('_', np.dtype('u1'), points.dtype.itemsize - pos))
    names = [f'_pad{k}' if n == '_' else n for k, (n, _, _) in enumerate(fields)]
    stored = np.empty(len(points), [(n, b.newbyteorder('<'), (c,) if c > 1 else ())
                                    for n, (_, b, c) in zip(names, fields)])
    for name, (real, _, _) in zip(names, fields):
        stored[name] = 0xAB if real == '_' else points[real]
    lines = {'VERSION': '0.7', 'FIELDS': ' '.join(f[0] for f in fields),
             'SIZE': ' '.join(str(f[1].itemsize) for f in fields),
             'TYPE': ' '.join(_TYPE[f[1].kind] for f in fields),
             'COUNT': ' '.join(str(f[2]) for f in fields), 'WIDTH': str(len(points) // height),
             'HEIGHT': str(height), 'VIEWPOINT': '0 0 0 1 0 0 0', 'POINTS': str(len(points)),
             'DATA': data}
    lines.update(header)
    lines['DATA'] = lines.pop('DATA')  # extra lines go before it
    text = '# .PCD v0.7 - Point Cloud Data file format\n' + ''.join(
        f'{k} {v}\n' for k, v in lines.items() if v is not None)
    if data == 'ascii':
        formats = [{'f4': '%.9g', 'f8': '%.17g'}.get(f'{b.kind}{b.itemsize}', '%d')
                   for _, b, _ in fields]
        rows = [' '.join(fmt % v for name, fmt in zip(names, formats)
                         for v in np.atleast_1d(stored[name][i]).tolist())
                for i in range(len(stored))]
        return (text + '\n'.join(rows) + '\n').encode()
    if data == 'binary':
        return text.encode() + stored.tobytes()
    packed = lzf_compress(columns := b''.join(stored[name].tobytes() for name in names))
    return text.encode() + struct.pack('<II', len(packed), len(columns)) + packed


def known_cloud(n: int = 200, seed: int = 0) -> np.ndarray:
    """x, y, z, a COUNT-3 normal, uint16 ring, float intensity, float64 time; padding between."""
    rng = np.random.default_rng(seed)
    points = np.zeros(n, {'names': ['x', 'y', 'z', 'normal', 'ring', 'intensity', 'time'],
                          'formats': ['<f4', '<f4', '<f4', ('<f4', (3,)), '<u2', '<f4', '<f8'],
                          'offsets': [0, 4, 8, 16, 28, 32, 40], 'itemsize': 56})
    for axis in 'xyz':
        points[axis] = rng.uniform(-40, 40, n)
    points['normal'] = rng.normal(size=(n, 3))
    points['ring'] = np.arange(n) % 16
    points['intensity'] = np.round(rng.uniform(0, 255, n))
    points['time'] = np.linspace(0, 0.1, n)
    return points


def run_import(*argv: object) -> int:
    parser = argparse.ArgumentParser()
    import_scans.add_arguments(parser)
    return import_scans.run(parser.parse_args([str(a) for a in (*argv, '--quiet')]))


def bag_messages(path: Path) -> dict[str, list[tuple[int, object]]]:
    out: dict[str, list] = {}
    for topic, stamp, msg in read_messages(path):
        out.setdefault(topic, []).append((stamp, msg))
    return out


def poses_text(poses: list[np.ndarray]) -> str:
    """KITTI odometry layout: 12 numbers (3x4 row-major) a line."""
    return ''.join(' '.join(f'{v:.12e}' for v in p[:3].ravel()) + '\n' for p in poses)


def expected_xyzi(points: np.ndarray, intensity: str = 'intensity') -> np.ndarray:
    return np.rec.fromarrays([points[n] for n in ('x', 'y', 'z', intensity)],
                             dtype=XYZI_DTYPE).view(np.ndarray)


def test_lzf_hand_encoded_stream() -> None:
    # literal 'abc'; overlapping reference (distance 3, length 6); literal 'X'; a reference of
    # 7 + 3 + 2 = 12 bytes at distance 1 (a run); a plain reference of 4 bytes at distance 22
    stream = b'\x02abc' + b'\x80\x02' + b'\x00X' + b'\xe0\x03\x00' + b'\x40\x15'
    assert lzf_decompress(stream, 26) == b'abcabcabcX' + b'X' * 12 + b'abca'


@pytest.mark.parametrize('data', [b'', b'a', bytes(5000), b'lane paint ' * 300,
                                  np.random.default_rng(1).integers(0, 4, 20000, np.uint8)
                                  .tobytes()])
def test_lzf_round_trip(data: bytes) -> None:
    packed = lzf_compress(data)
    if len(data) > 100:
        assert len(packed) < len(data)  # back-references were used
    assert lzf_decompress(packed, len(data)) == data


@pytest.mark.parametrize('stream, size, message', [
    (b'\x05abc', 6, 'runs past the end'),
    (b'\x00a\x20\x05', 3, 'before the start'),
    (b'\x00a\x20', 3, 'ends inside a back-reference'),
    (b'\x02abc', 4, 'expands to 3 bytes, the header states 4'),
    (b'\x02abc\x80\x02', 5, 'expands past the 5 bytes'),
])
def test_lzf_errors(stream: bytes, size: int, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        lzf_decompress(stream, size)


@pytest.mark.parametrize('data', ['ascii', 'binary', 'binary_compressed'])
@pytest.mark.parametrize('height', [1, 8])
def test_pcd_imports_equal_to_source(tmp_path: Path, data: str, height: int) -> None:
    points = known_cloud()
    if height > 1:
        points[[3, 50, 77]] = np.zeros(1, points.dtype)  # organised no-returns
        points['x'][[9, 120]] = np.nan
    (tmp_path / 'scan.pcd').write_bytes(pcd_bytes(points, data, height=height))
    cloud = read_pcd(tmp_path / 'scan.pcd')
    assert (cloud.width, cloud.height) == (len(points) // height, height)
    assert cloud.points.dtype.names == ('x', 'y', 'z', 'normal', 'ring', 'intensity', 'time')
    for name in cloud.points.dtype.names:  # fields after padding and COUNT 3 stay aligned
        np.testing.assert_array_equal(cloud.points[name], points[name])
    assert run_import(tmp_path / 'scan.pcd', tmp_path / 'bag') == 0
    (stamp, msg), = bag_messages(tmp_path / 'bag')['/points']
    assert stamp == stamp_to_ns(msg.header.stamp) == START_NS
    assert msg.header.frame_id == 'lidar'
    assert (msg.height, msg.width) == (height, len(points) // height)
    assert read_points(msg).tobytes() == expected_xyzi(points).tobytes()
    xyz, intensity = read_xyzi(msg)
    keep = np.isfinite(points['x']) & (np.abs(points['x']) + np.abs(points['y']) > 0)
    np.testing.assert_array_equal(xyz, np.stack([points[a][keep] for a in 'xyz'], axis=1))
    np.testing.assert_array_equal(intensity, points['intensity'][keep])


@pytest.mark.parametrize('data', ['binary', 'binary_compressed'])
def test_pcd_every_type_and_size(tmp_path: Path, data: str) -> None:
    types = ['<f8', '<i1', '<i2', '<i4', '<i8', '<u1', '<u2', '<u4', '<u8', '<u2']
    names = [*(f'v{k}' for k in range(9)), 'reflectivity']
    points = np.zeros(30, [(a, '<f4') for a in 'xyz'] + list(zip(names, types)))
    rng = np.random.default_rng(2)
    for name in points.dtype.names:
        ftype = points.dtype[name]
        points[name] = rng.integers(np.iinfo(ftype).min, np.iinfo(ftype).max, 30, ftype,
                                    endpoint=True) if ftype.kind in 'iu' else rng.normal(size=30)
    (tmp_path / 'types.pcd').write_bytes(pcd_bytes(points, data))
    cloud = read_pcd(tmp_path / 'types.pcd')
    assert cloud.points.dtype == points.dtype
    assert cloud.points.tobytes() == points.tobytes()
    run_import(tmp_path / 'types.pcd', tmp_path / 'bag')
    (_, msg), = bag_messages(tmp_path / 'bag')['/points']
    assert read_points(msg).tobytes() == expected_xyzi(points, 'reflectivity').tobytes()


@pytest.mark.parametrize('name', ['reflectivity', 'i', 'I'])
def test_pcd_intensity_fallbacks(tmp_path: Path, name: str, capsys) -> None:
    points = np.zeros(5, [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), (name, '<u1')])
    points['x'], points[name] = np.arange(1, 6), np.arange(10, 15)
    (tmp_path / 'a.pcd').write_bytes(pcd_bytes(points, 'ascii', VIEWPOINT='5 0 0 1 0 0 0'))
    run_import(tmp_path / 'a.pcd', tmp_path / 'bag')
    assert '1 file(s) have a non-identity VIEWPOINT' in capsys.readouterr().err
    (_, msg), = bag_messages(tmp_path / 'bag')['/points']
    np.testing.assert_array_equal(read_xyzi(msg)[1], np.arange(10, 15))


def _bad_pcds() -> list[tuple[str, object, str]]:
    xyzi = expected_xyzi(known_cloud(20))
    good = pcd_bytes(xyzi, 'binary')
    compressed = pcd_bytes(xyzi, 'binary_compressed')
    body = compressed.index(b'DATA binary_compressed\n') + len(b'DATA binary_compressed\n')
    big = struct.pack('<II', struct.unpack_from('<I', compressed, body)[0], 20 * 16 + 4)
    return [
        ('type', pcd_bytes(xyzi, 'binary', TYPE='F F F X'), "TYPE X with SIZE 4"),
        ('size', pcd_bytes(xyzi, 'binary', SIZE='4 4 4 2'), "TYPE F with SIZE 2"),
        ('no-z', pcd_bytes(xyzi[['x', 'y', 'intensity']], 'ascii'),
         r'no z field \(fields: x y intensity\)'),
        ('no-intensity', pcd_bytes(expected_xyzi(known_cloud(20))[['x', 'y', 'z']], 'binary'),
         'no intensity-like field .*; fields: x y z'),
        ('count', pcd_bytes(np.zeros(3, [*xyzi.dtype.descr[:3], ('intensity', '<f4', 2)]),
                            'binary'),
         "field 'intensity' has COUNT > 1"),
        ('truncated-binary', good[:-5], 'DATA binary truncated: 20 points of 16 bytes need'),
        ('truncated-ascii', pcd_bytes(xyzi, 'ascii', POINTS='21', WIDTH='21'),
         'DATA ascii truncated: 20 rows, POINTS says 21'),
        ('truncated-compressed', compressed[:-3], 'truncated: .* compressed bytes stated'),
        ('size-mismatch', compressed[:body] + big + compressed[body + 8:],
         'states 324 bytes uncompressed, 20 points of 16 bytes are 320'),
        ('lzf-short', compressed[:body] + struct.pack('<II', 6, 320) + b'\x02abc\x80\x02',
         'binary_compressed: LZF stream expands to 9 bytes'),
        ('no-data', good[:good.index(b'DATA')], 'bad PCD header: no DATA line'),
        ('no-data-line', good.replace(b'DATA binary\n', b''),
         'bad PCD header: line at byte .* is not text'),
        ('unknown-line', pcd_bytes(xyzi, 'binary', COLOUR='red'), "unknown line 'COLOUR red'"),
        ('counts', pcd_bytes(xyzi, 'binary', SIZE='4 4 4'), '4 FIELDS but 3 SIZE values'),
        ('points', pcd_bytes(xyzi, 'binary', POINTS='19'), 'WIDTH 20 x HEIGHT 1 does not match'),
        ('width', pcd_bytes(xyzi, 'binary', WIDTH='many'), 'WIDTH must be integers'),
        ('data-kind', pcd_bytes(xyzi, 'binary', DATA='binary_lz4'), "DATA 'binary_lz4'"),
        ('not-pcd', b'\x89PNG\r\n\x1a\n' + bytes(100), 'not text'),
    ]


@pytest.mark.parametrize('case', _bad_pcds(), ids=lambda case: case[0])
def test_pcd_errors_name_the_problem(tmp_path: Path, case: tuple[str, bytes, str]) -> None:
    name, raw, message = case
    src = tmp_path / f'{name}.pcd'
    src.write_bytes(raw)
    with pytest.raises(ConfigError, match=message) as info:
        run_import(src, tmp_path / 'bag')
    assert str(src) in str(info.value) and '\n' not in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == [src.name]  # nothing written


def test_kitti_folder_in_natural_order_with_poses_and_times(tmp_path: Path) -> None:
    (src := tmp_path / 'velodyne').mkdir()
    clouds = {}
    for index in (10, 2, 1):  # written out of order; 10 sorts after 2
        clouds[index] = expected_xyzi(known_cloud(40 + index, seed=index))
        clouds[index].tofile(src / f'{index}.bin')
    (src / 'notes.txt').write_text('ignored: neither .pcd nor .bin')
    poses = [euler_to_matrix(3.0 * k, 0.5 * k, 0.1, 0.01, -0.02, 0.3 * k) for k in range(3)]
    (tmp_path / 'poses.txt').write_text(poses_text(poses))
    (tmp_path / 'times.txt').write_text('0.000000e+00\n1.036e-01\n2.073e-01\n')
    assert run_import(src, tmp_path / 'bag', '--poses', tmp_path / 'poses.txt', '--times',
                      tmp_path / 'times.txt', '--start', '1234.5', '--frame-id', 'velo') == 0
    msgs = bag_messages(tmp_path / 'bag')
    expected_stamps = [1_234_500_000_000, 1_234_603_600_000, 1_234_707_300_000]
    assert [s for s, _ in msgs['/points']] == [s for s, _ in msgs['/odom']] == expected_stamps
    for k, ((_, cloud), (_, odom)) in enumerate(zip(msgs['/points'], msgs['/odom'])):
        assert read_points(cloud).tobytes() == clouds[(1, 2, 10)[k]].tobytes()
        assert stamp_to_ns(cloud.header.stamp) == stamp_to_ns(odom.header.stamp)
        assert (odom.header.frame_id, odom.child_frame_id) == ('odom', 'velo')
        np.testing.assert_allclose(odometry_to_matrix(odom), poses[k], atol=1e-9)


def test_kitti_rate_stamps_and_camera_poses(tmp_path: Path) -> None:
    for k in range(2):
        expected_xyzi(known_cloud(10, seed=k)).tofile(tmp_path / f'{k:06d}.bin')
    velo_to_cam = np.array([[0, -1, 0, -0.004], [0, 0, -1, -0.076], [1, 0, 0, -0.27],
                            [0, 0, 0, 1]], dtype=np.float64)  # KITTI's axes
    cam_poses = [euler_to_matrix(0.0, 0.0, 5.0 * k, 0.0, 0.1 * k, 0.0) for k in range(2)]
    (tmp_path / 'calib.txt').write_text('P0: ' + ' '.join(['0'] * 12) + '\nTr: '
                                        + poses_text([velo_to_cam]))
    (tmp_path / 'poses.txt').write_text(poses_text(cam_poses))
    out = tmp_path.parent / f'{tmp_path.name}_bag'
    run_import(tmp_path, out, '--rate', '4', '--poses', tmp_path / 'poses.txt',
               '--kitti-calib', tmp_path / 'calib.txt')
    msgs = bag_messages(out)
    assert [s for s, _ in msgs['/points']] == [START_NS, START_NS + 250_000_000]
    lidar_1 = odometry_to_matrix(msgs['/odom'][1][1])
    np.testing.assert_allclose(odometry_to_matrix(msgs['/odom'][0][1]), np.eye(4), atol=1e-9)
    # the camera 5 m along its z (forward) and turned 0.1 rad about its y (down) is the LiDAR
    # ~5 m along its x, yawed -0.1 rad about its z (up), with odom z still up
    assert abs(lidar_1[0, 3] - 5.0) < 0.05 and abs(lidar_1[2, 3]) < 1e-9
    assert np.isclose(np.arctan2(lidar_1[1, 0], lidar_1[0, 0]), -0.1)
    np.testing.assert_allclose(lidar_1[2, :3], [0, 0, 1], atol=1e-9)


def test_kitti_and_argument_errors(tmp_path: Path) -> None:
    (src := tmp_path / 'in').mkdir()
    for k in range(2):
        expected_xyzi(known_cloud(10)).tofile(src / f'{k}.bin')
    (tmp_path / 'poses.txt').write_text('1 0 0 0 0 1 0 0 0 0 1 0\n')
    (tmp_path / 'times.txt').write_text('0\n0.1\n0.2\n')
    (tmp_path / 'back.txt').write_text('0\n0.1\n0.1\n')
    out = tmp_path / 'bag'
    cases = [
        ((src, out, '--poses', tmp_path / 'poses.txt'), 'has 1 poses for 2 sweeps'),
        ((src, out, '--times', tmp_path / 'times.txt'), 'has 3 times for 2 sweeps'),
        ((src, out, '--times', tmp_path / 'back.txt'), r'line 3: 0.1 s does not follow 0.1 s'),
        ((src, out, '--rate', '0'), r'--rate must be within \(0, 1000\]'),
        ((src, out, '--start', 'soon'), '--start must be a number of seconds'),
        ((src, out, '--frame-id', 'odom'), '--frame-id and --odom-frame must differ'),
        ((tmp_path / 'missing', out), 'does not exist'),
        ((tmp_path / 'poses.txt', out), 'neither a .pcd nor a KITTI .bin'),
    ]
    for argv, message in cases:
        with pytest.raises(ConfigError, match=message):
            run_import(*argv)
    (src / '1.bin').write_bytes(b'\0' * 33)
    with pytest.raises(ConfigError, match=r'1.bin: 33 bytes is not a multiple of 16'):
        run_import(src, out)  # fails on the second sweep: nothing written
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == [
        'back.txt', 'in', 'poses.txt', 'times.txt']
    (src / 'a.pcd').write_bytes(pcd_bytes(expected_xyzi(known_cloud(5)), 'ascii'))
    with pytest.raises(ConfigError, match='mixes 1 .pcd and 2 .bin files'):
        run_import(src, out)


def test_output_paths_refused(tmp_path: Path) -> None:
    (src := tmp_path / 'scans').mkdir()
    expected_xyzi(known_cloud(10)).tofile(src / '0.bin')
    (tmp_path / 'poses.txt').write_text('1 0 0 0 0 1 0 0 0 0 1 0\n')
    for out, message in ((src, 'is SRC'), (src / 'bag', 'is inside SRC'),
                         (tmp_path, 'contains SRC'), (src / '0.bin', 'is inside SRC')):
        with pytest.raises(ConfigError, match=message):
            run_import(src, out, '--overwrite')
    with pytest.raises(ConfigError, match='contains SRC'):
        run_import(src / '0.bin', src, '--overwrite')
    with pytest.raises(ConfigError, match='is --poses'):
        run_import(src / '0.bin', tmp_path / 'poses.txt', '--poses', tmp_path / 'poses.txt',
                   '--overwrite')
    assert (tmp_path / 'poses.txt').read_text() == '1 0 0 0 0 1 0 0 0 0 1 0\n'
    (other := tmp_path / 'other').mkdir()
    (other / 'keep.txt').write_text('not a bag')
    with pytest.raises(ConfigError, match='exists and is not a rosbag2 bag'):
        run_import(src, other, '--overwrite')
    assert (other / 'keep.txt').read_text() == 'not a bag'
    run_import(src, tmp_path / 'bag')
    with pytest.raises(ConfigError, match=r'exists \(use --overwrite'):
        run_import(src, tmp_path / 'bag')
    expected_xyzi(known_cloud(12)).tofile(src / '1.bin')
    assert run_import(src, tmp_path / 'bag', '--overwrite') == 0
    assert topic_counts(tmp_path / 'bag') == {'/points': 2}


@pytest.mark.skipif(not REAL_PCD.is_file(), reason='../shared/real_scans is absent')
def test_real_pjlab_pcd(tmp_path: Path) -> None:
    run_import(REAL_PCD, tmp_path / 'bag')
    (_, msg), = bag_messages(tmp_path / 'bag')['/points']
    xyz, intensity = read_xyzi(msg)
    assert len(read_points(msg)) == 78238 and len(xyz) <= 78238
    np.testing.assert_allclose(xyz[0], [21.647913, 0.19822195, -1.8524752], rtol=1e-7)
    assert intensity[0] == 11 and 1 < intensity.max() <= 255  # the file's own 0-255 units


def replayed_frames(tmp_path: Path) -> set[str]:
    """Replay tmp_path/bag (3 sweeps) with the classical detector: /lanes for every sweep at
    its stamp; returns the frames they are published in."""
    stats = replay(tmp_path / 'bag', tmp_path / 'lanes', DetectorParams(detector='classical'),
                   progress=False)
    assert stats == {'sweeps': 3, 'dropped': 0, 'detections': 3}
    lanes = bag_messages(tmp_path / 'lanes')['/lanes']
    assert [s for s, _ in lanes] == [START_NS + k * 100_000_000 for k in range(3)]
    return {msg.markers[0].header.frame_id for _, msg in lanes}


def test_imported_pcd_bag_replays(tmp_path: Path) -> None:
    """Simulated Ouster sweeps (organised, padded, uint16 reflectivity) as binary_compressed
    PCDs plus their poses: the import replays with a /lanes message for every sweep."""
    sweeps = list(Simulator(4, sweeps=3, sensor='os1-32', columns=256).sweeps())
    (src := tmp_path / 'pcd').mkdir()
    for sweep in sweeps:
        (src / f'{sweep.index}.pcd').write_bytes(
            pcd_bytes(sweep.points, 'binary_compressed', height=sweep.height))
    (tmp_path / 'poses.txt').write_text(poses_text([s.odom_pose for s in sweeps]))
    run_import(src, tmp_path / 'bag', '--poses', tmp_path / 'poses.txt')
    clouds = [msg for _, msg in bag_messages(tmp_path / 'bag')['/points']]
    assert [(c.height, c.width) for c in clouds] == [(32, 256)] * 3
    assert read_points(clouds[2]).tobytes() == expected_xyzi(sweeps[2].points,
                                                             'reflectivity').tobytes()
    assert replayed_frames(tmp_path) == {'odom'}


def test_sweeps_without_odometry_each_get_their_lanes(tmp_path: Path) -> None:
    """A folder of KITTI sweeps and no poses: every sweep is detected on its own, the last one
    too (nothing waits for odometry that a bag without /odom will never bring)."""
    sweeps = list(Simulator(6, sweeps=3, sensor='hdl64e', columns=512).sweeps())
    (src := tmp_path / 'kitti').mkdir()
    for sweep in sweeps:
        xyzi = expected_xyzi(sweep.points)
        xyzi.tofile(src / f'{sweep.index:06d}.bin')
    run_import(src, tmp_path / 'bag')
    assert replayed_frames(tmp_path) == {'lidar'}
