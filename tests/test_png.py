"""Tests for jaxden.io.png: a PNG decoded by hand (chunks, CRCs, zlib, filter bytes) gives
back the pixels; the sRGB curve at known points; bad input refused."""

import struct
import zlib

import numpy as np
import pytest

from jaxden.errors import FrameError
from jaxden.io.png import PNG_SIGNATURE, encode_png, preview, srgb_encode, write_png


def decode(data: bytes):
    """Minimal PNG reader for 8-bit grey/RGB, filter 0 only: (header fields, pixels)."""
    assert data[:8] == PNG_SIGNATURE
    pos, chunks = 8, []
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF, kind
        chunks.append((kind, body))
        pos += 12 + length
    assert [k for k, _ in chunks] == [b"IHDR", b"IDAT", b"IEND"]
    w, h, depth, colour_type, comp, filt, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    channels = {0: 1, 2: 3}[colour_type]
    raw = np.frombuffer(zlib.decompress(chunks[1][1]), np.uint8).reshape(h, 1 + w * channels)
    assert np.all(raw[:, 0] == 0)  # filter type 0 on every row
    pixels = raw[:, 1:].reshape(h, w, channels)
    return (w, h, depth, colour_type, comp, filt, interlace), pixels


def test_rgb_and_grey_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    header, pixels = decode(encode_png(rgb))
    assert header == (7, 5, 8, 2, 0, 0, 0)
    np.testing.assert_array_equal(pixels, rgb)
    grey = rng.integers(0, 256, (4, 3), dtype=np.uint8)
    path = write_png(tmp_path / "g.png", grey)
    header, pixels = decode(path.read_bytes())
    assert header[:4] == (3, 4, 8, 0)
    np.testing.assert_array_equal(pixels[..., 0], grey)


def test_srgb_curve_known_points():
    np.testing.assert_allclose(srgb_encode([0.0, 0.0031308, 0.5, 1.0, 2.0, -1.0]),
                               [0.0, 0.04045, 0.735357, 1.0, 1.0, 0.0], atol=2e-5)
    assert preview(np.full((1, 1, 3), 0.5), exposure=2.0).tolist() == [[[255, 255, 255]]]
    assert preview(np.full((1, 1, 3), 0.5))[0, 0, 0] == round(0.735357 * 255)


def test_bad_input_refused():
    with pytest.raises(FrameError, match="NaN"):
        preview(np.array([[[np.nan, 0, 0]]]))
    with pytest.raises(FrameError, match="uint8"):
        encode_png(np.zeros((2, 2, 3), np.float32))
    with pytest.raises(FrameError, match="shape"):
        encode_png(np.zeros((2, 2, 4), np.uint8))
