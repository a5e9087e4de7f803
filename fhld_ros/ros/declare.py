"""The node's parameters on the ROS side: declared read-only from DetectorParams' one table,
with rclpy's and rcl's refusals turned into one line naming the parameter."""
from __future__ import annotations

import re

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node

from fhld_ros.dataclass_dict import field_docs, from_dict, to_plain
from fhld_ros.errors import ConfigError
from fhld_ros.parameters import DetectorParams, type_problem

# rclpy's refusal of a value of the wrong type (InvalidParameterTypeException's wording)
_WRONG_TYPE = re.compile(
    r"parameter '(?P<name>[^']+)' to '(?P<value>.*)' of type '(?P<given>\w+)'")
TOPIC_PARAMS = ('points_topic', 'odom_topic', 'lanes_topic')


def rcl_reason(exc: Exception) -> str:
    """rcl's error text in one line, without its C source location."""
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return re.sub(r'(\. Error: error not set)?, at /\S+$', '', first)


def declare_detector_params(node: Node) -> DetectorParams:
    """Declare every DetectorParams field, read-only and described by its doc; the values as
    DetectorParams. Read-only because the node reads them once: `ros2 param set` is refused
    with a reason instead of succeeding and changing nothing.

    Raises ConfigError naming the parameter for a wrong type, a refused value or a topic name
    ROS cannot use.
    """
    docs = field_docs(DetectorParams)
    try:
        declared = node.declare_parameters('', [
            (name, default, ParameterDescriptor(description=docs[name], read_only=True))
            for name, default in to_plain(DetectorParams()).items()])
    except ParameterException as exc:
        wrong = _WRONG_TYPE.search(str(exc))
        raise ConfigError(type_problem(**wrong.groupdict()) if wrong else str(exc)) from None
    params = from_dict(DetectorParams, {p.name: p.value for p in declared})
    for name in TOPIC_PARAMS:
        try:
            node.resolve_topic_name(getattr(params, name))
        except rclpy_implementation.RCLError as exc:
            reason = rcl_reason(exc).removeprefix('failed to resolve name: ')
            raise ConfigError(f'{name} {getattr(params, name)!r} is not a valid topic name: '
                              f'{reason}') from None
    return params
