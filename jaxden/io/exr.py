"""Read and write Frames and plain images as multi-channel OpenEXR files.

Channel names follow :data:`jaxden.frame.CHANNELS` (``R,G,B``, ``variance.R/G/B``,
``albedo.R/G/B``, ``normal.X/Y/Z``, ``depth.Z``, ``position.X/Y/Z``, ``motion.X/Y``), so any
EXR viewer shows ordinary named layers. Files of other renderers are read through their
conventions (:mod:`jaxden.io.conventions`: Cycles, pbrt-v4, Mitsuba), every part of a
multi-part file included. Header attributes ``jaxden.spp``, ``jaxden.seed``,
``jaxden.scene`` and ``jaxden.version`` record provenance; ``jaxden.variance_dof`` the degrees
of freedom of the variance estimate (``Frame.variance_dof``); ``jaxden.aux`` and
``jaxden.feature_spp`` how a render's features were made (the samples its feature pass
averaged; :func:`jaxden.render.core.feature_attributes`), which a trained denoiser compares
with its training data's (:mod:`jaxden.data.features`); a frame made from K buffers lists them
(:class:`jaxden.data.merge.BufferList`).

Writes are atomic: the file is written to a temporary name in the same folder and renamed, so
an interrupted job never leaves a half-written EXR under the final name. Reads never return
garbage: a missing, truncated or non-EXR file, a missing channel, or a channel of another size is
an :class:`~jaxden.errors.ExrError` naming the file and the problem.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.errors import ExrError, FrameError
from jaxden.fileio import atomic_write
from jaxden.frame import CHANNELS, IMAGE_FIELDS, Frame, NonFinitePolicy
from jaxden.io.conventions import WRITTEN_BY_JAXDEN, header_number
from jaxden.io.reading_checks import (
    adaptive_sampling,
    check_denoised,
    depth_misses,
    missing_message,
    read_albedo,
)
from jaxden.limits import check_exr_size

ATTRIBUTE_PREFIX = "jaxden."
#: Key that :func:`read_channels` sets in the header of a file with jaxden's attributes.
#: Channels written in float32 even by ``write_frame(half=True)``.
PRECISE_CHANNELS = frozenset(CHANNELS["variance"] + CHANNELS["covariance"] + CHANNELS["boxcox"])
_FIELDS_BY_CHANNEL_COUNT = {"color": 3, "variance": 3}


def _openexr():
    import OpenEXR  # imported lazily: keeps `import jaxden` light

    return OpenEXR


def _atomic_write(path: Path, write) -> None:
    """Call ``write(tmp_path)`` then rename onto ``path``; never leave the temp file behind."""
    path = Path(path)
    if not path.parent.exists():
        raise ExrError(f"{path}: the folder {path.parent} does not exist")
    atomic_write(path, write, suffix=".exr")


def write_channels(
    path: str | os.PathLike,
    channels: Mapping[str, np.ndarray],
    *,
    half: bool | Iterable[str] = False,
    attributes: Mapping[str, Any] | None = None,
    allow_nonfinite: bool = False,
) -> None:
    """Write named 2-D channels (all H x W) to ``path`` atomically, ZIP-compressed.

    ``half``: True stores every channel as float16, or give the channel names to store as half.
    ``attributes``: extra header attributes (str, int, float), written with the ``jaxden.``
    prefix unless the name already contains a dot. Non-finite values are refused (ExrError):
    jaxden never writes a NaN or inf image (``allow_nonfinite``: write them anyway, e.g. to
    make test files that imitate other renderers' output).
    """
    OpenEXR = _openexr()
    path = Path(path)
    if not channels:
        raise ExrError(f"{path}: nothing to write (no channels)")
    half_names = set(channels) if half is True else set(half or ())
    shape = None
    pixels: dict[str, np.ndarray] = {}
    for name, array in channels.items():
        array = np.asarray(array)
        if array.ndim != 2:
            raise ExrError(f"{path}: channel '{name}' must be 2-D (H, W), got shape {array.shape}")
        if shape is None:
            shape = array.shape
        elif array.shape != shape:
            raise ExrError(f"{path}: channel '{name}' has shape {array.shape}, others {shape}")
        finite = np.isfinite(array)
        if not allow_nonfinite and not finite.all():
            bad = int(array.size - np.count_nonzero(finite))
            raise ExrError(
                f"{path}: refusing to write channel '{name}' with {bad} non-finite value(s) "
                f"(NaN or inf) of {array.size}: the result is broken (check the inputs and the "
                f"weights that made it)")
        dtype = np.float16 if name in half_names else np.float32
        # A copy: OpenEXR.File replaces the values of the dict it is given (PLATFORM-NOTES).
        with np.errstate(over="ignore"):
            pixels[name] = np.ascontiguousarray(array, dtype=dtype).copy()
        overflow = np.isinf(pixels[name]) & np.isfinite(array)
        if overflow.any():
            peak = float(np.abs(np.asarray(array, np.float64)[overflow]).max())
            raise ExrError(
                f"{path}: channel '{name}' has {int(overflow.sum())} value(s) beyond the "
                f"{'float16' if dtype == np.float16 else 'float32'} range (largest {peak:.4g}; "
                f"float16 stops at 65504): store it as float32 (no --half / half = false)"
            )
    header: dict[str, Any] = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
    }
    for key, value in (attributes or {}).items():
        if value is None:
            continue
        name = key if "." in key else ATTRIBUTE_PREFIX + key
        if isinstance(value, (bool, np.bool_)) or isinstance(value, (np.integer,)):
            value = int(value)
        elif isinstance(value, (np.floating,)):
            value = float(value)
        elif not isinstance(value, (int, float, str)):
            value = str(value)
        header[name] = value

    def write(tmp: str) -> None:
        OpenEXR.File(header, pixels).write(tmp)

    _atomic_write(path, write)


@contextlib.contextmanager
def _native_output_held(native: dict[str, str] | None = None):
    """Hold what libOpenEXR and its binding print themselves while a file is decoded (on the
    stdout / stderr file descriptors, or through Python's sys.stdout). On success it is passed
    on to stderr; on failure it is dropped, kept in ``native["text"]`` for the caller's
    one-line ExrError. Only in the main thread (other threads decode without holding)."""
    import io
    import threading

    native = {} if native is None else native
    if threading.current_thread() is not threading.main_thread():
        yield native  # the descriptors are process-wide: only the main thread redirects them
        return
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    python_held = io.StringIO()
    with tempfile.TemporaryFile() as held:
        saved = [os.dup(1), os.dup(2)]
        streams = sys.stdout, sys.stderr
        failed = True
        try:
            os.dup2(held.fileno(), 1)
            os.dup2(held.fileno(), 2)
            sys.stdout = sys.stderr = python_held
            yield native
            failed = False
        finally:
            sys.stdout, sys.stderr = streams
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            held.seek(0)
            text = held.read().decode(errors="replace") + python_held.getvalue()
            native["text"] = text
            if not failed and text:
                sys.stderr.write(text)


def _decode_error(error: Exception, native: str = "") -> str:
    """libOpenEXR's own reason (its "(EXR_ERR_...)" line) when it printed or raised one, else
    the first line of the binding's message."""
    for text in (str(error), native):
        if "(EXR_ERR" in text:
            return text[text.index("(EXR_ERR"):].splitlines()[0]
    text = str(error)
    return text.splitlines()[0] if text else type(error).__name__


def _open(path: Path, header_only: bool = False):
    OpenEXR = _openexr()
    if path.is_symlink():
        try:
            path.resolve(strict=True)
        except (RuntimeError, OSError) as error:  # Python 3.11 raises RuntimeError on a loop
            loop = isinstance(error, RuntimeError) or getattr(error, "errno", None) == 40
            raise ExrError(f"{path}: " + ("a symbolic link that loops back on itself" if loop
                                          else "a symbolic link to nothing")) from None
    if not path.exists():
        raise ExrError(f"{path}: no such file")
    if path.is_dir():
        raise ExrError(f"{path}: is a folder, not an EXR file")
    if not path.is_file():  # a FIFO or a device would block or stream forever
        raise ExrError(f"{path}: is not a regular file (a pipe, socket or device?)")
    with open(path, "rb") as handle:
        magic = handle.read(4)
    if magic != b"\x76\x2f\x31\x01":
        raise ExrError(f"{path}: not an OpenEXR file (bad magic number)")
    try:
        with _native_output_held():
            return OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
    except Exception as error:  # the binding raises RuntimeError for every decode failure
        raise ExrError(f"{path}: cannot be read as EXR (truncated or corrupt?): "
                       f"{_decode_error(error)}") from None


def _plain_header(raw: Mapping[str, Any]) -> dict[str, Any]:
    header: dict[str, Any] = {}
    for key, value in raw.items():
        if key.startswith(ATTRIBUTE_PREFIX):
            header[key[len(ATTRIBUTE_PREFIX) :]] = value
        elif isinstance(value, (int, float, str)):
            header[key] = value
    return header


def read_header(path: str | os.PathLike) -> dict[str, Any]:
    """Header attributes: jaxden ones without their prefix (``spp``, ``seed``, ...), plus other
    plain (str/int/float) attributes, and ``channels`` (list of names) and ``size`` (W, H)."""
    path = Path(path)
    exr = _open(path, header_only=True)
    raw = exr.header()
    header = _plain_header(raw)
    names = []
    for index, part in enumerate(exr.parts):
        part_header = part.header
        names += [_part_channel_name(index, part_header, c.name) for c in part_header["channels"]]
        for key, value in _plain_header(part_header).items():
            header.setdefault(key, value)
    header["channels"] = sorted(names)
    lo, hi = raw["dataWindow"]
    header["size"] = (int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1))
    header["parts"] = len(exr.parts)
    return header


def _part_channel_name(index: int, header: Mapping[str, Any], name: str) -> str:
    """A channel's name in the flat namespace of every part of a file: the first part's names
    as they are; a later part's names prefixed with the part's name unless they already carry
    it (Blender writes ``ViewLayer.Combined.R`` inside the part ``ViewLayer.Combined``)."""
    part = header.get("name")
    if index == 0 or not part or name.startswith(f"{part}."):
        return name
    return f"{part}.{name}"


def _window(header: Mapping[str, Any]) -> tuple[int, int, int, int]:
    (x0, y0), (x1, y1) = header["dataWindow"]
    return int(x0), int(y0), int(x1), int(y1)


def read_channels(
    path: str | os.PathLike, names: Iterable[str] | None = None
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read channels (all, or ``names``) of every part of the file as float32 (H, W) arrays, and
    the header (a later part's channel names carry the part's name, as Blender writes them).

    Raises ExrError naming the missing channels and listing those present.
    """
    path = Path(path)
    native: dict[str, str] = {}
    parts = [part.header for part in _open(path, header_only=True).parts]
    x0, y0, x1, y1 = _window(parts[0])
    for index, part in enumerate(parts[1:], 1):
        if _window(part) != (x0, y0, x1, y1):
            raise ExrError(
                f"{path}: part {index} ({part.get('name', 'unnamed')!r}) has the data window "
                f"{_window(part)}, the first part {(x0, y0, x1, y1)}: jaxden reads multi-part "
                f"files whose parts cover the same pixels")
    check_exr_size(x1 - x0 + 1, y1 - y0 + 1, sum(len(p["channels"]) for p in parts), str(path),
                   ExrError)
    try:
        with _native_output_held(native):  # the pixels are decoded here, noise and all
            exr = _open(path)
            available = {}
            for index, part in enumerate(exr.parts):
                for name, channel in part.channels.items():
                    full = _part_channel_name(index, part.header, name)
                    if full in available:
                        raise ExrError(f"{path}: channel {full!r} appears in two parts")
                    available[full] = channel.pixels
            expected = {_part_channel_name(index, part, c.name)
                        for index, part in enumerate(parts) for c in part["channels"]}
            if not expected <= {name for name, pixels in available.items()
                                if pixels is not None}:
                # the binding drops a part whose pixels fail to decode (and only prints why)
                raise RuntimeError("a part's pixels did not decode")
    except ExrError:
        raise
    except Exception as error:
        raise ExrError(f"{path}: pixel data cannot be decoded (truncated or corrupt?): "
                       f"{_decode_error(error, native.get('text', ''))}") from None
    wanted = list(available) if names is None else list(names)
    missing = [n for n in wanted if n not in available]
    if missing:
        from jaxden.io.conventions import case_hints

        raise ExrError(
            f"{path}: missing channel(s) {', '.join(missing)}{case_hints(missing, available)}; "
            f"the file has {', '.join(sorted(available))}"
        )
    out = {}
    for name in wanted:
        array = available[name]
        if array is None or array.ndim != 2:
            raise ExrError(f"{path}: channel '{name}' is not a full-resolution 2-D channel")
        out[name] = np.asarray(array, dtype=np.float32)
    header = {}
    for part in exr.parts:  # the first part's attributes win
        for key, value in _plain_header(part.header).items():
            header.setdefault(key, value)
        if f"{ATTRIBUTE_PREFIX}version" in part.header:  # write_frame and write_image
            header[WRITTEN_BY_JAXDEN] = True
    return out, header


def write_frame(
    path: str | os.PathLike,
    frame: Frame,
    *,
    half: bool | Iterable[str] = False,
    attributes: Mapping[str, Any] | None = None,
) -> None:
    """Write one (unbatched) Frame to ``path`` atomically.

    ``attributes`` may carry ``seed``, ``scene``, the features' ``aux`` and ``feature_spp``
    (:func:`jaxden.render.core.feature_attributes`) and anything else worth recording; ``spp``
    and ``version`` are filled in from the frame and the package.
    """
    from jaxden import __version__

    path = Path(path)
    frame = frame.numpy()
    if frame.color is None or np.ndim(frame.color) != 3:
        raise FrameError(
            f"{path}: write_frame takes one frame of shape (H, W, 3), got colour shape "
            f"{None if frame.color is None else np.shape(frame.color)}"
        )
    frame.validated(where=str(path))  # never write a file that would fail to read back
    channels: dict[str, np.ndarray] = {}
    for field in frame.features():
        array = getattr(frame, field)
        for index, channel in enumerate(CHANNELS[field]):
            channels[channel] = array[..., index]
    if half is True:  # the variance and covariance stay float32: in half, small variances
        # round to 0 while their covariance does not, and SURE needs them to 3 digits
        half_names: bool | list[str] = [c for c in channels if c not in PRECISE_CHANNELS]
    elif half:
        half_fields = set(half)
        half_names = [c for f in half_fields if f in CHANNELS for c in CHANNELS[f]]
        half_names += [c for c in half_fields if c not in CHANNELS]
    else:
        half_names = False
    attrs = {"version": __version__}
    for name in ("spp", "variance_dof"):
        count = getattr(frame, name)
        if count is not None:
            count = float(np.asarray(count))
            attrs[name] = int(count) if count.is_integer() else count
    attrs.update(attributes or {})
    write_channels(path, channels, half=half_names, attributes=attrs)


def read_frame(
    path: str | os.PathLike,
    *,
    require: Iterable[str] = ("color",),
    nonfinite: NonFinitePolicy = "error",
    channel_map: Mapping[str, Iterable[str]] | None = None,
    variance_is_sample_variance: bool = False,
    spp: float | None = None,
    convention: str | None = None,
    layer: str | None = None,
    spp_override: bool = False,
    keep: Iterable[str] | None = None,
    refuse_denoised: bool = False,
    on_note: Callable[[str], None] | None = None,
) -> Frame:
    """Read a Frame from an EXR, checking it.

    ``require``: fields that must be present (e.g. ``("color", "variance")`` for SURE); a
    missing one is an ExrError naming the field, the channels expected and those found.
    ``nonfinite``: see :meth:`Frame.validated` ('error' or 'zero').
    ``channel_map``: override channel names per field for files from other renderers, e.g.
    ``{"variance": ("color_var.R", "color_var.G", "color_var.B")}``.
    ``variance_is_sample_variance``: the file stores the per-sample variance (and covariance),
    not that of the pixel mean; it is divided by spp (from ``spp`` or the header) on reading.
    ``spp``: supplies the sample count when the header has none; one that contradicts the
    header is an ExrError unless ``spp_override``.
    ``convention``: the renderer whose channel names the file follows (``cycles``,
    ``pbrt-v4``, ``mitsuba``, ``falcor``, ``jaxden``; :data:`jaxden.io.conventions.CONVENTIONS`):
    the fields, the variance's meaning and the header's sample count come from it; ``layer``
    picks the render layer of a layered (Cycles) file that holds several. ``channel_map`` wins.
    A renderer that writes one file per output (``falcor``) reads ``path`` with its sibling
    files (:mod:`jaxden.io.siblings`). A denoised render (Cycles with Denoise on) gives its raw
    colour (``Noisy Image``), not the denoised one. A render whose sample-count pass (Cycles'
    ``Debug Sample Count``) shows adaptive sampling gets no ``spp``: the header's count is not
    every pixel's (a ``spp`` given for it is an ExrError unless ``spp_override``).
    ``keep``: the fields to return (besides ``require``; None: every field the file has):
    what a command does not use is never stacked (memory at 8K).
    ``refuse_denoised``: the colour is to be merged into a variance (``jaxden merge``, ``jaxden
    dataset import``): a denoised one (a renderer's denoised pass named by ``channel_map``, or
    an image ``jaxden denoise`` / ``progressive`` wrote) is an ExrError saying what to read
    or change instead.
    ``on_note``: called with one line (without the path) for what the reading decided that a
    user may want to know: the colour taken from a denoised render's raw pass, the sample
    count dropped for adaptive sampling.
    The albedo is a reflectance in [0, 1]: a convention's albedo that holds light (Cycles'
    Denoising Albedo: the emission of the lamps it sees) is read clipped to [0, 1]; an albedo
    above 1 otherwise is kept and warned about (one stderr line; :func:`_albedo`).
    """
    path = Path(path)
    if convention is None:
        all_channels, header = read_channels(path)
    else:  # a convention may spread a frame over one file per output (Falcor)
        from jaxden.io.siblings import read_outputs

        all_channels, header = read_outputs(path, convention, channel_map, read_channels,
                                            read_header)
    present = set(all_channels)
    mapping = {field: tuple(names) for field, names in CHANNELS.items()}
    reading = None
    if convention is not None:
        from jaxden.io.conventions import resolve

        reading = resolve(convention, present, header, layer=layer, where=str(path))
        mapping, header_spp, kind = dict(reading.mapping), reading.spp, reading.variance
        if kind == "mean" and variance_is_sample_variance:
            raise ExrError(f"{path}: a {convention} file stores the variance of the pixel mean; "
                           f"it is not a per-sample variance (drop --sample-variance)")
        variance_is_sample_variance = variance_is_sample_variance or kind == "sample"
        header = {**header, "spp": header_spp}
        if header_spp is None:
            header.pop("spp")
    elif layer is not None:
        raise ExrError(f"{path}: layer= applies to a layered file's convention (--from cycles)")
    elif variance_is_sample_variance and header.get(WRITTEN_BY_JAXDEN):
        raise ExrError(f"{path}: jaxden wrote this file, and its variance channels hold the "
                       f"variance of the pixel mean already (drop --sample-variance)")
    for field, names in (channel_map or {}).items():
        if field not in CHANNELS:
            raise ExrError(f"channel_map: unknown field '{field}'; fields are {', '.join(CHANNELS)}")
        names = tuple(names)
        if len(names) != len(CHANNELS[field]):
            raise ExrError(
                f"channel_map['{field}'] must name {len(CHANNELS[field])} channels, got {names}"
            )
        mapping[field] = names
    required = list(require)
    for field in required:
        if field not in CHANNELS:
            raise ExrError(f"require: unknown field '{field}'; fields are {', '.join(CHANNELS)}")
    if "color" not in required:
        required.insert(0, "color")
    missing_fields = [f for f in required if f not in mapping or not set(mapping[f]) <= present]
    if missing_fields:
        raise ExrError(missing_message(path, missing_fields, mapping, present, convention,
                                        None if reading is None else reading.layer))
    check_denoised(path, header, mapping, reading, convention, refuse_denoised, on_note)
    if reading is not None and reading.sample_fraction is not None:
        header = adaptive_sampling(path, header, all_channels[reading.sample_fraction],
                                    convention, spp, spp_override, on_note)
    fields: dict[str, Any] = {}
    wanted = [f for f in IMAGE_FIELDS if f in mapping and (keep is None or f in keep
                                                             or f in required)]
    if "albedo" in wanted and set(mapping["albedo"]) <= present:
        fields["albedo"] = read_albedo(path, all_channels, mapping, convention,
                                   None if reading is None else reading.layer)
    # Channels no returned field reads go at once, and each field's channels as it is
    # stacked: the peak is the decoded file plus one field, not twice the file (7680 x 4320
    # x 22 channels: 2.9 GB).
    for name in set(all_channels) - {c for f in wanted for c in mapping[f]}:
        del all_channels[name]
    for field in IMAGE_FIELDS:
        if field not in mapping:
            continue
        names = mapping[field]
        if set(names) <= present:
            if field not in wanted:
                continue
            if field not in fields:
                fields[field] = np.stack([all_channels[c] for c in names], axis=-1)
            if field == "depth" and convention is not None:
                fields[field] = depth_misses(fields[field], names, convention,
                                              reading.layer)
            later = {c for f in wanted[wanted.index(field) + 1:] for c in mapping[f]}
            for name in names:
                if name not in later:
                    all_channels.pop(name, None)
        elif any(c in present for c in names):
            have = [c for c in names if c in present]
            raise ExrError(
                f"{path}: feature '{field}' is incomplete: has {', '.join(have)} but not "
                f"{', '.join(c for c in names if c not in present)}"
            )
    header_spp = header.get("spp")
    sample_count = spp if spp is not None else header_spp
    if sample_count is not None:
        sample_count = header_number(sample_count, f"{path}: header attribute spp")
        if not (np.isfinite(sample_count) and sample_count > 0):
            source = "spp=" if spp is not None else "header attribute jaxden.spp"
            raise ExrError(f"{path}: {source} must be a positive sample count, got "
                           f"{sample_count:g}")
    if spp is not None and header_spp is not None and not spp_override:
        try:
            agrees = bool(np.isclose(float(header_spp), float(spp), rtol=1e-6))
        except (TypeError, ValueError):
            agrees = False
        if not agrees:
            raise ExrError(f"{path}: its header says {header_spp} spp and --spp says {spp:g}; "
                           f"drop --spp, or pass --override-spp if the header is wrong")
    variance_dof = header.get("variance_dof")
    if variance_dof is not None:
        variance_dof = header_number(variance_dof, f"{path}: header attribute jaxden.variance_dof")
        if not (np.isfinite(variance_dof) and variance_dof > 0):
            raise ExrError(f"{path}: header attribute jaxden.variance_dof (the variance's "
                           f"degrees of freedom) must be > 0, got {variance_dof:g}")
        variance_dof = np.float32(variance_dof)
    if variance_is_sample_variance and "variance" in fields:
        if sample_count is None:
            raise ExrError(
                f"{path}: variance_is_sample_variance needs the sample count: the header has no "
                f"jaxden.spp; pass spp= (CLI: --spp N)"
            )
        fields["variance"] = fields["variance"] / np.float32(sample_count)
        if "covariance" in fields:  # stored alike: per sample
            fields["covariance"] = fields["covariance"] / np.float32(sample_count)
    frame = Frame(
        **fields, spp=None if sample_count is None else np.float32(sample_count),
        variance_dof=variance_dof,
    )
    try:
        return frame.validated(where=str(path), nonfinite=nonfinite)
    except FrameError as error:
        raise ExrError(str(error)) from None


def write_image(
    path: str | os.PathLike,
    image: np.ndarray,
    *,
    channels: tuple[str, ...] | None = None,
    half: bool = False,
    attributes: Mapping[str, Any] | None = None,
) -> None:
    """Write an (H, W, C) or (H, W) image. Default channel names: R,G,B for 3 channels, Y for 1,
    otherwise C0..C{n-1}."""
    array = np.asarray(image, dtype=np.float32)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3:
        raise ExrError(f"{path}: write_image takes (H, W) or (H, W, C), got shape {array.shape}")
    count = array.shape[-1]
    if channels is None:
        channels = {3: ("R", "G", "B"), 1: ("Y",)}.get(count, tuple(f"C{i}" for i in range(count)))
    if len(channels) != count:
        raise ExrError(f"{path}: {count} channels in the image but {len(channels)} names given")
    from jaxden import __version__

    write_channels(
        path,
        {name: array[..., i] for i, name in enumerate(channels)},
        half=half,
        attributes={"version": __version__, **(attributes or {})},
    )


def read_image(path: str | os.PathLike, channels: tuple[str, ...] | None = None) -> np.ndarray:
    """Read an (H, W, C) float32 image; default channels R,G,B (or the file's only channel)."""
    path = Path(path)
    if channels is None:
        available = read_header(path)["channels"]
        if {"R", "G", "B"} <= set(available):
            channels = ("R", "G", "B")
        elif len(available) == 1:
            channels = tuple(available)
        else:
            raise ExrError(
                f"{path}: has no R,G,B channels; name the channels to read (the file has "
                f"{', '.join(available)})"
            )
    data, _ = read_channels(path, channels)
    return np.stack([data[c] for c in channels], axis=-1)
