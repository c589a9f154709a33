"""Intel Open Image Denoise's own trained weights, read from the installed library at run time.

OIDN 2 compiles its weights into ``libOpenImageDenoise_core.so`` as TZA blobs, each exported as
a dynamic symbol ``oidn::blobs::weights::<name>`` (``rt_hdr``, ``rt_hdr_alb``,
``rt_hdr_calb_cnrm_large``, ...). This module finds the library through the installed
``pyoidn`` package, reads its ELF dynamic symbol table (no ``nm`` needed), parses each blob
(TZA 2.0: magic 0x41D7, a table of named fp16 tensors in ``oihw`` or ``x`` layout) and caches
the parsed weights as an ``.npz`` under the user cache, keyed by the library's sha256. Nothing
is copied into the repository or downloaded.

A missing library or one without the blobs is one :class:`jaxden.errors.CheckpointError`; a
blob whose header, table or data run outside it is refused whole, never half-loaded.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import struct
from pathlib import Path

import numpy as np

from jaxden.errors import CheckpointError

TZA_MAGIC = 0x41D7
_SYMBOL = re.compile(rb"^_ZN4oidn5blobs7weights(\d+)(\w+)E$")
#: Library file name pattern inside pyoidn's package.
LIBRARY_GLOB = "libOpenImageDenoise_core.so*"


def find_library() -> Path:
    """The installed OIDN core library (through pyoidn), or a CheckpointError."""
    try:
        import pyoidn
    except ImportError:
        raise CheckpointError("OIDN in JAX reads Intel's weights from the installed OIDN "
                              "library, but pyoidn is not installed (pip install pyoidn)") from None
    folder = Path(pyoidn.__file__).parent / "oidn" / "lib"
    candidates = sorted(p for p in folder.glob(LIBRARY_GLOB) if p.is_file() and not p.is_symlink())
    if not candidates:
        raise CheckpointError(f"no OIDN core library ({LIBRARY_GLOB}) in {folder}")
    return candidates[-1]


def _elf_symbols(data: bytes, where: str) -> dict[str, tuple[int, int]]:
    """``{blob name: (file offset, size)}`` of the ``oidn::blobs::weights::*`` dynamic symbols
    of a 64-bit little-endian ELF file."""
    if data[:4] != b"\x7fELF" or data[4] != 2 or data[5] != 1:
        raise CheckpointError(f"{where}: not a 64-bit little-endian ELF library")
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum = struct.unpack_from("<HH", data, 0x3A)
    sections = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + i * shentsize)
                for i in range(shnum)]
    symbols = {}
    for _, kind, _, _, offset, size, link, _, _, entsize in sections:
        if kind != 11:  # SHT_DYNSYM
            continue
        strings = sections[link]
        string_offset = strings[4]
        for start in range(offset, offset + size, entsize):
            name_at, _, _, section, value, length = struct.unpack_from("<IBBHQQ", data, start)
            end = data.index(b"\0", string_offset + name_at)
            match = _SYMBOL.match(data[string_offset + name_at:end])
            if match is None or not 0 < section < len(sections):
                continue
            _, _, _, address, section_offset, _, _, _, _, _ = sections[section]
            symbols[match.group(2).decode()] = (value - address + section_offset, length)
    return symbols


def parse_tza(blob: bytes, name: str) -> dict[str, np.ndarray]:
    """``{tensor name: float32 array}`` of one TZA 2.0 blob; CheckpointError if any part of
    it is malformed (nothing is returned then)."""
    def fail(reason):
        raise CheckpointError(f"OIDN weights {name}: {reason}; the blob is refused")

    if len(blob) < 12:
        fail("shorter than a TZA header")
    magic, major, minor, table = struct.unpack_from("<HBBQ", blob, 0)
    if magic != TZA_MAGIC or major != 2:
        fail(f"not a TZA 2.x blob (magic {magic:#x}, version {major}.{minor})")
    try:
        count, = struct.unpack_from("<I", blob, table)
        at = table + 4
        tensors = {}
        for _ in range(count):
            length, = struct.unpack_from("<H", blob, at)
            tensor = blob[at + 2:at + 2 + length].decode("ascii")
            at += 2 + length
            ndims = blob[at]
            dims = struct.unpack_from(f"<{ndims}I", blob, at + 1)
            at += 1 + 4 * ndims
            layout = blob[at:at + ndims].decode("ascii")
            dtype = blob[at + ndims:at + ndims + 1]
            at += ndims + 1
            offset, = struct.unpack_from("<Q", blob, at)
            at += 8
            if dtype != b"h" or layout not in ("oihw", "x"):
                fail(f"tensor {tensor} has dtype {dtype!r} and layout {layout!r} (expected "
                     f"fp16 'h' in oihw or x)")
            size = int(np.prod(dims, dtype=np.int64)) * 2
            if offset + size > len(blob) or len(dims) != len(layout):
                fail(f"tensor {tensor} runs outside the blob")
            tensors[tensor] = np.frombuffer(blob, np.float16, size // 2, offset).reshape(
                dims).astype(np.float32)
    except (struct.error, IndexError, UnicodeDecodeError):
        fail("its tensor table is truncated or corrupt")
    if not tensors:
        fail("it holds no tensors")
    return tensors


def _cache_path(library_sha: str) -> Path:
    root = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return root / "jaxden" / f"oidn-weights-{library_sha[:16]}.npz"


def load_blobs(library: str | os.PathLike | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Every weights blob of the installed (or given) OIDN library, ``{blob: {tensor: array}}``,
    parsed once and then read from the user cache; held in memory per library file (path,
    size and modification time) for the process. The arrays are shared: read them only."""
    path = Path(library) if library is not None else find_library()
    try:
        stat = path.stat()
    except OSError as error:
        raise CheckpointError(f"{path}: cannot read the OIDN library: {error.strerror}") from None
    return _load_blobs(str(path), stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=2)
def _load_blobs(where: str, size: int, mtime_ns: int) -> dict[str, dict[str, np.ndarray]]:
    del size, mtime_ns  # the cache key: a changed library file is read again
    blobs = _read_blobs(Path(where))
    for tensors in blobs.values():
        for array in tensors.values():
            array.flags.writeable = False
    return blobs


def _read_blobs(path: Path) -> dict[str, dict[str, np.ndarray]]:
    try:
        data = path.read_bytes()
    except OSError as error:
        raise CheckpointError(f"{path}: cannot read the OIDN library: {error.strerror}") from None
    sha = hashlib.sha256(data).hexdigest()
    cache = _cache_path(sha)
    if cache.is_file():
        try:
            with np.load(cache) as stored:
                blobs: dict[str, dict[str, np.ndarray]] = {}
                for key in stored.files:
                    blob, _, tensor = key.partition("/")
                    blobs.setdefault(blob, {})[tensor] = stored[key]
            return blobs
        except (OSError, ValueError):
            pass  # a broken cache is rebuilt below
    symbols = _elf_symbols(data, str(path))
    if not symbols:
        raise CheckpointError(f"{path}: no oidn::blobs::weights symbols; not an OIDN 2 core "
                              f"library?")
    blobs = {name: parse_tza(data[offset:offset + size], name)
             for name, (offset, size) in sorted(symbols.items())}
    cache.parent.mkdir(parents=True, exist_ok=True)
    from jaxden.fileio import atomic_write

    flat = {f"{blob}/{tensor}": array for blob, tensors in blobs.items()
            for tensor, array in tensors.items()}
    atomic_write(cache, lambda tmp: np.savez(tmp, **flat), suffix=".npz")
    return blobs
