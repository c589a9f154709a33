"""TensorBoard event files written without TensorFlow: scalars of a training run.

An event file (``events.out.tfevents.<unix time>.<host>.<pid>.<n>``) is a sequence of
records, each ``length`` (uint64, little-endian), the masked CRC-32C of those 8 bytes, the
``data`` and the masked CRC-32C of the data (masked: ``((crc >> 15) | (crc << 17)) +
0xa282ead8`` mod 2**32; CRC-32C: the Castagnoli polynomial, :func:`crc32c`). Each record's data
is an ``Event`` protobuf, encoded here by hand from the fields TensorBoard reads::

    Event      { double wall_time = 1; int64 step = 2; string file_version = 3;
                 Summary summary = 5; SessionLog session_log = 7; }
    Summary    { repeated Value value = 1; }
    Value      { string tag = 1; float simple_value = 2; }
    SessionLog { SessionStatus status = 1; }        // START = 1

The first event of a file carries ``file_version = "brain.Event:2"``. A run writes a new file
each time it starts (TensorBoard merges the files of one folder); when older files are there
(a resumed run), the new file's second event is a ``SessionLog`` START at the resume step,
TensorBoard's mark for "later steps of the older files are orphaned". Files are only ever
appended to, a whole record at a time; older files are never touched. :func:`read_events`
reads a file back (checksums verified), for tests and tools.
"""

from __future__ import annotations

import math
import os
import socket
import struct
import time
from pathlib import Path
from typing import Any

from jaxden.errors import JaxdenError, OutputError

FILE_PREFIX = "events.out.tfevents."
FILE_VERSION = "brain.Event:2"
#: SessionLog.SessionStatus START.
SESSION_START = 1
_MASK_DELTA = 0xA282EAD8


# ------------------------------------------------------------------------------- checksums
def _crc32c_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC32C_TABLE = _crc32c_table()


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli, reflected polynomial 0x82F63B78) of ``data``."""
    crc = 0xFFFFFFFF
    table = _CRC32C_TABLE
    for byte in data:
        crc = table[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def masked_crc32c(data: bytes) -> int:
    """The CRC-32C of ``data`` masked as TFRecord files store it."""
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


def record_bytes(data: bytes) -> bytes:
    """One TFRecord: length, its masked CRC, ``data``, the data's masked CRC."""
    header = struct.pack("<Q", len(data))
    return (header + struct.pack("<I", masked_crc32c(header)) + data
            + struct.pack("<I", masked_crc32c(data)))


# -------------------------------------------------------------------------------- protobuf
def _varint(value: int) -> bytes:
    value &= (1 << 64) - 1  # int64 as protobuf stores it: two's complement, 10 bytes if < 0
    out = bytearray()
    while True:
        bits, value = value & 0x7F, value >> 7
        out.append(bits | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _key(number: int, wire: int) -> bytes:
    return _varint(number << 3 | wire)


def _message(number: int, payload: bytes) -> bytes:
    return _key(number, 2) + _varint(len(payload)) + payload


def _float32(value: float) -> bytes:
    if math.isfinite(value) and abs(value) > 3.4028234663852886e38:
        value = math.copysign(math.inf, value)  # beyond float32: TensorBoard shows inf
    return struct.pack("<f", value)


def encode_event(step: int, wall_time: float, *, file_version: str | None = None,
                 scalars: dict[str, float] | None = None, session_status: int | None = None
                 ) -> bytes:
    """An ``Event`` (module docstring) with one of: ``file_version``, a Summary of
    ``scalars`` (tag -> simple_value) or a SessionLog of ``session_status``."""
    out = _key(1, 1) + struct.pack("<d", float(wall_time)) + _key(2, 0) + _varint(int(step))
    if file_version is not None:
        out += _message(3, file_version.encode("utf-8"))
    if scalars:
        values = b"".join(
            _message(1, _message(1, str(tag).encode("utf-8")) + _key(2, 5)
                     + _float32(float(value)))
            for tag, value in scalars.items())
        out += _message(5, values)
    if session_status is not None:
        out += _message(7, _key(1, 0) + _varint(session_status))
    return out


def _fields(data: bytes):
    """``(number, wire type, value)`` of each field of a protobuf message."""
    pos = 0

    def varint():
        nonlocal pos
        value = shift = 0
        while True:
            if pos >= len(data):
                raise JaxdenError("a protobuf varint runs past the end of its message")
            byte = data[pos]
            pos += 1
            value |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                return value

    while pos < len(data):
        key = varint()
        number, wire = key >> 3, key & 7
        if wire == 0:
            value = varint()
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            value, pos = data[pos:pos + size], pos + size
        elif wire == 2:
            size = varint()
            value, pos = data[pos:pos + size], pos + size
        else:
            raise JaxdenError(f"protobuf wire type {wire} (field {number}) is not supported")
        if pos > len(data):
            raise JaxdenError(f"protobuf field {number} runs past the end of its message")
        yield number, wire, value


def decode_event(data: bytes) -> dict[str, Any]:
    """An ``Event`` as ``{wall_time, step[, file_version][, scalars][, session_status]}``."""
    event: dict[str, Any] = {"wall_time": 0.0, "step": 0}
    for number, wire, value in _fields(data):
        if number == 1 and wire == 1:
            event["wall_time"] = struct.unpack("<d", value)[0]
        elif number == 2 and wire == 0:
            event["step"] = value - (1 << 64) if value >= 1 << 63 else value
        elif number == 3 and wire == 2:
            event["file_version"] = value.decode("utf-8")
        elif number == 5 and wire == 2:
            scalars = event.setdefault("scalars", {})
            for v_number, _, v_value in _fields(value):
                if v_number != 1:
                    continue
                fields = {n: x for n, _, x in _fields(v_value)}
                if 2 in fields:
                    scalars[fields.get(1, b"").decode("utf-8")] = struct.unpack("<f", fields[2])[0]
        elif number == 7 and wire == 2:
            event["session_status"] = {n: x for n, _, x in _fields(value)}.get(1, 0)
    return event


# ------------------------------------------------------------------------------ the files
def read_records(path: str | os.PathLike) -> list[bytes]:
    """The data of every record of ``path``, checksums verified; a last record cut short (a
    run killed while writing it) is left out. JaxdenError naming the file and the byte offset
    for a checksum that does not match."""
    path = Path(path)
    data = path.read_bytes()
    records, pos = [], 0
    while len(data) - pos >= 12:
        header = data[pos:pos + 8]
        (length,) = struct.unpack("<Q", header)
        if struct.unpack("<I", data[pos + 8:pos + 12])[0] != masked_crc32c(header):
            raise JaxdenError(f"{path}: the record at byte {pos} has a bad length checksum")
        end = pos + 12 + length + 4
        if end > len(data):
            break
        payload = data[pos + 12:pos + 12 + length]
        if struct.unpack("<I", data[end - 4:end])[0] != masked_crc32c(payload):
            raise JaxdenError(f"{path}: the record at byte {pos} has a bad data checksum")
        records.append(payload)
        pos = end
    return records


def read_events(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Every event of an event file (:func:`decode_event` of each record)."""
    return [decode_event(record) for record in read_records(path)]


def event_files(folder: str | os.PathLike) -> list[Path]:
    """The event files in ``folder``, in name order (the order TensorBoard reads them)."""
    return sorted(Path(folder).glob(FILE_PREFIX + "*"))


class EventWriter:
    """Appends scalar events to a new event file in ``folder`` (module docstring).

    ``resume_step``: the step the run starts from; when the folder already holds event files,
    a SessionLog START at that step follows the file version. Raises OutputError naming the
    file when it cannot be written (a record is appended whole or not at all)."""

    def __init__(self, folder: str | os.PathLike, *, resume_step: int = 0):
        folder = Path(folder)
        restarted = bool(event_files(folder))
        self.path = self._create(folder)
        now = time.time()
        self._append(encode_event(0, now, file_version=FILE_VERSION))
        if restarted:
            self._append(encode_event(resume_step, now, session_status=SESSION_START))

    @staticmethod
    def _create(folder: Path) -> Path:
        host = "".join(c if c.isalnum() or c in "-_" else "_" for c in socket.gethostname())
        stem = f"{FILE_PREFIX}{int(time.time()):010d}.{host or 'host'}.{os.getpid()}"
        for number in range(1000):
            path = folder / f"{stem}.{number}"
            try:
                os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
                return path
            except FileExistsError:
                continue
            except OSError as problem:
                raise OutputError(f"cannot write {path}: {problem.strerror or problem}") from None
        raise OutputError(f"cannot create an event file in {folder}: {stem}.* are all taken")

    def _append(self, event: bytes) -> None:
        from jaxden.fileio import append_bytes

        append_bytes(self.path, record_bytes(event), create=False)

    def scalars(self, step: int, values: dict[str, float], wall_time: float | None = None
                ) -> None:
        """One event at ``step`` with a scalar per entry of ``values`` (none: nothing)."""
        if values:
            self._append(encode_event(step, time.time() if wall_time is None else wall_time,
                                      scalars=values))
