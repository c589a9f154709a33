"""8-bit sRGB PNG previews of linear HDR images, with no imaging dependency.

``preview(color, exposure)`` tone maps linear radiance for display (exposure scale, clip to
[0, 1], the sRGB transfer curve, round to 8 bits); ``write_png(path, rgb8)`` writes an
(H, W, 3) or (H, W) uint8 array as a PNG (filter 0 on every row, zlib level 6), atomically.
Previews are for looking at images, not for measuring them: metrics use the EXR values.
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


__all__ = ["encode_png", "preview", "srgb_encode", "write_png"]
