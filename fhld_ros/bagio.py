"""rosbag2 MCAP bags through rosbags: read any bag, write MCAP bags atomically.

Messages come back as rosbags dataclasses (the Jazzy type store), which msg_adapters reads
like rclpy messages. A bag is written into a temporary sibling directory and moved into place
only when it closed cleanly, so a failure never leaves a half-written bag behind.

The one rule for every command's outputs (`check_output`, `check_file_output`): an existing
output is refused unless overwrite is asked for, and even then only a rosbag2 bag folder
(metadata.yaml plus the storage files it lists, nothing else) or, for a file output, a regular
file is replaced; an output equal to an input, inside it or containing it is always refused.
So a command never deletes what it did not write.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import yaml
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from fhld_ros.errors import ConfigError
from msg_adapters.family import RosbagsFamily, rosbags_family
from msg_adapters.lanes import LaneSet, marker_array_to_lanes


class BagError(ConfigError, ValueError):
    """A bag cannot be read or written; the message names the bag and the problem."""


def _open_reader(path: str | Path) -> Any:
    """A rosbags reader: rosbag2 for a bag directory (whatever its name), else AnyReader."""
    path = Path(path)
    if not path.exists():
        raise BagError(f'bag {path} does not exist')
    try:
        # AnyReader takes any path ending in .bag for a ROS 1 bag, even a rosbag2 directory
        reader = Reader(path) if path.is_dir() else AnyReader(
            [path], default_typestore=rosbags_family().typestore)
        reader.open()
    except Exception as exc:  # rosbags raises several types for corrupt/unknown bags
        raise BagError(f'cannot read bag {path}: {exc}') from exc
    return reader


def _select_topics(path: str | Path, types: dict[str, str],
                   topics: Iterable[str] | None) -> dict[str, str]:
    """types restricted to topics (all when None); a topic missing from the bag is an error."""
    if topics is None:
        return types
    wanted = list(topics)
    missing = [t for t in wanted if t not in types]
    if missing:
        raise BagError(f'bag {path} has no topic {", ".join(missing)} (it has: '
                       f'{", ".join(sorted(types)) or "nothing"})')
    return {t: types[t] for t in wanted}


def bag_topics(path: str | Path, topics: Iterable[str] | None = None) -> dict[str, str]:
    """Topic -> message type name of every connection in the bag, or of the given topics
    (BagError naming any the bag lacks)."""
    reader = _open_reader(path)
    try:
        return _select_topics(path, {c.topic: c.msgtype for c in reader.connections}, topics)
    finally:
        reader.close()


def topic_counts(path: str | Path) -> dict[str, int]:
    """Topic -> number of messages, from the bag's index (no message is read)."""
    reader = _open_reader(path)
    try:
        counts: dict[str, int] = {}
        for connection in reader.connections:
            counts[connection.topic] = counts.get(connection.topic, 0) + connection.msgcount
        return counts
    finally:
        reader.close()


def read_raw(path: str | Path,
             topics: Iterable[str] | None = None) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, message type, log time ns, CDR bytes) in time order, without decoding.

    Every requested topic must exist in the bag; an empty selection yields nothing.
    """
    reader = _open_reader(path)
    try:
        connections = list(reader.connections)
        wanted = _select_topics(path, {c.topic: c.msgtype for c in connections}, topics)
        connections = [c for c in connections if c.topic in wanted]
        for connection, stamp, raw in reader.messages(connections=connections):
            yield connection.topic, connection.msgtype, stamp, raw
    finally:
        reader.close()


def read_messages(path: str | Path,
                  topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """(topic, log time ns, deserialised rosbags message) in time order."""
    typestore = rosbags_family().typestore
    for topic, msgtype, stamp, raw in read_raw(path, topics):
        try:
            msg = typestore.deserialize_cdr(raw, msgtype)
        except Exception as exc:
            raise BagError(f'bag {path}: cannot decode a {msgtype} message on {topic} at '
                           f'{stamp} ns: {exc}') from exc
        yield topic, stamp, msg


def read_lane_sets(path: str | Path, topic: str) -> list[LaneSet]:
    """The lane sets of every MarkerArray on `topic`, in bag order; an empty array has no
    header, so its stamp is its log time."""
    sets = []
    for _, log_ns, msg in read_messages(path, [topic]):
        lane_set = marker_array_to_lanes(msg)
        if not msg.markers:
            lane_set.stamp_ns = log_ns
        sets.append(lane_set)
    return sets


def _bag_folder_problem(path: Path) -> str | None:
    """Why path is not a rosbag2 bag folder that may be replaced as a whole (None when it is)."""
    if path.is_symlink():
        return 'is a symbolic link, not a rosbag2 bag folder'
    if not path.is_dir():
        return 'is a file, not a rosbag2 bag folder'
    metadata = path / 'metadata.yaml'
    if not metadata.is_file():
        return 'is not a rosbag2 bag (no metadata.yaml)'
    try:
        info = yaml.safe_load(metadata.read_text())['rosbag2_bagfile_information']
        # older rosbag2 releases prefixed the bag folder: the name alone is the file
        files = {Path(str(f)).name for f in info['relative_file_paths']}
    except Exception:  # any malformed YAML or layout: not a bag we may delete
        return 'is not a rosbag2 bag (unreadable metadata.yaml)'
    allowed = files | {'metadata.yaml'}
    foreign = sorted(e.name for e in path.iterdir()
                     if e.name not in allowed or e.is_symlink() or not e.is_file())
    if foreign:
        more = f' and {len(foreign) - 3} more' if len(foreign) > 3 else ''
        return f'holds {", ".join(foreign[:3])}{more}, which the bag does not list'
    return None


def _file_problem(path: Path) -> str | None:
    """Why path is not a regular file that may be replaced (None when it is)."""
    if path.is_symlink():
        return 'is a symbolic link'
    return None if path.is_file() else 'is not a regular file'


def _check_target(path: str | Path, overwrite: bool, inputs: Mapping[str, str | Path | None],
                  label: str, problem: Callable[[Path], str | None]) -> None:
    path = Path(path)
    name = f'{label} {path}'.strip()
    out_r = path.resolve()
    for in_label, src in inputs.items():
        if src is None:
            continue
        src_r = Path(src).resolve()
        if out_r == src_r:
            raise BagError(f'{name} is {in_label} {src}: write it elsewhere')
        if src_r in out_r.parents:
            raise BagError(f'{name} is inside {in_label} {src}: write it elsewhere')
        if out_r in src_r.parents:
            raise BagError(f'{name} contains {in_label} {src}: write it elsewhere')
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise BagError(f'{name} exists (use --overwrite to replace it)')
        reason = problem(path)
        if reason is not None:
            raise BagError(f'{name} exists and {reason}: not replaced')
    if not out_r.parent.is_dir():
        raise BagError(f'cannot write {name}: directory {out_r.parent} does not exist')


def check_output(path: str | Path, overwrite: bool = False,
                 inputs: Mapping[str, str | Path | None] | None = None,
                 label: str = 'OUT_BAG') -> None:
    """BagError unless a bag may be written at path: see the module's rule.

    inputs maps a name for the message (e.g. 'IN_BAG') to a path (None: absent)."""
    _check_target(path, overwrite, inputs or {}, label, _bag_folder_problem)


def check_file_output(path: str | Path, overwrite: bool = False,
                      inputs: Mapping[str, str | Path | None] | None = None,
                      label: str = '') -> None:
    """BagError unless a plain file may be written at path (same rule; a regular file is
    what --overwrite may replace)."""
    _check_target(path, overwrite, inputs or {}, label, _file_problem)


def write_file_atomically(path: str | Path, write: Callable[[Path], None]) -> None:
    """write(tmp) to a file of path's name in a temporary sibling directory, then rename it
    onto path: a failure leaves the old file (or nothing), and a symbolic link at path is
    replaced, not followed."""
    path = Path(path)
    tmpdir = Path(tempfile.mkdtemp(prefix=f'.{path.name}.', dir=path.resolve().parent))
    try:
        write(tmpdir / path.name)
        os.replace(tmpdir / path.name, path)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


class BagWriter:
    """Context manager writing a rosbag2 MCAP bag: ``write(topic, msgtype, stamp_ns, msg)``,
    msg a rosbags message or its CDR bytes.

    The output is checked with `check_output` (overwrite, inputs) on entry, and again before
    the finished bag replaces an existing one (it may have changed meanwhile)."""

    def __init__(self, path: str | Path, overwrite: bool = False,
                 inputs: Mapping[str, str | Path | None] | None = None) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.inputs = dict(inputs or {})
        self.family: RosbagsFamily = rosbags_family()
        self._tmpdir: Path | None = None
        self._writer: Any = None
        self._connections: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        check_output(self.path, self.overwrite, self.inputs, label='bag')
        parent = self.path.resolve().parent
        self._tmpdir = Path(tempfile.mkdtemp(prefix=f'.{self.path.name}.', dir=parent))
        self._writer = Writer(self._tmpdir / 'bag', version=9,
                              storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        return self

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._writer.add_connection(topic, msgtype,
                                                     typestore=self.family.typestore)
            self._connections[topic] = connection
        elif connection.msgtype != msgtype:
            raise BagError(f'topic {topic} is {connection.msgtype}, not {msgtype}')
        data = msg if isinstance(msg, bytes) else self.family.typestore.serialize_cdr(msg, msgtype)
        self._writer.write(connection, int(stamp_ns), data)

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        try:
            self._writer.close()
            if exc_type is None:
                self._move_into_place()
        finally:
            shutil.rmtree(self._tmpdir, ignore_errors=True)

    def _move_into_place(self) -> None:
        """Rename the finished bag onto self.path; a bag there is moved aside first (into the
        temporary directory, deleted afterwards) and put back if the rename fails."""
        old = None
        if self.path.exists() or self.path.is_symlink():
            check_output(self.path, self.overwrite, label='bag')
            old = self._tmpdir / 'replaced'
            self.path.rename(old)
        try:
            (self._tmpdir / 'bag').rename(self.path)
        except OSError:
            if old is not None:
                old.rename(self.path)
            raise
