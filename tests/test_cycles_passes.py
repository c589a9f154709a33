"""The `cycles` convention against the files Blender 5.0.1 writes with every pass a user may
enable, and what jaxden does with denoised and adaptive renders.

The files in tests/data/cycles/ are real: experiments/renderers/cycles_fixtures.py rendered
them with ``bpy`` 5.0.1 from PyPI (24 x 16 pixels; a floor, a wall with a window and a sun, a
small emitter of strength 400, a gold Suzanne, a glossy torus; no clamping):
``passes-seed{1,2}`` (4 spp, every pass; ``passes-seed1-again``: seed 1 once more, used by
tests/test_merge.py), ``denoised-seed{1,2}`` (the same with Render >
Denoise on), ``adaptive-seed{1,2}`` (Noise Threshold 0.1, Max Samples 64) and
``single-layer`` (a plain OpenEXR). Older Blender's pass names (``Emit``, ``DiffCol``) are
written here by renaming a real file's channels.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_one_error_line, run_cli

from jaxden.data.merge import merge_renders, read_buffer_list
from jaxden.errors import ExrError
from jaxden.io.conventions import resolve
from jaxden.io.exr import (
    read_channels,
    read_frame,
    read_header,
    write_channels,
    write_frame,
    write_image,
)

CYCLES = Path(__file__).parent / "data" / "cycles"
PASSES = CYCLES / "passes-seed1.exr"
DENOISED = CYCLES / "denoised-seed1.exr"
ADAPTIVE = CYCLES / "adaptive-seed1.exr"
EVERY_PASS = ("Combined", "Depth", "Position", "Normal", "Diffuse Color", "Emission",
              "Debug Sample Count", "Denoising Normal", "Denoising Albedo", "Denoising Depth")


def _layer(name: str, channels: str) -> tuple[str, ...]:
    return tuple(f"ViewLayer.{name}.{c}" for c in channels)


def _copy(tmp_path, source, *, drop=(), rename=None) -> Path:
    """``source``'s channels and Cycles header written again, without the passes ``drop`` and
    with passes renamed by ``rename`` (old -> new): the file another Blender setup writes."""
    channels, header = read_channels(source)
    kept = {}
    for name, array in channels.items():
        layer, pass_, channel = name.split(".")
        if pass_ in drop:
            continue
        kept[f"{layer}.{(rename or {}).get(pass_, pass_)}.{channel}"] = array
    path = tmp_path / source.name
    write_channels(path, kept, attributes={k: v for k, v in header.items()
                                           if k.startswith("cycles.")})
    return path


def test_blender_5_writes_a_part_per_pass_and_the_samples_in_the_header():
    """What Blender 5.0.1 writes: one part per pass named ``ViewLayer.<pass>``, the channel
    names carrying the part's name; the sample setting in ``cycles.ViewLayer.samples`` (text)
    and nothing in the header about denoising or adaptive sampling."""
    header = read_header(PASSES)
    assert header["parts"] == len(EVERY_PASS) and header["Software"] == "Blender 5.0.1"
    assert {n.rsplit(".", 1)[0] for n in header["channels"]} == {
        f"ViewLayer.{p}" for p in EVERY_PASS}
    assert header["cycles.ViewLayer.samples"] == "4"
    cycles_keys = {k for k in header if k.startswith("cycles.")}
    assert cycles_keys == {f"cycles.ViewLayer.{k}" for k in (
        "samples", "render_time", "synchronization_time", "total_time")}
    for path in (DENOISED, ADAPTIVE):
        assert {k for k in read_header(path) if k.startswith("cycles.")} == cycles_keys
    assert read_header(ADAPTIVE)["cycles.ViewLayer.samples"] == "64"  # Max Samples
    assert "ViewLayer.Noisy Image.R" in read_header(DENOISED)["channels"]


@pytest.mark.parametrize("field, pass_, channels, drop", [
    ("color", "Combined", "RGB", ()),
    ("albedo", "Denoising Albedo", "RGB", ()),
    ("albedo", "Diffuse Color", "RGB", ("Denoising Albedo",)),
    ("normal", "Denoising Normal", "XYZ", ()),
    ("normal", "Normal", "XYZ", ("Denoising Normal",)),
    ("depth", "Denoising Depth", "Z", ()),
    ("position", "Position", "XYZ", ()),
    ("emission", "Emission", "RGB", ()),
])
def test_each_blender_5_pass_is_read_as_its_field(tmp_path, field, pass_, channels, drop):
    path = _copy(tmp_path, PASSES, drop=drop) if drop else PASSES
    frame = read_frame(path, convention="cycles", require=(field,))
    stored, _ = read_channels(path)
    expected = np.stack([stored[n] for n in _layer(pass_, channels)], axis=-1)
    if pass_ == "Denoising Albedo":  # the lamps' emission in it clipped (below)
        expected = np.clip(expected, 0, 1)
    np.testing.assert_array_equal(getattr(frame, field), expected)
    assert float(frame.spp) == 4.0


def test_the_z_pass_is_the_depth_without_denoising_data_its_misses_read_as_0(tmp_path):
    path = _copy(tmp_path, PASSES, drop=("Denoising Depth",))
    z = read_channels(path)[0]["ViewLayer.Depth.Z"]
    misses = z >= 1e10
    assert misses.any() and not misses.all()  # the sky through the window
    depth = read_frame(path, convention="cycles", require=("depth",)).depth[..., 0]
    np.testing.assert_array_equal(depth[misses], 0.0)
    np.testing.assert_array_equal(depth[~misses], z[~misses])


def test_older_blender_pass_names_still_read(tmp_path):
    """Older Blender versions wrote ``Emit`` and ``DiffCol``."""
    path = _copy(tmp_path, PASSES, drop=("Denoising Albedo",),
                 rename={"Emission": "Emit", "Diffuse Color": "DiffCol"})
    frame = read_frame(path, convention="cycles", require=("albedo", "emission"))
    (tmp_path / "new").mkdir()
    new = read_frame(_copy(tmp_path / "new", PASSES, drop=("Denoising Albedo",)),
                     convention="cycles")
    np.testing.assert_array_equal(frame.emission, new.emission)
    np.testing.assert_array_equal(frame.albedo, new.albedo)


def test_a_missing_pass_is_named_as_blender_names_its_checkbox():
    with pytest.raises(ExrError, match=r"missing feature\(s\) emission .*ViewLayer\.Emission\.R"
                                       r".*enable View Layer Properties > Passes > Light > "
                                       r"Emission"):
        read_frame(CYCLES / "spheres-16spp-seed1.exr", convention="cycles",
                   require=("color", "emission"))


def test_a_single_layer_exr_is_told_to_save_a_multilayer_one():
    with pytest.raises(ExrError, match=r"single-layer\.exr: a single-layer EXR \(channels A, B, "
                                       r"G, R\).*Media Type: Multi-Layer EXR"):
        read_frame(CYCLES / "single-layer.exr", convention="cycles")
    with pytest.raises(ExrError, match=r"no '<layer>\.Combined\.R' channel among its passes.*"
                                       r"Passes > Data > Combined"):
        resolve("cycles", ["ViewLayer.Emission.R", "ViewLayer.Emission.G"], {})


def _stored(path, pass_: str) -> np.ndarray:
    stored, _ = read_channels(path, _layer(pass_, "RGB"))
    return np.stack([stored[n] for n in _layer(pass_, "RGB")], axis=-1)


def test_the_denoising_albedo_of_a_seen_emitter_holds_its_emission(tmp_path, capsys):
    """What Blender writes on lamp pixels: the Denoising Albedo is the Emission pass plus the
    surface's own albedo (at most 1), up to the emitter's strength (on the one pixel left
    above 1, (10, 10), the gold Suzanne mirrors a light, which no pass holds); the Diffuse
    Color pass holds no emission. Read clipped to [0, 1], as OIDN reads it, whatever passes
    the file has and whichever fields are kept; merged renders average the clipped albedos."""
    raw, emission = _stored(PASSES, "Denoising Albedo"), _stored(PASSES, "Emission")
    lamp = emission.max(axis=-1) > 0
    assert lamp.any() and emission.max() > 100 and raw.max() > 100
    surplus = raw - emission
    assert surplus[lamp].min() >= 0 and surplus[lamp].max() <= 1
    assert np.argwhere(surplus.max(axis=-1) > 1).tolist() == [[10, 10]]
    assert _stored(PASSES, "Diffuse Color").max() <= 1
    notes = []
    frame = read_frame(PASSES, convention="cycles", on_note=notes.append)
    np.testing.assert_array_equal(frame.albedo, np.clip(raw, 0, 1))
    assert notes == [] and frame.albedo[lamp].min() > 0.99  # a lamp pixel is white
    kept = read_frame(_copy(tmp_path, PASSES, drop=("Emission",)), convention="cycles",
                      keep=("albedo",))
    np.testing.assert_array_equal(kept.albedo, frame.albedo)
    renders = [CYCLES / f"passes-seed{s}.exr" for s in (1, 2)]
    out = tmp_path / "merged.exr"
    code, lines, _ = run_cli(["merge", *renders, "--from", "cycles", "--out", out], capsys)
    assert code == 0 and lines == [], lines
    np.testing.assert_allclose(read_frame(out).albedo, (np.clip(raw, 0, 1) + np.clip(
        _stored(renders[1], "Denoising Albedo"), 0, 1)) / 2, rtol=1e-6)


def test_the_albedo_named_by_hand_is_read_alike():
    """``--channels albedo=`` naming the Denoising Albedo clips it as the preset does; the
    Diffuse Color holds no emission and is read as it is."""
    albedo = _layer("Denoising Albedo", "RGB")
    named = read_frame(PASSES, convention="cycles", channel_map={"albedo": albedo})
    np.testing.assert_array_equal(named.albedo, read_frame(PASSES, convention="cycles").albedo)
    diffuse = read_frame(PASSES, convention="cycles",
                         channel_map={"albedo": _layer("Diffuse Color", "RGB")})
    np.testing.assert_array_equal(diffuse.albedo, _stored(PASSES, "Diffuse Color"))


def test_an_albedo_above_1_that_nothing_explains_is_one_warning(tmp_path, capsys, monkeypatch):
    """A file in jaxden's channels whose albedo is Blender's raw Denoising Albedo (merged
    before jaxden clipped it): kept as it is, one warning line, once a process."""
    from jaxden.io import reading_checks

    monkeypatch.setattr(reading_checks, "_warned", set())
    frame = read_frame(PASSES, convention="cycles")
    raw = _stored(PASSES, "Denoising Albedo")
    path = tmp_path / "old.exr"
    write_frame(path, frame.replace(albedo=raw))
    capsys.readouterr()
    np.testing.assert_array_equal(read_frame(path).albedo, raw)
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [(f"jaxden: warning: {path}: the albedo is above 1 on 3 pixel(s) (up to "
                     f"200.8), but an albedo is a reflectance in [0, 1]: WSKP divides the colour "
                     f"by it, which brightens or darkens those pixels, and OIDN clips it at 1. "
                     f"Blender's Denoising Albedo holds the emission of the lamps it sees: read "
                     f"Cycles renders with --from cycles (merge them again), which clips it")]
    read_frame(path)
    assert capsys.readouterr().err == ""
    write_frame(tmp_path / "fine.exr", frame)  # an albedo in [0, 1]: nothing said
    monkeypatch.setattr(reading_checks, "_warned", set())
    read_frame(tmp_path / "fine.exr")
    assert capsys.readouterr().err == ""


# --------------------------------------------------------------------- denoised renders
def test_a_denoised_render_gives_its_noisy_image():
    notes = []
    frame = read_frame(DENOISED, convention="cycles", on_note=notes.append)
    stored, _ = read_channels(DENOISED)
    np.testing.assert_array_equal(frame.color, np.stack(
        [stored[n] for n in _layer("Noisy Image", "RGB")], axis=-1))
    assert notes == [("a denoised render: the colour read is its raw Monte Carlo mean, "
                     "ViewLayer.Noisy Image, not the denoised ViewLayer.Combined")]
    named = read_frame(DENOISED, convention="cycles", channel_map={
        "color": _layer("Combined", "RGB")})  # asked for by name: allowed outside merging
    np.testing.assert_array_equal(named.color[..., 0], stored["ViewLayer.Combined.R"])


def test_merging_denoised_renders_merges_their_noisy_images(tmp_path, capsys):
    """Merged from their Noisy Image passes, two denoised renders give the variance two plain
    renders of the same setup give; their denoised Combined passes would give thousands of
    times less (measured on these files: sum 7.3 against 22900)."""
    out = tmp_path / "merged.exr"
    renders = [CYCLES / f"denoised-seed{s}.exr" for s in (1, 2)]
    code, lines, _ = run_cli(["merge", *renders, "--from", "cycles", "--out", out], capsys)
    assert code == 0, lines
    assert lines == [(f"jaxden: note: {renders[0]}, {renders[1]}: a denoised render: the colour "
                     f"read is its raw Monte Carlo mean, ViewLayer.Noisy Image, not the denoised "
                     f"ViewLayer.Combined")]
    merged = read_frame(out, require=("variance",))
    plain = merge_renders([read_frame(CYCLES / f"passes-seed{s}.exr", convention="cycles")
                           for s in (1, 2)])
    denoised = merge_renders([read_frame(p, convention="cycles", channel_map={
        "color": _layer("Combined", "RGB")}) for p in renders])
    assert 0.5 < merged.variance.sum() / plain.variance.sum() < 2
    assert merged.variance.sum() > 1000 * denoised.variance.sum()
    assert float(merged.spp) == 8.0
    # sub-buffer SURE reads the buffers' colours as the merge read them
    assert run_cli(["sure", out, "--buffers", *renders, "--denoiser", "oidn", "--out",
                    tmp_path / "sure.exr"], capsys)[0] == 0


def test_merge_refuses_a_denoised_colour(tmp_path, capsys):
    renders = [CYCLES / f"denoised-seed{s}.exr" for s in (1, 2)]
    out = tmp_path / "merged.exr"
    code, lines, _ = run_cli(["merge", *renders, "--from", "cycles", "--channels",
                              "color=" + ",".join(_layer("Combined", "RGB")), "--out", out],
                             capsys)
    assert_one_error_line(code, lines, "denoised image", "Noisy Image",
                          "Render Properties > Sampling > Render > Denoise")
    assert not out.exists()
    # images that jaxden's denoisers wrote are no renders either
    frame = read_frame(PASSES, convention="cycles")
    for k in range(2):
        write_image(tmp_path / f"d{k}.exr", frame.color * (1 + k), attributes={
            "denoiser": "oidn"})
    code, lines, _ = run_cli(["merge", tmp_path / "d0.exr", tmp_path / "d1.exr", "--out", out],
                             capsys)
    assert_one_error_line(code, lines, "d0.exr", "denoised by oidn", "merge the renders")


# --------------------------------------------------------------------- adaptive renders
def test_an_adaptive_render_records_no_sample_count():
    """Its Debug Sample Count pass (each pixel's samples over the most any pixel took) is
    below 1 on most pixels; the header's 64 (Max Samples) is no pixel count, so none is
    read, and one given is refused naming the Blender setting."""
    fraction = read_channels(ADAPTIVE)[0]["ViewLayer.Debug Sample Count.X"]
    assert 0.5 < np.mean(fraction < 1) < 1 and fraction.max() == 1
    assert np.all(read_channels(PASSES)[0]["ViewLayer.Debug Sample Count.X"] == 1)
    notes = []
    frame = read_frame(ADAPTIVE, convention="cycles", on_note=notes.append)
    assert frame.spp is None
    assert notes == [("rendered with adaptive sampling (its sample-count pass differs between "
                     "pixels): no one sample count holds for every pixel, so the header's 64 "
                     "is not used")]
    with pytest.raises(ExrError, match=r"adaptive sampling: its sample-count pass says \d+% of "
                                       r"the pixels took fewer samples.*turn off Render "
                                       r"Properties > Sampling > Render > Noise Threshold"):
        read_frame(ADAPTIVE, convention="cycles", spp=64)
    assert float(read_frame(ADAPTIVE, convention="cycles", spp=64, spp_override=True).spp) == 64


def test_adaptive_renders_merge_by_their_spread_without_a_sample_count(tmp_path, capsys):
    renders = [CYCLES / f"adaptive-seed{s}.exr" for s in (1, 2)]
    out = tmp_path / "merged.exr"
    code, lines, printed = run_cli(["merge", *renders, "--from", "cycles", "--out", out], capsys)
    assert code == 0, lines
    assert len(lines) == 1 and "adaptive sampling" in lines[0] and str(renders[1]) in lines[0]
    assert "no sample count" in printed
    merged = read_frame(out, require=("variance",))
    frames = [read_frame(r, convention="cycles") for r in renders]
    np.testing.assert_allclose(merged.variance, np.square(frames[0].color - frames[1].color) / 4,
                               rtol=1e-5, atol=1e-12)
    assert merged.spp is None and float(merged.variance_dof) == 1
    assert "spp" not in read_header(out)
    assert run_cli(["sure", out, "--buffers", *renders, "--denoiser", "oidn", "--out",
                    tmp_path / "sure.exr"], capsys)[0] == 0
    # one adaptive render among plain ones: not one setup
    code, lines, _ = run_cli(["merge", renders[0], PASSES, "--from", "cycles", "--out",
                              tmp_path / "mixed.exr"], capsys)
    assert_one_error_line(code, lines, "no sample count", "4 spp", "adaptive sampling")


# --------------------------------------------------------------------- merge and import
def test_merge_keeps_the_emission_for_emission_separate(tmp_path, capsys):
    """The issue's run: `merge --from cycles` of Blender 5 renders keeps the Emission pass,
    and the merged file denoises with OIDN's emission=separate."""
    renders = [CYCLES / f"passes-seed{s}.exr" for s in (1, 2)]
    out = tmp_path / "merged.exr"
    assert run_cli(["merge", *renders, "--from", "cycles", "--out", out], capsys)[0] == 0
    merged = read_frame(out, require=("emission", "position", "albedo", "normal", "depth"))
    frames = [read_frame(r, convention="cycles") for r in renders]
    np.testing.assert_allclose(merged.emission, (frames[0].emission + frames[1].emission) / 2,
                               rtol=1e-6)
    code, lines, _ = run_cli(["denoise", out, "--model", "oidn:emission=separate", "--out",
                              tmp_path / "d.exr"], capsys)
    assert code == 0, lines


def test_merge_channels_by_hand_and_records_them_for_the_buffers(tmp_path, capsys):
    renders = [CYCLES / f"passes-seed{s}.exr" for s in (1, 2)]
    out = tmp_path / "merged.exr"
    diffuse = ",".join(_layer("Diffuse Color", "RGB"))
    code, lines, _ = run_cli(["merge", *renders, "--from", "cycles", "--channels",
                              f"albedo={diffuse}", "--out", out], capsys)
    assert code == 0, lines
    stored = [read_channels(r)[0] for r in renders]
    np.testing.assert_allclose(
        read_frame(out).albedo[..., 1],
        (stored[0]["ViewLayer.Diffuse Color.G"] + stored[1]["ViewLayer.Diffuse Color.G"]) / 2,
        rtol=1e-6)
    listed = read_buffer_list(out)
    assert listed.reading() == {"convention": "cycles", "layer": None,
                                "channel_map": {"albedo": _layer("Diffuse Color", "RGB")}}
    code, lines, _ = run_cli(["merge", *renders, "--from", "cycles", "--channels",
                              "emission=ViewLayer.Emit.R,ViewLayer.Emit.G,ViewLayer.Emit.B",
                              "--out", tmp_path / "other.exr"], capsys)
    assert_one_error_line(code, lines, "missing feature(s) emission", "ViewLayer.Emit.R")


def _cycles_source(tmp_path, pattern: str) -> Path:
    """SRC/view/spp8/b0..b1.exr and reference/b0..b1.exr from the fixtures ``pattern``
    (seeds 1 and 2)."""
    src = tmp_path / "src"
    for folder in ("spp8", "reference"):
        (src / "view" / folder).mkdir(parents=True)
        for k, seed in enumerate((1, 2)):
            shutil.copy(CYCLES / pattern.format(seed=seed), src / "view" / folder / f"b{k}.exr")
    return src


def test_import_reads_every_pass_and_channels_by_hand(tmp_path, capsys):
    from jaxden.data.layout import load_manifest

    src = _cycles_source(tmp_path, "passes-seed{seed}.exr")
    out = tmp_path / "data"
    diffuse = ",".join(_layer("Diffuse Color", "RGB"))
    code, lines, _ = run_cli(["dataset", "import", src, "--from", "cycles", "--channels",
                              f"albedo={diffuse}", "--crop", 16, "--crops-per-view", 1,
                              "--reference-spp", 8, "--quiet", "--out", out], capsys)
    assert code == 0, lines
    manifest = load_manifest(out)
    assert manifest.extra["import"]["channels"] == {"albedo": list(_layer("Diffuse Color",
                                                                          "RGB"))}
    item = next(i for i in manifest.items if i.kind == "input")
    written = read_frame(out / item.path)
    assert written.emission is not None and written.position is not None
    (crop,) = manifest.crops
    top, left, height, width = crop.window
    stored = [read_channels(src / "view" / "spp8" / f"b{k}.exr")[0] for k in range(2)]
    expected = (stored[0]["ViewLayer.Diffuse Color.B"] + stored[1]["ViewLayer.Diffuse Color.B"])
    np.testing.assert_allclose(written.albedo[..., 2],
                               (expected / 2)[top:top + height, left:left + width], rtol=1e-6)


@pytest.mark.parametrize("pattern, words", [
    ("adaptive-seed{seed}.exr", ("adaptive sampling", "Noise Threshold")),
    ("denoised-seed{seed}.exr", ("denoised image", "Denoise")),
])
def test_import_refuses_adaptive_and_denoised_colours(tmp_path, capsys, pattern, words):
    src = _cycles_source(tmp_path, pattern)
    out = tmp_path / "data"
    argv = ["dataset", "import", src, "--from", "cycles", "--crop", 16, "--crops-per-view", 1,
            "--reference-spp", 8 if "denoised" in pattern else 128, "--quiet", "--out", out]
    if "denoised" in pattern:
        argv += ["--channels", "color=" + ",".join(_layer("Combined", "RGB"))]
    else:  # the headers say 64 each (Max Samples): a 128-spp level by name
        (src / "view" / "spp8").rename(src / "view" / "spp128")
    code, lines, _ = run_cli(argv, capsys)
    assert_one_error_line(code, lines, *words)
    assert not out.exists()


def test_denoised_renders_import_from_their_noisy_images(tmp_path, capsys):
    from jaxden.data.layout import load_manifest

    src = _cycles_source(tmp_path, "denoised-seed{seed}.exr")
    out = tmp_path / "data"
    code, lines, _ = run_cli(["dataset", "import", src, "--from", "cycles", "--crop", 16,
                              "--crops-per-view", 1, "--quiet", "--out", out], capsys)
    assert code == 0, lines
    item = next(i for i in load_manifest(out).items if i.kind == "input")
    noisy = merge_renders([read_frame(src / "view" / "spp8" / f"b{k}.exr", convention="cycles")
                           for k in range(2)])
    (crop,) = load_manifest(out).crops
    top, left, height, width = crop.window
    np.testing.assert_array_equal(read_frame(out / item.path).color,
                                  noisy.color[top:top + height, left:left + width])


def test_a_jaxden_render_is_not_taken_for_a_denoised_image(tmp_path):
    """Only an image that jaxden's denoisers wrote (its ``jaxden.denoiser``) is refused."""
    frame = read_frame(PASSES, convention="cycles")
    write_frame(tmp_path / "r.exr", frame.replace(spp=np.float32(4)))
    assert read_frame(tmp_path / "r.exr", refuse_denoised=True).color is not None


@pytest.mark.parametrize("merged", [False, True])
def test_a_cycles_frame_keeps_its_lamp_out_of_the_filter_by_default(tmp_path, capsys, merged):
    """Cycles' Denoising Albedo holds the lamp's emission (read clipped to [0, 1]), so
    `denoise` on a Cycles render, read directly or merged, runs the denoiser with
    emission=separate unless told otherwise: the output equals the explicit spec's and the
    note says so; `:emission=filter` keeps the old filter (a different image on the lamp)."""
    from jaxden.io.exr import read_image

    if merged:
        source = tmp_path / "merged.exr"
        renders = [CYCLES / f"passes-seed{s}.exr" for s in (1, 2)]
        assert run_cli(["merge", *renders, "--from", "cycles", "--out", source], capsys)[0] == 0
        reading: list[str] = []
    else:
        source, reading = PASSES, ["--from", "cycles"]

    def denoise(model, name):
        code, lines, _ = run_cli(["denoise", source, *reading, "--model", model, "--out",
                                  tmp_path / name], capsys)
        assert code == 0, lines
        return read_image(tmp_path / name), " ".join(lines)

    default, said = denoise("wskp-6", "default.exr")
    separate, said_explicit = denoise("wskp-6:emission=separate", "separate.exr")
    filtered, said_filter = denoise("wskp-6:emission=filter", "filter.exr")
    np.testing.assert_array_equal(default, separate)
    assert "wskp-6:emission=separate" in said and "emission is kept out of the filter" in said
    assert "kept out of the filter" not in said_explicit + said_filter
    lamp = read_frame(source, convention=None if merged else "cycles").emission.max(-1) > 0
    assert lamp.any() and not np.allclose(filtered[lamp], default[lamp], rtol=0.05)


def test_a_cycles_frame_without_an_emission_pass_is_filtered_as_before(tmp_path, capsys):
    path = _copy(tmp_path, PASSES, drop=("Emission",))
    code, lines, _ = run_cli(["denoise", path, "--from", "cycles", "--model", "wskp-6",
                              "--out", tmp_path / "d.exr"], capsys)
    assert code == 0 and "kept out of the filter" not in " ".join(lines), lines
