"""8-bit sRGB PNG previews of linear HDR images (written with no imaging dependency), and
reading PNG pixels.

``preview(color, exposure)`` tone maps linear radiance for display (exposure scale, clip to
[0, 1], the sRGB transfer curve, round to 8 bits); ``write_png(path, rgb8)`` writes an
(H, W, 3) or (H, W) uint8 array as a PNG (filter 0 on every row, zlib level 6), atomically.
Previews are for looking at images, not for measuring them: metrics use the EXR values.

``read_png(path)`` returns the stored integers of an 8-bit grey, grey + alpha, RGB or RGBA
PNG (or a 16-bit grey one), for renderers that write a feature as PNG (Falcor's frame capture
writes its 8-bit outputs so); it decodes with Pillow (a dependency of matplotlib).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from jaxden.errors import FrameError
from jaxden.fileio import atomic_write_bytes

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def srgb_encode(linear) -> np.ndarray:
    """The sRGB transfer curve (IEC 61966-2-1) of values in [0, 1]; clips outside."""
    v = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def preview(color, exposure: float = 1.0) -> np.ndarray:
    """Linear HDR (H, W, 3) or (H, W) -> uint8 sRGB after scaling by ``exposure`` and clipping.

    NaN and infinities are refused (a preview must not hide them)."""
    color = np.asarray(color, dtype=np.float64)
    if color.ndim not in (2, 3) or (color.ndim == 3 and color.shape[-1] not in (1, 3)):
        raise FrameError(f"preview: expected (H, W) or (H, W, 1|3), got shape {color.shape}")
    if not np.all(np.isfinite(color)):
        raise FrameError("preview: the image has NaN or infinite values")
    return np.round(srgb_encode(color * exposure) * 255.0).astype(np.uint8)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


def encode_png(image) -> bytes:
    """PNG bytes of an (H, W) grey or (H, W, 3) RGB uint8 array."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise FrameError(f"encode_png: expected uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[-1] == 1:
        image = image[..., 0]
    if image.ndim == 2:
        colour_type = 0
    elif image.ndim == 3 and image.shape[-1] == 3:
        colour_type = 2
    else:
        raise FrameError(f"encode_png: expected (H, W) or (H, W, 3), got shape {image.shape}")
    h, w = image.shape[:2]
    if h == 0 or w == 0:
        raise FrameError(f"encode_png: empty image {image.shape}")
    rows = np.ascontiguousarray(image).reshape(h, -1)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()
    header = struct.pack(">IIBBBBB", w, h, 8, colour_type, 0, 0, 0)
    return (PNG_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(raw, 6))
            + _chunk(b"IEND", b""))


def write_png(path, image) -> Path:
    """Write :func:`encode_png` of ``image`` to ``path`` atomically; returns the path."""
    path = Path(path)
    atomic_write_bytes(path, encode_png(image))
    return path


#: PNG colour type -> channel names (greyscale, RGB, grey + alpha, RGBA).
PNG_CHANNELS = {0: ("Y",), 2: ("R", "G", "B"), 4: ("Y", "A"), 6: ("R", "G", "B", "A")}


def png_header(path) -> tuple[int, int, int, tuple[str, ...]]:
    """(width, height, bits per channel, channel names) from a PNG's IHDR chunk alone.
    Refuses (FrameError naming the file) a file that is no PNG, and colour types and depths
    :func:`read_png` does not read exactly: palette images, 16-bit colour or grey + alpha."""
    path = Path(path)
    if not path.is_file():
        raise FrameError(f"{path}: no such file")
    with open(path, "rb") as handle:
        head = handle.read(29)
    if len(head) < 29 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise FrameError(f"{path}: not a PNG file (bad signature or no IHDR chunk first)")
    width, height, depth, colour_type, _, _, _ = struct.unpack(">IIBBBBB", head[16:29])
    if colour_type not in PNG_CHANNELS or depth not in (8, 16) or (
            depth == 16 and colour_type != 0):
        raise FrameError(f"{path}: a PNG of colour type {colour_type} at {depth} bits; jaxden "
                         f"reads 8-bit grey, grey + alpha, RGB and RGBA, and 16-bit grey")
    return width, height, depth, PNG_CHANNELS[colour_type]


def read_png(path) -> tuple[np.ndarray, tuple[str, ...]]:
    """The stored integers of a PNG as an (H, W, C) uint8 (uint16 for 16-bit grey) array, and
    its channel names (:data:`PNG_CHANNELS`); what they mean (linear or sRGB) is the caller's
    to know. A truncated or corrupt file is a FrameError naming it."""
    from PIL import Image  # a dependency of matplotlib; imported here: keeps the writer light

    path = Path(path)
    width, height, depth, names = png_header(path)
    try:
        with Image.open(path) as image:
            image.load()
            pixels = np.array(image)
    except (OSError, ValueError, SyntaxError) as error:
        raise FrameError(f"{path}: PNG pixel data cannot be decoded (truncated or corrupt?): "
                         f"{str(error).splitlines()[0] if str(error) else type(error).__name__}"
                         ) from None
    pixels = pixels.reshape(height, width, -1)
    if pixels.shape[-1] != len(names):
        raise FrameError(f"{path}: decoded {pixels.shape[-1]} channels, the header says "
                         f"{len(names)}")
    return pixels.astype(np.uint16 if depth == 16 else np.uint8), names


__all__ = ["encode_png", "png_header", "preview", "read_png", "srgb_encode", "write_png"]
