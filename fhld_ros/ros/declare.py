"""A node's parameters on the ROS side: declared read-only from a parameter dataclass's one
table (DetectorParams, CameraParams), with rclpy's and rcl's refusals turned into one line
naming the parameter. Imports neither parameter module: each node names its own."""
from __future__ import annotations

import dataclasses
import re
from typing import TypeVar

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node

from fhld_ros.dataclass_dict import field_docs, from_dict, to_plain
from fhld_ros.errors import ConfigError

# rclpy's refusal of a value of the wrong type (InvalidParameterTypeException's wording)
_WRONG_TYPE = re.compile(
    r"parameter '(?P<name>[^']+)' to '(?P<value>.*)' of type '(?P<given>\w+)'")
_WANTED = {bool: 'true or false', int: 'an integer', str: 'a string',
           float: 'a number with a decimal point (e.g. 10.0)',
           tuple: 'a list of numbers with decimal points (e.g. [0.0, 1.5])'}
P = TypeVar('P')


def rcl_reason(exc: Exception) -> str:
    """rcl's error text in one line, without its C source location."""
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return re.sub(r'(\. Error: error not set)?, at /\S+$', '', first)


def type_problem(cls: type, name: str, value: str, given: str) -> str:
    """One line for parameter `name` of `cls` given a value of the wrong type (`given`: ROS's
    type name, e.g. INTEGER for `rate_hz:=10`, which ROS does not turn into the double it
    declares)."""
    wanted = _WANTED.get(type(getattr(cls(), name, None)), 'of its declared type')
    return f'{name} must be {wanted}, not {given.lower().replace("_", " ")} {value}'


def declare_params(node: Node, cls: type[P]) -> P:
    """Declare every field of the parameter dataclass `cls`, read-only and described by its
    doc; the values as a `cls`. Read-only because a node reads them once: `ros2 param set` is
    refused with a reason instead of succeeding and changing nothing.

    Raises ConfigError naming the parameter for a wrong type, a refused value or a topic name
    (a field named *_topic) ROS cannot use.
    """
    docs = field_docs(cls)
    try:
        declared = node.declare_parameters('', [
            (name, default, ParameterDescriptor(description=docs[name], read_only=True))
            for name, default in to_plain(cls()).items()])
    except ParameterException as exc:
        wrong = _WRONG_TYPE.search(str(exc))
        raise ConfigError(type_problem(cls, **wrong.groupdict()) if wrong
                          else str(exc)) from None
    params = from_dict(cls, {p.name: p.value for p in declared})
    for name in (f.name for f in dataclasses.fields(cls) if f.name.endswith('_topic')):
        try:
            node.resolve_topic_name(getattr(params, name))
        except rclpy_implementation.RCLError as exc:
            reason = rcl_reason(exc).removeprefix('failed to resolve name: ')
            raise ConfigError(f'{name} {getattr(params, name)!r} is not a valid topic name: '
                              f'{reason}') from None
    return params
