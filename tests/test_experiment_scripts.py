"""Pure helpers of the experiment scripts (experiments/*.py), tested without data or renders."""

import argparse
import json
import math
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent.parent / "experiments"))
import aux_features
import cflogit_bound
import closed_form_sigma
import closed_form_stops
import mix_combinations
import pd_figure  # the experiment scripts are part of the repository: no skip
import sure_stein


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


def test_neighbour_mean_excludes_the_centre():
    rng = np.random.default_rng(0)
    values = rng.random((5, 6, 3))
    got = sure_stein.neighbour_mean(values)
    padded = np.pad(values, ((1, 1), (1, 1), (0, 0)), mode="edge")
    i, j = 2, 3
    window = padded[i:i + 3, j:j + 3]
    np.testing.assert_allclose(got[i, j], (window.sum((0, 1)) - values[i, j]) / 8)
    corner = padded[0:3, 0:3]
    np.testing.assert_allclose(got[0, 0], (corner.sum((0, 1)) - values[0, 0]) / 8)


def test_aux_features_ratios_are_ratios_of_crop_means():
    names = ["first-hit:16:clean", "specular-chain:256:noisy"]
    rows = []
    for crop, errors in (("a", (1.0, 0.5)), ("b", (3.0, 3.0))):
        for spp in (64, 256):
            rows.append({"crop": crop, "spp": spp, "errors": {
                name: {"rmse": e * 64 / spp, "relmse": e, "mse_nc": e * e}
                for name, e in zip(names, errors)}})
    summary = aux_features.summarize(rows, names)
    # Per spp: (0.5 + 3) / (1 + 3) = 0.875 for RMSE and relMSE; (0.25 + 9) / (1 + 9) for MSE.
    for spp in (64, 256):
        ratio = summary["per_spp"][spp]["ratio"][names[1]]
        assert ratio["rmse"] == pytest.approx(0.875) and ratio["relmse"] == pytest.approx(0.875)
        assert ratio["mse_nc"] == pytest.approx(9.25 / 10)
        assert summary["per_spp"][spp]["ratio"][names[0]]["rmse"] == 1.0
    assert summary["per_crop"]["a"][names[1]]["rmse"] == pytest.approx(0.5)
    assert summary["mean_over_spp"][names[1]]["rmse"] == pytest.approx(0.875)
    assert aux_features.parse_variant("specular-chain:256:noisy") == ("specular-chain", 256, "noisy")
    assert aux_features.parse_variant("none") == ("none", 0, "clean")
    for bad in ("first-hit:16", "next-hit:16:clean", "first-hit:0:clean", "first-hit:x:clean"):
        with pytest.raises(SystemExit, match="--variant"):
            aux_features.parse_variant(bad)


def test_closed_form_sigma_summary_and_selection():
    rows = []
    for crop, oidn in (("a", 1.0), ("b", 4.0)):
        for spp in (8, 64):
            # sigma=2: 2x OIDN on crop a, 0.5x on b (geometric mean 1); sigma=8: 0.9x on both.
            rows.append({"crop": crop, "spp": spp, "mc": 3 * oidn, "oidn": oidn,
                         "sigma=2": oidn * (2.0 if crop == "a" else 0.5),
                         "sigma=8": 0.9 * oidn, "mixer m": oidn})
    summary = closed_form_sigma.summarize(rows, [2.0, 8.0], ["m"])
    assert summary["sigma=2"]["geometric_mean"] == pytest.approx(1.0)
    assert summary["sigma=8"]["geometric_mean"] == pytest.approx(0.9)
    assert summary["mc"]["median"] == pytest.approx(3.0)
    # crop means per spp: (2 + 2) / (1 + 4) = 0.8, the metric a bright crop dominates
    assert summary["sigma=2"]["mean_over_spp_of_crop_mean_ratio"] == pytest.approx(0.8)
    text = closed_form_sigma.markdown(summary, rows, worst=1)
    assert "best: **sigma=8**" in text  # the criterion picks 8 although 2 wins crop means
    assert "| a | 8 |" in text or "| a | 64 |" in text  # the worst input at sigma=8 (a tie)


def test_mix_combinations_summary():
    rows = []
    for crop, oidn in (("a", 1.0), ("b", 3.0)):
        for spp in (8, 64):
            row = {"crop": crop, "spp": spp, "mc": [2.0 * oidn, 4.0], "oidn": [oidn, 1.0]}
            # mixer: 0.9x OIDN in RMSE, 1.1x in relMSE; at 64 spp above MC on crop b only.
            row["mixer"] = [0.9 * oidn, 1.1]
            if spp == 64 and crop == "b":
                row["mixer"] = [7.0, 1.1]
            row["closed form"] = row["min"] = row["mean"] = [oidn, 1.0]
            rows.append(row)
    summary = mix_combinations.summarize(rows)["mixer"]
    # 8 spp: (0.9 + 2.7) / 4 = 0.9; 64 spp: (0.9 + 7) / 4 = 1.975; mean over spp 1.4375
    assert summary["rmse_over_oidn"] == pytest.approx(1.4375)
    assert summary["relmse_over_oidn"] == pytest.approx(1.1)
    assert summary["rmse_over_mc_at_max_spp"] == pytest.approx(7.9 / 8.0)
    assert summary["worst_crop"] == "b" and summary["worst_crop_over_mc"] == pytest.approx(7 / 6)
    assert summary["crops_above_mc"] == 1 and summary["max_spp"] == 64
    text = mix_combinations.markdown(mix_combinations.summarize(rows))
    assert "| mixer | 1.438 | 1.100 | 0.988 | 1.167 (b) | 1 of 2 |" in text


def test_cflogit_bound_interpolates_from_the_closed_form_to_the_oracle():
    """B = 0 is the closed form, B = inf the oracle (both clipped to [eps, 1 - eps]); in
    between the logit moves min(|c*|, B) toward the oracle, never past it."""
    rng = np.random.default_rng(3)
    a_cf = rng.uniform(0, 1, (6, 6, 3))
    a_cf[0, 0] = 1.0
    oracle = rng.uniform(0, 1, (6, 6, 3))
    oracle[0, 0] = 0.0
    got = cflogit_bound.bounded_alphas(a_cf, oracle, (0.0, 1.0, math.inf))
    eps = cflogit_bound.EPS
    np.testing.assert_allclose(got[0.0], np.clip(a_cf, eps, 1 - eps), rtol=1e-9)
    np.testing.assert_allclose(got[math.inf], np.clip(oracle, eps, 1 - eps), rtol=1e-9)
    shift = cflogit_bound.logit(got[1.0]) - cflogit_bound.logit(a_cf)
    wanted = cflogit_bound.logit(oracle) - cflogit_bound.logit(a_cf)
    np.testing.assert_allclose(shift, np.clip(wanted, -1, 1), atol=1e-9)
    assert got[1.0][0, 0, 0] == pytest.approx(1 / (1 + np.exp(-(np.log((1 - eps) / eps) - 1))))
    assert cflogit_bound.bound_name(math.inf) == "B=inf (oracle)"
    assert cflogit_bound.bound_name(2.0) == "B=2"


def test_mixer_alpha_worst_pixels_finds_the_largest_errors():
    import mixer_alpha

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
    import ship_mixer

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


def test_closed_form_stops_summary_and_selection():
    rows = []
    for crop, oidn in (("a", [1.0, 0.1]), ("b", [4.0, 0.2])):
        for spp in (8, 64):
            # stops=none: RMSE 0.9x, relMSE 2x; stops=1: RMSE 0.95x, relMSE 0.8x (wins on the
            # mean of the two geometric means, 0.875 against 1.45).
            rows.append({"crop": crop, "spp": spp, "mc": [3 * oidn[0], 5 * oidn[1]],
                         "oidn": oidn, "stops=none": [0.9 * oidn[0], 2 * oidn[1]],
                         "stops=1": [0.95 * oidn[0], 0.8 * oidn[1]]})
    keys = ["mc", "stops=none", "stops=1"]
    summary = closed_form_stops.summarize(rows, keys)
    assert summary["rmse"]["stops=none"]["geometric_mean"] == pytest.approx(0.9)
    assert summary["relmse"]["stops=1"]["median"] == pytest.approx(0.8)
    assert summary["relmse"]["mc"]["mean_over_spp_of_crop_mean_ratio"] == pytest.approx(5.0)
    assert closed_form_stops.best_stops(summary, keys) == "stops=1"
    assert "best: **stops=1**" in closed_form_stops.markdown(summary, keys, len(rows))
    assert closed_form_stops.parse_stops("none") is None
    assert closed_form_stops.parse_stops("0.5") == 0.5
    for bad in ("0", "-1", "x"):
        with pytest.raises(argparse.ArgumentTypeError):
            closed_form_stops.parse_stops(bad)


def test_demo_mixers_bands_and_specs():
    import demo_mixers

    reference = np.zeros((2, 2, 3))
    reference[0] = 0.5  # top row in [0.3, 1), bottom row in [0, 0.02)
    image = reference + 0.1
    rows = demo_mixers.band_rows(reference, {"m": image}, {"m": np.full((2, 2, 3), 0.25)})
    assert [r["band"] for r in rows] == [[0.0, 0.02], [0.3, 1.0]]
    assert rows[0]["fraction"] == 0.5 and rows[0]["alpha m"] == 0.25
    assert rows[0]["m"] == pytest.approx(0.01 / 0.01)  # relMSE eps 0.01
    assert rows[1]["m"] == pytest.approx(0.01 / 0.26)
    _, config = demo_mixers.load("closed-form|closed_form_stops=2, closed_form_sigma=3")
    assert (config.closed_form_stops, config.closed_form_sigma) == (2.0, 3.0)
    from jaxden.errors import ConfigError

    with pytest.raises(ConfigError, match="closed_form_stop"):
        demo_mixers.load("closed-form|closed_form_stop=2")
    assert demo_mixers.parse_band("cornell-box:64") == ("cornell-box", 64)
    with pytest.raises(argparse.ArgumentTypeError):
        demo_mixers.parse_band("cornell-box")


def test_ship_mixer_reship_sets_inference_fields_and_keeps_the_weights(tmp_path, monkeypatch):
    """--reship re-exports shipped weights without their run: the parameters byte for byte,
    the training facts (read back from the card for weights shipped before training_facts),
    the --set field changed in the shipped config and stated in the card."""
    import shutil

    import ship_mixer

    import jaxden.denoisers
    from jaxden import progressive as P

    for suffix in (".msgpack", ".json", ".md"):
        shutil.copy(jaxden.denoisers.WEIGHTS_DIR / f"oidn-pd{suffix}", tmp_path)
    meta = json.loads((tmp_path / "oidn-pd.json").read_text())
    meta.pop("training_facts", None)  # as shipped before session 11: facts from the card
    meta.pop("inference_overrides", None)
    (tmp_path / "oidn-pd.json").write_text(json.dumps(meta))
    original_card = (tmp_path / "oidn-pd.md").read_text()
    validation = next(line for line in original_card.splitlines() if "- Validation" in line)
    _, original_config = P.load_mixer(str(tmp_path / "oidn-pd.msgpack"))
    weights = (tmp_path / "oidn-pd.msgpack").read_bytes()
    monkeypatch.setattr(jaxden.denoisers, "WEIGHTS_DIR", tmp_path)
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
    # A second re-ship reads the recorded facts and keeps the recorded overrides.
    assert ship_mixer.main(["--reship", "oidn-pd", "--config", meta["train_config_file"]]) == 0
    assert json.loads((tmp_path / "oidn-pd.json").read_text())["inference_overrides"] == [
        "closed_form_stops=2"]
    assert (tmp_path / "oidn-pd.md").read_text() == card
