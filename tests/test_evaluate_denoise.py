"""jaxden.evaluate.denoise (the ``denoise`` and ``sequences`` evaluators): every row equals
the metrics computed directly on the same images; on frames with an emitter, the lamp pixels'
relMSE and mean ratio equal a NumPy computation of their definition, and data without emission
gets no lamp entry; temporal accumulation on a static-camera sequence of a fixed image beats
single frames; the sweep's [evaluate] denoise table reaches result.json and summary.md."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import run_cli

from jaxden import metrics
from jaxden.data.builder import build_dataset
from jaxden.data.config import DatasetConfig, SplitConfig
from jaxden.data.crops import iter_crops
from jaxden.denoise.registry import Denoiser, DenoiserDef
from jaxden.evaluate import denoise as report
from jaxden.render.synthetic import synthetic_render


def box3(params, config, frame):
    """A 3 x 3 box filter (edge-padded): a denoiser with a known output."""
    x = np.asarray(frame.color, np.float32)
    padded = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = x.shape[:2]
    return sum(padded[i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0


BOX = Denoiser(DenoiserDef("box3", "3x3 box", object, lambda c: ("color",), box3,
                           differentiable=False), None)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("rt")
    config = DatasetConfig(name="rt-tiny", scenes=("a", "b"), size=(32, 32), crop_size=16,
                           crops_per_scene=1, spp=(1, 4), reference_spp=64, seed=2,
                           splits=SplitConfig(train=0.0, val=0.0, test=1.0))
    build_dataset(config, out, render_fn=synthetic_render, progress=False)
    return out


def test_rows_equal_direct_metrics(dataset):
    rows = report.evaluate_denoiser(dataset, BOX, spp=(1,))
    assert len(rows) == 2 and all(r["spp"] == 1 for r in rows)
    crop, reference, [(spp, frame)] = next(iter_crops(dataset, "test", (1,), min_spp=1))
    assert spp == 1 and frame.variance is None
    row = rows[0]
    assert row["crop"] == crop.id
    denoised = box3(None, None, frame)
    assert row["den_psnr"] == pytest.approx(float(metrics.psnr(denoised, reference.color)))
    assert row["den_ssim"] == pytest.approx(float(metrics.ssim(denoised, reference.color)))
    assert row["den_relmse"] == pytest.approx(float(metrics.relmse(denoised, reference.color)))
    assert row["mc_flip"] == pytest.approx(float(metrics.flip(frame.color, reference.color)))
    nc = float(metrics.noise_corrected_mse(denoised, reference.color, reference.variance))
    assert row["den_mse_nc"] == pytest.approx(nc)
    # the box filter removes most of the per-pixel noise of this smooth image
    assert row["den_psnr"] > row["mc_psnr"] + 3
    summary = report.summarize(rows)
    assert summary["count"] == 2
    assert summary["den_psnr"] == pytest.approx(np.mean([r["den_psnr"] for r in rows]))
    assert summary["den_rmse_nc"] == pytest.approx(np.sqrt(max(summary["den_mse_nc"], 0)))
    table = report.markdown({"box": summary})
    assert f"{summary['den_psnr']:.2f}" in table


# ------------------------------------------------------------------------ lamp pixels
LAMP_CENTRE, LAMP_RADIUS = (16.0, 16.0), 4.0  # film pixels, of the 32 x 32 view
LAMP_RADIANCE = np.array([50.0, 40.0, 30.0], np.float32)


def lamp_render(scene, spp, seed=0, size=None, *, crop=None):
    """``synthetic_render`` with the emission: the view of scene ``lamp`` sees a disc emitter
    (every 16 x 16 crop of the 32 x 32 view sees part of it); each pixel's emission is
    LAMP_RADIANCE times the fraction of its ``spp`` samples that hit the disc (binomial in
    the pixel's coverage, so a 1-spp input sees an edge or not by chance), added to the
    colour. Other scenes have an emission of 0 everywhere."""
    frame = synthetic_render(scene, spp, seed, size, crop=crop)
    top, left, height, width = crop
    coverage = np.zeros((height, width))
    if scene == "lamp":  # the fraction of each pixel inside the disc, on an 8 x 8 grid
        sub = (np.arange(8) + 0.5) / 8
        ys = top + np.arange(height)[:, None, None, None] + sub[None, None, :, None]
        xs = left + np.arange(width)[None, :, None, None] + sub[None, None, None, :]
        inside = (ys - LAMP_CENTRE[0]) ** 2 + (xs - LAMP_CENTRE[1]) ** 2 < LAMP_RADIUS ** 2
        coverage = inside.mean(axis=(2, 3))
    hits = np.random.default_rng(seed + 1000).binomial(spp, coverage) / spp
    emission = (hits[..., None] * LAMP_RADIANCE).astype(np.float32)
    return frame.replace(color=(frame.color + emission).astype(np.float32), emission=emission)


@pytest.fixture(scope="module")
def lamp_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("lamp")
    config = DatasetConfig(name="lamp-tiny", scenes=("lamp", "dark"), size=(32, 32),
                           crop_size=16, crops_per_scene=2, spp=(1, 4), reference_spp=64,
                           seed=3, splits=SplitConfig(train=0.0, val=0.0, test=1.0))
    build_dataset(config, out, executor="serial", render_fn=lamp_render, progress=False)
    return out


def numpy_lamps(dataset, denoise, spp) -> dict:
    """The lamp numbers by their definition, in NumPy: over every (crop, spp) input, the
    pixels whose reference emission is > 0 in a channel; the mean over them of each pixel's
    mean over channels of (x - y)^2 / (y^2 + 0.01), and the mean of x over them divided by
    the mean of y."""
    errors, images, truths = [], [], []
    for _, reference, inputs in iter_crops(dataset, "test", spp, min_spp=1):
        y = np.asarray(reference.color, np.float64)
        mask = (np.asarray(reference.emission) > 0).any(axis=-1)
        for _, frame in inputs:
            x = np.asarray(denoise(frame), np.float64)
            errors.append((((x - y) ** 2) / (y ** 2 + 0.01)).mean(axis=-1)[mask])
            images.append(x[mask])
            truths.append(y[mask])
    return {"relmse": np.concatenate(errors).mean(), "pixels": sum(map(len, errors)),
            "ratio": np.concatenate(images).mean() / np.concatenate(truths).mean()}


def test_lamp_relmse_equals_numpy(lamp_dataset):
    """The lamp pixels are the reference's (not the 1-spp input's, which misses disc edges
    that the 64-spp reference sees); the summary pools every lamp pixel of the split's crops
    and spp levels, and the table and a sweep show them."""
    rows = report.evaluate_denoiser(lamp_dataset, BOX, spp=(1, 4))
    assert len(rows) == 8
    lit = [r for r in rows if r["scene"] == "lamp"]
    assert all(r["lamp_pixels"] > 0 for r in lit)
    dark = [r for r in rows if r["scene"] == "dark"]
    assert all(r["lamp_pixels"] == 0 and r["den_lamp_relmse"] is None for r in dark)
    _, reference, [(_, one), _] = next(iter_crops(lamp_dataset, "test", (1, 4), min_spp=1))
    assert not np.array_equal(report.lamp_mask(reference),
                              (np.asarray(one.emission) > 0).any(axis=-1))
    summary = report.summarize(rows)
    expected = numpy_lamps(lamp_dataset, lambda f: box3(None, None, f), (1, 4))
    assert summary["lamp_pixels"] == expected["pixels"]
    assert summary["den_lamp_relmse"] == pytest.approx(expected["relmse"], rel=1e-5)
    assert summary["den_lamp_ratio"] == pytest.approx(expected["ratio"], rel=1e-5)
    noisy = numpy_lamps(lamp_dataset, lambda f: f.color, (1, 4))
    assert summary["mc_lamp_relmse"] == pytest.approx(noisy["relmse"], rel=1e-5)
    assert summary["mc_lamp_ratio"] == pytest.approx(noisy["ratio"], rel=1e-5)
    # the other metrics are still plain means over the rows, lamp crops or not
    assert summary["den_relmse"] == pytest.approx(np.mean([r["den_relmse"] for r in rows]))
    # the box filter spreads the lamp onto its dark surroundings: dimmer lamp pixels
    assert summary["den_lamp_ratio"] < 0.95
    table = report.markdown({"box": summary}, prefixes=("den", "mc"))
    assert "| relMSE (lamps) | lamp mean / reference | lamp pixels |" in table.splitlines()[0]
    assert (f"| {summary['den_lamp_relmse']:.4f} | {summary['den_lamp_ratio']:.3f} | "
            f"{expected['pixels']} |") in table
    assert "Lamp pixels: those whose reference sees an emitter" in table
    columns = report.DENOISE.sweep_columns(summary)
    assert columns["lamp relMSE"] == summary["den_lamp_relmse"]


def test_lamp_columns_only_where_the_frames_carry_emission(dataset, lamp_dataset, tmp_path,
                                                           capsys):
    """`jaxden evaluate denoise`: OUT.json and OUT.md have the lamp entries on data with an
    emitter, and on data without emission (or without a lamp in the split) none: the rows,
    summary and table of before."""
    out = tmp_path / "lamp"
    code, _, _ = run_cli(["evaluate", "denoise", "--data", lamp_dataset, "--denoiser", "oidn",
                          "--out", out], capsys)
    assert code == 0
    result = json.loads(out.with_suffix(".json").read_text())
    assert result["summary"]["lamp_pixels"] == sum(r["lamp_pixels"] for r in result["rows"])
    assert {"den_lamp_relmse", "den_lamp_ratio", "mc_lamp_relmse"} <= set(result["summary"])
    assert "relMSE (lamps)" in out.with_suffix(".md").read_text()
    header = ("| method | PSNR (dB) | SSIM | relMSE | FLIP | RMSE (noise-corrected) |\n"
              "|---|---:|---:|---:|---:|---:|\n")
    for data, only_dark in ((dataset, False), (lamp_dataset, True)):
        rows = report.evaluate_denoiser(data, BOX, spp=(1,))
        if only_dark:  # emission, 0 everywhere: entries in the rows, no lamp in the summary
            rows = [r for r in rows if r["scene"] == "dark"]
            assert rows and all(r["lamp_pixels"] == 0 for r in rows)
        else:
            assert not [k for r in rows for k in r if "lamp" in k]
        summary = report.summarize(rows)
        assert not [k for k in summary if "lamp" in k]
        assert "lamp" not in json.dumps(report.DENOISE.sweep_columns(summary))
        table = report.markdown({"box": summary}, prefixes=("den", "mc"))
        assert table.startswith(header) and len(table.splitlines()) == 4, table
    code, _, _ = run_cli(["evaluate", "denoise", "--data", dataset, "--denoiser", "oidn",
                          "--out", tmp_path / "plain"], capsys)
    assert code == 0
    result = json.loads((tmp_path / "plain.json").read_text())
    assert "lamp" not in json.dumps([result["rows"], result["summary"]])
    text = (tmp_path / "plain.md").read_text()
    assert text.split("\n", 1)[1].startswith(header) and len(text.splitlines()) == 5


def test_finetune_gain_shows_the_lamps_of_both_reports(lamp_dataset, tmp_path):
    """experiments/finetune_gain.py on two reports with lamp entries: per spp and over all,
    each model's lamp relMSE and lamp mean ratio, pooled as the evaluator's summary pools
    them; without lamp entries in one report, no lamp column."""
    from helpers import load_script

    finetune_gain = load_script("finetune_gain")
    reports = {}
    for name, model in (("stock", BOX), ("tuned", Denoiser(DenoiserDef(
            "same", "identity", object, lambda c: ("color",),
            lambda p, c, f: np.asarray(f.color), differentiable=False), None))):
        rows = report.evaluate_denoiser(lamp_dataset, model, spp=(1, 4), include_input=False)
        reports[name] = tmp_path / f"{name}.json"
        reports[name].write_text(json.dumps({"rows": rows, "provenance": {
            "dataset": {"manifest_sha256": "abc", "dir": "d", "split": "test"},
            "denoiser": {"spec": name}}}))
    out = tmp_path / "gain"
    assert finetune_gain.main(["--stock", str(reports["stock"]), "--tuned",
                               str(reports["tuned"]), "--out", str(out)]) == 0
    table = json.loads(out.with_suffix(".json").read_text())["per_spp"]
    stock = report.summarize(json.loads(reports["stock"].read_text())["rows"])
    assert table["all"]["stock_lamp_relmse"] == pytest.approx(stock["den_lamp_relmse"])
    assert table["all"]["stock_lamp_ratio"] == pytest.approx(stock["den_lamp_ratio"])
    assert table["all"]["lamp_pixels"] == stock["lamp_pixels"]
    one = [r for r in json.loads(reports["tuned"].read_text())["rows"] if r["spp"] == 1]
    assert table["1"]["tuned_lamp_relmse"] == pytest.approx(
        numpy_lamps(lamp_dataset, lambda f: f.color, (1,))["relmse"], rel=1e-5)
    assert table["1"]["lamp_pixels"] == sum(r["lamp_pixels"] for r in one)
    text = out.with_suffix(".md").read_text()
    assert ("| relMSE on lamps: stock | fine-tuned | lamp mean / reference: stock | "
            "fine-tuned | lamp pixels |") in text
    assert (f"| {table['all']['stock_lamp_relmse']:.4f} | {table['all']['tuned_lamp_relmse']:.4f}"
            f" | {table['all']['stock_lamp_ratio']:.3f} | {table['all']['tuned_lamp_ratio']:.3f}"
            f" | {stock['lamp_pixels']} |") in text
    plain = json.loads(reports["tuned"].read_text())
    plain["rows"] = [{k: v for k, v in r.items() if "lamp" not in k} for r in plain["rows"]]
    reports["tuned"].write_text(json.dumps(plain))
    assert finetune_gain.main(["--stock", str(reports["stock"]), "--tuned",
                               str(reports["tuned"]), "--out", str(out)]) == 0
    assert "lamp" not in out.with_suffix(".md").read_text().split("\n", 1)[1]


@pytest.mark.slow  # ~20 s; test_temporal.py tests accumulation, rt-main measures it on rt-seq
def test_temporal_accumulation_beats_single_frames(tmp_path):
    """A static camera (orbit of 0 degrees): accumulation averages the frames, so its input
    error falls about as 1 / frames, and the denoised accumulated frames beat the single ones.
    (At 24 x 24 a pixel spans ~3 % of the depth and 1-spp positions jitter within it: the
    position test gets a tolerance above that.)"""
    from jaxden.data.sequences import SequenceConfig, build_sequences
    from jaxden.denoise.temporal import TemporalConfig

    config = SequenceConfig(scenes=("cornell-box",), size=(24, 24), frames=6, spp=1,
                            reference_spp=64, seed=1, path="orbit", rotation_deg=0.0)
    build_sequences(config, tmp_path, progress=False)
    rows = report.evaluate_sequences(tmp_path, BOX,
                                      temporal=TemporalConfig(position_tolerance=0.1))
    assert [r["frame"] for r in rows] == [1, 2, 3, 4, 5]
    last = rows[-1]
    assert last["acc_mse_nc"] < 0.5 * last["mc_mse_nc"]
    summary = report.summarize(rows)
    assert summary["tdn_mse_nc"] < summary["den_mse_nc"]
