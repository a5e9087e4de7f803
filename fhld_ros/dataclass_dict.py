"""Frozen config dataclasses to and from plain dicts (YAML files, checkpoints, ROS parameters),
and the one check of their values.

Plain data has lists where the dataclasses keep tuples (frozen, hashable): `from_dict` turns a
list into a tuple for every field whose default is a tuple, `to_plain` goes back. Unknown keys
are refused by name, so a typo in a YAML file is an error, not a silently ignored setting.

A field declared with `documented` carries its one description (metadata 'doc': ROS parameter
descriptors, --help) and, beside it, the values it takes: 'range' (an interval such as
'(0, 1000]' or '[1, inf)'), 'choices', 'length' (of a tuple or string) and 'kind' (the type,
when the default does not tell it). `check_fields` checks every field against them and the
type of its default, and raises one ConfigError naming each bad field and value.
"""
from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Iterable, Mapping
from typing import Any, NamedTuple, TypeVar

from fhld_ros.errors import ConfigError

T = TypeVar('T')


class Interval(NamedTuple):
    low: float
    high: float
    low_open: bool = False
    high_open: bool = False

    def holds(self, value: float) -> bool:
        return ((self.low < value if self.low_open else self.low <= value)
                and (value < self.high if self.high_open else value <= self.high))

    def describe(self) -> str:
        """' >= 0 and <= 1' (nothing for an infinite side)."""
        sides = []
        if self.low > -math.inf:
            sides.append(f'{">" if self.low_open else ">="} {self.low:.10g}')
        if self.high < math.inf:
            sides.append(f'{"<" if self.high_open else "<="} {self.high:.10g}')
        return ' ' + ' and '.join(sides) if sides else ''


_INTERVAL = re.compile(r'([\[(])\s*([^,\s]+)\s*,\s*([^\])\s]+)\s*([\])])')


def interval(text: str) -> Interval:
    """'[a, b]', '(a, b]', '[a, inf)' ...: square brackets include the bound, round exclude it."""
    match = _INTERVAL.fullmatch(text.strip())
    if match is None:
        raise ValueError(f'not an interval: {text!r}')  # a declaration's typo, found at import
    opening, low, high, closing = match.groups()
    return Interval(float(low), float(high), opening == '(', closing == ')')


def documented(default: Any, doc: str, *, range: str | None = None,
               choices: Iterable[Any] | None = None, length: int | str | None = None,
               kind: type | None = None) -> Any:
    """A dataclass field with a default, its one description (metadata 'doc') and the values it
    takes: `range` of numbers, `choices`, `length` of a tuple or string (an exact count or an
    interval), `kind` of the value or of a tuple's items. On a tuple, range, choices and kind
    hold for each item."""
    metadata: dict[str, Any] = {'doc': doc}
    if range is not None:
        metadata['range'] = interval(range)
    if choices is not None:
        metadata['choices'] = tuple(choices)
    if length is not None:
        metadata['length'] = (Interval(length, length) if isinstance(length, int)
                              else interval(length))
    if kind is not None:
        metadata['kind'] = kind
    return dataclasses.field(default=default, metadata=metadata)


def field_docs(cls: type) -> dict[str, str]:
    """Field name -> its metadata 'doc' ('' when a field has none)."""
    return {f.name: f.metadata.get('doc', '') for f in dataclasses.fields(cls)}


def field_problems(obj: Any, where: str = '', names: Mapping[str, str] | None = None
                   ) -> list[str]:
    """One line per field whose value its declaration refuses, naming the field (`where.name`,
    or the name `names` gives it) and the value."""
    problems = []
    for item in dataclasses.fields(obj):
        value = getattr(obj, item.name)
        wanted = _wanted(item, value)
        if wanted is not None:
            name = (names or {}).get(item.name, item.name)
            problems.append(f'{where + "." if where else ""}{name} must be {wanted}, '
                            f'not {value!r}')
    return problems


def check_fields(obj: Any, where: str = '', names: Mapping[str, str] | None = None) -> None:
    """ConfigError naming every field of obj whose value its declaration refuses."""
    problems = field_problems(obj, where, names)
    if problems:
        raise ConfigError('; '.join(problems))


def _wanted(item: dataclasses.Field, value: Any) -> str | None:
    """What the field must be, when value is not that; None when it is."""
    meta, default = item.metadata, _default(item)
    if not isinstance(default, tuple):
        kind = meta.get('kind', _kind(default))
        return None if _fits(meta, kind, value) else _describe(meta, kind)
    kinds = {_kind(x) for x in default}
    kind = meta.get('kind', kinds.pop() if len(kinds) == 1 else None)
    length = meta.get('length')
    if isinstance(value, tuple) and (length is None or length.holds(len(value))) \
            and all(_fits({**meta, 'length': None}, kind, x) for x in value):
        return None
    return _describe_items(meta, kind, length)


def _kind(default: Any) -> type | None:
    """The type a field's values must have, from its default (None: any)."""
    return type(default) if isinstance(default, (bool, int, float, str)) else None


def _fits(meta: Mapping[str, Any], kind: type | None, value: Any) -> bool:
    if 'choices' in meta:
        return (kind is None or type(value) is kind) and value in meta['choices']
    if kind is bool or kind is str:
        length = meta.get('length')
        return isinstance(value, kind) and (length is None or length.holds(len(value)))
    if kind is int or kind is float:
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        return (number and (kind is float or isinstance(value, int)) and math.isfinite(value)
                and ('range' not in meta or meta['range'].holds(value)))
    return True


def _alternatives(choices: tuple[Any, ...]) -> str:
    return ', '.join(map(repr, choices[:-1])) + f' or {choices[-1]!r}' if len(choices) > 1 \
        else repr(choices[0])


def _describe(meta: Mapping[str, Any], kind: type | None) -> str:
    """'an integer >= 0 and <= 64', "'cpu' or 'cuda'", 'true or false', ..."""
    if 'choices' in meta:
        return _alternatives(meta['choices'])
    if kind is bool:
        return 'true or false'
    if kind is str:
        return 'a non-empty string' if meta.get('length') else 'a string'
    bounds = meta['range'].describe() if 'range' in meta else ''
    if kind is int:
        return f'an integer{bounds}'
    return f'a number{bounds}' if bounds else 'a finite number'


def _describe_items(meta: Mapping[str, Any], kind: type | None, length: Interval | None
                    ) -> str:
    """'4 integers >= 1 and <= 4096', 'one or more of 'a' or 'b'', 'a list', ..."""
    if length is None:
        count = 'a list'
    elif length.low == length.high:
        count = f'{length.low:.10g}'
    elif length.high == math.inf:
        count = f'{"one" if length.low == 1 else f"{length.low:.10g}"} or more'
    else:
        count = f'{length.low:.10g} to {length.high:.10g}'
    if 'choices' in meta:
        return f'{count} of {_alternatives(meta["choices"])}'
    if kind is None:
        return count if length is None else f'{count} items'
    bounds = meta['range'].describe() if 'range' in meta else ''
    noun = {bool: 'true or false values', int: 'integers', str: 'strings'}.get(
        kind, 'numbers' if bounds else 'finite numbers')
    return f'{"a list of" if length is None else count} {noun}{bounds}'


def from_dict(cls: type[T], data: Mapping[str, Any], where: str = '',
              ignore: Iterable[str] = ()) -> T:
    """cls(**data) with lists as tuples; ConfigError naming unknown keys and `where`."""
    if not isinstance(data, Mapping):
        raise ConfigError(f'{where or cls.__name__} must be a mapping, not '
                          f'{type(data).__name__}')
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(known) - set(ignore))
    if unknown:
        place = f' in {where}' if where else ''
        raise ConfigError(f'unknown key(s) {", ".join(map(str, unknown))}{place} '
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


def _default(item: dataclasses.Field) -> Any:
    if item.default is not dataclasses.MISSING:
        return item.default
    if item.default_factory is not dataclasses.MISSING:
        return item.default_factory()
    return None
