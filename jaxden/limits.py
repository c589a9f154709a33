"""One size guard for every image from any source: the memory a request implies is computed
first and refused with a clear error above a limit derived from the machine's memory, before
anything is allocated.

Sources: ``--size`` and ``render_frame(size=)``, a scene file's film (its XML width and
height, after ``$parameters``), an EXR's data window (read from the header before any pixel is
decoded), the closed-form mixer's Gaussian window. Each call names what it guards, so the
error says where the size came from.

The limit is half the machine's physical memory (``JAXDEN_MEMORY_LIMIT`` in bytes, or with a
K/M/G suffix, overrides it), and never more than the process may still map under its own
limits: ``RLIMIT_AS`` (``ulimit -v``) less the address space it maps already, ``RLIMIT_DATA``
(``ulimit -d``) less its data segment (:func:`address_space_room`). Per-pixel costs are
estimates of the peak working set (stated next to each constant); they err on the large side.
"""

from __future__ import annotations

import os

from jaxden.errors import JaxdenError

#: Rendering: the moment integrator's AOVs and film (~20 float32 channels), Mitsuba's sample
#: buffers and the Frame (16 channels) written from them.
RENDER_BYTES_PER_PIXEL = 256
#: Reading an EXR: the decoded channels plus the Frame stacked from them (float32 each).
EXR_BYTES_PER_CHANNEL_PIXEL = 8
ENV_LIMIT = "JAXDEN_MEMORY_LIMIT"


def physical_memory() -> int:
    """Bytes of physical memory (0 when unknown)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def parse_bytes(text: str, what: str = ENV_LIMIT) -> int:
    """A byte count such as ``8G``, ``512M`` or ``1000000`` (K/M/G: binary units)."""
    text = text.strip()
    scale = {"k": 1 << 10, "m": 1 << 20, "g": 1 << 30}.get(text[-1:].lower(), 1)
    digits = text[:-1] if scale > 1 else text
    try:
        value = int(float(digits) * scale)
    except ValueError:
        raise JaxdenError(f"{what}={text!r}: expected a byte count such as 8G") from None
    if value <= 0:
        raise JaxdenError(f"{what}={text!r}: expected a positive byte count such as 8G")
    return value


def _status_bytes(field: str) -> int:
    """A ``kB`` field of ``/proc/self/status`` (``VmSize``, ``VmData``) in bytes; 0 when the
    system has no such file."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as handle:
            for line in handle:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def address_space_room() -> tuple[int, str] | None:
    """``(bytes, which limit)``: what this process may still map under its soft
    ``RLIMIT_AS`` (less ``VmSize``, what it maps now) and ``RLIMIT_DATA`` (less ``VmData``),
    the smaller of the two; None when neither is set."""
    try:
        import resource
    except ImportError:  # not a POSIX system
        return None
    room = None
    for name, field, label in (("RLIMIT_AS", "VmSize", "address-space limit (ulimit -v)"),
                               ("RLIMIT_DATA", "VmData", "data-segment limit (ulimit -d)")):
        kind = getattr(resource, name, None)
        if kind is None:
            continue
        try:
            soft, _ = resource.getrlimit(kind)
        except (OSError, ValueError):
            continue
        if soft == resource.RLIM_INFINITY or soft < 0:
            continue
        left = max(int(soft) - _status_bytes(field), 0)
        if room is None or left < room[0]:
            room = (left, label)
    return room


def _limit_and_source() -> tuple[int, str]:
    """:func:`memory_limit` and the words that say where it comes from."""
    text = os.environ.get(ENV_LIMIT, "").strip()
    if text:
        limit, source = parse_bytes(text), f"set by {ENV_LIMIT}"
    else:
        memory = physical_memory()
        limit = memory // 2 if memory else 8 << 30
        source = f"half its memory; set {ENV_LIMIT} to change it"
    room = address_space_room()
    if room is not None and room[0] < limit:
        limit, source = room[0], (f"what this process's {room[1]} leaves beside the "
                                  f"{format_bytes(_status_bytes('VmSize'))} it maps already")
    return limit, source


def memory_limit() -> int:
    """The byte budget of one image request (see the module docstring)."""
    return _limit_and_source()[0]


def format_bytes(count: float) -> str:
    for unit, size in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if count >= size:
            return f"{count / size:.1f} {unit}"
    return f"{count:.0f} bytes"


def check_budget(needed: float, what: str, error=JaxdenError) -> None:
    """Raise ``error`` when ``needed`` bytes exceed :func:`memory_limit`; ``what`` names the
    request and where its size came from."""
    limit, source = _limit_and_source()
    if needed > limit:
        raise error(f"{what} would need about {format_bytes(needed)}, more than this machine "
                    f"allows for one image ({format_bytes(limit)}: {source})")


def check_render_size(width: int, height: int, what: str, error=JaxdenError) -> None:
    """Guard a render of ``width`` x ``height`` pixels (:data:`RENDER_BYTES_PER_PIXEL`)."""
    check_budget(float(width) * float(height) * RENDER_BYTES_PER_PIXEL,
                 f"{what}: a {width}x{height} render", error)


def check_exr_size(width: int, height: int, channels: int, what: str, error=JaxdenError) -> None:
    """Guard decoding an EXR data window of ``channels`` channels."""
    check_budget(float(width) * float(height) * max(channels, 1) * EXR_BYTES_PER_CHANNEL_PIXEL,
                 f"{what}: its {width}x{height} data window of {channels} channel(s)", error)
