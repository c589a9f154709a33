"""Atomic file writes and folder locks, shared by every writer in jaxden.

An interrupted job never leaves a half-written file under its final name: data goes to a
temporary file ``.<name>.<random>.tmp<suffix>`` in the same folder, which is renamed onto the
final name once complete (and removed if anything fails). Temporary names match
``jaxden.data.layout.TEMP_PATTERN`` so dataset builders can clean up leftovers.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from jaxden.errors import JaxdenError

_UMASK = os.umask(0)
os.umask(_UMASK)


def atomic_write(path: str | os.PathLike, write: Callable[[str], None], suffix: str = "") -> None:
    """Call ``write(tmp_path)``, then rename the temporary file onto ``path``.

    The file gets the usual permissions (0666 less the umask; mkstemp's are 0600).
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{suffix}", dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


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


__all__ = ["JaxdenError", "atomic_write", "atomic_write_bytes", "atomic_write_text", "folder_lock"]
