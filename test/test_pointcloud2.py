"""msg_adapters.pointcloud2: layouts, validation, and agreement across message families."""
from __future__ import annotations

import array
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

import msg_adapters.pointcloud2 as pc2
from fhld_ros.bagio import BagWriter
from msg_adapters.family import rclpy_family, rosbags_family
from msg_adapters.pointcloud2 import (
    DATATYPES,
    FLOAT32,
    FLOAT64,
    UINT8,
    UINT16,
    create_cloud,
    read_points,
    read_xyzi,
)

FAMILIES = [rosbags_family(), rclpy_family()]


def _cloud(family, points, height=1):
    return create_cloud(family.cls('sensor_msgs/msg/PointCloud2'), family.header(7, 'lidar'),
                        points, height=height)


def _xyzi_points(n, intensity='intensity', itype='<f4', itemsize=32, order='<'):
    dtype = np.dtype({'names': ['x', 'y', 'z', intensity],
                      'formats': [f'{order}f4'] * 3 + [itype],
                      'offsets': [0, 4, 8, 16], 'itemsize': itemsize})
    points = np.zeros(n, dtype=dtype)
    rng = np.random.default_rng(n)
    for axis in 'xyz':
        points[axis] = rng.uniform(-30, 30, n)
    points[intensity] = np.arange(n) % 200
    return points


@pytest.mark.parametrize('family', FAMILIES, ids=lambda f: f.name)
def test_padded_organised_cloud_round_trips(family):
    points = _xyzi_points(4 * 6)
    msg = _cloud(family, points, height=4)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (4, 6, 32, 6 * 32)
    back = read_points(msg)
    assert back.shape == (24,)
    assert back.dtype.itemsize == 32
    for name in points.dtype.names:
        np.testing.assert_array_equal(back[name], points[name])


def test_row_step_padding_and_rows_are_honoured():
    points = _xyzi_points(3 * 5, itemsize=20)
    msg = _cloud(rosbags_family(), points, height=3)
    row = bytes(msg.data)
    pad = 12
    rows = [row[r * 100:(r + 1) * 100] + b'\xee' * pad for r in range(3)]
    msg.row_step = 100 + pad
    msg.data = np.frombuffer(b''.join(rows), dtype=np.uint8)
    xyz, intensity = read_xyzi(msg)
    np.testing.assert_array_equal(xyz[:, 1], points['y'])
    np.testing.assert_array_equal(intensity, points['intensity'])


def test_big_endian_is_converted_without_touching_a_read_only_buffer():
    little = _xyzi_points(10)
    big = little.astype(little.dtype.newbyteorder('>'))
    family = rosbags_family()
    msg = _cloud(family, big)
    assert msg.is_bigendian
    msg.data = np.frombuffer(bytes(msg.data), dtype=np.uint8)  # read-only buffer
    assert not msg.data.flags.writeable
    xyz, intensity = read_xyzi(msg)
    np.testing.assert_array_equal(xyz[:, 0], little['x'])
    np.testing.assert_array_equal(intensity, little['intensity'])
    assert read_points(msg).dtype['x'].isnative


@pytest.mark.parametrize('itemsize', [12, 16, 48])
def test_xyz_is_a_writable_copy_whatever_the_point_step(itemsize):
    # packed x, y, z are copied as 12-byte records; with point_step 12 they are the whole
    # buffer, which must still be copied, not handed out (read-only, the message's own)
    dtype = np.dtype({'names': ['x', 'y', 'z'], 'formats': ['<f4'] * 3, 'offsets': [0, 4, 8],
                      'itemsize': itemsize})
    points = np.zeros(5, dtype=dtype)
    points['x'], points['y'], points['z'] = np.arange(1, 6), 2.0, -np.arange(5)
    msg = _cloud(rosbags_family(), points)
    msg.data = np.frombuffer(bytes(msg.data), dtype=np.uint8)  # read-only buffer
    xyz, _ = read_xyzi(msg)
    np.testing.assert_array_equal(xyz, np.stack([points['x'], points['y'], points['z']], 1))
    xyz[:] = 0.0  # a copy: writable, and the message keeps its points
    np.testing.assert_array_equal(read_xyzi(msg)[0][:, 0], points['x'])


def test_nan_and_all_zero_points_are_dropped():
    points = _xyzi_points(6)
    points['x'][1] = np.nan
    points['z'][2] = np.inf
    points[['x', 'y', 'z']][3] = (0.0, 0.0, 0.0)
    points['y'][4] = 0.0  # a single zero coordinate is a real return
    xyz, intensity = read_xyzi(_cloud(rosbags_family(), points))
    np.testing.assert_array_equal(intensity, points['intensity'][[0, 4, 5]])
    assert xyz.shape == (3, 3)


@pytest.mark.parametrize('itype', ['<u2', '<f8', 'u1', '<i4'])
def test_reflectivity_is_used_when_intensity_is_absent(itype):
    points = _xyzi_points(8, intensity='reflectivity', itype=itype)
    _, intensity = read_xyzi(_cloud(rosbags_family(), points))
    assert intensity.dtype == np.float32
    np.testing.assert_array_equal(intensity, points['reflectivity'].astype(np.float32))


def test_no_intensity_field_gives_zeros_and_warns_once(caplog):
    pc2._warned_no_intensity = False
    dtype = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4')])
    points = np.ones(5, dtype=dtype)
    with caplog.at_level('WARNING'):
        for _ in range(3):
            _, intensity = read_xyzi(_cloud(rosbags_family(), points))
    np.testing.assert_array_equal(intensity, np.zeros(5))
    assert sum('neither intensity nor reflectivity' in r.message for r in caplog.records) == 1


@pytest.mark.parametrize('order', ['<', '>'])
def test_count_greater_than_one_is_a_sub_array_field(order):
    dtype = np.dtype([('x', f'{order}f4'), ('y', f'{order}f4'), ('z', f'{order}f4'),
                      ('normal', f'{order}f4', (3,))])
    points = np.zeros(4, dtype=dtype)
    points['x'] = 1
    points['normal'] = np.arange(12).reshape(4, 3)
    msg = _cloud(rosbags_family(), points)
    assert msg.fields[3].count == 3 and msg.is_bigendian == (order == '>')
    back = read_points(msg)
    assert back.dtype.names == ('x', 'y', 'z', 'normal')
    np.testing.assert_array_equal(back['normal'], np.arange(12).reshape(4, 3))
    assert read_xyzi(msg)[0].shape == (4, 3)


@pytest.mark.parametrize('family', FAMILIES, ids=lambda f: f.name)
def test_empty_cloud(family):
    points = _xyzi_points(0)
    msg = _cloud(family, points)
    assert read_points(msg).shape == (0,)
    xyz, intensity = read_xyzi(msg)
    assert xyz.shape == (0, 3) and intensity.shape == (0,)


def _field(family, name, offset, datatype, count=1):
    return family.new('sensor_msgs/msg/PointField', name=name, offset=offset,
                      datatype=datatype, count=count)


def _raw_msg(fields, point_step=16, width=2, height=1, data_len=None, row_step=None):
    family = rosbags_family()
    row_step = point_step * width if row_step is None else row_step
    data_len = row_step * height if data_len is None else data_len
    return family.new('sensor_msgs/msg/PointCloud2', height=height, width=width,
                      fields=[_field(family, *f) for f in fields], point_step=point_step,
                      row_step=row_step, data=np.zeros(data_len, dtype=np.uint8))


XYZ = [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32)]


@pytest.mark.parametrize('msg,message', [
    (lambda: _raw_msg(XYZ, data_len=20), 'data has 20 bytes, expected row_step*height = 32'),
    (lambda: _raw_msg(XYZ + [('intensity', 12, FLOAT64)]), "'intensity' ends at byte 20"),
    (lambda: _raw_msg(XYZ + [('intensity', 12, 42)]), 'unknown datatype 42'),
    (lambda: _raw_msg(XYZ[:2]), 'no z field'),
    (lambda: _raw_msg(XYZ + [('y', 12, FLOAT32)]), 'duplicate field names: y'),
    (lambda: _raw_msg(XYZ, row_step=8), 'row_step 8 is smaller'),
    (lambda: _raw_msg(XYZ + [('t', 12, UINT16, 3)]),
     r"'t' ends at byte 18 \(offset 12 \+ count 3 x 2 bytes\), beyond point_step 16"),
    (lambda: _raw_msg([('x', 0, FLOAT32, 3), ('y', 4, FLOAT32), ('z', 8, FLOAT32)]),
     "field 'x' has count 3, expected 1"),
    (lambda: _raw_msg(XYZ + [('intensity', 12, UINT16, 2)]), "'intensity' has count 2"),
    (lambda: _raw_msg(XYZ + [(f'f{k}', 12, UINT8) for k in range(1100)]), '1103 fields'),
    (lambda: _raw_msg(XYZ, point_step=-16, row_step=32), 'negative size'),
])
def test_malformed_clouds_raise_clear_errors(msg, message):
    with pytest.raises(ValueError, match=message.replace('*', r'\*')):
        read_xyzi(msg())


@pytest.mark.parametrize('count', [2 ** 32 - 1, 20_000_000])
def test_a_hostile_field_count_is_refused_at_once(count):
    # issue #17: one dtype name per count hung the node, then it was killed for memory
    msg = _raw_msg(XYZ + [('pad', 12, UINT8, count)], width=1)
    start = time.perf_counter()
    with pytest.raises(ValueError, match=f"field 'pad' ends at byte {12 + count} .*count "
                                         f'{count} x 1 bytes.*beyond point_step 16'):
        read_xyzi(msg)
    with pytest.raises(ValueError, match=f'count {count}'):
        read_points(msg)
    assert time.perf_counter() - start < 0.1


def test_clouds_over_max_points_are_refused_from_the_header():
    # 2**40 points claimed over 32 bytes of data: refused before the buffer or dtype is looked
    # at, so nothing is allocated
    huge = _raw_msg(XYZ + [('pad', 12, UINT8, 2 ** 32 - 1)], width=2 ** 20, height=2 ** 20,
                    data_len=32)
    start = time.perf_counter()
    with pytest.raises(ValueError, match=f'1048576 x 1048576 = {2 ** 40} points, more than '
                                         f'max_points {pc2.DEFAULT_MAX_POINTS}'):
        read_xyzi(huge)
    assert time.perf_counter() - start < 0.1
    msg = _cloud(rosbags_family(), _xyzi_points(6 * 50), height=6)
    with pytest.raises(ValueError, match='6 x 50 = 300 points, more than max_points 299'):
        read_xyzi(msg, max_points=299)
    with pytest.raises(ValueError, match='more than max_points 299'):
        read_points(msg, max_points=299)
    assert read_xyzi(msg, max_points=300)[0].shape == (300, 3)
    assert read_points(msg, max_points=None).shape == (300,)


def test_every_datatype_reads_back():
    for code, dtype in DATATYPES.items():
        points = np.zeros(3, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                    ('v', dtype.newbyteorder('<'))])
        points['x'] = 1
        points['v'] = [1, 2, 3]
        msg = _cloud(rosbags_family(), points)
        assert msg.fields[3].datatype == code
        np.testing.assert_array_equal(read_points(msg)['v'], [1, 2, 3])


# Random layouts: any order of fields, padding, byte order and row count round-trip.
_TYPES = [np.dtype(t) for t in ('i1', 'u1', 'i2', 'u2', 'i4', 'u4', 'f4', 'f8')]


@st.composite
def _layouts(draw):
    extra = draw(st.lists(st.sampled_from(_TYPES), max_size=4))
    fields = [('x', np.dtype('f4')), ('y', np.dtype('f4')), ('z', np.dtype('f4'))]
    fields += [(f'f{k}', t) for k, t in enumerate(extra)]
    order = draw(st.permutations(range(len(fields))))
    big = draw(st.booleans())
    offsets, names, formats, offset = [], [], [], 0
    for k in order:
        offset += draw(st.integers(0, 3))
        name, dtype = fields[k]
        names.append(name)
        formats.append(dtype.newbyteorder('>' if big else '<'))
        offsets.append(offset)
        offset += dtype.itemsize
    itemsize = offset + draw(st.integers(0, 8))
    height = draw(st.integers(1, 3))
    width = draw(st.integers(0, 5))
    dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                      'itemsize': itemsize})
    raw = draw(st.binary(min_size=itemsize * height * width, max_size=itemsize * height * width))
    return np.frombuffer(raw, dtype=dtype).copy(), height


@settings(max_examples=60, deadline=None)
@given(_layouts())
def test_random_layouts_round_trip(layout):
    points, height = layout
    msg = _cloud(rosbags_family(), points, height=height)
    back = read_points(msg)
    for name in points.dtype.names:
        native = points[name].astype(points[name].dtype.newbyteorder('='))
        np.testing.assert_array_equal(back[name], native)


def test_rclpy_rosbags_and_mcap_ros2_messages_decode_identically(tmp_path):
    points = _xyzi_points(64 * 16, intensity='reflectivity', itype='<u2', itemsize=48)
    points['x'][::7] = np.nan
    rclpy_msg = _cloud(rclpy_family(), points, height=64)
    bags_msg = _cloud(rosbags_family(), points, height=64)
    with BagWriter(tmp_path / 'bag') as writer:
        writer.write('/points', 'sensor_msgs/msg/PointCloud2', 7, bags_msg)
    mcap_file = next((tmp_path / 'bag').glob('*.mcap'))
    with open(mcap_file, 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        mcap_msg = next(reader.iter_decoded_messages())[3]
    assert isinstance(rclpy_msg.data, array.array)
    results = [read_xyzi(m) for m in (rclpy_msg, bags_msg, mcap_msg)]
    for xyz, intensity in results[1:]:
        np.testing.assert_array_equal(xyz, results[0][0])
        np.testing.assert_array_equal(intensity, results[0][1])
    assert results[0][0].shape == (64 * 16 - len(points['x'][::7]), 3)
    structured = [read_points(m) for m in (rclpy_msg, bags_msg, mcap_msg)]
    assert structured[0].dtype == structured[1].dtype == structured[2].dtype


def test_create_cloud_rejects_unstructured_and_ragged_input():
    with pytest.raises(ValueError, match='structured'):
        _cloud(rosbags_family(), np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match='do not fill 2 rows'):
        _cloud(rosbags_family(), _xyzi_points(5), height=2)


def test_uint16_field_is_described_with_its_code():
    points = _xyzi_points(2, intensity='reflectivity', itype='<u2')
    assert _cloud(rosbags_family(), points).fields[3].datatype == UINT16
