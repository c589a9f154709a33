"""Other renderers' EXR files: every part of a multi-part file, layered names, the channel
conventions of Cycles, pbrt-v4 and Mitsuba (jaxden.io.conventions), and the messages when a
channel is missing or named under another case.

The Cycles files spheres-16spp-seed{1,2}.exr in tests/data/cycles/ are real: Blender 5.0.1
(``bpy`` from PyPI) rendered them with experiments/renderers/cycles_render.py (32 x 24, 16 spp,
seeds 1 and 2; tests/test_cycles_passes.py reads the files with every other pass). The pbrt-v4
and Mitsuba files are written here with the channel names their sources and films use.
"""

from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from jaxden.errors import ExrError
from jaxden.io.conventions import CONVENTIONS, resolve
from jaxden.io.exr import read_channels, read_frame, read_header, write_channels

CYCLES = Path(__file__).parent / "data" / "cycles"
CYCLES_FILE = CYCLES / "spheres-16spp-seed1.exr"
SHAPE = (6, 7)


def _ramp(seed: int, low: float = 0.1) -> np.ndarray:
    return np.random.default_rng(seed).uniform(low, 1.0, SHAPE).astype(np.float32)


def _part(channels: dict, name: str, window=None) -> "OpenEXR.Part":
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if window is not None:
        header["dataWindow"] = window
        header["displayWindow"] = (np.array([0, 0], np.int32),
                                   np.array([SHAPE[1] - 1, SHAPE[0] - 1], np.int32))
    return OpenEXR.Part(header, dict(channels), name=name)  # the binding rewrites the dict


def test_cycles_file_reads_with_its_convention():
    header = read_header(CYCLES_FILE)
    assert header["parts"] == 5
    assert "ViewLayer.Denoising Albedo.R" in header["channels"]
    frame = read_frame(CYCLES_FILE, convention="cycles", require=("color", "albedo", "normal"))
    channels, _ = read_channels(CYCLES_FILE)
    np.testing.assert_array_equal(frame.color[..., 0], channels["ViewLayer.Combined.R"])
    # Cycles' Denoising Albedo holds a seen emitter's light: read clipped to [0, 1]
    np.testing.assert_array_equal(frame.albedo[..., 2],
                                  np.clip(channels["ViewLayer.Denoising Albedo.B"], 0, 1))
    np.testing.assert_array_equal(frame.normal[..., 1], channels["ViewLayer.Denoising Normal.Y"])
    np.testing.assert_array_equal(frame.depth[..., 0], channels["ViewLayer.Denoising Depth.Z"])
    assert float(frame.spp) == 16.0  # from cycles.ViewLayer.samples
    assert frame.variance is None  # Cycles writes none
    # The normal is a mean of unit normals over the pixel's samples (0 where a sample sees
    # the background), so at most 1 long, and 1 where every sample hits the flat floor.
    length = np.linalg.norm(frame.normal, axis=-1)
    assert length.max() <= 1 + 1e-3 and np.mean(length > 0.999) > 0.3
    assert 0 <= frame.albedo.min() and frame.albedo.max() <= 1


def test_cycles_variance_is_refused_with_the_way_to_get_it():
    with pytest.raises(ExrError, match=r"variance: a cycles file has no such channels.*merge"):
        read_frame(CYCLES_FILE, convention="cycles", require=("color", "variance"))


def test_a_name_under_another_case_gets_a_did_you_mean():
    names = ("viewlayer.combined.R", "ViewLayer.Combined.G", "ViewLayer.Combined.B")
    with pytest.raises(ExrError, match=r"did you mean 'ViewLayer.Combined.R' for "
                                       r"'viewlayer.combined.R'"):
        read_frame(CYCLES_FILE, channel_map={"color": names})


def test_unknown_convention_suggests_the_close_one():
    with pytest.raises(ExrError, match=r"did you mean 'cycles'"):
        read_frame(CYCLES_FILE, convention="cylces")


def test_later_parts_get_their_part_name(tmp_path):
    path = tmp_path / "parts.exr"
    rgb = {c: _ramp(i) for i, c in enumerate("RGB")}
    diffuse = {c: 2 * _ramp(i) for i, c in enumerate("RGB")}
    OpenEXR.File([_part(rgb, "rgba"), _part(diffuse, "diffuse")]).write(str(path))
    channels, _ = read_channels(path)
    assert sorted(channels) == ["B", "G", "R", "diffuse.B", "diffuse.G", "diffuse.R"]
    np.testing.assert_array_equal(channels["diffuse.G"], diffuse["G"])
    frame = read_frame(path, channel_map={"albedo": ("diffuse.R", "diffuse.G", "diffuse.B")})
    np.testing.assert_array_equal(frame.albedo[..., 0], diffuse["R"])


def test_parts_over_other_pixels_are_refused(tmp_path):
    path = tmp_path / "windows.exr"
    whole = (np.array([0, 0], np.int32), np.array([SHAPE[1] - 1, SHAPE[0] - 1], np.int32))
    half = (np.array([0, 0], np.int32), np.array([SHAPE[1] - 1, SHAPE[0] // 2 - 1], np.int32))
    small = {"Y": np.ones((SHAPE[0] // 2, SHAPE[1]), np.float32)}
    OpenEXR.File([_part({c: _ramp(1) for c in "RGB"}, "rgba", whole),
                  _part(small, "mask", half)]).write(str(path))
    with pytest.raises(ExrError, match=r"part 1 \('mask'\) has the data window"):
        read_channels(path)


def test_pbrt_v4_gbuffer_layout(tmp_path):
    """pbrt-v4's GBufferFilm: R,G,B, Albedo.*, Ns.*, N.*, P.*, Variance.* and the
    samplesPerPixel attribute. Its Variance.* (per sample, of the sensor's XYZ) is read only
    when named, then divided by the sample count."""
    path = tmp_path / "pbrt.exr"
    channels = {"R": _ramp(1), "G": _ramp(2), "B": _ramp(3),
                "Albedo.R": _ramp(4), "Albedo.G": _ramp(5), "Albedo.B": _ramp(6),
                "Ns.X": np.zeros(SHAPE, np.float32), "Ns.Y": np.zeros(SHAPE, np.float32),
                "Ns.Z": np.ones(SHAPE, np.float32), "N.X": np.ones(SHAPE, np.float32),
                "N.Y": np.zeros(SHAPE, np.float32), "N.Z": np.zeros(SHAPE, np.float32),
                "P.X": _ramp(7), "P.Y": _ramp(8), "P.Z": 3 * _ramp(9),
                "Variance.R": _ramp(10), "Variance.G": _ramp(11), "Variance.B": _ramp(12)}
    write_channels(path, channels, attributes={"samplesPerPixel": 64})
    frame = read_frame(path, convention="pbrt-v4", require=("color", "normal"))
    assert float(frame.spp) == 64.0 and frame.variance is None
    np.testing.assert_array_equal(frame.normal[..., 2], 1.0)  # the shading normal, Ns
    np.testing.assert_array_equal(frame.depth[..., 0], channels["P.Z"])
    named = read_frame(path, convention="pbrt-v4", variance_is_sample_variance=True,
                       channel_map={"variance": ("Variance.R", "Variance.G", "Variance.B")})
    np.testing.assert_allclose(named.variance[..., 1], channels["Variance.G"] / 64, rtol=1e-6)
    with pytest.raises(ExrError, match="stores the variance of the pixel mean"):
        read_frame(path, convention="jaxden", variance_is_sample_variance=True)


def test_mitsuba_aov_layout(tmp_path):
    path = tmp_path / "mitsuba.exr"
    channels = {"R": _ramp(1), "G": _ramp(2), "B": _ramp(3),
                "albedo.R": _ramp(4), "albedo.G": _ramp(5), "albedo.B": _ramp(6),
                "sh_normal.X": _ramp(7), "sh_normal.Y": _ramp(8), "sh_normal.Z": _ramp(9),
                "depth.T": _ramp(10)}
    write_channels(path, channels)
    frame = read_frame(path, convention="mitsuba", require=("color", "albedo", "normal", "depth"))
    np.testing.assert_array_equal(frame.normal[..., 0], channels["sh_normal.X"])
    np.testing.assert_array_equal(frame.depth[..., 0], channels["depth.T"])


def test_layers_must_be_chosen_when_a_file_holds_several():
    present = [f"{layer}.Combined.{c}" for layer in ("Front", "Back") for c in "RGB"]
    with pytest.raises(ExrError, match="layers found: Back, Front; choose one with --layer"):
        resolve("cycles", present, {})
    reading = resolve("cycles", present, {"cycles.Back.samples": "8"}, layer="Back")
    assert reading.mapping["color"] == ("Back.Combined.R", "Back.Combined.G", "Back.Combined.B")
    assert reading.spp == 8.0 and reading.variance == "none" and reading.layer == "Back"
    assert reading.denoised == () and reading.sample_fraction is None
    noisy = [f"Back.Noisy Image.{c}" for c in "RGB"] + ["Back.Debug Sample Count.X"]
    reading = resolve("cycles", present + noisy, {}, layer="Back")
    assert reading.mapping["color"] == tuple(noisy[:3])  # the raw colour of a denoised render
    assert reading.denoised == ("Back.Combined.R", "Back.Combined.G", "Back.Combined.B")
    assert reading.sample_fraction == "Back.Debug Sample Count.X"
    with pytest.raises(ExrError, match="no render layer 'Side'"):
        resolve("cycles", present, {}, layer="Side")


def test_every_convention_names_colour_and_a_known_variance_kind():
    for name, convention in CONVENTIONS.items():
        assert convention.name == name
        assert "color" in convention.fields
        assert convention.variance in ("mean", "sample", "none")
        assert (convention.variance == "none") == ("variance" not in convention.fields)


def _jaxden_frame(spp=16.0, seed=0):
    from jaxden.frame import Frame

    rng = np.random.default_rng(seed)
    variance = rng.uniform(1e-9, 1e-3, (*SHAPE, 3)).astype(np.float32)  # below half's range
    corr = rng.uniform(-0.9, 0.9, (*SHAPE, 3)).astype(np.float32)
    covariance = corr * np.sqrt(variance * np.roll(variance, -1, axis=-1))
    return Frame(color=rng.uniform(0, 4, (*SHAPE, 3)).astype(np.float32), variance=variance,
                 covariance=covariance, spp=np.float32(spp))


def test_half_files_keep_variance_and_covariance_exact(tmp_path):
    """write_frame(half=True) (`jaxden render --half`) stores colour and features in float16
    but the variance and covariance in float32, so every jaxden command reads it back."""
    from jaxden.io.exr import write_frame

    frame = _jaxden_frame()
    write_frame(tmp_path / "h.exr", frame, half=True)
    back = read_frame(tmp_path / "h.exr", require=("color", "variance", "covariance"))
    np.testing.assert_array_equal(back.variance, frame.variance)
    np.testing.assert_array_equal(back.covariance, frame.covariance)
    np.testing.assert_allclose(back.color, frame.color, rtol=1e-3)  # half: 11 bits
    assert not np.array_equal(back.color, frame.color)


def test_spp_that_contradicts_the_header_is_refused(tmp_path):
    from jaxden.io.exr import write_frame

    write_frame(tmp_path / "f.exr", _jaxden_frame(spp=16))
    with pytest.raises(ExrError, match="its header says 16 spp and --spp says 64"):
        read_frame(tmp_path / "f.exr", spp=64)
    assert float(read_frame(tmp_path / "f.exr", spp=16).spp) == 16
    assert float(read_frame(tmp_path / "f.exr", spp=64, spp_override=True).spp) == 64


def test_one_spp_input_is_told_it_needs_two(tmp_path, capsys):
    from jaxden.cli import main
    from jaxden.frame import Frame
    from jaxden.io.exr import write_frame

    write_frame(tmp_path / "one.exr", Frame(color=np.ones((*SHAPE, 3), np.float32),
                                            spp=np.float32(1)))
    assert main(["sure", str(tmp_path / "one.exr"), "--denoiser", "oidn",
                 "--out", str(tmp_path / "s.exr")]) == 2
    assert "one sample per pixel cannot estimate" in capsys.readouterr().err


@pytest.mark.parametrize("convention, key", [("jaxden", "jaxden.spp"),
                                             ("jaxden", "jaxden.variance_dof"),
                                             ("pbrt-v4", "samplesPerPixel")])
def test_a_header_count_that_is_no_number_is_one_error(tmp_path, convention, key):
    """A sample count or variance dof stored as text is refused naming the file and the
    attribute, whichever reader (jaxden's header or a renderer convention's) meets it."""
    path = tmp_path / "f.exr"
    write_channels(path, {"R": _ramp(1), "G": _ramp(2), "B": _ramp(3)},
                   attributes={key: "sixty-four"})
    shown = key.removeprefix("jaxden.")
    with pytest.raises(ExrError, match=rf"f\.exr: header attribute .*{shown} is not a number: "
                                       r"'sixty-four'"):
        read_frame(path, convention=convention)
