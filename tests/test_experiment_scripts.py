"""The experiment scripts that stay in experiments/ (pd_figure, mixer_alpha, ship_mixer,
relmse_crops, pd_ood, ...) and what they share through the package (provenance, the SURE
check, the cross-fitted oracle), tested without data or renders. The scripts are loaded from
their files (helpers.load_script); none imports another."""

import json
import math
import shutil
import sys
import xml.etree.ElementTree as ET
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest
from helpers import load_script

pd_figure = load_script("pd_figure")  # the experiment scripts are part of the repository: no skip


def _rows():
    rows = []
    for crop, scale in (("a", 1.0), ("b", 3.0)):
        for spp in (32, 64, 128):
            row = {"crop": crop, "spp": spp}
            for i, (method, _, _) in enumerate(pd_figure.METHODS):
                for metric, _ in pd_figure.PANELS:
                    row[f"{method}_{metric}"] = scale * (i + 1) * 0.01 * 32 / spp
            rows.append(row)
    return rows


def test_mean_curves_average_over_crops():
    curves = pd_figure.mean_curves(_rows())
    # mean of scale 1 and 3 = 2; MC is method 0
    assert curves["rmse"]["mc"] == [(32, pytest.approx(0.02)), (64, pytest.approx(0.01)),
                                     (128, pytest.approx(0.005))]
    assert curves["relmse"]["oracle"][0] == (32, pytest.approx(0.08))


def test_svg_plot_is_valid_and_maps_log_values_to_ticks():
    svg = pd_figure.svg_plot(pd_figure.mean_curves(_rows()), "t")
    root = ET.fromstring(svg)
    ns = "{http://www.w3.org/2000/svg}"
    lines = root.findall(f"{ns}polyline")
    assert len(lines) == len(pd_figure.PANELS) * len(pd_figure.METHODS)
    # the 1e-02 tick label and MC's point at 64 spp (value 0.01) sit at the same height
    ticks = {t.text: float(t.get("y")) - 4 for t in root.findall(f"{ns}text")
             if t.get("text-anchor") == "end"}
    mc = [tuple(map(float, p.split(","))) for p in lines[0].get("points").split()]
    assert mc[1][1] == pytest.approx(ticks["1e-02"], abs=0.06)
    assert mc[0][0] < mc[1][0] < mc[2][0] and mc[0][1] < mc[1][1] < mc[2][1]  # falls with spp


def test_mixer_alpha_worst_pixels_finds_the_largest_errors():
    mixer_alpha = load_script("mixer_alpha")

    truth = np.zeros((4, 5, 3))
    x = np.ones((4, 5, 3))
    z = np.zeros((4, 5, 3))
    z[1, 2] = 3.0  # the worst pixel
    z[3, 4, 0] = 2.0  # the second worst
    alphas = {"a": np.full((4, 5, 3), 0.25)}
    got = mixer_alpha.worst_pixels(truth, x, 2 * x, 3 * x, 4 * x, alphas, z, 2)
    assert [p["pixel"] for p in got] == [[1, 2], [3, 4]]
    assert got[0]["error"] == pytest.approx(np.sqrt(27)) and got[1]["error"] == pytest.approx(2)
    assert (got[0]["x"], got[0]["y"], got[0]["var"], got[0]["sure"], got[0]["a"]) == (
        1.0, 2.0, 3.0, 4.0, 0.25)
    assert got[0]["reference"] == 0.0


def test_ship_mixer_card_describes_the_head():
    ship_mixer = load_script("ship_mixer")

    bounded = ship_mixer._head_text({"head": "closed_form_logit", "logit_bound": 4.0,
                                     "logit_eps": 1e-4, "closed_form_sigma": 12.0})
    assert "4 tanh(raw / 4)" in bounded and "12.0 px" in bounded and "[0.0001, 1 - 0.0001]" in bounded
    unbounded = ship_mixer._head_text({"head": "closed_form_logit", "logit_bound": None,
                                       "logit_eps": 1e-3, "closed_form_sigma": 12.0})
    assert "logit(alpha_cf) + raw)" in unbounded and "brightness" not in unbounded
    strata = ship_mixer._head_text({"head": "closed_form_logit", "logit_bound": 4.0,
                                    "logit_eps": 1e-4, "closed_form_sigma": 12.0,
                                    "closed_form_stops": 1.0})
    assert "similar brightness (strata 1 stops wide" in strata
    assert "f_act" in ship_mixer._head_text({"head": "f_act"})
    assert "w/o f_act" in ship_mixer._head_text({"head": "sigmoid"})


def test_ship_mixer_reship_sets_inference_fields_and_keeps_the_weights(tmp_path, monkeypatch):
    """--reship re-exports shipped weights without their run: the parameters byte for byte,
    the training facts (read back from the card for weights shipped before training_facts),
    the --set field changed in the shipped config and stated in the card."""
    import shutil

    ship_mixer = load_script("ship_mixer")

    import jaxden.denoise.registry
    from jaxden import progressive as P

    for suffix in (".msgpack", ".json", ".md"):
        shutil.copy(jaxden.denoise.registry.WEIGHTS_DIR / f"oidn-pd{suffix}", tmp_path)
    meta = json.loads((tmp_path / "oidn-pd.json").read_text())
    meta.pop("training_facts", None)  # as shipped before commit ff78750: facts from the card
    meta.pop("inference_overrides", None)
    meta["pyoidn_version"] = "unknown"  # as recorded before the version was read from metadata
    (tmp_path / "oidn-pd.json").write_text(json.dumps(meta))
    original_card = (tmp_path / "oidn-pd.md").read_text()
    validation = next(line for line in original_card.splitlines() if "- Validation" in line)
    _, original_config = P.load_mixer(str(tmp_path / "oidn-pd.msgpack"))
    weights = (tmp_path / "oidn-pd.msgpack").read_bytes()
    monkeypatch.setattr(jaxden.denoise.registry, "WEIGHTS_DIR", tmp_path)
    root = Path(__file__).parent.parent
    monkeypatch.chdir(root)
    assert ship_mixer.main(["--reship", "oidn-pd", "--set", "closed_form_stops=2",
                            "--config", meta["train_config_file"]]) == 0
    assert (tmp_path / "oidn-pd.msgpack").read_bytes() == weights
    shipped = json.loads((tmp_path / "oidn-pd.json").read_text())
    assert shipped["inference_overrides"] == ["closed_form_stops=2"]
    assert shipped["model_config"]["closed_form_stops"] == 2.0
    assert shipped["train_config"] == meta["train_config"]
    assert shipped["jaxden_commit"] == meta["jaxden_commit"] and shipped["reshipped_commit"]
    installed = version("pyoidn")
    assert shipped["pyoidn_version"] == installed and "pyoidn_version_trained" not in shipped
    facts = shipped["training_facts"]
    assert facts["steps"] == meta["trained_steps"] and facts["val_metric"] == "smape"
    assert facts["dataset_config"]["crop_size"] == 128
    _, config = P.load_mixer(str(tmp_path / "oidn-pd.msgpack"))
    import dataclasses

    assert config == dataclasses.replace(original_config, closed_form_stops=2.0)
    card = (tmp_path / "oidn-pd.md").read_text()
    assert validation in card  # the training facts survive the round trip exactly
    assert "Shipped with `closed_form_stops=2` set at inference" in card
    assert "--set closed_form_stops=2" in card
    assert f"OIDN via pyoidn {installed} (CPU" in card
    # A second re-ship reads the recorded facts and keeps the recorded overrides.
    assert ship_mixer.main(["--reship", "oidn-pd", "--config", meta["train_config_file"]]) == 0
    assert json.loads((tmp_path / "oidn-pd.json").read_text())["inference_overrides"] == [
        "closed_form_stops=2"]
    assert (tmp_path / "oidn-pd.md").read_text() == card


def test_ship_mixer_reship_keeps_a_known_training_version(tmp_path, monkeypatch):
    """Weights trained with another pyoidn than the installed one say so in .json and card."""
    import shutil

    ship_mixer = load_script("ship_mixer")

    import jaxden.denoise.registry

    for suffix in (".msgpack", ".json", ".md"):
        shutil.copy(jaxden.denoise.registry.WEIGHTS_DIR / f"oidn-pd{suffix}", tmp_path)
    meta = json.loads((tmp_path / "oidn-pd.json").read_text())
    meta["pyoidn_version"] = "0.0.1"
    (tmp_path / "oidn-pd.json").write_text(json.dumps(meta))
    monkeypatch.setattr(jaxden.denoise.registry, "WEIGHTS_DIR", tmp_path)
    monkeypatch.chdir(Path(__file__).parent.parent)
    assert ship_mixer.main(["--reship", "oidn-pd", "--config", meta["train_config_file"]]) == 0
    shipped = json.loads((tmp_path / "oidn-pd.json").read_text())
    assert shipped["pyoidn_version"] == version("pyoidn")
    assert shipped["pyoidn_version_trained"] == "0.0.1"
    assert f"pyoidn {version('pyoidn')} (trained with 0.0.1)" in (tmp_path / "oidn-pd.md").read_text()


def test_shipped_card_states_the_installed_pyoidn():
    """The card in the package was written by the fixed ship_mixer.py, not left at 'unknown'."""
    from jaxden.denoise.registry import WEIGHTS_DIR

    meta = json.loads((WEIGHTS_DIR / "oidn-pd.json").read_text())
    assert meta["pyoidn_version"] not in ("unknown", "unavailable")
    assert f"OIDN via pyoidn {meta['pyoidn_version']}" in (WEIGHTS_DIR / "oidn-pd.md").read_text()


def test_ship_mixer_card_names_the_probe_distribution():
    """A mixer trained on Rademacher probes says so on its card; a normal-probe card reads as
    before the option existed."""
    ship_mixer = load_script("ship_mixer")
    base = {"spec": "oidn-jax", "black_box": False, "shipped": None, "model": None,
            "label": "OIDN in JAX", "description": ""}
    mc = {"sure_method": "jvp", "sure_probes": 1, "sure_eps": None, "sure_seed": 0}
    assert "jax.jvp (forward-mode derivative), 1 probe, probe seed 0" in \
        ship_mixer._denoiser_text(mc, base, {})
    text = ship_mixer._denoiser_text(mc | {"sure_probe_dist": "rademacher"}, base, {})
    assert "jax.jvp (forward-mode derivative), 1 rademacher probe, probe seed 0" in text
    fd = ship_mixer._denoiser_text(mc | {"sure_method": "fd", "sure_probes": 4,
                                         "sure_probe_dist": "rademacher"}, base, {})
    assert "forward differences, 4 rademacher probes, eps 1e-3" in fd


def test_mixer_alpha_first_layer_weights_and_table():
    """Per-feature first-layer weights of a network mixer; the closed form has none and is left
    out; the table names the denoiser and lists worst pixels when there are any."""
    mixer_alpha = load_script("mixer_alpha")

    weights = mixer_alpha.first_layer_weights(["oidn-pd", "closed-form"])
    assert list(weights) == ["oidn-pd"]
    assert list(weights["oidn-pd"]) == ["hdr", "den", "var", "sure", "residual", "divergence"]
    assert all(v > 0 for v in weights["oidn-pd"].values())
    entry = {"tstat_sigma": 0.5, "single": {"alpha": 0.2, "pd_over_mc": 0.9},
             "swapped": {"alpha": 0.4, "pd_over_mc": 0.8},
             "average": {"alpha": 0.3, "pd_over_mc": 0.85},
             "worst_pixels": [{"pixel": [1, 2], "error": 0.5, "x": 1.0, "y": 2.0,
                               "reference": 0.1, "var": 0.01, "sure": 0.02,
                               "closed_form": 0.7, "single": 0.2, "swapped": 0.4,
                               "average": 0.3}]}
    rows = [{"crop": "s000-c000", "spp": 8, "denoiser_over_mc": 0.5,
             "sure_over_var_median": 1.5, "var_mean": 1e-3, "mixers": {"m": entry}}]
    text = mixer_alpha.markdown(rows, ["m"], weights, "wskp")
    assert text.startswith("| crop | spp | wskp / MC |")
    assert "| s000-c000 | 8 | 0.500 | 1.50 | 1.00e-03 | `m` | 0.5 | 0.200 / 0.400 / 0.300 | " \
           "0.900 / 0.800 / 0.850 |" in text
    assert "| s000-c000 | 8 | `m` | 1, 2 | 0.5 | 1 | 2 | 0.1 | 0.01 | 0.02 | 0.700 |" in text
    assert "| `oidn-pd` |" in text


def test_provenance_records_package_versions():
    from jaxden.provenance import package_version, versions

    assert package_version("pyoidn") == version("pyoidn")
    assert package_version("no-such-package-jaxden") == "not installed"
    assert versions(("pyoidn",)) == {"pyoidn": version("pyoidn")}


def test_sure_median_crop_check_reads_only_levels_from_64_spp():
    """The SURE target: the median crop's ratio within 5 % at every spp >= 64; a level below
    64 spp never decides it, and the farthest level is the one named."""
    from jaxden.evaluate import sure as pd_report

    def summary(ratios):
        return {"per_spp": {str(s): {"median_crop_ratio": r} for s, r in ratios.items()}}

    checks = pd_report.median_crop_checks({"a": summary({32: 0.5, 64: 1.04, 128: 0.97}),
                                           "b": summary({32: 1.0, 64: 1.01, 4096: 0.94})})
    assert checks["a"]["within"] and checks["a"]["worst_spp"] == 64
    assert not checks["b"]["within"] and checks["b"]["worst_spp"] == 4096
    assert checks["b"]["worst_ratio"] == pytest.approx(0.94)
    text = pd_report.markdown_checks(checks)
    assert "- a: yes (farthest from 1: 1.040 at 64 spp)" in text
    assert "- b: NO (farthest from 1: 0.940 at 4096 spp)" in text


def test_pd_tables_keeps_reports_of_the_same_build_only(tmp_path):
    """pd_tables.sh remakes a report unless it was made on the dataset's current build."""
    import hashlib
    import subprocess

    root = Path(__file__).parent.parent
    script = (root / "experiments" / "pd_tables.sh").read_text()
    function = script[script.index("current() {"):script.index("\n}\n", script.index("current() {")) + 3]
    manifest = tmp_path / "data" / "manifest.json"
    manifest.parent.mkdir()
    manifest.write_text('{"items": []}')
    sha = hashlib.sha256(manifest.read_bytes()).hexdigest()

    def current(report: dict | None) -> int:
        out = tmp_path / "report"
        out.with_suffix(".json").unlink(missing_ok=True)
        if report is not None:
            out.with_suffix(".json").write_text(json.dumps(report))
        command = f'python={sys.executable}\n{function}\ncurrent "{out}" "{manifest.parent}"'
        return subprocess.run(["bash", "-c", command], cwd=root, check=False).returncode

    assert current({"provenance": {"dataset": {"manifest_sha256": sha}}}) == 0
    assert current({"provenance": {"dataset": {"manifest_sha256": "0" * 64}}}) == 1
    assert current(None) == 1


def test_every_result_file_is_listed_in_the_experiments_readme():
    """experiments/results/ keeps only current files, grouped in one sub-folder per family, each
    named in experiments/README.md with its folder (FOLDER/STEM) and the command that
    regenerates it; every script in experiments/ is listed there too."""
    root = Path(__file__).parent.parent / "experiments"
    index = (root / "README.md").read_text()
    results = sorted(p for p in (root / "results").rglob("*") if p.is_file())
    assert results
    assert [p.name for p in results if p.parent == root / "results"] == []  # none left loose
    named = [p.relative_to(root / "results").parent / p.name.split(".")[0] for p in results]
    assert [str(n) for n in named if n.as_posix() not in index] == []
    scripts = sorted(p.name for p in root.iterdir() if p.suffix in (".py", ".sh"))
    assert [name for name in scripts if name not in index] == []


# ------------------------------------------------------------------------- rt_tables
def _rt_result(model, seed, psnr, sizes=None, deploy=False, steps=4000, target_spp=None):
    name = f"{model}-{'-'.join(map(str, sizes or []))}-{deploy}-{target_spp}-{seed}"
    return {"run": name, "config": {
                "model": model, "seed": seed, "optim": {"steps": steps},
                "data": {"target_spp": target_spp},
                "model_config": {**({"kernel_sizes": sizes} if sizes else {}), "deploy": deploy}},
            "evaluations": {"den:/x/rt-test": {"den_psnr": psnr, "den_ssim": 0.5,
                                               "den_relmse": 0.2, "den_flip": 0.2}}}


def test_rt_tables_verdicts_from_seeds(tmp_path):
    """Targets are 'met' only beyond the seed-to-seed spread, say when one seed is all there
    is, and group the ablation's rows by kernel sizes and deploy form."""
    rt_tables = load_script("rt_tables")

    assert rt_tables.verdict(None, (1.0, 0.1, 2)).startswith("not measured")
    assert rt_tables.verdict((26.0, float("nan"), 1), (25.0, 0.1, 2)).startswith("one seed")
    assert rt_tables.verdict((26.0, 0.1, 2), (25.5, 0.6, 2)).startswith("NOT met")
    assert rt_tables.verdict((26.0, 0.1, 2), (25.5, 0.2, 2)).startswith("met")
    # Noise2Noise is a measurement: a change within the spread is "no measurable difference".
    assert rt_tables.change((22.3, 0.26, 2), (22.14, 0.33, 2)).endswith("no measurable difference")
    assert rt_tables.change((22.0, 0.1, 2), (23.0, 0.2, 2)).endswith("noisy targets are worse")
    assert rt_tables.change((22.0, 0.1, 1), (23.0, 0.2, 2)).startswith("one seed")
    runs = {"rt-main": [_rt_result("wskp", 0, 26.8), _rt_result("wskp", 1, 26.6),
                        _rt_result("kp", 0, 26.1), _rt_result("kp", 1, 26.3)],
            "rt-ablation": [_rt_result("wskp", s, p, sizes=k, steps=1000)
                            for s in (0, 1) for k, p in (([3], 24.0 + s), ([13], 25.0),
                                                         ([3, 5, 7, 9, 11, 13], 26.5 + 0.1 * s))]
            + [_rt_result("wskp", s, 25.9, sizes=[3, 5, 7, 9, 11, 13], deploy=True, steps=1000)
               for s in (0, 1)]}
    for sweep, results in runs.items():
        for result in results:
            folder = tmp_path / "home" / "runs" / "sweeps" / sweep / result["run"]
            folder.mkdir(parents=True, exist_ok=True)
            (folder / "result.json").write_text(json.dumps(result))
    out = tmp_path / "out"
    out.mkdir()
    assert rt_tables.main(["--home", str(tmp_path / "home"), "--out", str(out)]) == 0
    table1 = (out / "rt-table1.md").read_text()
    assert "| WSKP-6 | 26.70 ± 0.14 (2 seeds) |" in table1
    assert "WSKP-6 PSNR >= KP's - 0.1 dB: met (26.70 against 26.20 dB)" in table1
    fusion = (out / "rt-fusion.md").read_text()
    assert "1000 steps" in fusion and "| kernel 3 | 24.50 ± 0.71 (2 seeds) |" in fusion
    assert "six sizes beats the best single size" in fusion and ": met (margin +1.55 dB" in fusion
    table5 = (out / "rt-table5.md").read_text()
    assert "| WSKP-6, plain 5x5 convolutions | 25.90 ± 0.00 (2 seeds) |" in table5
    assert "+0.6 dB): met (margin +0.65 dB" in table5


def test_relmse_crops_matches_a_numpy_relmse_and_names_the_worst_crop(tmp_path, capsys):
    # A tiny synthetic dataset (no Mitsuba); "oidn" is the model, so no training is needed.
    relmse_crops = load_script("relmse_crops")
    from helpers import build_tiny_dataset

    from jaxden.data.layout import load_manifest
    from jaxden.denoise.registry import load_denoiser
    from jaxden.io.exr import read_frame
    from jaxden.metrics import relmse

    data = build_tiny_dataset(tmp_path / "tiny", ["crops_per_scene=2"])
    manifest = load_manifest(data)
    split = manifest.crops[0].split
    out = tmp_path / "crops.md"
    assert relmse_crops.main(["--dataset", str(data), "--split", split, "--spp", "2",
                              "--model", "oidn", "--out", str(out)]) == 0
    result = json.loads(out.with_suffix(".json").read_text())
    oidn = load_denoiser("oidn")
    expected = {}
    for crop in manifest.crops:
        if crop.split != split:
            continue
        items = manifest.items_of(crop.id)
        noisy = next(i for i in items if i.kind != "reference" and i.spp == 2)
        ref = read_frame(data / next(i for i in items if i.kind == "reference").path).color
        frame = read_frame(data / noisy.path)
        expected[crop.id] = float(relmse(np.asarray(oidn(frame)), ref))
    got = {r["crop"]: r["oidn"] for r in result["crops"]}
    assert got.keys() == expected.keys() and len(got) >= 2
    for crop, value in expected.items():
        assert got[crop] == pytest.approx(value, rel=1e-4)
    summary = result["summary"]["oidn"]
    worst = max(expected, key=expected.get)
    assert summary["worst_crop"] == worst
    assert summary["mean"] == pytest.approx(np.mean(list(expected.values())), rel=1e-4)
    assert "| oidn |" in out.read_text()


def test_pd_ood_ratios_bound_and_diagnosis(tmp_path):
    pd_ood = load_script("pd_ood")

    def row(scene, spp, pd, den, sure):
        return {"scene": scene, "crop": scene, "spp": spp, "pd_rmse": pd, "denoiser_rmse": den,
                "pd_relmse": 2 * pd, "denoiser_relmse": 2 * den, "oracle_rmse": 0.9 * den,
                "mixed_rmse": pd, "mc_rmse": 3 * den, "alpha": 0.8, "sure": sure,
                "denoiser_mse_nc": den ** 2}

    rows = [row("a", 16, 1.0, 1.0, 1.0), row("a", 32, 2.2, 2.0, 4.4),   # 1.00 and 1.10
            row("b", 16, 0.5, 1.0, 1.0), row("b", 32, 0.5, 1.0, 1.0)]   # 0.50 twice
    result = pd_ood.diagnose({"rows": rows})
    assert result["scenes"]["a"]["rmse_gmean"] == pytest.approx(math.sqrt(1.1))
    assert result["scenes"]["a"]["rmse_worst"] == pytest.approx(1.1)
    assert result["scenes"]["a"]["cells_over_bound"] == 1
    assert result["scenes"]["b"]["cells_over_bound"] == 0
    assert result["overall"]["cells_over_bound"] == 1
    # The set's ratio per spp is a ratio of means over crops, as the PD result's table.
    assert result["per_spp"][32]["rmse"] == pytest.approx(2.7 / 3.0)
    sure_errors = sorted(c["sure_error"] for c in result["cells"])
    assert sure_errors[-1] == pytest.approx(0.1)  # 4.4 / 2.0^2 - 1
    assert result["t_forms"] == {"pd": {"cells_over_bound": 1, "worst": pytest.approx(1.1),
                                        "cells": 4}}
    # Each form of the t-statistic the rows hold is counted alike.
    shared = [{**r, "pd_shared_rmse": 1.05 * r["denoiser_rmse"],
               "pd_shared_relmse": r["denoiser_relmse"]} for r in rows]
    forms = pd_ood.diagnose({"rows": shared})["t_forms"]
    assert forms["pd_shared"] == {"cells_over_bound": 4, "worst": pytest.approx(1.05),
                                  "cells": 4}
    out = tmp_path / "diag"
    report = tmp_path / "r.json"
    report.write_text(json.dumps({"rows": rows}))
    assert pd_ood.main([str(report), "--out", str(out)]) == 0
    assert "| a | 1.049 |" in (tmp_path / "diag.md").read_text()
    assert "PD as configured: 1 of 4 cells over the bound (worst 1.100)" in (
        tmp_path / "diag.md").read_text()


def test_sure_figure_curves_and_svg(tmp_path):
    rows = []
    for crop, scale in (("a", 1.0), ("b", 3.0)):
        for spp in (2, 4):
            rows.append({"crop": crop, "spp": spp, "input_mse_nc": scale / spp,
                         "input_var": 1.1 * scale / spp, "mse_nc": 0.1 * scale,
                         "sure": 0.12 * scale})
    report = {"rows": {"oidn": rows, "runs/x": rows},
              "provenance": {"dataset": {"config": {"name": "t"}}}}
    curves = pd_figure.sure_curves(report)
    assert curves["oidn"]["input_mse_nc"] == [(2, pytest.approx(1.0)), (4, pytest.approx(0.5))]
    assert curves["runs/x"]["sure"][0] == (2, pytest.approx(0.24))
    path = tmp_path / "r.json"
    path.write_text(json.dumps(report))
    assert pd_figure.main(["sure", "--report", str(path), "--out", str(tmp_path / "f")]) == 0
    svg = ET.fromstring((tmp_path / "f.svg").read_text())
    texts = [t.text for t in svg.iter("{http://www.w3.org/2000/svg}text")]
    assert "oidn (mean over crops)" in texts and "x (mean over crops)" in texts
    # the estimates are dashed, the true errors solid
    dashed = [line for line in svg.iter("{http://www.w3.org/2000/svg}polyline")
              if line.get("stroke-dasharray")]
    assert len(dashed) == 4  # two estimates in each of two panels


# ------------------------------------------------------- a mixer over another base denoiser
def _fake_mixer_run(root: Path, workdir: Path, weights: Path) -> dict:
    """A training workdir of a mixer over the shipped WSKP-6, as `jaxden train
    experiments/configs/mixer-wskp6.toml` leaves it (config.json, metrics.jsonl, a checkpoint
    of freshly initialised parameters), its dataset's manifest and a weights folder holding
    wskp-6; returns the run's config."""
    import shutil
    import tomllib

    import jax

    from jaxden.checkpoint import Checkpointer
    from jaxden.config import config_to_dict, load_config
    from jaxden.progressive.mixer import MixerConfig, mixer_init
    from jaxden.progressive.mixer import mixer_meta as _mixer_meta
    from jaxden.train.config import load_train_config

    weights.mkdir()
    for suffix in (".msgpack", ".json"):
        shutil.copy(root / "jaxden" / "weights" / f"wskp-6{suffix}", weights)
    dataset = workdir.parent / "data" / "pd-rt"
    dataset.mkdir(parents=True)
    data_config = tomllib.loads((root / "experiments/configs/dataset-pd-rt.toml").read_text())
    (dataset / "manifest.json").write_text(json.dumps({"config": data_config, "items": []}))
    config = config_to_dict(load_train_config(root / "experiments/configs/mixer-wskp6.toml",
                                              [f"data.dataset={dataset}"]))
    workdir.mkdir()
    (workdir / "config.json").write_text(json.dumps(config))
    steps = config["optim"]["steps"]
    log = [{"step": 0, "val_loss": 0.03},  # the untrained mixer
           {"step": steps // 2, "loss": 0.2, "grad_norm": 1.0, "lr": 1e-4, "seconds": 600.0},
           {"step": steps, "loss": 0.1, "grad_norm": 1.0, "lr": 1e-5, "seconds": 600.0},
           {"step": steps, "val_loss": 0.02, "val_baseline_loss": 0.025}]
    (workdir / "metrics.jsonl").write_text("".join(json.dumps(e) + "\n" for e in log))
    mixer = load_config(config["model_config"], MixerConfig)
    checkpointer = Checkpointer(workdir)
    checkpointer.save(steps, {"params": mixer_init(jax.random.PRNGKey(0), mixer)},
                      _mixer_meta(mixer))
    checkpointer.wait()
    checkpointer.close()
    return config


def test_ship_mixer_card_of_a_mixer_over_wskp6_names_its_base(tmp_path, monkeypatch):
    """A mixer trained over WSKP-6: the card says WSKP-6 wherever it said OIDN (title, use,
    denoiser and SURE method, validation baseline, tables, limits) and no OIDN at all; its
    .json carries no pyoidn version but the hash of the WSKP-6 weights."""
    import hashlib

    ship_mixer = load_script("ship_mixer")

    import jaxden.denoise.registry
    from jaxden.progressive.pipeline import SHIPPED_MIXERS

    root = Path(__file__).parent.parent
    weights = tmp_path / "weights"
    _fake_mixer_run(root, tmp_path / "run", weights)
    monkeypatch.setattr(jaxden.denoise.registry, "WEIGHTS_DIR", weights)
    monkeypatch.chdir(root)
    ratios = {"rmse": 0.9, "rmse_nc": 0.8, "relmse": 0.7, "flip": 0.95}
    report = {"summary": {"headline": {"pd_over_denoiser": ratios, "oracle_over_denoiser": ratios},
                          "per_spp": {"2": {}, "1024": {}}, "max_spp": 1024, "crops": 4},
              "provenance": {"dataset": {"dir": "data/pd-test", "config": {
                  "name": "pd-test", "reference_spp": 4096}}, "command": "python pd_report.py",
                  "commit": "0000000", "denoiser": "wskp-6"}}
    (tmp_path / "report.json").write_text(json.dumps(report))
    assert ship_mixer.main(["--workdir", str(tmp_path / "run"),
                            "--report", str(tmp_path / "report.json")]) == 0
    card = (weights / "wskp-6-pd.md").read_text()  # the name defaults to the base's + "-pd"
    assert "oidn" not in card.lower()
    use = next(line for line in card.splitlines() if line.startswith("Use:"))
    assert use.startswith("Use: `jaxden progressive IN.exr --denoiser wskp-6 --mixer wskp-6-pd "
                          "--out OUT.exr`")
    assert "albedo (`albedo.R/G/B`), normal (`normal.X/Y/Z`) and depth (`depth.Z`) for " \
           "WSKP-6." in use
    # the library function only where it loads this mixer for that base
    assert ("shipped_progressive_denoiser('wskp-6')" in use) == (
        SHIPPED_MIXERS.get("wskp-6") == "wskp-6-pd")
    sha = hashlib.sha256((weights / "wskp-6.msgpack").read_bytes()).hexdigest()
    for needle in ("# Model card: `wskp-6-pd` (progressive-denoising mixer for WSKP-6)",
                   "and WSKP-6's output y per pixel",
                   "`jaxden dataset build experiments/configs/dataset-pd-rt.toml --out ",
                   (f"- Denoiser: WSKP-6, the weights shipped as `wskp-6` (`jaxden/weights/"
                    f"wskp-6.msgpack`, sha256 `{sha[:16]}...`; model `wskp`"),
                   ("SURE of its output by jax.jvp (forward-mode derivative), 1 probe, probe "
                    "seed 0"), "(WSKP-6 alone: 0.02500)",
                   "Config: `experiments/configs/mixer-wskp6.toml`",
                   "| PD(WSKP-6) / WSKP-6, all spp | 0.900 |", "| oracle mix / WSKP-6, all spp |",
                   "crops of 24 scenes at 2..1024 spp", "Trained for WSKP-6's output only"):
        assert needle in card
    meta = json.loads((weights / "wskp-6-pd.json").read_text())
    assert not [key for key in meta if "pyoidn" in key]
    assert meta["denoiser_weights_sha256"] == sha
    assert meta["train_config_file"] == "experiments/configs/mixer-wskp6.toml"
    # A re-ship reads it all back: the same card.
    assert ship_mixer.main(["--reship", "wskp-6-pd", "--report",
                            str(tmp_path / "report.json")]) == 0
    assert (weights / "wskp-6-pd.md").read_text() == card


def test_ship_mixer_labels_base_denoisers():
    ship_mixer = load_script("ship_mixer")

    assert ship_mixer.denoiser_label("oidn") == "OIDN"
    assert ship_mixer.denoiser_label("wskp-6") == "WSKP-6"
    assert ship_mixer.denoiser_label("/home/x/runs/pd-bases/unet-hdr/") == "unet-hdr"
    assert ship_mixer.denoiser_label("weights/kp-5.msgpack") == "kp-5"


def test_convergence_figure_names_the_reports_denoiser(tmp_path):
    """The curves of a report over WSKP-6 are WSKP-6 and PD(WSKP-6); a report over OIDN (or
    from before reports named other bases) keeps OIDN's."""
    ns = "{http://www.w3.org/2000/svg}"
    for denoiser, names in (("wskp-6", ["MC", "WSKP-6", "PD(WSKP-6)"]),
                            ("oidn", ["MC", "OIDN", "PD(OIDN)"]), (None, ["OIDN", "PD(OIDN)"])):
        provenance = {"dataset": {"config": {"name": "t"}}}
        if denoiser is not None:
            provenance["denoiser"] = denoiser
        path = tmp_path / "r.json"
        path.write_text(json.dumps({"rows": _rows(), "provenance": provenance}))
        assert pd_figure.main(["convergence", "--report", str(path),
                               "--out", str(tmp_path / "f")]) == 0
        texts = [t.text for t in ET.fromstring((tmp_path / "f.svg").read_text()).iter(f"{ns}text")]
        assert all(name in texts for name in names)
        if denoiser == "wskp-6":
            assert not [t for t in texts if t and "OIDN" in t]


def test_pd_bases_tables_ratios_targets_and_table4(tmp_path):
    """Table 1's PD / den is the ratio of spp-averaged crop-mean errors (the paper's form) next
    to the mean per-spp ratio; the 0.6 target and the top-spp check read the worst base and
    crop; Table 4 rows come from the named runs and methods; unfinished runs say so."""
    T = load_script("pd_bases_tables")

    def evaluation(den, pd, top_crops):
        levels = (32, 4096)
        per_spp = {}
        for i, s in enumerate(levels):
            m = {}
            for metric in ("rmse", "rmse_nc", "relmse", "flip"):
                m |= {f"mc_{metric}": 0.1, f"denoiser_{metric}": den[i], f"pd_{metric}": pd[i],
                      f"mixed_{metric}": pd[i] * 1.1}
            per_spp[str(s)] = m
        ratios = {metric: float(np.mean([pd[i] / den[i] for i in range(2)]))
                  for metric in ("rmse", "rmse_nc", "relmse", "flip")}
        return {"per_spp": per_spp, "crops": len(top_crops),
                "headline": {"pd_over_denoiser": ratios,
                             "pd_over_mc_at_max_spp": {"rmse": pd[1] / 0.1}},
                "per_crop": {f"c{i}": {"pd_over_mc_rmse_at_max_spp": v}
                             for i, v in enumerate(top_crops)}}

    sweep = tmp_path / "runs" / "sweeps" / "pd-mixers"
    bounded = evaluation((0.2, 0.02), (0.08, 0.01), (0.9, 0.95))
    bounded["headline"] |= {"oracle_over_denoiser": {"rmse": 0.35},
                            "pd_true_sure_over_denoiser": {"rmse": 0.42}}
    runs = {"unet-hdr": bounded,
            "unet-hdr-var": evaluation((0.1, 0.01), (0.07, 0.009), (0.99, 1.02)),
            "t4-full": evaluation((0.3, 0.03), (0.15, 0.02), (0.9,))}
    for name, ev in runs.items():
        (sweep / name).mkdir(parents=True)
        (sweep / name / "result.json").write_text(json.dumps(
            {"run": name, "evaluations": {"pd:/data/pd-test-high": ev}}))
    cov = tmp_path / "runs" / "sweeps" / "pd-mixers-cov" / "unet-hdr"
    cov.mkdir(parents=True)
    (cov / "result.json").write_text(json.dumps({"run": "unet-hdr", "evaluations": {
        "pd:/data/pd-test-high": evaluation((0.2, 0.02), (0.066, 0.011), (0.9, 0.97))}}))
    closed = tmp_path / "runs" / "pd-closed-form"
    closed.mkdir(parents=True)
    (closed / "unet-hdr.json").write_text(json.dumps({
        "summary": evaluation((0.2, 0.02), (0.07, 0.012), (0.98, 0.99)),
        "provenance": {"dataset": {"path": "/data/pd-test-high"}}}))
    # a base with Eq. 9 alone only (no network mixer has run over it): listed, den included
    (closed / "kp5.json").write_text(json.dumps({
        "summary": evaluation((0.3, 0.03), (0.12, 0.02), (0.95,)),
        "provenance": {"dataset": {"path": "/data/pd-test-high"}}}))
    out = tmp_path / "out"
    assert T.main(["--home", str(tmp_path), "--out", str(out)]) == 0
    data = json.loads((out / "pd-table1.json").read_text())
    assert "| 1 | | Eq. 9 alone, covariance SURE | 0.04100 (0.373x; 0.475x) |" in (
        out / "pd-table1.md").read_text()
    assert data["rows"]["unet-hdr"]["closed_form"]["worst_crop_pd_over_mc_at_top"] == 0.99
    # the covariance-SURE row: its PD over the same base's den (0.0385 / 0.11)
    assert "| 1 | | PD, covariance SURE | 0.03850 (0.350x; 0.440x) |" in (
        out / "pd-table1.md").read_text()
    assert data["rows"]["unet-hdr"]["covariance_sure"]["worst_crop_pd_over_mc_at_top"] == 0.97
    hdr = data["rows"]["unet-hdr"]["pd"]["rmse"]
    assert hdr["ratio_of_averages"] == pytest.approx(0.09 / 0.22)
    assert hdr["mean_ratio"] == pytest.approx((0.4 + 0.5) / 2)
    worst = 0.079 / 0.11  # unet-hdr-var's ratio of averages: over 0.6
    assert f"- PD: PD(U-Net) RMSE at most 0.6 of the U-Net's own, averaged over 32..4096 spp, " \
           f"for every feature set (paper: 0.40-0.57): worst {worst:.3f} over 2 of 4 feature " \
           f"sets: NOT met so far." in data["targets"]
    assert any(t.startswith("- PD: PD at or below MC's RMSE") and "worst crop 1.0200 (base "
               "unet-hdr-var) over 2 of 6 bases: NOT met so far." in t for t in data["targets"])
    # each mixer is judged on its own: Eq. 9 alone over unet-hdr only (0.07 / 0.11 at most)
    assert any(t.startswith("- Eq. 9 alone, covariance SURE: PD(U-Net)") and "worst 0.373 "
               "over 1 of 4 feature sets: met so far." in t for t in data["targets"])
    assert set(data["missing"]) == {"unet-hdr-alb-nrm", "unet-hdr-alb-nrm-var", "wskp6"}
    assert "| 2 | KP, 5 x 5 kernels (the paper's KPCN) | den | 0.16500 |" in (
        out / "pd-table1.md").read_text()
    assert "- Eq. 9 alone, covariance SURE: PD(KP) reported: PD / den RMSE 0.424." in \
        data["targets"]  # (0.12 + 0.02) / (0.3 + 0.03)
    # PD's mean ratio 0.45 against the oracle's 0.35: (1 - 0.45) / (1 - 0.35) of its gain
    assert "| U-Net: HDR | PD | 0.450 | 0.420 | 0.350 | 85% |" in (
        out / "pd-table1.md").read_text()
    assert "| | MC (the input) | MC | 0.10000 | 0.10000 | 0.10000 | 0.10000 | 1 |" in (
        out / "pd-table1.md").read_text()
    assert "| U-Net: HDR, VAR |" not in (out / "pd-table1.md").read_text().split(
        "## Against the bounds")[1]  # a report without the oracle has no row there
    table4 = (out / "pd-table4.md").read_text()
    assert "| pro-den (f_act head, the paper's) | 0.15000 | 0.02000 |" in table4
    assert "| w/o t-test (f_act head) | 0.16500 | 0.02200 |" in table4
    assert "| w/o SURE (f_act head) | not run |" in table4
    assert "| den (U-Net: HDR, ALB, NRM, VAR) | 0.30000 | 0.03000 |" in table4  # from t4-full
    assert "| mc-render | 0.10000 | 0.10000 |" in table4
    svg = (out / "pd-convergence-bases.svg").read_text()
    ET.fromstring(svg)
    assert "U-Net: HDR, VAR" in svg and "PD(base)" in svg
    # With no run over Table 4's base, its current file is left as it is (not emptied).
    shutil.rmtree(sweep)
    assert T.main(["--home", str(tmp_path), "--out", str(out)]) == 0
    assert (out / "pd-table4.md").read_text() == table4
    assert "| 1 | | PD, covariance SURE |" in (out / "pd-table1.md").read_text()


def test_sure_figure_adds_the_per_channel_curve_only_when_every_row_has_it():
    rows = [{"spp": s, "crop": c, "input_mse_nc": 1.0, "input_var": 1.0, "mse_nc": 0.5,
             "sure": 0.5, "sure_diag": 0.25} for s in (32, 64) for c in ("a", "b")]
    report = {"rows": {"den": rows}}
    assert pd_figure.sure_methods(report)[-1] == pd_figure.SURE_DIAG
    assert pd_figure.sure_curves(report)["den"]["sure_diag"] == [(32, 0.25), (64, 0.25)]
    del rows[0]["sure_diag"]
    assert pd_figure.sure_methods(report) == pd_figure.SURE_METHODS


def test_oracle_crossfit_blend_has_the_variance_of_n_spp_and_the_summary_its_shares():
    """The cross-fitted oracle's twin render: w x_2N + (1 - w) x_N/2 has exactly the variance
    of an N-spp render; the summary's shares of the oracle's gain follow from the ratios; the
    PD column is named after the report's mixer."""
    from jaxden.evaluate import oracle as X

    for n in (64, 256, 2048):
        w = X.blend_weight(n, n // 2, 2 * n)
        assert 0 <= w <= 1 and w**2 / (2 * n) + (1 - w) ** 2 / (n // 2) == pytest.approx(1 / n)
    with pytest.raises(ValueError, match="no blend of 32 and 64 spp"):
        X.blend_weight(16, 32, 64)
    rows = [{"crop": c, "spp": 64, "oracle_rmse_0": 0.5, "oracle_rmse_1": 0.7,
             "crossfit_rmse_0": 0.8, "crossfit_rmse_1": 0.8, "denoiser_rmse_0": 1.0,
             "denoiser_rmse_1": 1.0} for c in ("a", "b")]
    report = {"rows": [{"crop": c, "spp": 64, "pd_rmse": 0.7, "denoiser_rmse": 1.0}
                       for c in ("a", "b")],
              "provenance": {"mixer": {"spec": "closed-form"},
                             "mixer_overrides": ["sure_covariance=true"]}}
    summary = X.summarize_crossfit(rows, report)
    assert summary["mean_over_spp"] == pytest.approx({"oracle": 0.6, "crossfit": 0.8, "pd": 0.7})
    assert summary["share_of_oracle_gain"] == pytest.approx({"crossfit": 0.5, "pd": 0.75})
    text = X.markdown_crossfit(summary, "den", X.report_label(report))
    assert "| spp | 8 x 8 oracle | cross-fitted oracle | PD (mixer closed-form, " \
           "sure_covariance=true) |" in text and "- PD: 75%" in text
    # the twin's variance and covariance are the blend's, with the squared weights
    from jaxden.frame import Frame

    ones = np.ones((2, 2, 3), np.float32)
    high = Frame(color=ones, variance=ones * 0.5, covariance=ones * 0.25)
    low = Frame(color=ones * 3, variance=ones * 2.0, covariance=ones * 1.0)
    twin = X.blend_frames(high, low, 0.5)
    np.testing.assert_allclose(twin.color, 2.0)
    np.testing.assert_allclose(twin.variance, 0.25 * 0.5 + 0.25 * 2.0)
    np.testing.assert_allclose(twin.covariance, 0.25 * 0.25 + 0.25 * 1.0)


# ------------------------------------------------------------------------- pd_targets
def test_pd_targets_checks_each_image_against_mc_and_the_better_of_mc_and_the_denoiser():
    pd_targets = load_script("pd_targets")

    def row(crop, spp, mc, den, pd, margin=0.0, relmse=(1.0, 1.0, 1.0)):
        return {"crop": crop, "scene": f"s/{crop}.xml", "spp": spp, "mc_mse_nc": mc,
                "denoiser_mse_nc": den, "pd_mse_nc": pd, "pd_vs_mc_margin": margin,
                "mc_relmse": relmse[0], "denoiser_relmse": relmse[1], "pd_relmse": relmse[2]}

    report = {"rows": [
        # a: at the top spp 2 % above MC but within the margin; at 8 spp PD = 1.1x den's RMSE^2
        row("a", 8, 4.0, 1.0, 1.21), row("a", 4096, 1.0, 9.0, 1.02, margin=0.03),
        # b: above MC beyond the margin at the top spp; relMSE 1.04x the better one
        row("b", 8, 4.0, 9.0, 3.0, relmse=(2.0, 1.0, 1.04)),
        row("b", 4096, 1.0, 9.0, 1.02, margin=0.01)]}
    a, b = pd_targets.check(report, factor=1.05)
    assert (a["crop"], a["top_spp"], a["top_ok"]) == ("a", 4096, True)
    assert a["worst_rmse"] == pytest.approx(1.1) and a["worst_rmse_spp"] == 8
    assert not a["rmse_ok"] and a["relmse_ok"]
    assert not b["top_ok"] and b["top_pd_over_mc"] == pytest.approx(1.02)
    assert b["worst_rmse"] == pytest.approx(math.sqrt(1.02)) and b["rmse_ok"]
    assert b["worst_relmse"] == pytest.approx(1.04) and b["relmse_ok"]
    assert "**no**" in pd_targets.table({"r": [a, b]}, 1.05)


def test_scripts_are_clients_of_the_package():
    """No script under experiments/ imports another one, and nothing under experiments/ or
    tests/ edits sys.path: what scripts share lives in the package (read from the source)."""
    import ast

    root = Path(__file__).parent.parent
    scripts = {p.stem for p in (root / "experiments").glob("*.py")}
    files = [*(root / "experiments").glob("*.py"), *(root / "tests").glob("*.py")]
    found = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name.split(".")[0] for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [(node.module or "").split(".")[0]]
            else:
                names = []
            if path.parent.name == "experiments":
                found += [f"{path.name} imports {n}" for n in names if n in scripts]
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute)
                    and node.value.attr == "path" and isinstance(node.value.value, ast.Name)
                    and node.value.value.id == "sys"):
                found.append(f"{path.name} edits sys.path ({node.attr})")
    assert found == []


def _denoise_report(path, psnr_by_cell, manifest="abc"):
    rows = [{"crop": crop, "spp": spp, "den_psnr": psnr, "den_ssim": 0.5, "den_relmse": 0.1,
             "den_flip": 0.2} for (crop, spp), psnr in psnr_by_cell.items()]
    path.write_text(json.dumps({"rows": rows, "provenance": {
        "dataset": {"manifest_sha256": manifest, "dir": "d", "split": "test"},
        "denoiser": {"spec": path.stem}}}))
    return path


def test_finetune_gain_tabulates_per_spp_and_refuses_other_data(tmp_path, capsys):
    """experiments/finetune_gain.py: crop means per spp and over all, the mean PSNR gain and
    the crops that gain, by hand; reports of another build or other crops are one line, exit 2,
    no output written."""
    finetune_gain = load_script("finetune_gain")
    stock = _denoise_report(tmp_path / "stock.json", {("a", 2): 20.0, ("b", 2): 30.0,
                                                      ("a", 4): 22.0, ("b", 4): 32.0})
    tuned = _denoise_report(tmp_path / "tuned.json", {("a", 2): 21.0, ("b", 2): 29.5,
                                                      ("a", 4): 23.0, ("b", 4): 33.0})
    out = tmp_path / "gain"
    assert finetune_gain.main(["--stock", str(stock), "--tuned", str(tuned),
                               "--out", str(out)]) == 0
    table = json.loads(out.with_suffix(".json").read_text())["per_spp"]
    assert table["2"]["stock_psnr"] == 25.0 and table["2"]["tuned_psnr"] == 25.25
    assert table["2"]["psnr_gain"] == 0.25 and table["2"]["crops_gaining"] == 1
    assert table["2"]["worst_psnr_gain"] == -0.5 and table["4"]["crops_gaining"] == 2
    assert table["all"]["crops"] == 4 and table["all"]["psnr_gain"] == 0.625
    assert "| 2 | 2 | 25.00 | 25.25 |" in out.with_suffix(".md").read_text()
    other = _denoise_report(tmp_path / "other.json", {("a", 2): 1.0, ("b", 2): 1.0,
                                                      ("a", 4): 1.0, ("b", 4): 1.0}, "xyz")
    fewer = _denoise_report(tmp_path / "fewer.json", {("a", 2): 21.0})
    for bad, message in ((other, "another dataset build"), (fewer, "other crops or spp")):
        capsys.readouterr()
        assert finetune_gain.main(["--stock", str(stock), "--tuned", str(bad),
                                   "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert message in err and bad.name in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "bad.md").exists()


def test_probe_noise_rademacher_has_no_diagonal_noise():
    """experiments/probe_noise.py: through a denoiser with a diagonal Jacobian (y = a x per
    pixel) a Rademacher probe's estimate b (J b) is exactly var * a, with no spread, while
    Gaussian probes scatter around it; through a pixel-mixing one both scatter, and both
    average to var * J_ii (2000 probes: within 5 standard errors)."""
    import jax.numpy as jnp

    from jaxden.frame import Frame

    probe_noise = load_script("probe_noise")
    rng = np.random.default_rng(0)
    variance = rng.uniform(0.5, 2.0, (4, 5, 3)).astype(np.float32)
    frame = Frame(color=rng.uniform(0, 1, (4, 5, 3)).astype(np.float32), variance=variance)
    scale = jnp.asarray(rng.uniform(0.2, 0.9, (4, 5, 3)), jnp.float32)
    estimates = probe_noise.one_probe_estimates(lambda f: scale * f.color, frame, 16, 0)
    np.testing.assert_allclose(estimates["rademacher"], np.broadcast_to(
        variance * np.asarray(scale), (16, 4, 5, 3)), rtol=1e-5)
    assert estimates["gaussian"].std(axis=0).min() > 0.01
    blur = lambda f: 0.5 * f.color + 0.25 * (jnp.roll(f.color, 1, 0) + jnp.roll(f.color, -1, 0))  # noqa: E731
    many = probe_noise.one_probe_estimates(blur, frame, 2000, 1)
    for kind, values in many.items():
        assert values.std(axis=0).min() > 0.01, kind
        error = np.abs(values.mean(axis=0) - 0.5 * variance)
        assert np.all(error < 5 * values.std(axis=0) / np.sqrt(2000)), kind


# ------------------------------------------------------------------------- pd_fig11
def test_pd_fig11_tables_and_claims_from_evaluate_pd_rows(tmp_path):
    """Means per spp of the columns each run gives, per-crop ratios to MC at the top spp, and
    the claims decided on those numbers; a missing run is named."""
    fig11 = load_script("pd_fig11")
    folder = tmp_path / "home" / "runs" / "pd-fig11"
    folder.mkdir(parents=True)

    def rows(den, pd):  # two crops at 2 and 4096 spp; MC RMSE 1.0 / 0.01
        out = []
        for crop, scale in (("a", 1.0), ("b", 3.0)):
            for spp, mc in ((2, 1.0), (4096, 0.01)):
                out.append({"crop": crop, "spp": spp, "mc_rmse": mc * scale,
                            "mc_relmse": mc, "denoiser_rmse": den[spp] * scale,
                            "denoiser_relmse": den[spp], "pd_rmse": pd[spp] * scale,
                            "pd_relmse": pd[spp]})
        return out

    for name, den, pd in (("pd-oidn", {2: 0.3, 4096: 0.02}, {2: 0.35, 4096: 0.0099}),
                          ("pd-dc-s0", {2: 0.2, 4096: 0.015}, {2: 0.25, 4096: 0.01})):
        (folder / f"{name}.json").write_text(json.dumps({"rows": rows(den, pd)}))
    out = tmp_path / "fig11"
    assert fig11.main(["--home", str(tmp_path / "home"), "--out", str(out)]) == 0
    text = (out.with_suffix(".md")).read_text()
    assert "| 2 | 2 | 0.6 | 0.4 | 0.7 | 0.5 |" in text  # MC, OIDN, DC s0, PD(OIDN), PD(DC s0)
    assert "- DC s0 below PD over it at 2 spp (RMSE): yes (0.4 against 0.5)" in text
    assert "- DC s0 above MC at 4096 spp (RMSE): yes (0.03 against MC 0.02)" in text
    assert "PD(DC s0) at or below MC at the top spp (4096) on every crop: met (worst crop " \
           "1.0000x" in text
    assert "| PD(OIDN) | 4096 | 0.9900 | 0 of 2 |" in text
    assert "Missing: `pd-oidn-closed-form`" in text and "`pd-dc-s1`" in text


# ------------------------------------------------------------------------- rt_comparisons
def test_rt_comparisons_rows_seeds_and_claims(tmp_path, monkeypatch):
    """The scored methods' rows (per frame; per frame, accumulated and own history on the
    sequences, the last only where a summary has it), trained runs as mean ± std over seeds,
    and the claims decided from them with the bench's time ratio."""
    rt = load_script("rt_comparisons")

    def summary(psnr, seq=False):
        out = {f"{p}_{m}": psnr + i for i, p in enumerate(("mc", "den", "acc", "tdn"))
               for m in ("psnr",)} | {f"{p}_{m}": 0.5 for p in ("mc", "den", "acc", "tdn")
                                      for m in ("ssim", "relmse", "flip")}
        if seq:
            out |= {"seq_psnr": psnr + 9, "seq_ssim": 0.5, "seq_relmse": 0.5, "seq_flip": 0.5}
        return out

    scored = {key: {"den": summary(20.0), "seq": summary(21.0, seq=key == "svgf")}
              for key, _, _ in rt.SCORED}
    monkeypatch.setattr(rt, "score", lambda home, rescore=False: scored)
    for sweep, model, seed, psnr in (("rt-main", "wskp", 0, 26.6), ("rt-main", "wskp", 1, 26.8),
                                     ("rt-main", "kp", 0, 26.1), ("rt-main", "kp", 1, 26.3),
                                     ("rt-baselines", "nbgd", 0, 25.0),
                                     ("rt-wskp3", "wskp3", 0, 26.0), ("rt-wskp3", "wskp3", 1, 26.4),
                                     ("rt-variants", "wskp3", 0, 26.0)):  # the same run again
        folder = tmp_path / "home" / "runs" / "sweeps" / sweep / f"{model}-s{seed}"
        folder.mkdir(parents=True)
        result = {"run": folder.name, "config": {"model": model, "seed": seed},
                  "evaluations": {"den:/x/rt-test": {"den_psnr": psnr, "den_ssim": 0.7,
                                                     "den_relmse": 0.2, "den_flip": 0.2}}}
        (folder / "result.json").write_text(json.dumps(result))
    out = tmp_path / "out"
    out.mkdir()
    assert rt.main(["--home", str(tmp_path / "home"), "--out", str(out)]) == 0
    text = (out / "rt-comparisons.md").read_text()
    assert "| WSKP-6, trained here (runs: 2) | 26.70 ± 0.14 (2 seeds) |" in text
    assert "| NBGD, trained here (runs: 1) | 25.00 |" in text
    assert "| WSKP-3, trained here (runs: 2) | 26.20 ± 0.28 (2 seeds) |" in text
    assert "| MR-KP, trained here (runs: 0) | not run |" in text
    assert "| SVGF (paper settings), own history | 30.00 |" in text
    assert "BMFR, own history" not in text
    assert ("- WSKP-6 comparable to KP at about half its time: PSNR 26.70 against 26.20 dB "
            "(margin +0.50 dB, seed-to-seed standard deviation 0.14 dB)") in text
    assert "- WSKP-6 better than NBGD at equal time: PSNR 26.70 against 25.00 dB" in text


def test_consistent_table_ratios_and_missing_methods(tmp_path):
    """Per-image ratios: the top spp over MC, the every-spp worst over the better of MC and the
    base; methods without results are named, none is filled in."""
    table = load_script("consistent_table")
    folder = tmp_path / "runs" / "consistent" / "stress-stats"
    folder.mkdir(parents=True)

    def rows(kind):
        out = []
        for crop, scale in (("a", 1.0), ("b", 2.0)):
            for spp in (4, 64):
                mc = scale / spp ** 0.5
                row = {"crop": crop, "scene": crop, "spp": spp}
                if kind == "pd":
                    row |= {"mc_rmse": mc, "denoiser_rmse": 0.5 * mc if spp == 4 else 2 * mc,
                            "pd_rmse": 0.6 * mc if spp == 4 else 0.9 * mc}
                else:
                    row |= {"mc_rmse": mc, "den_rmse": 1.2 * mc}
                out.append(row)
        return {"rows": out}

    (folder / "pd-oidn.json").write_text(json.dumps(rows("pd")))
    (folder / "statmc.json").write_text(json.dumps(rows("den")))
    text, summary = table.report(tmp_path)
    entry = summary["sets"]["stress-stats"]["rmse"]
    top = entry["top_spp_over_mc"]
    assert top["PD(OIDN)"]["worst"] == pytest.approx(0.9) and top["PD(OIDN)"]["above"] == 0
    assert top["StatMC"]["worst"] == pytest.approx(1.2) and top["StatMC"]["above"] == 2
    # at 4 spp the base is the better (0.5 MC): PD at 0.6 MC is 1.2x it
    bar = entry["every_spp_over_min_mc_base"]["PD(OIDN)"]
    assert bar["worst"] == pytest.approx(1.2) and bar["over_1_05"] == 2 and bar["cells"] == 4
    assert "Not in this set yet: WSKP-6" in text and "NJS(OIDN) s0" in text
    assert "No results yet" in text  # the other two sets


# ------------------------------------------------------------------------- statmc_bound
def test_statmc_bound_two_materials_share_the_boxcox_mean_and_chunks_pool_exactly():
    """experiments/statmc_bound.py: the two halves of ``two-materials`` have the same mean of
    sqrt(L) (what StatMC's test compares) but truths 3.94x apart, and their samples have the
    image's truth as their mean (20000 samples per pixel: within 5 standard errors); the
    Accumulator's statistics over chunks equal those of all the samples at once."""
    from jaxden.render.integrators import boxcox_of_samples

    bound = load_script("statmc_bound")
    truth = bound.truth_image("two-materials", 0)
    left, right = truth[:, 0], truth[:, -1]
    assert np.allclose(right / left, bound._root_mean_gamma() ** 2 / bound.GLOSSY_P)
    assert 3.9 < right[0, 0] / left[0, 0] < 4.0
    small = truth[:2, 30:34]  # two columns of each half
    samples = bound.draw(np.random.default_rng(3), "equal-root", 20000, small)
    for values, target in ((samples, small), (np.sqrt(samples), None)):
        mean, error = values.mean(0), values.std(0) / np.sqrt(len(values))
        if target is None:  # equal roots: each column against the first
            target = np.broadcast_to(mean[:, :1], mean.shape)
            error = error * np.sqrt(2.0)
        assert np.all(np.abs(mean - target) < 5 * error)
    acc = bound.Accumulator(small.shape)
    for start, stop in ((0, 7), (7, 100), (100, 356)):
        acc.add(samples[start:stop])
    frame = acc.frame()
    np.testing.assert_allclose(frame.boxcox, boxcox_of_samples(samples[:356]), rtol=2e-4,
                               atol=1e-6)
    np.testing.assert_allclose(frame.color, samples[:356].mean(0), rtol=1e-6)
    np.testing.assert_allclose(frame.variance, samples[:356].var(0, ddof=1) / 356, rtol=1e-4)
    assert frame.spp == 356
