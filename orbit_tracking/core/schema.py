"""A small declarative validator for YAML configuration.

Every check raises :class:`~orbit_tracking.core.errors.ConfigError` naming the file,
the dotted key path (``stations[3].sigma.range``) and what was expected, so a wrong key
or value in a scenario file is a one-line fix for the user.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from orbit_tracking.core.errors import ConfigError

__all__ = [
    'REQUIRED',
    'Bool',
    'Check',
    'Choice',
    'Intervals',
    'ListOf',
    'Nullable',
    'Num',
    'Obj',
    'Str',
    'Tagged',
    'Vec',
]

REQUIRED: Any = object()
"""Marker for a key without default."""


class Check:
    """Base class: ``check(value, path, source)`` returns the normalised value."""

    expected = 'a value'

    def __call__(self, value: Any, path: str, source: str) -> Any:
        raise NotImplementedError

    def fail(self, value: Any, path: str, source: str, what: str | None = None) -> ConfigError:
        return ConfigError(source, path, f'expected {what or self.expected}, got {value!r}')


@dataclass(frozen=True)
class Num(Check):
    """A real number within optional bounds (``gt``/``ge``/``lt``/``le``)."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    integer: bool = False

    @property
    def expected(self) -> str:  # type: ignore[override]
        kind = 'an integer' if self.integer else 'a number'
        parts = []
        if self.gt is not None:
            parts.append(f'> {self.gt:g}')
        if self.ge is not None:
            parts.append(f'>= {self.ge:g}')
        if self.lt is not None:
            parts.append(f'< {self.lt:g}')
        if self.le is not None:
            parts.append(f'<= {self.le:g}')
        return kind + (' ' + ' and '.join(parts) if parts else '')

    def __call__(self, value: Any, path: str, source: str) -> Any:
        if isinstance(value, str):
            # YAML 1.1 reads ``5e-6`` (no dot) as a string; accept what float() accepts
            try:
                value = float(value)
            except ValueError:
                raise self.fail(value, path, source) from None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(value, path, source)
        if self.integer and not float(value).is_integer():
            raise self.fail(value, path, source)
        x = float(value)
        if not math.isfinite(x):
            raise self.fail(value, path, source)
        if (
            (self.gt is not None and not x > self.gt)
            or (self.ge is not None and not x >= self.ge)
            or (self.lt is not None and not x < self.lt)
            or (self.le is not None and not x <= self.le)
        ):
            raise self.fail(value, path, source)
        return int(x) if self.integer else x


@dataclass(frozen=True)
class Str(Check):
    """A non-empty string, optionally matching a predicate."""

    pattern: Callable[[str], bool] | None = None
    what: str = 'a non-empty string'

    @property
    def expected(self) -> str:  # type: ignore[override]
        return self.what

    def __call__(self, value: Any, path: str, source: str) -> Any:
        if not isinstance(value, str) or not value or (self.pattern and not self.pattern(value)):
            raise self.fail(value, path, source)
        return value


@dataclass(frozen=True)
class Choice(Check):
    """One of a fixed set of strings."""

    choices: tuple[str, ...]

    def __call__(self, value: Any, path: str, source: str) -> Any:
        if value not in self.choices:
            raise self.fail(value, path, source, f'one of {list(self.choices)}')
        return value


class Bool(Check):
    expected = 'true or false'

    def __call__(self, value: Any, path: str, source: str) -> Any:
        if not isinstance(value, bool):
            raise self.fail(value, path, source)
        return value


@dataclass(frozen=True)
class Vec(Check):
    """A list of ``n`` finite numbers."""

    n: int

    def __call__(self, value: Any, path: str, source: str) -> Any:
        what = f'a list of {self.n} numbers'
        if not isinstance(value, list | tuple) or len(value) != self.n:
            raise self.fail(value, path, source, what)
        return [Num()(v, f'{path}[{i}]', source) for i, v in enumerate(value)]


@dataclass(frozen=True)
class ListOf(Check):
    """A list whose items all pass ``item``."""

    item: Check
    min_len: int = 0

    def __call__(self, value: Any, path: str, source: str) -> Any:
        if not isinstance(value, list):
            raise self.fail(value, path, source, f'a list of {self.item.expected}')
        if len(value) < self.min_len:
            raise self.fail(value, path, source, f'a list of at least {self.min_len} item(s)')
        return [self.item(v, f'{path}[{i}]', source) for i, v in enumerate(value)]


@dataclass(frozen=True)
class Nullable(Check):
    inner: Check

    def __call__(self, value: Any, path: str, source: str) -> Any:
        return None if value is None else self.inner(value, path, source)


@dataclass(frozen=True)
class Obj(Check):
    """A mapping with known keys: ``{key: (check, default)}``; unknown keys are errors."""

    fields: Mapping[str, tuple[Check, Any]]
    expected = 'a mapping'

    def __call__(self, value: Any, path: str, source: str) -> Any:
        if not isinstance(value, Mapping):
            raise self.fail(value, path, source, f'a mapping with keys {sorted(self.fields)}')
        out: dict[str, Any] = {}
        for key in value:
            if key not in self.fields:
                near = difflib.get_close_matches(str(key), list(self.fields), n=1)
                hint = f' (did you mean {near[0]!r}?)' if near else ''
                raise ConfigError(
                    source,
                    _join(path, str(key)),
                    f'unknown key{hint}; expected one of {sorted(self.fields)}',
                )
        for key, (check, default) in self.fields.items():
            sub = _join(path, key)
            if key in value:
                out[key] = check(value[key], sub, source)
            elif default is REQUIRED:
                raise ConfigError(source, sub, f'missing required key ({check.expected})')
            else:
                out[key] = default
        return out


@dataclass(frozen=True)
class Tagged(Check):
    """A mapping whose ``tag`` key selects which :class:`Obj` validates it."""

    tag: str
    variants: Mapping[str, Obj]

    def __call__(self, value: Any, path: str, source: str) -> Any:
        if not isinstance(value, Mapping) or self.tag not in value:
            raise self.fail(value, path, source, f'a mapping with a {self.tag!r} key')
        kind = Choice(tuple(self.variants))(value[self.tag], _join(path, self.tag), source)
        body = {k: v for k, v in value.items() if k != self.tag}
        out = self.variants[kind](body, path, source)
        out[self.tag] = kind
        return out


@dataclass(frozen=True)
class Intervals(Check):
    """A list of ``{start, end}`` windows (optionally with more keys) with start < end."""

    extra: Mapping[str, tuple[Check, Any]] | None = None

    def __call__(self, value: Any, path: str, source: str) -> Any:
        fields = {'start': (Num(), REQUIRED), 'end': (Num(), REQUIRED), **(self.extra or {})}
        items = ListOf(Obj(fields))(value, path, source)
        for i, it in enumerate(items):
            if not it['start'] < it['end']:
                raise ConfigError(
                    source, f'{path}[{i}]', f'expected start < end, got {it["start"]}..{it["end"]}'
                )
        return items


def _join(path: str, key: str) -> str:
    return f'{path}.{key}' if path else key
