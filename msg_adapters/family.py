"""Message families: build ROS messages of one type name for rclpy or for rosbags.

Code that writes messages (the node with rclpy, the simulator and replay with rosbags) asks a
family for ``new('visualization_msgs/msg/Marker', ...)`` and never imports the classes itself.
Unspecified fields get their ROS defaults in both families (rosbags dataclasses have none).
"""
from __future__ import annotations

import importlib
from functools import cache, lru_cache
from typing import Any

import numpy as np

_BASE_DEFAULTS = {'bool': False, 'string': '', 'wstring': ''}
_NUMPY_BASE = {
    'int8': np.int8, 'uint8': np.uint8, 'byte': np.uint8, 'char': np.uint8,
    'int16': np.int16, 'uint16': np.uint16, 'int32': np.int32, 'uint32': np.uint32,
    'int64': np.int64, 'uint64': np.uint64, 'float32': np.float32, 'float64': np.float64,
}


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (any family) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class MessageFamily:
    """Base: ``cls(name)`` gives the class, ``new(name, **fields)`` an instance."""

    name = 'abstract'

    def cls(self, msgtype: str) -> type:
        raise NotImplementedError

    def new(self, msgtype: str, **fields: Any) -> Any:
        raise NotImplementedError

    def stamp(self, ns: int) -> Any:
        sec, nanosec = divmod(int(ns), 1_000_000_000)
        return self.new('builtin_interfaces/msg/Time', sec=sec, nanosec=nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        return self.new('std_msgs/msg/Header', stamp=self.stamp(stamp_ns), frame_id=frame_id)


class RclpyFamily(MessageFamily):
    name = 'rclpy'

    def cls(self, msgtype: str) -> type:
        return _rclpy_class(msgtype)

    def new(self, msgtype: str, **fields: Any) -> Any:
        return self.cls(msgtype)(**fields)


@cache
def _rclpy_class(msgtype: str) -> type:
    # cached: building a /lanes message asks for ~4000 classes, an import lookup each
    package, kind, type_name = msgtype.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), type_name)


class RosbagsFamily(MessageFamily):
    name = 'rosbags'

    def __init__(self, typestore: Any) -> None:
        self.typestore = typestore

    def cls(self, msgtype: str) -> type:
        return self.typestore.types[msgtype]

    def new(self, msgtype: str, **fields: Any) -> Any:
        _, field_defs = self.typestore.fielddefs[msgtype]
        for name, desc in field_defs:
            if name not in fields:
                fields[name] = self._default(desc)
        return self.cls(msgtype)(**fields)

    def _default(self, desc: tuple) -> Any:
        # Nodetype values of rosbags: 1 BASE, 2 NAME, 3 ARRAY (fixed), 4 SEQUENCE
        kind, rest = int(desc[0]), desc[1]
        if kind == 1:
            return _BASE_DEFAULTS.get(rest[0], 0.0 if rest[0].startswith('float') else 0)
        if kind == 2:
            return self.new(rest)
        inner, length = rest
        size = length if kind == 3 else 0
        if int(inner[0]) == 1 and inner[1][0] in _NUMPY_BASE:
            return np.zeros(size, dtype=_NUMPY_BASE[inner[1][0]])
        return [self._default(inner) for _ in range(size)]


@lru_cache(maxsize=1)
def rosbags_family() -> RosbagsFamily:
    """Family of rosbags dataclasses from the ROS 2 Jazzy type store."""
    from rosbags.typesys import Stores, get_typestore
    return RosbagsFamily(get_typestore(Stores.ROS2_JAZZY))


@lru_cache(maxsize=1)
def rclpy_family() -> RclpyFamily:
    """Family of rclpy (rosidl-generated) message classes."""
    return RclpyFamily()


def family_of(msg: Any) -> MessageFamily:
    """The family a message instance or class belongs to."""
    return rosbags_family() if hasattr(msg, '__msgtype__') else rclpy_family()
