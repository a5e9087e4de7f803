"""rosbag2 MCAP bags through rosbags: read any bag, write MCAP bags atomically.

Messages come back as rosbags dataclasses (the Jazzy type store), which msg_adapters reads
like rclpy messages. A bag is written into a temporary sibling directory and moved into place
only when it closed cleanly, so a failure never leaves a half-written bag behind.
"""
from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from fhld_ros.errors import CliError
from msg_adapters.family import RosbagsFamily, rosbags_family


class BagError(CliError, ValueError):
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


class BagWriter:
    """Context manager writing a rosbag2 MCAP bag: ``write(topic, msgtype, stamp_ns, msg)``."""

    def __init__(self, path: str | Path, overwrite: bool = True) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.family: RosbagsFamily = rosbags_family()
        self._tmpdir: Path | None = None
        self._writer: Any = None
        self._connections: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        if self.path.exists() and not self.overwrite:
            raise BagError(f'{self.path} exists')
        parent = self.path.resolve().parent
        if not parent.is_dir():
            raise BagError(f'cannot write bag {self.path}: directory {parent} does not exist')
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
        data = self.family.typestore.serialize_cdr(msg, msgtype)
        self._writer.write(connection, int(stamp_ns), data)

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        try:
            self._writer.close()
            if exc_type is None:
                if self.path.exists():
                    shutil.rmtree(self.path) if self.path.is_dir() else self.path.unlink()
                (self._tmpdir / 'bag').rename(self.path)
        finally:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
