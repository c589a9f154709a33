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


def read_jsonl(path: str | os.PathLike, what: str, *, error=JaxdenError,
               fields: dict | None = None) -> tuple[list[dict], bool]:
    """Read the JSON-lines file ``path`` (one object per line, e.g. ``metrics.jsonl``):
    ``(records, cut)``. A last line without its newline that does not parse is what a write
    cut short (a kill, a full disk) leaves: it is dropped and ``cut`` is True. Anything else
    that is not an object with ``fields`` (see :func:`read_json`) raises ``error`` naming the
    file and the line. Blank lines are skipped."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise error(f"{path}: {what} is missing") from None
    except OSError as problem:
        raise error(f"{path}: cannot read {what}: {problem.strerror or problem}") from None
    lines = data.split(b"\n")
    records, cut = [], False
    for number, raw in enumerate(lines, 1):
        if not raw.strip():
            continue
        last = number == len(lines)  # no newline after it
        try:
            record = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as problem:
            if last:
                cut = True
                break
            reason = getattr(problem, "msg", None) or problem.reason
            raise error(f"{path}: line {number} of {what} is not valid JSON ({reason}); "
                        f"fix or delete that line") from None
        where = f"{path}: line {number} of {what}"
        if not isinstance(record, dict):
            raise error(f"{where}: expected an object, found {_json_type_name(type(record))}")
        if fields:
            check_json_fields(record, fields, where, error)
        records.append(record)
    return records, cut


def append_line(path: str | os.PathLike, line: str) -> None:
    """Append ``line`` and a newline to ``path`` (created if missing) in one piece: a write
    that fails (a full disk) is cut off again, so the file never ends in half a line; raises
    :class:`OutputError` naming the file."""
    append_bytes(path, (line + "\n").encode("utf-8"))


def append_bytes(path: str | os.PathLike, data: bytes, *, create: bool = True) -> None:
    """Append ``data`` to ``path`` in one piece (created if missing, unless ``create`` is
    False): a write that fails is cut off again, so the file never ends in a partial record;
    raises :class:`OutputError` naming the file."""
    path = Path(path)
    data = memoryview(data)
    flags = os.O_WRONLY | os.O_APPEND | (os.O_CREAT if create else 0)
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as problem:
        raise OutputError(f"cannot write {path}: {problem.strerror or problem}") from None
    try:
        size = os.fstat(fd).st_size
        try:
            while data:
                data = data[os.write(fd, data):]
        except OSError as problem:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, size)
            raise OutputError(f"cannot write {path}: {problem.strerror or problem}") from None
    finally:
        os.close(fd)
