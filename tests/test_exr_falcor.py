"""Frames spread over one file per output (Falcor's frame capture, jaxden.io.siblings) and the
pbrt-v4 GBufferFilm preset, on files laid out as those renderers write them.

tests/data/falcor/make_fixtures.py wrote the Falcor captures (16 x 12, frame 256, half-float
EXRs and an 8-bit PNG albedo) and tests/data/pbrt/make_fixtures.py the pbrt-v4 file; their
docstrings cite the renderers' source for every name and type. Expected values are read from
the files with OpenEXR and Pillow directly, not through jaxden.
"""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from helpers import assert_one_error_line, cli_env, run_cli
from PIL import Image

from jaxden.errors import ExrError
from jaxden.io.exr import read_frame

FALCOR = Path(__file__).parent / "data" / "falcor"
PBRT = Path(__file__).parent / "data" / "pbrt" / "gbuffer-16spp.exr"
COLOUR = "Mogwai.AccumulatePass.output.256.exr"
SKY_ROWS = 3  # make_fixtures.py: camera rays of the top rows miss


def _exr(path: Path) -> dict[str, np.ndarray]:
    exr = OpenEXR.File(str(path), separate_channels=True)
    return {name: np.asarray(c.pixels, np.float32) for name, c in exr.channels().items()}


def _rgb(path: Path) -> np.ndarray:
    channels = _exr(path)
    return np.stack([channels[c] for c in "RGB"], axis=-1)


def _capture(tmp_path: Path, base: str = "Mogwai") -> Path:
    """A copy of one fixture capture in ``tmp_path`` (to add, drop or rename files)."""
    for file in FALCOR.glob(f"{base}.*"):
        shutil.copy(file, tmp_path / file.name)
    return tmp_path


def _write_rgb(path: Path, image: np.ndarray) -> None:
    channels = {c: np.asarray(image[..., i], np.float16) for i, c in enumerate("RGB")}
    OpenEXR.File({"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage},
                 channels).write(str(path))


def test_falcor_capture_gives_each_field_from_its_output_file():
    """Colour from AccumulatePass.output (not the one-frame PathTracer.color beside it),
    albedo = the 8-bit PNG's integers / 255, the world-space guide normal, depth = linearZ's R
    with the misses (1e8, +inf in half) read as 0; any file of the capture names it."""
    frame = read_frame(FALCOR / COLOUR, convention="falcor")
    np.testing.assert_array_equal(frame.color, _rgb(FALCOR / COLOUR))
    assert not np.array_equal(frame.color, _rgb(FALCOR / "Mogwai.PathTracer.color.256.exr"))
    albedo8 = np.asarray(Image.open(FALCOR / "Mogwai.PathTracer.albedo.256.png"))
    np.testing.assert_allclose(frame.albedo, albedo8 / 255.0, rtol=0, atol=1e-7)
    np.testing.assert_array_equal(frame.normal,
                                  _rgb(FALCOR / "Mogwai.PathTracer.guideNormal.256.exr"))
    linear_z = _exr(FALCOR / "Mogwai.GBufferRT.linearZ.256.exr")["R"]
    assert np.isposinf(linear_z[:SKY_ROWS]).all()  # the file holds what Falcor's holds
    np.testing.assert_array_equal(frame.depth[SKY_ROWS:, :, 0], linear_z[SKY_ROWS:])
    np.testing.assert_array_equal(frame.depth[:SKY_ROWS], 0.0)
    assert frame.variance is None and frame.spp is None and frame.position is None
    surface = np.linalg.norm(np.asarray(frame.normal[SKY_ROWS:]), axis=-1)
    np.testing.assert_allclose(surface, 1.0, atol=2e-3)  # unit normals, to half precision
    same = read_frame(FALCOR / "Mogwai.PathTracer.albedo.256.png", convention="falcor")
    for field in ("color", "albedo", "normal", "depth"):
        np.testing.assert_array_equal(getattr(same, field), getattr(frame, field))


def test_falcor_masked_captures_renamed_passes_and_fallbacks(tmp_path):
    """A one-channel capture (``.R``) gives that channel; without AccumulatePass the colour is
    PathTracer.color; --channels names the outputs of a pass the preset does not know."""
    folder = _capture(tmp_path)
    (folder / "Mogwai.GBufferRT.linearZ.256.exr").rename(
        folder / "Mogwai.GBufferRT.linearZ.256.R.exr")
    (folder / COLOUR).unlink()
    frame = read_frame(folder / "Mogwai.PathTracer.color.256.exr", convention="falcor")
    np.testing.assert_array_equal(frame.color, _rgb(FALCOR / "Mogwai.PathTracer.color.256.exr"))
    np.testing.assert_array_equal(frame.depth[SKY_ROWS:, :, 0],
                                  _exr(FALCOR / "Mogwai.GBufferRT.linearZ.256.exr")["R"][SKY_ROWS:])
    (folder / "Mogwai.PathTracer.color.256.exr").rename(folder / "Mogwai.PT.radiance.256.exr")
    renamed = read_frame(folder / "Mogwai.PT.radiance.256.exr", convention="falcor",
                         channel_map={"color": ("PT.radiance.R", "PT.radiance.G",
                                                "PT.radiance.B")})
    np.testing.assert_array_equal(renamed.color, frame.color)


def test_falcor_outputs_no_field_reads_are_never_decoded(monkeypatch):
    """keep=("color",) (what jaxden sure --buffers reads) decodes the colour file alone."""
    from jaxden.io import exr

    decoded, read_channels = [], exr.read_channels

    def counting(path, names=None):
        decoded.append(Path(path).name)
        return read_channels(path, names)

    monkeypatch.setattr(exr, "read_channels", counting)
    frame = read_frame(FALCOR / "Mogwai.PathTracer.guideNormal.256.exr", convention="falcor",
                       keep=("color",))
    assert decoded == [COLOUR] and frame.normal is None and frame.albedo is None


@pytest.mark.parametrize("case", ["size", "frame", "colour", "ambiguous", "name", "png"])
def test_falcor_capture_refusals_are_one_line_naming_the_files(tmp_path, capsys, case):
    folder = _capture(tmp_path)
    given = folder / COLOUR
    if case == "size":
        _write_rgb(folder / "Mogwai.PathTracer.guideNormal.256.exr", np.ones((6, 8, 3)))
        words = ["Mogwai.PathTracer.guideNormal.256.exr is 8x6 pixels", COLOUR, "16x12"]
    elif case == "frame":
        (folder / "Mogwai.PathTracer.albedo.256.png").rename(
            folder / "Mogwai.PathTracer.albedo.255.png")
        words = ["albedo of frame 256", "Mogwai.PathTracer.albedo.255.png"]
    elif case == "colour":
        (folder / COLOUR).unlink()
        (folder / "Mogwai.PathTracer.color.256.exr").unlink()
        given = folder / "Mogwai.PathTracer.guideNormal.256.exr"
        words = ["no colour output of frame 256", COLOUR, "Mogwai.PathTracer.color.256.exr"]
    elif case == "ambiguous":
        shutil.copy(folder / "Mogwai.PathTracer.guideNormal.256.exr",
                    folder / "Mogwai.PathTracer.guideNormal.256.RGBA.exr")
        words = ["2 files give the output PathTracer.guideNormal",
                 "Mogwai.PathTracer.guideNormal.256.RGBA.exr"]
    elif case == "png":
        albedo = folder / "Mogwai.PathTracer.albedo.256.png"
        albedo.write_bytes(albedo.read_bytes()[:80])
        words = ["Mogwai.PathTracer.albedo.256.png: PNG pixel data cannot be decoded"]
    else:
        given = folder / "shot.exr"
        shutil.copy(folder / COLOUR, given)
        words = ["shot.exr: not named as falcor names its files", COLOUR]
    with pytest.raises(ExrError):
        read_frame(given, convention="falcor")
    out = folder / "out.exr"
    code, lines, _ = run_cli(["denoise", given, "--from", "falcor", "--model", "oidn",
                              "--out", out], capsys)
    assert_one_error_line(code, lines, *words)
    assert not out.exists()


def test_falcor_capture_without_variance_points_to_merge(capsys, tmp_path):
    code, lines, _ = run_cli(["progressive", FALCOR / COLOUR, "--from", "falcor",
                              "--denoiser", "oidn", "--out", tmp_path / "pd.exr"], capsys)
    assert_one_error_line(code, lines, "jaxden merge", "--from falcor")


def test_pbrt_v4_gbuffer_film_file():
    """pbrt-v4's channel names (Albedo.*, Ns.* camera-space shading normal, P.Z depth,
    samplesPerPixel): Variance.* is not taken as the variance of the mean (per sample, of the
    sensor's XYZ, hits only); named by hand with sample_variance it is divided by the spp."""
    stored = _exr(PBRT)
    frame = read_frame(PBRT, convention="pbrt-v4")
    assert float(frame.spp) == 16.0 and frame.variance is None
    np.testing.assert_array_equal(frame.color, np.stack([stored[c] for c in "RGB"], -1))
    np.testing.assert_array_equal(frame.albedo[..., 1], stored["Albedo.G"])
    np.testing.assert_array_equal(frame.normal, np.stack([stored[f"Ns.{c}"] for c in "XYZ"], -1))
    assert not np.array_equal(frame.normal, np.stack([stored[f"N.{c}"] for c in "XYZ"], -1))
    np.testing.assert_array_equal(frame.depth[..., 0], stored["P.Z"])
    np.testing.assert_array_equal(frame.position[..., 0], stored["P.X"])
    names = ("Variance.R", "Variance.G", "Variance.B")
    with_variance = read_frame(PBRT, convention="pbrt-v4", channel_map={"variance": names},
                               variance_is_sample_variance=True)
    np.testing.assert_allclose(with_variance.variance[..., 2], stored["Variance.B"] / 16,
                               rtol=1e-6)


def test_merge_two_falcor_captures_then_denoise_from_the_command_line(tmp_path):
    """jaxden merge --from falcor of two captures: the variance of the mean from their spread,
    sum_k (c_k - mean)^2 / ((K - 1) K); then jaxden denoise --model oidn on the result."""
    env = cli_env(tmp_path / "cache")
    merged, denoised = tmp_path / "merged.exr", tmp_path / "denoised.exr"
    captures = [FALCOR / COLOUR, FALCOR / "Mogwai-run1.AccumulatePass.output.256.exr"]
    for argv in (["merge", *captures, "--from", "falcor", "--out", merged],
                 ["denoise", merged, "--model", "oidn", "--out", denoised]):
        done = subprocess.run([sys.executable, "-m", "jaxden.cli", *map(str, argv)], env=env,
                              capture_output=True, text=True, timeout=120, check=False)
        assert done.returncode == 0, done.stderr
    colours = np.stack([_rgb(path) for path in captures]).astype(np.float64)
    spread = np.square(colours - colours.mean(0)).sum(0) / 2
    written = _exr(merged)
    np.testing.assert_allclose(np.stack([written[f"variance.{c}"] for c in "RGB"], -1),
                               spread, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(np.stack([written[f"albedo.{c}"] for c in "RGB"], -1),
                               np.asarray(Image.open(FALCOR / "Mogwai.PathTracer.albedo.256.png"))
                               / 255.0, atol=1e-6)  # the captures share their features
    result = _rgb(denoised)
    assert result.shape == (12, 16, 3) and np.isfinite(result).all()
