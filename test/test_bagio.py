"""fhld_ros.bagio: MCAP bags written atomically and read back with clear errors; the output
rule (refuse existing outputs unless overwrite, replace only bag folders or regular files, never
an output overlapping an input)."""
from __future__ import annotations

import numpy as np
import pytest

from fhld_ros.bagio import (
    BagError,
    BagWriter,
    bag_topics,
    check_file_output,
    check_output,
    read_messages,
    write_file_atomically,
)
from msg_adapters.lanes import lanes_to_marker_array, marker_array_to_lanes


def _write(path, count=3):
    with BagWriter(path) as writer:
        family = writer.family
        for k in range(count):
            msg = lanes_to_marker_array(family, family.header(k, 'odom'),
                                        [np.ones((2, 3)) * k], [1.0], [k])
            writer.write('/lanes_gt', 'visualization_msgs/msg/MarkerArray', k * 100, msg)


def test_round_trip(tmp_path):
    _write(tmp_path / 'bag')
    assert bag_topics(tmp_path / 'bag') == {'/lanes_gt': 'visualization_msgs/msg/MarkerArray'}
    got = list(read_messages(tmp_path / 'bag', ['/lanes_gt']))
    assert [stamp for _, stamp, _ in got] == [0, 100, 200]
    assert marker_array_to_lanes(got[2][2]).lanes[0][0, 0] == 2


def test_failure_leaves_nothing_behind(tmp_path):
    with pytest.raises(RuntimeError):
        with BagWriter(tmp_path / 'bag') as writer:
            writer.write('/a', 'std_msgs/msg/Header', 0, writer.family.header(0, 'x'))
            raise RuntimeError('boom')
    assert list(tmp_path.iterdir()) == []


def test_clear_errors(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        list(read_messages(tmp_path / 'missing'))
    (tmp_path / 'junk').mkdir()
    (tmp_path / 'junk' / 'x.mcap').write_bytes(b'not a bag')
    with pytest.raises(BagError, match='cannot read bag'):
        list(read_messages(tmp_path / 'junk'))
    _write(tmp_path / 'bag')
    with pytest.raises(BagError, match='no topic /points'):
        list(read_messages(tmp_path / 'bag', ['/points']))
    with pytest.raises(BagError, match='directory'):
        with BagWriter(tmp_path / 'nope' / 'bag'):
            pass


def test_writer_refuses_an_existing_output_unless_overwrite(tmp_path):
    (tmp_path / 'notes.txt').write_text('mine')
    with pytest.raises(BagError, match=r'exists \(use --overwrite'):
        with BagWriter(tmp_path / 'notes.txt'):
            pass
    with pytest.raises(BagError, match='is a file, not a rosbag2 bag folder'):
        with BagWriter(tmp_path / 'notes.txt', overwrite=True):
            pass
    assert (tmp_path / 'notes.txt').read_text() == 'mine'
    _write(tmp_path / 'bag', count=3)
    with pytest.raises(BagError, match='exists'):
        _write(tmp_path / 'bag', count=1)
    with BagWriter(tmp_path / 'bag', overwrite=True) as writer:
        writer.write('/a', 'std_msgs/msg/Header', 0, writer.family.header(0, 'x'))
    assert bag_topics(tmp_path / 'bag') == {'/a': 'std_msgs/msg/Header'}
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bag', 'notes.txt']


def test_only_a_bag_folder_holding_nothing_else_is_replaced(tmp_path):
    _write(tmp_path / 'bag')
    before = {p.name: p.read_bytes() for p in (tmp_path / 'bag').iterdir()}
    (tmp_path / 'bag' / 'labels.csv').write_text('hand labels')
    with pytest.raises(BagError, match='holds labels.csv, which the bag does not list'):
        check_output(tmp_path / 'bag', overwrite=True)
    (tmp_path / 'bag' / 'labels.csv').unlink()
    (tmp_path / 'link').symlink_to(tmp_path / 'bag')
    with pytest.raises(BagError, match='symbolic link'):
        _write_over(tmp_path / 'link')
    (tmp_path / 'plain').mkdir()
    (tmp_path / 'plain' / 'metadata.yaml').write_text('{not: [yaml')
    with pytest.raises(BagError, match='unreadable metadata.yaml'):
        _write_over(tmp_path / 'plain')
    assert {p.name: p.read_bytes() for p in (tmp_path / 'bag').iterdir()} == before
    # older rosbag2 releases wrote the folder name in front of each file
    (old := tmp_path / 'old').mkdir()
    (old / 'old_0.db3').write_bytes(b'x')
    (old / 'metadata.yaml').write_text('rosbag2_bagfile_information:\n'
                                       '  relative_file_paths: [old/old_0.db3]\n')
    _write_over(old)
    assert bag_topics(old) == {'/a': 'std_msgs/msg/Header'}


def _write_over(path):
    with BagWriter(path, overwrite=True) as writer:
        writer.write('/a', 'std_msgs/msg/Header', 0, writer.family.header(0, 'x'))


@pytest.mark.parametrize('where, message', [
    (lambda src: src, 'is IN_BAG'),
    (lambda src: src / 'sub', 'is inside IN_BAG'),
    (lambda src: src.parent, 'contains IN_BAG'),
])
def test_an_output_overlapping_an_input_is_always_refused(tmp_path, where, message):
    _write(tmp_path / 'in')
    (tmp_path / 'sibling.txt').write_text('kept')
    with pytest.raises(BagError, match=message):
        with BagWriter(where(tmp_path / 'in'), overwrite=True, inputs={'IN_BAG': tmp_path / 'in'}):
            pass
    (tmp_path / 'alias').symlink_to(tmp_path / 'in')  # the same folder under another name
    with pytest.raises(BagError, match='is IN_BAG'):
        check_output(tmp_path / 'in', overwrite=True, inputs={'IN_BAG': tmp_path / 'alias'})
    assert bag_topics(tmp_path / 'in') == {'/lanes_gt': 'visualization_msgs/msg/MarkerArray'}
    assert sorted(p.name for p in tmp_path.iterdir()) == ['alias', 'in', 'sibling.txt']


def test_something_that_appears_while_writing_is_not_replaced(tmp_path):
    with pytest.raises(BagError, match='is not a rosbag2 bag'):
        with BagWriter(tmp_path / 'bag', overwrite=True) as writer:
            writer.write('/a', 'std_msgs/msg/Header', 0, writer.family.header(0, 'x'))
            (tmp_path / 'bag').mkdir()
            (tmp_path / 'bag' / 'theirs.txt').write_text('theirs')
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob('*')) == [
        'bag', 'bag/theirs.txt']


def test_file_outputs_are_replaced_atomically_and_links_not_followed(tmp_path):
    target = tmp_path / 'target.png'
    target.write_text('not ours')
    (tmp_path / 'out.png').symlink_to(target)
    with pytest.raises(BagError, match='symbolic link'):
        check_file_output(tmp_path / 'out.png', overwrite=True)
    with pytest.raises(BagError, match='is not a regular file'):
        check_file_output(tmp_path, overwrite=True)
    write_file_atomically(tmp_path / 'out.png', lambda tmp: tmp.write_text('new'))
    assert target.read_text() == 'not ours' and not (tmp_path / 'out.png').is_symlink()
    # the permissions of any new file (umask), not mkstemp's 0600
    assert (tmp_path / 'out.png').stat().st_mode == target.stat().st_mode

    def fail(tmp):
        tmp.write_text('half')
        raise RuntimeError('boom')

    with pytest.raises(RuntimeError):
        write_file_atomically(tmp_path / 'out.png', fail)
    assert (tmp_path / 'out.png').read_text() == 'new'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['out.png', 'target.png']
