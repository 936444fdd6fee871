"""A small declarative validator for plain data read from YAML or JSON.

A schema is a tree of specs (:class:`Number`, :class:`Text`, :class:`Flag`, :class:`ListOf`,
:class:`Record`). :meth:`Spec.check` walks a value against the tree and returns the validated,
normalised value (numbers as ``float``, lists as ``tuple``, records built into dataclasses), or
raises :class:`SchemaError` for the first problem found, with the key path of the offending
value (e.g. ``ders[3].p_inst_w``).

Unknown keys are always rejected, with the closest valid key suggested, so that a typo never
silently falls back to a default.
"""

from __future__ import annotations

import difflib
import math
import re
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "Field",
    "Flag",
    "ListOf",
    "Number",
    "Record",
    "SchemaError",
    "Spec",
    "Text",
    "at_index",
    "at_key",
    "show",
]


class SchemaError(Exception):
    """A value does not match its schema.

    Parameters
    ----------
    path : str
        Key path of the offending value, e.g. ``"ders[3].p_inst_w"``; ``""`` for the document root.
    problem : str
        One-line description, e.g. ``"must be a positive number, got -2"``.
    """

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"{path}: {problem}" if path else problem)
        self.path = path
        self.problem = problem


def at_key(path: str, key: object) -> str:
    """Return the key path of mapping entry ``key`` below ``path``."""
    return f"{path}.{key}" if path else str(key)


def at_index(path: str, index: int) -> str:
    """Return the key path of list item ``index`` below ``path``."""
    return f"{path}[{index}]"


def show(value: object) -> str:
    """Render a value read from a document for an error message (short, one line)."""
    if value is None:
        return "nothing (null)"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        text = value if len(value) <= 40 else value[:37] + "..."
        return repr(text)
    if isinstance(value, Mapping):
        return "a mapping"
    if isinstance(value, list | tuple):
        return "a list"
    return type(value).__name__


class Spec(ABC):
    """One node of a schema."""

    @abstractmethod
    def check(self, value: Any, path: str) -> Any:
        """Validate ``value`` found at key path ``path``; return it normalised.

        Raises
        ------
        SchemaError
            For the first problem found.
        """


@dataclass(frozen=True)
class Number(Spec):
    """A finite real number (YAML int or float, not a boolean), optionally bounded.

    Parameters
    ----------
    what : str
        How the requirement reads in an error message: "must be <what>, got ...".
    low, high : float or None
        Bounds; ``None`` for unbounded.
    low_open, high_open : bool
        Whether the respective bound is excluded.
    nonzero : bool
        Reject zero.
    """

    what: str = "a number"
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    nonzero: bool = False

    def check(self, value: Any, path: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise SchemaError(path, f"must be {self.what}, got {show(value)}")
        number = float(value)
        too_low = self.low is not None and (
            number < self.low or (self.low_open and number == self.low)
        )
        too_high = self.high is not None and (
            number > self.high or (self.high_open and number == self.high)
        )
        if not math.isfinite(number) or too_low or too_high or (self.nonzero and number == 0):
            raise SchemaError(path, f"must be {self.what}, got {show(value)}")
        return number


@dataclass(frozen=True)
class Text(Spec):
    """A non-empty string, optionally one of ``choices`` or matching ``pattern`` (full match)."""

    what: str = "a non-empty string"
    choices: tuple[str, ...] = ()
    pattern: str | None = None

    def check(self, value: Any, path: str) -> str:
        ok = isinstance(value, str) and value != ""
        if ok and self.choices:
            ok = value in self.choices
        if ok and self.pattern is not None:
            ok = re.fullmatch(self.pattern, value) is not None
        if not ok:
            raise SchemaError(path, f"must be {self.what}, got {show(value)}")
        return value


@dataclass(frozen=True)
class Flag(Spec):
    """A boolean (YAML ``true`` / ``false``)."""

    def check(self, value: Any, path: str) -> bool:
        if not isinstance(value, bool):
            raise SchemaError(path, f"must be true or false, got {show(value)}")
        return value


@dataclass(frozen=True)
class ListOf(Spec):
    """A list whose items all match ``item``; returned as a tuple.

    Parameters
    ----------
    item : Spec
        Schema of every item.
    min_len : int
        Minimum number of items.
    """

    item: Spec
    min_len: int = 0

    def check(self, value: Any, path: str) -> tuple[Any, ...]:
        if not isinstance(value, list):
            raise SchemaError(path, f"must be a list, got {show(value)}")
        if len(value) < self.min_len:
            raise SchemaError(path, f"must have at least {self.min_len} item(s), got {len(value)}")
        return tuple(self.item.check(v, at_index(path, i)) for i, v in enumerate(value))


@dataclass(frozen=True)
class Field:
    """One key of a :class:`Record`.

    Parameters
    ----------
    spec : Spec
        Schema of the value.
    required : bool
        Whether the key must be present. A missing optional key is left out of the values
        passed to ``Record.build``, so the default of the built class applies.
    """

    spec: Spec
    required: bool = True


@dataclass(frozen=True)
class Record(Spec):
    """A mapping with a fixed set of keys.

    Parameters
    ----------
    fields : Mapping[str, Field]
        The accepted keys, in the order they are checked (unknown keys are reported first).
    build : callable or None
        Called with the validated values as keyword arguments (e.g. a dataclass); ``None``
        returns them as a ``dict``.
    """

    fields: Mapping[str, Field]
    build: Callable[..., Any] | None = field(default=None)

    def check(self, value: Any, path: str) -> Any:
        if not isinstance(value, Mapping):
            raise SchemaError(path, f"must be a mapping, got {show(value)}")
        for key in value:
            if key not in self.fields:
                raise SchemaError(at_key(path, key), self._unknown(key))
        values = {}
        for key, spec_field in self.fields.items():
            if key in value:
                values[key] = spec_field.spec.check(value[key], at_key(path, key))
            elif spec_field.required:
                raise SchemaError(at_key(path, key), "required key is missing")
        return values if self.build is None else self.build(**values)

    def _unknown(self, key: object) -> str:
        close = difflib.get_close_matches(str(key), list(self.fields), n=1, cutoff=0.6)
        if close:
            return f"unknown key (did you mean '{close[0]}'?)"
        return f"unknown key (valid keys: {', '.join(self.fields)})"
