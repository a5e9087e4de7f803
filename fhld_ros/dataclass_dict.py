"""Frozen config dataclasses to and from plain dicts (YAML files, checkpoints, ROS parameters).

Plain data has lists where the dataclasses keep tuples (frozen, hashable): `from_dict` turns a
list into a tuple for every field whose default is a tuple, `to_plain` goes back. Unknown keys
are refused by name, so a typo in a YAML file is an error, not a silently ignored setting.
Field metadata 'doc' is the one description of a setting (ROS parameter descriptors, --help).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

T = TypeVar('T')


def from_dict(cls: type[T], data: Mapping[str, Any], where: str = '',
              ignore: Iterable[str] = ()) -> T:
    """cls(**data) with lists as tuples; raises ValueError naming unknown keys and `where`."""
    if not isinstance(data, Mapping):
        raise ValueError(f'{where or cls.__name__} must be a mapping, not {type(data).__name__}')
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(known) - set(ignore))
    if unknown:
        place = f' in {where}' if where else ''
        raise ValueError(f'unknown key(s) {", ".join(map(str, unknown))}{place} '
                         f'(known: {", ".join(known)})')
    values = {}
    for name, value in data.items():
        if name not in known:
            continue
        if isinstance(value, list) and isinstance(_default(known[name]), tuple):
            value = tuple(value)
        values[name] = value
    return cls(**values)


def to_plain(value: Any) -> Any:
    """Dataclasses as dicts, tuples as lists, recursively: what YAML and weights_only take."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {key: to_plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_plain(item) for item in value]
    return value


def documented(default: Any, doc: str) -> Any:
    """A dataclass field with a default and its one description (metadata 'doc')."""
    return dataclasses.field(default=default, metadata={'doc': doc})


def field_docs(cls: type) -> dict[str, str]:
    """Field name -> its metadata 'doc' ('' when a field has none)."""
    return {f.name: f.metadata.get('doc', '') for f in dataclasses.fields(cls)}


def _default(item: dataclasses.Field) -> Any:
    if item.default is not dataclasses.MISSING:
        return item.default
    if item.default_factory is not dataclasses.MISSING:
        return item.default_factory()
    return None
