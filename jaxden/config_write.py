"""Configs written back: as plain dicts (:func:`config_to_dict`), as differences between two
(:func:`config_diff`) and as TOML text that :func:`jaxden.config.load_config` reads back to an
equal config (:func:`dump_config`, :func:`save_config`, :func:`toml_value`).

TOML has no null: a ``None`` value is written by omitting the key when the field's default is
``None`` and as the string ``"none"`` otherwise. Import these from :mod:`jaxden.config`, the
one place configs are read and written.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from jaxden.errors import ConfigError

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def config_to_dict(config: Any) -> dict[str, Any]:
    """The config as plain JSON-able data: tables as dicts, tuples as lists, paths as strings."""

    def plain(value: Any) -> Any:
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return {
                f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value) if f.init
            }
        if isinstance(value, Mapping):
            return {str(k): plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        if isinstance(value, os.PathLike):
            return os.fspath(value)
        return value

    if not (dataclasses.is_dataclass(config) and not isinstance(config, type)):
        raise TypeError(f"config_to_dict needs a dataclass instance, got {config!r}")
    return plain(config)


def config_diff(a: Mapping[str, Any], b: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Keys whose values differ between two plain config dicts, as 'key: a -> b' lines."""
    lines = []
    for key in sorted(set(a) | set(b), key=str):
        name = f"{prefix}{key}"
        if key not in a:
            lines.append(f"{name}: (absent) -> {json.dumps(b[key])}")
        elif key not in b:
            lines.append(f"{name}: {json.dumps(a[key])} -> (absent)")
        elif isinstance(a[key], Mapping) and isinstance(b[key], Mapping):
            lines.extend(config_diff(a[key], b[key], prefix=f"{name}."))
        elif a[key] != b[key]:
            lines.append(f"{name}: {json.dumps(a[key])} -> {json.dumps(b[key])}")
    return lines


_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _toml_string(text: str) -> str:
    """A TOML basic string: quotes, backslashes and every control character escaped (TOML
    forbids raw U+0000-U+001F and U+007F; JSON's escaping would let U+007F through)."""
    out = []
    for char in text:
        code = ord(char)
        if char in _ESCAPES:
            out.append(_ESCAPES[char])
        elif code < 0x20 or code == 0x7F:
            out.append(f"\\u{code:04x}")
        elif 0xD800 <= code <= 0xDFFF:
            raise ConfigError(f"cannot write the string {text!r} as TOML: it has a lone surrogate")
        else:
            out.append(char)
    return '"' + "".join(out) + '"'


def _toml_key(key: str) -> str:
    return key if _BARE_KEY.fullmatch(key) else _toml_string(key)


def toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        text = repr(value)  # shortest round-tripping form; always has '.', 'e' or 'inf'
        return text if any(c in text for c in ".en") else text + ".0"
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, os.PathLike):
        return toml_value(os.fspath(value))
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        items = [
            f"{_toml_key(f.name)} = {toml_value(getattr(value, f.name))}"
            for f in dataclasses.fields(value)
            if f.init and (getattr(value, f.name) is not None or f.default is not None)
        ]
        return "{" + ", ".join(items) + "}"
    if isinstance(value, Mapping):
        pairs = (f"{_toml_key(str(k))} = {toml_value(v)}" for k, v in value.items())
        return "{" + ", ".join(pairs) + "}"
    if value is None:
        return '"none"'
    raise TypeError(f"cannot write {value!r} ({type(value).__name__}) as TOML")


def _is_table(value: Any) -> bool:
    return (dataclasses.is_dataclass(value) and not isinstance(value, type)) or isinstance(
        value, Mapping
    )


def _dump_table(obj: Any, path: tuple[str, ...], out: list[str]) -> None:
    if isinstance(obj, Mapping):
        entries = [(str(k), v, None) for k, v in obj.items()]
    else:
        entries = [
            (f.name, getattr(obj, f.name), f) for f in dataclasses.fields(obj) if f.init
        ]
    tables = []
    for name, value, field in entries:
        if _is_table(value):
            tables.append((name, value))
            continue
        if value is None:
            if field is None or field.default is None or field.default is dataclasses.MISSING:
                continue  # omitted key = the default None
            out.append(f"{_toml_key(name)} = \"none\"")
            continue
        out.append(f"{_toml_key(name)} = {toml_value(value)}")
    for name, value in tables:
        sub = path + (name,)
        if out:
            out.append("")
        out.append("[" + ".".join(_toml_key(p) for p in sub) + "]")
        _dump_table(value, sub, out)


def dump_config(config: Any, *, header: str | None = None) -> str:
    """The config as TOML text that :func:`load_config` reads back to an equal config.

    ``header``: optional comment lines put at the top (each prefixed with '# ').
    """
    if not (dataclasses.is_dataclass(config) and not isinstance(config, type)):
        raise TypeError(f"dump_config needs a dataclass instance, got {config!r}")
    out: list[str] = []
    if header:
        out.extend(f"# {line}".rstrip() for line in header.splitlines())
        out.append("")
    _dump_table(config, (), out)
    return "\n".join(out).rstrip() + "\n"


def save_config(config: Any, path: str | os.PathLike, *, header: str | None = None) -> None:
    """Write ``dump_config(config)`` to ``path`` atomically (temporary file, then rename)."""
    path = Path(path)
    text = dump_config(config, header=header)
    from jaxden.fileio import atomic_write_text

    atomic_write_text(path, text)
