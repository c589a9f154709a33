"""How the report page stores its pixels: linear values, compressed, in the page itself.

The page changes exposure and reads pixel values under the cursor, so it needs the linear
values, not 8-bit previews. Images go in as float16 (3 significant digits, plenty for display;
values beyond float16's 65504 are clipped to it), error and alpha maps as float32; each array
is little-endian, zlib-compressed and base64-encoded into the page's JSON. The page inflates
them with the browser's own ``DecompressionStream("deflate")``, so nothing is fetched and no
library is needed. Arrays larger than ``max_size`` on a side are box-filtered by a whole factor
first (display only: metrics use the full images).
"""

from __future__ import annotations

import base64
import math
import zlib

import numpy as np

FLOAT16_MAX = 65504.0
DTYPES = {"f16": "<f2", "f32": "<f4"}


def encode_array(array, dtype: str = "f16") -> dict:
    """``{"dtype", "shape", "data"}``: ``array`` as ``dtype`` (``f16`` or ``f32``), zlib
    (level 6), base64. Non-finite values become 0 (a display must not break on them)."""
    values = np.nan_to_num(np.asarray(array, np.float64), nan=0.0, posinf=FLOAT16_MAX,
                           neginf=-FLOAT16_MAX)
    if dtype == "f16":
        values = np.clip(values, -FLOAT16_MAX, FLOAT16_MAX)
    raw = np.ascontiguousarray(values.astype(DTYPES[dtype])).tobytes()
    return {"dtype": dtype, "shape": list(np.shape(array)),
            "data": base64.b64encode(zlib.compress(raw, 6)).decode("ascii")}


def decode_array(blob: dict) -> np.ndarray:
    """Inverse of :func:`encode_array` (what the page does), as float32."""
    raw = zlib.decompress(base64.b64decode(blob["data"]))
    return np.frombuffer(raw, DTYPES[blob["dtype"]]).astype(np.float32).reshape(blob["shape"])


def display_factor(height: int, width: int, max_size: int | None) -> int:
    """The whole box-filter factor that brings the longer side to at most ``max_size``."""
    if not max_size or max(height, width) <= max_size:
        return 1
    return math.ceil(max(height, width) / max_size)


def downsample(array, factor: int) -> np.ndarray:
    """Box-filter (H, W[, C]) by ``factor`` (edges that do not fill a box are cropped)."""
    array = np.asarray(array)
    if factor == 1:
        return array
    height, width = (array.shape[0] // factor) * factor, (array.shape[1] // factor) * factor
    cropped = array[:height, :width].astype(np.float64)
    shape = (height // factor, factor, width // factor, factor) + array.shape[2:]
    return cropped.reshape(shape).mean(axis=(1, 3))


def data_uri(data: bytes, mime: str) -> str:
    """``data:MIME;base64,...`` for an <img> in the page."""
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


__all__ = ["FLOAT16_MAX", "data_uri", "decode_array", "display_factor", "downsample",
           "encode_array"]
