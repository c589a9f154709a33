"""The mixer shipped for OIDN (jaxden/weights/oidn-pd.*) and the demo that uses it.

The weights must load on a fresh install with their recorded layout, carry a model card with
the command that retrains them, be found by name and by default in `jaxden progressive`, and
give the same output through every entry point. The demo (README's main command) runs on a
tiny setting and must write its files and beat the noisy input with OIDN.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from jaxden import cli
from jaxden import progressive as P
from jaxden.denoise.registry import WEIGHTS_DIR
from jaxden.errors import CheckpointError
from jaxden.io.exr import read_image, write_frame
from jaxden.progressive.inputs import MIXER_FEATURES
from jaxden.progressive.mixer_config import upgrade_mixer_config
from jaxden.render.synthetic import synthetic_render
from jaxden.sure.settings import SureSettings


def test_shipped_mixer_files_and_model_card():
    path = P.shipped_mixer_path("oidn")
    assert path == WEIGHTS_DIR / "oidn-pd.msgpack"
    assert path.stat().st_size < 4 * 2**20  # "a few MB at most"
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["kind"] == "mixer" and meta["model_config"]["denoiser"] == "oidn"
    assert meta["trained_steps"] >= 100 and meta["dataset_manifest_sha256"]
    # the card's retrain command (the committed config) reproduces these weights' recipe
    from pathlib import Path

    from jaxden.config import config_to_dict, load_config
    from jaxden.train.config import OptimConfig, load_train_config

    config_file = meta.get("train_config_file", "experiments/configs/mixer-oidn.toml")
    committed = load_train_config(Path(__file__).parent.parent / config_file)
    assert meta["trained_steps"] == committed.optim.steps and meta["seed"] == committed.seed
    # The recorded recipe, with today's defaults for optim fields added since (the same run).
    recorded = config_to_dict(load_config(meta["train_config"]["optim"], OptimConfig))
    assert recorded == config_to_dict(committed.optim)
    # (recorded with the flat SURE keys of before: the one map of older configs reads them)
    assert upgrade_mixer_config(meta["train_config"]["model_config"]) == committed.model_config
    card = path.with_suffix(".md").read_text()
    for needle in (f"jaxden train {config_file}",
                   "dataset-default.toml", "## Measured", "PD(OIDN) / OIDN"):
        assert needle in card
    params, config = P.load_mixer("oidn-pd")
    assert config.features[:len(MIXER_FEATURES)] == MIXER_FEATURES
    assert config.head == "closed_form_logit" and config.logit_bound == 4.0  # the bounded head
    # The closed form under the logit is range-aware and the t-statistic per channel, both
    # set at inference: the shipped config is the trained one with exactly the recorded
    # overrides applied.
    assert config.closed_form_stops == 1.0 and config.tstat.per_channel
    assert meta["inference_overrides"] == ["closed_form_stops=1", "tstat.per_channel=true"]
    trained = load_config(upgrade_mixer_config(meta["train_config"]["model_config"]),
                          P.MixerConfig)
    assert trained.closed_form_stops is None
    assert config == load_config(trained, P.MixerConfig,
                                 overrides=["swap_average=true", *meta["inference_overrides"]])
    leaves = jax.tree_util.tree_leaves(params)
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in leaves)
    assert P.shipped_mixer_path("unet") is None and P.shipped_progressive_denoiser("unet") is None


def test_progressive_cli_defaults_to_the_shipped_mixer(tmp_path, capsys):
    frame = synthetic_render("shipped", 16, seed=3, size=(24, 20)).numpy()
    source = tmp_path / "in.exr"
    write_frame(source, frame)
    out = tmp_path / "out.exr"
    assert cli.main(["progressive", str(source), "--denoiser", "oidn", "--out", str(out),
                     "--seed", "4"]) == 0
    params, config = P.load_mixer("oidn-pd")
    z, alpha, _ = P.progressive_denoise(frame, "oidn", params, config, jax.random.PRNGKey(4))
    np.testing.assert_allclose(read_image(out), np.asarray(z), rtol=1e-6, atol=1e-6)
    run = P.shipped_progressive_denoiser("oidn", seed=4)
    z2, alpha2 = run(frame)
    np.testing.assert_allclose(z2, np.asarray(z), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(alpha2, np.asarray(alpha), atol=1e-6)
    assert np.all((alpha2 >= 0) & (alpha2 <= 1))

    capsys.readouterr()
    code = cli.main(["progressive", str(source), "--denoiser", "kp", "--out",
                     str(tmp_path / "kp.exr")])
    err = capsys.readouterr().err
    assert code == 2 and "no mixer ships for denoiser 'kp'" in err and "--mixer" in err
    assert not (tmp_path / "kp.exr").exists()


def test_a_twin_loads_its_originals_mixer_with_its_own_sure():
    """oidn-jax ships no mixer of its own: it loads oidn-pd's weights, with one Rademacher jvp
    probe (TWIN_SURE) in place of the four finite-difference probes oidn-pd was trained on;
    oidn itself gets oidn-pd exactly as shipped."""
    import dataclasses

    params, config = P.load_mixer("oidn-pd")
    assert config.sure == SureSettings(probes=4, method="auto", fd_scheme="forward",
                                       probe_dist="normal", covariance=False, seed=0)
    twin_params, twin = P.load_shipped_mixer("oidn-jax")
    assert twin == dataclasses.replace(config, sure=config.sure.replace(
        probes=1, method="jvp", probe_dist="rademacher"))
    assert jax.tree_util.tree_all(jax.tree_util.tree_map(np.array_equal, twin_params, params))
    assert P.load_shipped_mixer("oidn")[1] == config
    assert P.load_shipped_mixer("unet") is None


@pytest.mark.slow  # ~20-30 s (OIDN in JAX compiled twice); the twin's settings are tested above
def test_oidn_in_jax_takes_oidns_mixer_with_one_rademacher_probe(tmp_path, capsys):
    """`--denoiser oidn-jax` defaults to oidn-pd (OIDN's own output to float32 rounding, so no
    note that the mixer was trained on another denoiser) fed one Rademacher jvp probe
    (TWIN_SURE): what progressive_denoise gives with those settings; --probes 4
    --probe-dist normal is what the mixer's own K = 4 gives."""
    import dataclasses

    from jaxden.io.exr import read_header

    frame = synthetic_render("shipped", 16, seed=3, size=(24, 20)).numpy()
    source, out, four = tmp_path / "in.exr", tmp_path / "out.exr", tmp_path / "four.exr"
    write_frame(source, frame)
    capsys.readouterr()
    assert cli.main(["progressive", str(source), "--denoiser", "oidn-jax", "--out", str(out),
                     "--seed", "4"]) == 0
    assert "trained on the output of" not in capsys.readouterr().err
    header = read_header(out)
    assert int(header["probes"]) == 1 and header["probe_dist"] == "rademacher"
    params, config = P.load_mixer("oidn-pd")
    assert config.sure.probes == 4 and config.sure.probe_dist == "normal"
    assert P.load_shipped_mixer("oidn-jax")[1] == dataclasses.replace(
        config, sure=config.sure.replace(probes=1, method="jvp", probe_dist="rademacher"))
    key = jax.random.PRNGKey(4)
    z, _, _ = P.progressive_denoise(frame, "oidn-jax", params, config, key,
                                    sure=SureSettings(probes=1, probe_dist="rademacher"))
    # The CLI's compiled program differs from progressive_denoise's: OIDN's U-Net and its jvp
    # round differently, measured up to 1e-4 relative in z on this frame.
    close = dict(rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(read_image(out), np.asarray(z), **close)
    z2, _ = P.shipped_progressive_denoiser("oidn-jax", seed=4)(frame)
    np.testing.assert_allclose(z2, np.asarray(z), **close)
    assert cli.main(["progressive", str(source), "--denoiser", "oidn-jax", "--probes", "4",
                     "--probe-dist", "normal", "--out", str(four), "--seed", "4"]) == 0
    z4, _, _ = P.progressive_denoise(frame, "oidn-jax", params, config, key)
    np.testing.assert_allclose(read_image(four), np.asarray(z4), **close)
    assert not np.allclose(z4, np.asarray(z), **close)  # the SURE form shows at this tolerance


@pytest.mark.slow  # ~7 s; tests/test_demo_outputs.py runs the same demo entry point by default
def test_demo_writes_frames_and_oidn_beats_the_noisy_input(tmp_path):
    from jaxden.demo import DemoSettings, run_demo

    settings = DemoSettings(scenes=("cornell-box",), size=(32, 32), spp_levels=(4, 16),
                            reference_spp=256, seed=7)
    summary = run_demo(tmp_path, settings=settings)
    rows = summary["rows"]
    assert {(r["spp"], r["method"]) for r in rows} == {
        (s, m) for s in (4, 16) for m in ("mc", "oidn", "wskp6", "pd_oidn", "pd_wskp6")}
    assert json.loads((tmp_path / "summary.json").read_text())["rows"] == rows
    for name in ("reference.exr", "spp00004.exr", "spp00004.oidn.exr", "spp00016.pd_oidn.exr"):
        assert (tmp_path / "cornell-box" / name).is_file()
    at4 = {r["method"]: r for r in rows if r["spp"] == 4}
    assert at4["oidn"]["relmse"] < 0.75 * at4["mc"]["relmse"]  # measured 0.55x (seed 7)
    assert at4["pd_oidn"]["relmse"] < at4["mc"]["relmse"]


def test_mixer_name_that_does_not_exist_is_a_clear_error():
    with pytest.raises(CheckpointError, match="no-such-mixer: no such checkpoint"):
        P.load_mixer("no-such-mixer")


@pytest.mark.slow
def test_progressive_bench_quick():
    """`jaxden bench progressive` runs end to end on the quick size (structure only: speed is
    the benchmark's business, not a unit test's)."""
    from jaxden import bench

    result = bench.run("progressive", quick=True)
    keys = ("pd_over_oidn", "pd_single_over_oidn", "mixer_over_oidn", "tstat_over_oidn",
            "closed_form_over_oidn", "closed_form_stops_over_closed_form")
    assert all(np.isfinite(result[k]) and result[k] > 0 for k in keys)
    assert (result["width"], result["height"]) == (320, 180)


def test_wskp6_mixer_ships_with_its_recipe_and_is_the_default_for_wskp6(tmp_path, capsys):
    """`wskp-6-pd`: PD over the shipped real-time WSKP-6. Its recorded recipe is the committed
    mixer-wskp6.toml (jvp SURE, one probe), `jaxden progressive --denoiser wskp-6` picks it by
    default and gives what progressive_denoise gives with its probes, and the card names its
    base, not OIDN."""
    from pathlib import Path

    from jaxden.train.config import load_train_config

    path = P.shipped_mixer_path("wskp-6")
    assert path == WEIGHTS_DIR / "wskp-6-pd.msgpack"
    assert path.stat().st_size < 4 * 2**20
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["kind"] == "mixer" and meta["model_config"]["denoiser"] == "wskp-6"
    assert meta["train_config_file"] == "experiments/configs/mixer-wskp6.toml"
    committed = load_train_config(Path(__file__).parent.parent / meta["train_config_file"])
    assert upgrade_mixer_config(meta["train_config"]["model_config"]) == committed.model_config
    assert meta["trained_steps"] == committed.optim.steps and meta["seed"] == committed.seed
    params, config = P.load_mixer("wskp-6-pd")
    assert (config.sure.probes, config.sure.method, config.width) == (1, "auto", 16)
    card = path.with_suffix(".md").read_text()
    assert "OIDN" not in card and "--denoiser wskp-6 --mixer wskp-6-pd" in card
    assert "jax.jvp" in card and "## Measured" in card

    frame = synthetic_render("shipped", 16, seed=3, size=(24, 20)).numpy()
    source, out = tmp_path / "in.exr", tmp_path / "out.exr"
    write_frame(source, frame)
    assert cli.main(["progressive", str(source), "--denoiser", "wskp-6", "--out", str(out),
                     "--seed", "4"]) == 0
    assert "trained on the output" not in capsys.readouterr().err
    z, alpha, _ = P.progressive_denoise(frame, "wskp-6", params, config, jax.random.PRNGKey(4))
    np.testing.assert_allclose(read_image(out), np.asarray(z), rtol=1e-5, atol=1e-5)
    z2, alpha2 = P.shipped_progressive_denoiser("wskp-6", seed=4)(frame)
    np.testing.assert_allclose(z2, np.asarray(z), rtol=1e-5, atol=1e-5)
    assert np.all((alpha2 >= 0) & (alpha2 <= 1))
