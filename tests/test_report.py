"""Tests for jaxden.report (the library side of `jaxden report`): the naming convention and
its errors, the tone map and colour maps, the page's pixel encoding, the error maps against
NumPy, the convergence plot, and the page as a whole (self-contained, data that decodes back).
The page in a real browser: tests/test_report_browser.py."""

from __future__ import annotations

import argparse
import base64
import json
import re

import numpy as np
import pytest

from jaxden.errors import ExrError, JaxdenError
from jaxden.io.exr import write_channels, write_image
from jaxden.io.png import preview
from jaxden.report import ReportError, build_report, discover, encode, errormaps, figures, tonemap
from jaxden.report.discover import mean_rows, parse_image_name, pd_report_rows

SIZE = 32


def synthetic_images(seed: int = 0, size: int = SIZE, levels=(4, 16)):
    """A smooth HDR reference and, per spp, noisy MC and two 'denoised' variants."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    reference = np.stack([0.2 + 0.8 * x, 0.1 + 0.5 * y, 0.3 + 0.2 * x * y], -1)
    reference[size // 4: size // 2, size // 4: size // 2] = 6.0  # a bright "light"
    images = {}
    for spp in levels:
        noise = rng.normal(size=reference.shape) * reference / np.sqrt(spp)
        images[spp, "mc"] = reference + noise
        images[spp, "blur"] = reference * 0.97 + 0.2 * noise
        images[spp, "mix"] = reference + 0.5 * noise
    return reference.astype(np.float32), {k: v.astype(np.float32) for k, v in images.items()}


def write_scene(folder, seed: int = 0, alpha: bool = True, levels=(4, 16),
                methods=("mc", "blur", "mix")):
    """A scene folder of the report's convention; returns (reference, images)."""
    folder.mkdir(parents=True, exist_ok=True)
    reference, images = synthetic_images(seed, levels=levels)
    write_image(folder / "reference.exr", reference)
    for (spp, method), image in images.items():
        if method not in methods:
            continue
        name = f"spp{spp:05d}.exr" if method == "mc" else f"spp{spp}.{method}.exr"
        write_image(folder / name, image)
        if alpha and method == "mix":
            write_image(folder / f"spp{spp}.mix.alpha.exr",
                        np.full((SIZE, SIZE, 3), 0.25 * spp / 16, np.float32))
    return reference, images


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp("results")
    write_scene(root / "scene-a", seed=0)
    write_scene(root / "scene-b", seed=1, alpha=False)
    return root


@pytest.fixture(scope="module")
def page(results):
    """The report over ``results`` and its embedded JSON."""
    path = build_report(results, results / "report.html")
    text = path.read_text()
    data = json.loads(re.search(r'<script type="application/json" id="jaxden-data">(.*?)'
                                r"</script>", text, re.DOTALL).group(1))
    return text, data


# ----------------------------------------------------------------------- naming convention
@pytest.mark.parametrize("name, parsed", [
    ("spp4.exr", (4, "mc", False)), ("spp00004.exr", (4, "mc", False)),
    ("spp0100.oidn.exr", (100, "oidn", False)), ("spp16.pd_oidn.alpha.exr", (16, "pd_oidn", True)),
    ("spp8.my-method.exr", (8, "my-method", False)), ("spp0.exr", None), ("spp.exr", None),
    ("spp4.alpha.exr", None), ("ref.exr", None), ("spp4.oidn.png", None),
    ("spp4.a.b.exr", None)])
def test_image_names(name, parsed):
    assert parse_image_name(name) == parsed


def test_discover_finds_scenes_methods_and_alpha(results):
    (results / "scene-a" / "notes.exr").write_bytes(b"")  # not of the convention: ignored
    found = discover(results)
    (results / "scene-a" / "notes.exr").unlink()
    assert [s.name for s in found.scenes] == ["scene-a", "scene-b"]
    a = found.scenes[0]
    assert a.spp_levels == [4, 16] and a.methods == ["mc", "blur", "mix"]
    assert set(a.alphas) == {(4, "mix"), (16, "mix")} and not found.scenes[1].alphas
    assert a.images[4, "mc"].name == "spp00004.exr"
    assert [p.name for p in found.ignored] == ["notes.exr"]


def test_a_scene_folder_itself_is_a_report(results):
    found = discover(results / "scene-b")
    assert [s.name for s in found.scenes] == ["scene-b"]


@pytest.mark.parametrize("case", ["missing", "empty", "nothing", "no-reference", "no-images",
                                  "duplicate", "orphan-alpha", "not-a-report-json"])
def test_bad_input_is_a_one_line_error_naming_the_path(tmp_path, case):
    target = tmp_path / "dir"
    if case != "missing":
        target.mkdir()
    if case == "nothing":
        (target / "readme.txt").write_text("hi")
    image = np.ones((4, 4, 3), np.float32)
    if case in ("no-reference", "duplicate", "orphan-alpha"):
        write_image(target / "spp4.exr", image)
    if case in ("no-images", "duplicate", "orphan-alpha"):
        write_image(target / "reference.exr", image)
    if case == "duplicate":
        write_image(target / "spp0004.exr", image)
    if case == "orphan-alpha":
        write_image(target / "spp4.den.alpha.exr", image)
    if case == "not-a-report-json":
        target = tmp_path / "other.json"
        target.write_text(json.dumps({"rows": {"a": 1}}))
    with pytest.raises(ReportError) as error:
        discover(target)
    message = str(error.value)
    assert "\n" not in message and str(target) in message
    expected = {"missing": "no such file", "empty": "is empty", "nothing": "nothing a report",
                "no-reference": "no reference.exr", "no-images": "no sppN",
                "duplicate": "names the same image", "orphan-alpha": "without its image",
                "not-a-report-json": "jaxden evaluate pd"}[case]
    assert expected in message
    assert isinstance(error.value, JaxdenError)


def test_unreadable_or_wrong_images_name_the_file(tmp_path):
    folder = tmp_path / "s"
    write_scene(folder, alpha=False, levels=(4,), methods=("mc", "blur"))
    bad = folder / "spp4.blur.exr"
    bad.write_bytes(b"not an exr at all")
    with pytest.raises(ExrError, match=re.escape(str(bad))) as error:
        build_report(folder, tmp_path / "r.html")
    assert "\n" not in str(error.value) and not (tmp_path / "r.html").exists()
    write_image(bad, np.ones((8, 8, 3), np.float32))
    with pytest.raises(ReportError, match=re.escape(str(bad)) + ".*8x8 pixels.*32x32"):
        build_report(folder, tmp_path / "r.html")
    nan = np.full((SIZE, SIZE), np.nan, np.float32)  # as another tool might write it
    write_channels(bad, {c: nan for c in "RGB"}, allow_nonfinite=True)
    with pytest.raises(ReportError, match=re.escape(str(bad)) + ": 3072 NaN"):
        build_report(folder, tmp_path / "r.html")


# ------------------------------------------------------------------------ display transforms
def test_tonemap_is_the_png_preview_at_the_exposure():
    image = np.random.default_rng(0).uniform(0, 4, (5, 6, 3))
    np.testing.assert_array_equal(tonemap.tonemap(image, 0.0), preview(image, 1.0))
    np.testing.assert_array_equal(tonemap.tonemap(image, -1.5), preview(image, 2 ** -1.5))
    assert tonemap.exposure(3) == 8.0


def test_auto_stops_brings_the_log_average_to_middle_grey():
    assert tonemap.auto_stops(np.full((4, 4, 3), 0.18)) == 0.0
    assert tonemap.auto_stops(np.full((4, 4, 3), 0.18 / 8)) == 3.0
    assert tonemap.auto_stops(np.full((4, 4, 3), 0.18 * 3)) == -2.0  # rounded down, 0.5 steps
    light = np.full((10, 10, 3), 0.18)
    light[0, :3] = 1e4  # a few very bright pixels hardly move it
    assert tonemap.auto_stops(light) == -0.5
    assert tonemap.auto_stops(np.zeros((4, 4, 3))) == 0.0


def test_false_colour_scale_and_ends():
    table = tonemap.colormap_table("viridis")
    assert table.shape == (256, 3) and table.dtype == np.uint8
    values = np.array([[1e-6, 1e-4], [1e-2, 5.0]])
    position = tonemap.map_position(values, 1e-4, 1.0, log=True)
    np.testing.assert_allclose(position, [[0, 0], [0.5, 1]])
    coloured = tonemap.false_colour(values, 1e-4, 1.0, log=True)
    np.testing.assert_array_equal(coloured[0, 0], table[0])
    np.testing.assert_array_equal(coloured[1, 1], table[255])
    np.testing.assert_array_equal(coloured[1, 0], table[128])
    np.testing.assert_allclose(tonemap.map_position(np.array([0.25]), 0, 1, log=False), [0.25])
    assert tonemap.log_range([np.array([0.003, 0.02, 0.04])], decades=3) == (1e-4, 0.1)


def test_alpha_preview():
    alpha = np.array([[0.0, 0.5, 1.0]])[..., None]
    np.testing.assert_array_equal(tonemap.alpha_preview(alpha)[0, :, 0], [0, 128, 255])


# ----------------------------------------------------------------------------- page pixels
def test_encoding_round_trip():
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 3, (7, 5, 3)).astype(np.float32)
    blob = encode.encode_array(image, "f16")
    assert blob["shape"] == [7, 5, 3] and blob["dtype"] == "f16"
    np.testing.assert_array_equal(encode.decode_array(blob), image.astype(np.float16))
    np.testing.assert_array_equal(encode.decode_array(encode.encode_array(image, "f32")), image)
    big = np.array([[1e6, np.nan, -np.inf]])
    np.testing.assert_array_equal(encode.decode_array(encode.encode_array(big)),
                                  [[65504, 0, -65504]])


def test_display_downsampling():
    assert encode.display_factor(100, 300, 1024) == 1
    assert encode.display_factor(1080, 1920, 1024) == 2
    assert encode.display_factor(10, 10, None) == 1
    array = np.arange(5 * 4, dtype=float).reshape(5, 4)
    np.testing.assert_array_equal(encode.downsample(array, 2), [[2.5, 4.5], [10.5, 12.5]])


# ---------------------------------------------------------------------------- error maps
def test_relative_squared_error_matches_numpy_and_relmse():
    from jaxden import metrics

    reference, images = synthetic_images()
    image = images[4, "mc"]
    relse = errormaps.relative_squared_error(image, reference)
    x, r = image.astype(np.float64), reference.astype(np.float64)
    expected = ((x - r) ** 2 / (r ** 2 + 0.01)).mean(axis=-1)
    assert relse.shape == (SIZE, SIZE)
    np.testing.assert_allclose(relse, expected, rtol=1e-12)
    np.testing.assert_allclose(relse.mean(), float(metrics.relmse(image, reference)), rtol=1e-5)
    with pytest.raises(JaxdenError, match="same"):
        errormaps.relative_squared_error(image, reference[:-1])


def test_flip_map_is_flips_per_pixel_error():
    from jaxden import metrics

    reference, images = synthetic_images()
    mean, flip_values = errormaps.flip_map(images[4, "mc"], reference)
    assert flip_values.shape == (SIZE, SIZE)
    assert 0 <= flip_values.min() and flip_values.max() <= 1
    assert mean == pytest.approx(float(metrics.flip(images[4, "mc"], reference)), rel=1e-6)
    assert flip_values.mean() == pytest.approx(mean, rel=1e-4)
    same_mean, same = errormaps.flip_map(reference, reference)
    assert same_mean == 0 and not same.any()


def test_image_metrics_and_best():
    reference, images = synthetic_images()
    values = errormaps.image_metrics(images[4, "mc"], reference)
    assert set(values) == {"relmse", "smape", "rmse", "flip", "psnr", "ssim"}
    rows = [{"spp": 4, "method": m, **errormaps.image_metrics(images[4, m], reference)}
            for m in ("mc", "mix")]
    assert errormaps.best_methods(rows, "rmse") == {4: "mix"}
    assert errormaps.best_methods(rows, "psnr") == {4: "mix"}  # higher is better


# ------------------------------------------------------------------------------ the plot
def _rows():
    return [{"scene": "s", "spp": spp, "method": method, "relmse": value / spp,
             "rmse": value / spp ** 0.5, "flip": 0.3 / spp ** 0.3}
            for spp in (4, 16, 64) for method, value in (("mc", 1.0), ("den", 0.2))]


def test_convergence_figure_has_log_axes_and_the_mc_guide():
    figure = figures.convergence_figure(_rows())
    axes = figure.axes
    assert [a.get_ylabel() for a in axes] == ["relMSE", "RMSE", "FLIP"]
    assert all(a.get_xscale() == "log" and a.get_yscale() == "log" for a in axes)
    for ax, rate in zip(axes, (1.0, 0.5, None)):
        labels = [line.get_label() for line in ax.get_lines()]
        assert labels[:2] == ["mc", "den"]
        guides = [line for line in ax.get_lines() if line.get_label().startswith("∝")]
        if rate is None:
            assert not guides
            continue
        x, y = (np.asarray(v, float) for v in guides[0].get_data())
        slope = np.diff(np.log(y)) / np.diff(np.log(x))
        np.testing.assert_allclose(slope, -rate)
        mc_x, mc_y = ax.get_lines()[0].get_data()
        assert (x[0], y[0]) == (mc_x[0], mc_y[0])  # through MC's first point


def test_figures_render_reproducibly():
    svg = figures.svg_bytes(figures.convergence_figure(_rows()))
    assert svg.lstrip().startswith(b"<?xml") and b"<svg" in svg
    assert svg == figures.svg_bytes(figures.convergence_figure(_rows()))
    png = figures.png_bytes(figures.convergence_figure(_rows()))
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


# ------------------------------------------------------------------------------ the page
def test_page_is_self_contained(page):
    text, _ = page
    assert text.startswith("<!DOCTYPE html>")
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:|//)""", text)
    assert "<script src" not in text and 'rel="stylesheet"' not in text
    assert "@import" not in text and "url(http" not in text
    for name in ("scene-a", "scene-b", 'data-control="split"', 'data-control="stops"',
                 'data-control="a"', 'data-control="b"', "data-colorbar", "Mixer alpha"):
        assert name in text


def test_page_data_decodes_to_the_images_and_maps(results, page):
    _, data = page
    scene = data["scenes"][0]
    reference, images = synthetic_images(0)
    assert (scene["name"], scene["width"], scene["height"]) == ("scene-a", SIZE, SIZE)
    assert scene["spp"] == [4, 16] and scene["methods"] == ["mc", "blur", "mix"]
    arrays = scene["arrays"]
    np.testing.assert_array_equal(encode.decode_array(arrays["reference"]),
                                  reference.astype(np.float16))
    np.testing.assert_array_equal(encode.decode_array(arrays["16/blur"]),
                                  images[16, "blur"].astype(np.float16))
    np.testing.assert_allclose(encode.decode_array(arrays["relse/4/mc"]),
                               errormaps.relative_squared_error(images[4, "mc"], reference),
                               rtol=1e-6)
    np.testing.assert_allclose(encode.decode_array(arrays["alpha/16/mix"]), 0.25)
    assert "alpha/4/mc" not in arrays and "alpha/4/mix" not in data["scenes"][1]["arrays"]
    assert scene["stops"] == tonemap.auto_stops(reference)
    relse = scene["layers"]["relse"]
    assert relse["scale"] == "log" and relse["high"] / relse["low"] == pytest.approx(1e4)
    assert scene["layers"]["flip"]["colormap"] == "magma"
    row = next(r for r in scene["rows"] if (r["spp"], r["method"]) == (4, "mix"))
    expected = errormaps.image_metrics(images[4, "mix"], reference)
    assert row == pytest.approx({"scene": "scene-a", "spp": 4, "method": "mix", **expected})
    cmap = np.frombuffer(base64.b64decode(data["colormaps"]["magma"]), np.uint8)
    np.testing.assert_array_equal(cmap.reshape(256, 3), tonemap.colormap_table("magma"))


def test_page_embeds_one_plot_per_scene(page):
    text, _ = page
    plots = re.findall(r'<img class="plot"[^>]*src="data:image/svg\+xml;base64,([^"]+)"', text)
    assert len(plots) == 2
    assert b"samples per pixel" in base64.b64decode(plots[0])


def test_large_images_are_shown_smaller(tmp_path):
    write_scene(tmp_path / "s", alpha=False, levels=(4,), methods=("mc",))
    build_report(tmp_path / "s", tmp_path / "r.html", max_size=16)
    text = (tmp_path / "r.html").read_text()
    data = json.loads(re.search(r'id="jaxden-data">(.*?)</script>', text, re.DOTALL).group(1))
    scene = data["scenes"][0]
    assert (scene["width"], scene["factor"]) == (16, 2)
    assert encode.decode_array(scene["arrays"]["4/mc"]).shape == (16, 16, 3)
    assert "1/2 resolution" in text


# -------------------------------------------------------------------------- pd_report JSON
def _pd_report(path):
    rows = []
    for crop in ("s000-c000", "s001-c000"):
        for spp in (2, 8, 32):
            row = {"crop": crop, "spp": spp, "scene": "procedural:1", "alpha": 0.5}
            for method, scale in (("mc", 1.0), ("denoiser", 0.3), ("pd", 0.25)):
                row.update({f"{method}_rmse": scale / spp ** 0.5,
                            f"{method}_rmse_nc": scale / spp ** 0.5,
                            f"{method}_relmse": scale / spp, f"{method}_flip": 0.2 * scale,
                            f"{method}_mse_nc": scale ** 2 / spp})
            rows.append(row)
    path.write_text(json.dumps({"rows": rows, "summary": {},
                                "provenance": {"denoiser": "oidn", "command": "x"}}))


def test_pd_report_rows_and_means(tmp_path):
    _pd_report(tmp_path / "pd.json")
    long_rows, metrics = pd_report_rows(json.loads((tmp_path / "pd.json").read_text()))
    assert set(metrics) == {"rmse", "rmse_nc", "relmse", "flip", "mse_nc"}
    assert {r["method"] for r in long_rows} == {"mc", "denoiser", "pd"}
    means = mean_rows(long_rows, "pd")
    assert len(means) == 9
    assert next(r for r in means if (r["spp"], r["method"]) == (8, "pd"))["relmse"] == 0.25 / 8
    assert pd_report_rows({"rows": {"oidn": []}}) is None  # a SURE report: not this kind


def test_report_of_a_pd_report_json(tmp_path):
    _pd_report(tmp_path / "pd-oidn.json")
    (tmp_path / "summary.json").write_text("{}")  # other JSON in the folder is skipped
    for source, out in ((tmp_path / "pd-oidn.json", tmp_path / "pd-oidn.html"),
                        (tmp_path, tmp_path / "report.html")):
        path = build_report(source)
        assert path == out
        text = path.read_text()
        assert "pd-oidn" in text and "mean over 2 crops" in text and "data:image/svg+xml" in text
        assert text.count("<tr>") == 1 + 9  # header + spp x method


# ---------------------------------------------------------------------------------- CLI
def run_cli(argv, capsys=None) -> int:
    """``jaxden report ...`` through jaxden.cli.main once wired there, else through the
    command group's own parser with main()'s error handling."""
    from jaxden import cli
    from jaxden.cli import report as report_cli

    parser = cli.build_parser()
    if "report" in parser._subparsers._group_actions[0].choices:
        return cli.main(argv)
    parser = argparse.ArgumentParser(prog="jaxden")
    report_cli.add_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except JaxdenError as error:
        print(f"jaxden: error: {error}", file=__import__("sys").stderr)
        return 2


def test_cli_writes_the_page_and_names_it(capsys, tmp_path):
    out = tmp_path / "page.html"
    write_scene(tmp_path / "s", alpha=False, levels=(4,), methods=("mc",))
    (tmp_path / "s" / "extra.exr").write_bytes(b"")
    assert run_cli(["report", str(tmp_path / "s"), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert f"wrote {out} (1 scene," in captured.out
    assert "ignored 1 .exr file(s)" in captured.err and "extra.exr" in captured.err
    assert out.stat().st_size > 10_000


def test_cli_errors_are_one_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert run_cli(["report", str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("jaxden: error: ") and "empty" in err
    write_scene(tmp_path / "s", alpha=False, levels=(4,), methods=("mc",))
    assert run_cli(["report", str(tmp_path / "s"), "--out", str(tmp_path / "r.txt")]) == 2
    assert ".html" in capsys.readouterr().err
    assert run_cli(["report", str(tmp_path / "s"), "--out", str(tmp_path / "no" / "r.html")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_cli_help_documents_the_convention(capsys):
    with pytest.raises(SystemExit):
        run_cli(["report", "--help"])
    text = capsys.readouterr().out
    for part in ("SCENE/reference.exr", "SCENE/sppN.exr", "sppN.METHOD.exr",
                 "sppN.METHOD.alpha.exr", "jaxden evaluate pd"):
        assert part in text


# ------------------------------------------------------------------------ training runs
def _curve_points(svg: str, key: str) -> np.ndarray:
    """The (x, y) vertices of the line with SVG id ``curve-KEY`` (matplotlib's path data)."""
    group = re.search(rf'<g id="curve-{re.escape(key)}">(.*?)</g>', svg, re.DOTALL).group(1)
    path = re.search(r'<path d="([^"]*)"', group).group(1)
    return np.array([[float(a), float(b)]
                     for a, b in re.findall(r"[ML] ?([-0-9.e]+) ([-0-9.e]+)", path)])


def test_report_draws_a_runs_training_curves(tmp_path):
    from jaxden.train.workdir import MetricsLog

    run = tmp_path / "runs" / "tiny-run"
    run.mkdir(parents=True)
    log = MetricsLog(run / "metrics.jsonl", 0)  # as jaxden train writes it
    log.write({"step": 0, "val_loss": 0.5, "val_baseline_loss": 0.9})
    for step in range(1, 13):
        log.write({"step": step, "loss": 1.0 / step, "grad_norm": 1.0, "lr": 1e-3,
                   "seconds": 0.1})
        if step % 6 == 0:
            log.write({"step": step, "val_loss": 0.5 / step, "val_baseline_loss": 0.9})
    (run / "checkpoints").mkdir()
    for source in (tmp_path / "runs", run):  # a folder of runs, or the workdir itself
        text = build_report(source, tmp_path / "r.html").read_text()
        assert "tiny-run (training)" in text and 'href="#run-0"' in text
        plots = re.findall(r'<img class="plot" alt="training curves of tiny-run" '
                           r'src="data:image/svg\+xml;base64,([^"]+)"', text)
        assert len(plots) == 1
        svg = base64.b64decode(plots[0]).decode()
        loss = _curve_points(svg, "loss")
        assert len(loss) == 12
        assert len(_curve_points(svg, "val_loss")) == len(_curve_points(
            svg, "val_baseline_loss")) == 3
        # x is linear in the step, y in log(loss): the loss 1/step spans 12x (log scale)
        steps = np.arange(1, 13)
        for column, against in ((0, steps), (1, np.log(1.0 / steps))):
            fit = np.polyval(np.polyfit(against, loss[:, column], 1), against)
            np.testing.assert_allclose(loss[:, column], fit, atol=0.05)
        assert "last values: loss 0.08333 (step 12)" in text
    narrow = figures.training_figure({"loss": [(1, 0.3), (2, 0.2)]})
    wide = figures.training_figure({"loss": [(1, 1.0), (2, 0.1)]})
    assert (narrow.axes[0].get_yscale(), wide.axes[0].get_yscale()) == ("linear", "log")
    with (run / "metrics.jsonl").open("a") as handle:
        handle.write("garbage\n")
    with pytest.raises(ReportError, match=r"metrics.jsonl: line 16 .*not valid JSON"):
        build_report(run, tmp_path / "r.html")
