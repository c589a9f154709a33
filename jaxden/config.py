"""TOML configuration files <-> frozen dataclasses.

Every configurable part of jaxden (datasets, training, sweeps) is a frozen dataclass; a TOML
file is validated into it by :func:`load_config` and written back by :func:`dump_config`
(the writing side lives in :mod:`jaxden.config_write`; import it from here).
Nested dataclasses are TOML tables, tuples and lists are arrays, and the supported leaf types
are ``int``, ``float`` (an integer is accepted), ``str``, ``bool``, ``pathlib.Path`` (as a
string), ``Literal[...]`` choices, ``Optional[X]`` / ``X | None`` and other unions (tried in
order), ``tuple[X, ...]``, ``tuple[X, Y]``, ``list[X]`` and ``dict[str, X]``.

Errors are :class:`~jaxden.errors.ConfigError` with a message that names the file (and line
where it can be found), the table and the key, what was found and what was expected; an unknown
key also lists the allowed keys and suggests the closest one. Validation in a dataclass's
``__post_init__`` that raises ``ConfigError`` or ``ValueError`` is reported with the file name.

TOML has no null: a ``None`` value is written by omitting the key when the field's default is
``None`` and as the string ``"none"`` otherwise; the strings ``"none"`` / ``"null"`` are read as
``None`` for optional fields whose other alternatives are not strings.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import math
import os
import re
import tomllib
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, TypeVar, Union

from jaxden.config_write import (
    config_diff,
    config_to_dict,
    dump_config,
    save_config,
    toml_value,
)
from jaxden.errors import ConfigError

T = TypeVar("T")

__all__ = [
    "bounded",
    "check_fields",
    "check_ranges",
    "config_diff",
    "config_to_dict",
    "dump_config",
    "load_config",
    "parse_override",
    "save_config",
    "toml_value",
]

_NONE_STRINGS = ("none", "null")


# ----------------------------------------------------------------------------- error context
@dataclasses.dataclass
class _Source:
    """Where the values come from, for error messages."""

    origin: str  # "file x.toml", "dict", ...
    text: str | None = None  # the TOML text, for line look-ups
    overrides: dict[tuple[str, ...], str] = dataclasses.field(default_factory=dict)

    def where(self, path: tuple[str, ...]) -> str:
        """'file x.toml, line 7' or "override 'a.b=1' (on file x.toml)" for a key path."""
        for length in range(len(path), 0, -1):
            text = self.overrides.get(path[:length])
            if text is not None:
                return f"override '{text}' (applied to {self.origin})"
        line = _find_line(self.text, path) if self.text is not None and path else None
        return f"{self.origin}, line {line}" if line else self.origin


def _table_name(path: tuple[str, ...]) -> str:
    """'in table [a.b]' or 'at the top level'."""
    return f"in table [{'.'.join(path)}]" if path else "at the top level"


def _key_name(path: tuple[str, ...]) -> str:
    return ".".join(str(p) for p in path)


def _strip_key(part: str) -> str:
    part = part.strip()
    if len(part) >= 2 and part[0] == part[-1] and part[0] in "\"'":
        return part[1:-1]
    return part


def _find_line(text: str, path: tuple[str, ...]) -> int | None:
    """Best-effort 1-based line of ``path`` in TOML ``text`` (a key or a table header)."""
    path = tuple(str(p) for p in path)
    table: tuple[str, ...] = ()
    header = re.compile(r"^\s*\[\[?\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")
    assignment = re.compile(r"^\s*([A-Za-z0-9_\-\"'. ]+?)\s*=")
    for number, line in enumerate(text.splitlines(), start=1):
        match = header.match(line)
        if match:
            table = tuple(_strip_key(p) for p in match.group(1).split("."))
            if table == path:
                return number
            continue
        match = assignment.match(line)
        if match:
            key = table + tuple(_strip_key(p) for p in match.group(1).split("."))
            if key == path[: len(key)] and len(key) >= len(table) + 1:
                return number
    return None


# ----------------------------------------------------------------------------- type handling
def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if tp is type(None):
        return "none"
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin in (tuple, list, Sequence):
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            return f"an array of {len(args)} ({', '.join(_type_name(a) for a in args)})"
        inner = _type_name(args[0]) if args else "values"
        return f"an array of {inner}"
    if origin is dict:
        return "a table"
    if dataclasses.is_dataclass(tp):
        return f"a table ({tp.__name__})"
    return getattr(tp, "__name__", str(tp))


def _found(value: Any) -> str:
    text = repr(value)
    if len(text) > 60:
        text = text[:57] + "..."
    return f"{text} ({type(value).__name__})"


class _Mismatch(Exception):
    """Internal: a value does not fit a type; carries the message tail."""


#: No config int may exceed this in size (seeds, counts, sizes): 2^53, exact in a float.
MAX_INT = 2**53


def bounded(default: Any = dataclasses.MISSING, *, low: float | None = None,
            high: float | None = None, low_open: bool = False, high_open: bool = False,
            unit: str = "", **field_options) -> Any:
    """A dataclass field whose value must lie in [low, high] (``low_open`` / ``high_open``:
    without that end),
    checked by :func:`load_config` for every source (TOML, ``key=value`` overrides, compact
    CLI specs) and, for a config built in Python, by :func:`check_fields` in its
    ``__post_init__``; None passes (optional). The declaration is the one place the range is
    written: ``__post_init__`` checks only what involves several fields."""
    metadata = {"range": (low, high, low_open, high_open, unit)}
    if default is dataclasses.MISSING:
        return dataclasses.field(metadata=metadata, **field_options)
    return dataclasses.field(default=default, metadata=metadata, **field_options)


def _range_text(low, high, low_open: bool, high_open: bool, unit: str) -> str:
    def show(value, infinite):
        if value is None:
            return infinite
        return str(value) if isinstance(value, int) else f"{value:g}"

    left = "(" if low_open else "["
    right = ")" if high_open else "]"
    text = f"{left}{show(low, '-inf')}, {show(high, 'inf')}{right}"
    return text + (f" ({unit})" if unit else "")


def check_ranges(instance: Any) -> None:
    """Raise ConfigError for a field of a dataclass instance outside its declared range
    (:func:`bounded`); numbers inside tuples are checked one by one."""
    for field in dataclasses.fields(instance):
        bounds = field.metadata.get("range")
        if bounds is None:
            continue
        low, high, low_open, high_open, unit = bounds
        value = getattr(instance, field.name)
        values = value if isinstance(value, (tuple, list)) else (value,)
        for item in values:
            if item is None or isinstance(item, bool) or not isinstance(item, (int, float)):
                continue
            too_low = low is not None and (item <= low if low_open else item < low)
            too_high = high is not None and (item >= high if high_open else item > high)
            if too_low or too_high or not math.isfinite(item):
                raise ConfigError(
                    f"{type(instance).__name__}.{field.name}: {item!r} is outside the valid "
                    f"range {_range_text(low, high, low_open, high_open, unit)}")


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def check_fields(instance: Any) -> None:
    """Raise ConfigError for a field of a config dataclass instance whose value does not fit
    its declaration: its type (a choice of a ``Literal``, a bool, an int, a finite float, a
    nested config, ...) and its :func:`bounded` range. What :func:`load_config` checks for a
    TOML file, for a config built in Python: call it first in ``__post_init__``."""
    cls = type(instance)
    types_ = _field_types(cls)
    source = _Source(origin=f"{cls.__name__} object")
    for field in dataclasses.fields(instance):
        tp = types_[field.name]
        value = getattr(instance, field.name)
        if dataclasses.is_dataclass(tp):
            if not isinstance(value, tp):
                raise ConfigError(f"{cls.__name__}.{field.name}: expected a {tp.__name__}, "
                                  f"found {_found(value)}")
            continue
        try:
            _convert(tp, value, source, (field.name,))
        except _Mismatch as mismatch:
            raise ConfigError(f"{cls.__name__}.{field.name}: {mismatch}") from None
    check_ranges(instance)


def _convert(tp: Any, value: Any, source: _Source, path: tuple[str, ...]) -> Any:
    if tp is Any:
        return value
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, source, path)
    if origin in (Union, types.UnionType):
        return _convert_union(tp, value, source, path)
    if origin is Literal:
        choices = typing.get_args(tp)
        for choice in choices:
            if type(value) is type(choice) and value == choice:
                return value
        hint = ""
        if isinstance(value, str):
            close = difflib.get_close_matches(value, [c for c in choices if isinstance(c, str)], 1)
            if close:
                hint = f"; did you mean {close[0]!r}?"
        raise _Mismatch(f"expected {_type_name(tp)}, found {_found(value)}{hint}")
    if tp is type(None):
        if value is None:
            return None
        raise _Mismatch(f"expected none, found {_found(value)}")
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise _Mismatch(f"expected bool (true or false), found {_found(value)}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            if not -MAX_INT <= value <= MAX_INT:
                raise _Mismatch(f"expected an int of at most {MAX_INT:.3g} in size, found "
                                f"{_found(value)}")
            return value
        raise _Mismatch(f"expected int, found {_found(value)}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(float(value)):
                raise _Mismatch(f"expected a finite number, found {_found(value)}")
            return float(value)
        raise _Mismatch(f"expected float, found {_found(value)}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise _Mismatch(f"expected str, found {_found(value)}")
    if tp is Path or (isinstance(tp, type) and issubclass(tp, os.PathLike)):
        if isinstance(value, (str, os.PathLike)):
            return Path(value)
        raise _Mismatch(f"expected a path (string), found {_found(value)}")
    if origin in (tuple, list, Sequence):
        return _convert_sequence(tp, value, source, path)
    if origin is dict:
        key_type, value_type = typing.get_args(tp) or (str, Any)
        if key_type is not str:
            raise TypeError(f"config dict fields need str keys, got {tp}")
        if not isinstance(value, Mapping):
            raise _Mismatch(f"expected a table, found {_found(value)}")
        return {
            str(k): _convert_at(value_type, v, source, path + (str(k),)) for k, v in value.items()
        }
    raise TypeError(f"unsupported type in a config dataclass: {tp!r} (at {_key_name(path)})")


def _convert_union(tp: Any, value: Any, source: _Source, path: tuple[str, ...]) -> Any:
    alternatives = typing.get_args(tp)
    optional = type(None) in alternatives
    others = [a for a in alternatives if a is not type(None)]
    if value is None and optional:
        return None
    if (
        optional
        and isinstance(value, str)
        and value.lower() in _NONE_STRINGS
        and not any(a is str or a is Path for a in others)
    ):
        return None
    messages = []
    for alternative in others:
        try:
            return _convert(alternative, value, source, path)
        except _Mismatch as mismatch:
            messages.append(str(mismatch))
    if len(others) == 1:
        raise _Mismatch(messages[0] + (" (or none: leave the key out)" if optional else ""))
    raise _Mismatch(f"expected {_type_name(tp)}, found {_found(value)}")


def _convert_sequence(tp: Any, value: Any, source: _Source, path: tuple[str, ...]) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, (list, tuple)):
        raise _Mismatch(f"expected {_type_name(tp)}, found {_found(value)}")
    if origin is tuple and args and args[-1] is not Ellipsis:
        if len(value) != len(args):
            raise _Mismatch(
                f"expected {_type_name(tp)}, found {len(value)} value(s): {_found(list(value))}"
            )
        items = [
            _convert_at(a, v, source, path + (str(i),)) for i, (a, v) in enumerate(zip(args, value))
        ]
    else:
        item_type = args[0] if args else Any
        items = [_convert_at(item_type, v, source, path + (str(i),)) for i, v in enumerate(value)]
    return items if origin is list else tuple(items)


def _convert_at(tp: Any, value: Any, source: _Source, path: tuple[str, ...]) -> Any:
    """Convert, turning a mismatch into a ConfigError that names the key and the place."""
    try:
        return _convert(tp, value, source, path)
    except _Mismatch as mismatch:
        key_path = tuple(p for p in path if not p.isdigit()) or path
        raise ConfigError(
            f"{source.where(key_path)}: key '{_key_name(path)}': {mismatch}"
        ) from None


def _build(cls: type[T], data: Any, source: _Source, path: tuple[str, ...]) -> T:
    if not isinstance(data, Mapping):
        raise _Mismatch(f"expected a table ({cls.__name__}), found {_found(data)}")
    upgrade = getattr(cls, "upgrade_config", None)  # a class's map of its older keys
    if upgrade is not None:
        data = upgrade(data)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    allowed = sorted(fields)
    for key in data:
        if key not in fields:
            close = difflib.get_close_matches(str(key), allowed, n=1, cutoff=0.6)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            raise ConfigError(
                f"{source.where(path + (str(key),))}: unknown key '{key}' "
                f"{_table_name(path)} ({cls.__name__}){hint} Allowed keys: {', '.join(allowed)}"
            )
    kwargs = {}
    for name, field in fields.items():
        if name in data:
            kwargs[name] = _convert_at(hints[name], data[name], source, path + (name,))
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise ConfigError(
                f"{source.where(path)}: missing required key '{name}' {_table_name(path)} "
                f"({cls.__name__}), expected {_type_name(hints[name])}"
            )
    try:
        instance = cls(**kwargs)
        check_ranges(instance)
        return instance
    except (ConfigError, ValueError) as error:
        where = f"table [{'.'.join(path)}]: " if path else ""
        applied = [text for key, text in source.overrides.items() if key[: len(path)] == path]
        note = f" (with override(s) {', '.join(repr(t) for t in applied)})" if applied else ""
        raise ConfigError(f"{source.where(path)}{note}: {where}{error}") from None


# ----------------------------------------------------------------------------- overrides
def parse_override(text: str) -> tuple[tuple[str, ...], Any]:
    """Parse ``'table.key=value'`` into (('table', 'key'), value).

    The value is parsed as a TOML value (``3``, ``0.5``, ``true``, ``[2, 4]``, ``"x"``,
    ``{a = 1}``); anything that is not valid TOML (or is a TOML date/time) is taken as a plain
    string, so ``scene=cornell-box`` works without quotes.
    """
    if not isinstance(text, str) or "=" not in text:
        raise ConfigError(f"override {text!r} must have the form key=value (e.g. crop_size=64)")
    key, raw = text.split("=", 1)
    parts = tuple(_strip_key(p) for p in key.strip().split("."))
    if not key.strip() or any(not p for p in parts):
        raise ConfigError(f"override {text!r}: empty key before '='")
    raw = raw.strip()
    try:
        value = tomllib.loads(f"value = {raw}")["value"]
    except tomllib.TOMLDecodeError:
        value = raw
    if not isinstance(value, (str, int, float, bool, list, dict)):
        value = raw  # dates and times: keep the text
    return parts, value


def _apply_overrides(data: dict, overrides: Sequence[str], source: _Source) -> None:
    if isinstance(overrides, str):
        overrides = [overrides]
    for text in overrides:
        parts, value = parse_override(text)
        node = data
        for depth, part in enumerate(parts[:-1]):
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                raise ConfigError(
                    f"override '{text}': '{_key_name(parts[: depth + 1])}' is not a table "
                    f"(it is {_found(child)})"
                )
            node = child
        node[parts[-1]] = value
        source.overrides[parts] = text


# ----------------------------------------------------------------------------- loading
def load_config(
    source: str | os.PathLike | Mapping[str, Any] | Any,
    cls: type[T],
    overrides: Sequence[str] = (),
) -> T:
    """Validate a TOML file (or a dict, or an existing config) into the frozen dataclass ``cls``.

    ``source``: a path to a TOML file, a mapping (as from ``tomllib``), or an instance of a
    dataclass (its values are the base, e.g. to apply overrides to an existing config).
    ``overrides``: ``'key=value'`` / ``'table.key=value'`` strings applied on top, values parsed
    as TOML (see :func:`parse_override`).

    Raises ConfigError for a missing or unreadable file, invalid TOML (with its line), an
    unknown key (naming the table, the allowed keys and the closest match), a wrong type, a
    missing required key, or a value rejected by the dataclass's own validation.
    """
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise TypeError(f"load_config needs a dataclass type, got {cls!r}")
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if not path.exists():
            raise ConfigError(f"config file {path} does not exist")
        if path.is_dir():
            raise ConfigError(f"config file {path} is a folder, not a TOML file")
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as error:
            raise ConfigError(f"config file {path} cannot be read: {error}") from None
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as error:
            # tomllib's message ends with "(at line L, column C)" or "(at end of document)".
            message = str(error)
            if "at end of document" in message:
                message += f" (line {len(text.splitlines())} is the last line)"
            raise ConfigError(f"file {path}: invalid TOML: {message}") from None
        src = _Source(origin=f"file {path}", text=text)
    elif dataclasses.is_dataclass(source) and not isinstance(source, type):
        data = config_to_dict(source)
        src = _Source(origin=f"{type(source).__name__} object")
    elif isinstance(source, Mapping):
        data = copy.deepcopy(dict(source))
        src = _Source(origin="config dict")
    else:
        raise ConfigError(
            f"load_config takes a TOML file path, a dict or a config object, got {_found(source)}"
        )
    _apply_overrides(data, overrides, src)
    try:
        return _build(cls, data, src, ())
    except _Mismatch as mismatch:  # only when the top level is not a table: cannot happen
        raise ConfigError(f"{src.origin}: {mismatch}") from None
