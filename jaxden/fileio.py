"""Atomic file writes and folder locks, shared by every writer in jaxden.

An interrupted job never leaves a half-written file under its final name: data goes to a
temporary file ``.<name>.<random>.tmp<suffix>`` in the same folder, which is renamed onto the
final name once complete (and removed if anything fails). Temporary names match
``jaxden.data.layout.TEMP_PATTERN`` so dataset builders can clean up leftovers.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from jaxden.errors import JaxdenError, OutputError

_UMASK = os.umask(0)
os.umask(_UMASK)

# Files written by atomic_write inside all_or_nothing() blocks, innermost block last.
_GROUPS: list[list[Path]] = []


def check_outputs(*outputs: tuple[str, str | os.PathLike]) -> list[Path]:
    """Check ``(option, path)`` output files before any work is done: distinct paths, none an
    existing folder, each in an existing, writable folder. Returns the paths; raises
    :class:`OutputError` naming the option and the path."""
    paths, seen = [], {}
    for option, path in outputs:
        path = Path(path)
        key = os.path.realpath(path)
        if key in seen:
            raise OutputError(f"{option} {path}: the same file as {seen[key]}; give another name")
        seen[key] = f"{option} {path}"
        if path.is_dir():
            raise OutputError(f"{option} {path}: is a folder; give a file name")
        parent = path.parent
        if not parent.is_dir():
            raise OutputError(f"{option} {path}: the folder {parent} does not exist")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise OutputError(f"{option} {path}: no permission to write into {parent}")
        paths.append(path)
    return paths


@contextlib.contextmanager
def all_or_nothing() -> Iterator[None]:
    """Files that :func:`atomic_write` completes inside the block are removed again if the
    block raises: a command writing several files leaves all of them or none."""
    written: list[Path] = []
    _GROUPS.append(written)
    try:
        yield
    except BaseException:
        for path in written:
            with contextlib.suppress(OSError):
                path.unlink()
        raise
    finally:
        _GROUPS.remove(written)


def atomic_write(path: str | os.PathLike, write: Callable[[str], None], suffix: str = "") -> None:
    """Call ``write(tmp_path)``, then rename the temporary file onto ``path``.

    The file gets the usual permissions (0666 less the umask; mkstemp's are 0600).
    """
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a folder; cannot write a file there")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{suffix}",
                                   dir=path.parent)
    except OSError as error:
        raise OutputError(f"cannot write {path}: {error.strerror or error}") from None
    os.close(fd)
    try:
        try:
            write(tmp)
        except OSError as error:
            raise OutputError(f"cannot write {path}: {error.strerror or error}") from None
        except RuntimeError as error:  # OpenEXR's C++ errors ("No space left on device", ...)
            reason = str(error).replace(tmp, str(path)).strip().splitlines()
            raise OutputError(f"cannot write {path}: {reason[0] if reason else 'failed'}") \
                from None
        os.chmod(tmp, 0o666 & ~_UMASK)
        try:
            os.replace(tmp, path)
        except OSError as error:
            raise OutputError(f"cannot write {path}: {error.strerror or error}") from None
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    if _GROUPS:
        _GROUPS[-1].append(path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (flushed to disk before the rename)."""

    def write(tmp: str) -> None:
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())

    atomic_write(path, write)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


@contextlib.contextmanager
def folder_lock(directory: str | os.PathLike, name: str, what: str) -> Iterator[None]:
    """Hold an exclusive, non-blocking lock on ``directory/name`` while ``what`` runs there;
    a second holder gets a JaxdenError (DatasetError for callers that pass one)."""
    import fcntl

    from jaxden.errors import DatasetError

    directory = Path(directory)
    handle = open(directory / name, "a+")
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise DatasetError(
                f"another {what} is writing into {directory} (its {name} is locked); wait for "
                f"it to finish or stop it first"
            ) from None
        yield
    finally:
        handle.close()


__all__ = ["JaxdenError", "OutputError", "all_or_nothing", "atomic_write", "atomic_write_bytes",
           "atomic_write_text", "check_outputs", "folder_lock"]


# ------------------------------------------------------------------------------------ JSON
_JSON_TYPES = {dict: "an object", list: "a list", str: "a string", int: "a whole number",
               float: "a number", bool: "true or false", type(None): "null"}


def _json_type_name(types) -> str:
    types = types if isinstance(types, tuple) else (types,)
    return " or ".join(_JSON_TYPES.get(t, t.__name__) for t in types)


def _is_instance(value, types) -> bool:
    types = types if isinstance(types, tuple) else (types,)
    if isinstance(value, bool) and bool not in types:
        return False  # JSON true is not a number here
    if float in types and isinstance(value, int) and not isinstance(value, bool):
        return True
    return isinstance(value, types)


def read_json(path: str | os.PathLike, what: str, *, error=JaxdenError, kind=dict,
              fields: dict | None = None):
    """Read the JSON file ``path`` (``what`` it is, for messages: "the dataset manifest",
    "the weights' meta record"): its top level must be ``kind`` and, for objects, each of
    ``fields`` (``{name: type or (types...)}``; a name ending in ``?`` is optional) must have
    that type. Anything else (missing, unreadable, not UTF-8, malformed, wrongly typed) raises
    ``error`` with one line naming the file and the field. Every JSON file jaxden reads goes
    through here or :func:`check_json_fields`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: {what} is missing") from None
    except (OSError, UnicodeDecodeError) as problem:
        reason = getattr(problem, "strerror", None) or problem
        raise error(f"{path}: cannot read {what}: {reason}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as problem:
        raise error(f"{path}: {what} is not valid JSON ({problem.msg} at line "
                    f"{problem.lineno}, column {problem.colno})") from None
    if not _is_instance(data, kind):
        raise error(f"{path}: {what} must be {_json_type_name(kind)} at its top level, found "
                    f"{_json_type_name(type(data))}")
    if fields and isinstance(data, dict):
        check_json_fields(data, fields, f"{path}: {what}", error)
    return data


def check_json_fields(data: dict, fields: dict, where: str, error=JaxdenError) -> dict:
    """Check that ``data[name]`` has the type ``fields[name]`` (a trailing ``?`` on the name:
    optional, may be absent or null); raise ``error`` naming ``where`` and the field."""
    if not isinstance(data, dict):
        raise error(f"{where}: expected an object, found {_json_type_name(type(data))}")
    for name, types in fields.items():
        optional = name.endswith("?")
        key = name.rstrip("?")
        if key not in data or (optional and data[key] is None):
            if optional:
                continue
            raise error(f"{where}: field {key!r} is missing")
        if not _is_instance(data[key], types):
            raise error(f"{where}: field {key!r} must be {_json_type_name(types)}, found "
                        f"{_json_type_name(type(data[key]))} {str(data[key])[:40]!r}")
    return data
