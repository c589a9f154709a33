"""A frame whose fields come from several files: one image per render-graph output, the way
Falcor's frame capture (Mogwai) writes them.

A convention with a ``file_pattern`` (:class:`jaxden.io.conventions.Convention`) names its
files ``<prefix>.<output>.<frame>[.<mask>].<ext>``; for Falcor ``<output>`` is
``<pass>.<output>`` as the render graph names it, e.g.

    Mogwai.AccumulatePass.output.256.exr     colour, accumulated over frames
    Mogwai.PathTracer.albedo.256.png         8-bit outputs are written as PNG
    Mogwai.PathTracer.guideNormal.256.exr
    Mogwai.GBufferRT.linearZ.256.exr

The file given is any one of them; its siblings are the files of the same folder with the
same prefix and frame number. Their channels form one namespace, ``<output>.<channel>``
(``AccumulatePass.output.R``), which the convention's fields and ``--channels`` name. A file
captured with a channel mask (``....256.R.exr``: the one channel of the output, stored in
R) gives ``<output>.<mask>``; ``RGBA`` gives R, G, B and A. PNG values are read as the stored
integers over their maximum (Falcor's 8-bit outputs hold linear values, not sRGB).

Before any pixel is decoded the reader refuses, in one line naming the files: a name the
pattern does not match, no colour output beside the file, a field whose outputs were captured
at another frame only, two files giving one output (``.exr`` and ``.png``, or a plain and a
masked capture), and a file of another size than the colour's. Files no field reads are not
decoded (memory at 8K); their channels are still listed, so ``--channels`` can name them.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterator, Mapping, MutableMapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.errors import ExrError, JaxdenError

ReadChannels = Callable[[Path], tuple[dict[str, np.ndarray], dict[str, Any]]]
ReadHeader = Callable[[Path], dict[str, Any]]


class OutputFiles(MutableMapping):
    """Channel name -> (H, W) float32 array over several files, each decoded when one of its
    channels is first read and dropped when none of its channels is left (a dict to
    :func:`jaxden.io.exr.read_frame`)."""

    def __init__(self, sources: Mapping[str, tuple[Path, str]], read_file):
        self._sources = dict(sources)  # channel -> (file, the channel's name in the file)
        self._read_file = read_file
        self._decoded: dict[Path, dict[str, np.ndarray]] = {}

    def __getitem__(self, name: str) -> np.ndarray:
        path, stored = self._sources[name]
        if path not in self._decoded:
            self._decoded[path] = self._read_file(path)
        return self._decoded[path][stored]

    def __delitem__(self, name: str) -> None:
        path, _ = self._sources.pop(name)
        if all(other != path for other, _ in self._sources.values()):
            self._decoded.pop(path, None)

    def __setitem__(self, name: str, value) -> None:
        raise TypeError("the channels of a capture are read from its files")

    def __contains__(self, name) -> bool:  # without decoding (Mapping's would read the file)
        return name in self._sources

    def __iter__(self) -> Iterator[str]:
        return iter(self._sources)

    def __len__(self) -> int:
        return len(self._sources)

    def files(self) -> list[Path]:
        """The files the remaining channels come from."""
        return sorted({path for path, _ in self._sources.values()})


def _png_channels(path: Path) -> dict[str, np.ndarray]:
    from jaxden.io.png import read_png

    try:
        pixels, names = read_png(path)
    except JaxdenError as error:
        raise ExrError(str(error)) from None
    scale = np.float32(1.0 / np.iinfo(pixels.dtype).max)
    return {name: pixels[..., i].astype(np.float32) * scale for i, name in enumerate(names)}


def _png_header(path: Path) -> dict[str, Any]:
    from jaxden.io.png import png_header

    try:
        width, height, _, names = png_header(path)
    except JaxdenError as error:
        raise ExrError(str(error)) from None
    return {"channels": list(names), "size": (width, height)}


def _names(paths: Sequence[Path]) -> str:
    return ", ".join(p.name for p in paths)


def read_outputs(path, convention: str | None, channel_map: Mapping | None,
                 read_channels: ReadChannels, read_header: ReadHeader):
    """The channels (a dict, or :class:`OutputFiles` for a per-output convention) and header
    of the frame ``path`` belongs to: ``read_channels(path)`` for a convention whose files
    each hold a frame (or none), else the sibling files of ``path``, checked as the module
    docstring says. ``read_channels`` and ``read_header`` read one EXR
    (:mod:`jaxden.io.exr`)."""
    from jaxden.io.conventions import CONVENTIONS

    path = Path(path)
    rule = CONVENTIONS.get(convention) if convention is not None else None
    if rule is None or rule.file_pattern is None:
        return read_channels(path)
    pattern = re.compile(rule.file_pattern, re.IGNORECASE)
    match = pattern.match(path.name)
    if match is None:
        raise ExrError(f"{path}: not named as {rule.name} names its files "
                       f"(<prefix>.<pass>.<output>.<frame>.exr, e.g. {rule.file_example}); "
                       f"rename it, or read it without convention={rule.name!r}")
    if not path.is_file():
        raise ExrError(f"{path}: no such file")
    prefix, frame = match["prefix"], match["frame"]
    folder = path.parent
    capture: list[tuple[Path, re.Match]] = []  # this prefix and frame
    elsewhere: dict[str, list[Path]] = {}  # output -> files of this prefix at other frames
    for name in sorted(os.listdir(folder)):
        found = pattern.match(name)
        if found is None or found["prefix"] != prefix:
            continue
        if found["frame"] == frame:
            capture.append((folder / name, found))
        else:
            elsewhere.setdefault(found["output"], []).append(folder / name)

    # Every channel of the capture, and every file that claims it.
    claims: dict[str, list[tuple[Path, str]]] = {}
    headers: dict[Path, dict[str, Any]] = {}
    for file, found in capture:
        png = found["ext"].lower() == "png"
        headers[file] = header = _png_header(file) if png else read_header(file)
        mask = found["mask"]
        if mask is None or mask.upper() == "RGBA":
            stored = {f"{found['output']}.{c}": c for c in header["channels"]}
        else:  # a one-channel capture: the output's channel `mask`, stored first (R, or Y)
            first = "R" if "R" in header["channels"] else min(header["channels"])
            stored = {f"{found['output']}.{mask.upper()}": first}
        for channel, name in stored.items():
            claims.setdefault(channel, []).append((file, name))

    def output_of(channel: str) -> str:
        return channel.rsplit(".", 1)[0]

    fields = {field: list(candidates) for field, candidates in rule.fields.items()}
    for field, names in (channel_map or {}).items():
        fields[field] = [tuple(names)]
    wanted = {output_of(c) for candidates in fields.values() for names in candidates
              for c in names}
    for channel, files in claims.items():
        if len(files) > 1 and output_of(channel) in wanted:
            paths = sorted({f for f, _ in files})
            raise ExrError(f"{path}: {len(paths)} files give the output {output_of(channel)} "
                           f"of frame {frame} ({_names(paths)}); keep one of them")
    sources = {c: files[0] for c, files in claims.items() if len(files) == 1}

    def present(names) -> bool:
        return all(c in sources for c in names)

    colour = next((names for names in fields["color"] if present(names)), None)
    if colour is None:
        looked = [f"{prefix}.{output_of(names[0])}.{frame}.exr" for names in fields["color"]]
        other = sorted({f for names in fields["color"]
                        for f in elsewhere.get(output_of(names[0]), [])})
        raise ExrError(f"{path}: no colour output of frame {frame} beside it: looked for "
                       f"{' or '.join(looked)}"
                       + (f"; found it at other frames only ({_names(other)})" if other else "")
                       + f"; the capture has {_names([f for f, _ in capture])}")
    colour_file = sources[colour[0]][0]
    for field, candidates in fields.items():
        if field == "color" or any(present(names) for names in candidates):
            continue
        other = sorted({f for names in candidates
                        for f in elsewhere.get(output_of(names[0]), [])})
        if other:
            raise ExrError(f"{path}: the {field} of frame {frame} is missing, but captured at "
                           f"another frame ({_names(other)}): the files of one frame are one "
                           f"capture; capture every output in the same frame")
    size = headers[colour_file]["size"]
    chosen = [next((names for names in candidates if present(names)), ())
              for candidates in fields.values()]
    used = {output_of(c) for names in chosen for c in names}
    for channel, (file, _) in list(sources.items()):
        if tuple(headers[file]["size"]) == tuple(size):
            continue
        if output_of(channel) in used:
            width, height = headers[file]["size"]
            raise ExrError(f"{path}: {file.name} is {width}x{height} pixels, the colour "
                           f"{colour_file.name} {size[0]}x{size[1]}: the outputs of one frame "
                           f"have one size")
        del sources[channel]  # an output of another size that nothing reads

    def read_file(file: Path) -> dict[str, np.ndarray]:
        if file.suffix.lower() == ".png":
            return _png_channels(file)
        channels, _ = read_channels(file)
        return channels

    header = {k: v for k, v in headers[colour_file].items()
              if k not in ("channels", "size", "parts")}
    return OutputFiles(sources, read_file), header  # misses in depth: read_frame
