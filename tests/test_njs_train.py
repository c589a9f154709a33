"""The neural James-Stein combiner as a trained jaxden model (``njs``): its cache over a
dataset and its replica (contents, resumption, refusals), a few training steps by jaxden's
generic loop, the run folder reloaded as a whole model (base digest checked), inference from
two half buffers (the library function and ``jaxden denoise --buffers``), and the ``njs``
evaluator. Tiny everything: the Mitsuba-free tiny dataset and its replica (32 x 32 items,
16 x 16 crops), OIDN (the pyoidn black box) as the base, a 4/8/8-wide network, 5 x 5
combination and 11 x 11 regression windows."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from jaxden.errors import ConfigError, DatasetError

TRAIN_TOML = """
model = "njs"
seed = 1
log_every = 1
eval_every = 3
eval_batches = 2
checkpoint_every = 3
[model_config]
base = "oidn"
replica = "{replica}"
cache = "{cache}"
ols_window = 11
widths = [4, 8, 8]
kernel_size = 5
[data]
dataset = "{dataset}"
crop_size = 16
batch_size = 2
[optim]
steps = 6
learning_rate = 1e-3
schedule = "constant"
loss = "relmse_njs"
"""


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """``{"root", "dataset", "replica"}``: the tiny dataset and its replica."""
    from helpers import build_tiny_dataset

    root = tmp_path_factory.mktemp("njs")
    return {"root": root, "dataset": build_tiny_dataset(root / "tiny"),
            "replica": build_tiny_dataset(root / "tiny-r1", ["replica=1"])}


@pytest.fixture(scope="module")
def run(data):
    """A run trained 6 steps (its cache built first, as a sweep would): ``(workdir, result,
    train config)``."""
    from jaxden.train.config import load_train_config
    from jaxden.train.loop import prepare_shared_data, shared_data_key, train_and_evaluate

    path = data["root"] / "train-njs.toml"
    path.write_text(TRAIN_TOML.format(dataset=data["dataset"], replica=data["replica"],
                                      cache=data["root"] / "cache"))
    config = load_train_config(path)
    assert "njs" in shared_data_key(config) and str(data["replica"]) in shared_data_key(config)
    prepare_shared_data(config, progress=False)
    workdir = data["root"] / "run"
    result = train_and_evaluate(config, workdir, progress=False, tensorboard=False)
    return workdir, result, config


def item_frames(data, spp=8):
    from jaxden.io.exr import read_frame

    path = f"s000-cornell-box/c000/spp{spp:05d}.exr"
    return read_frame(data["dataset"] / path), read_frame(data["replica"] / path), path


# -------------------------------------------------------------------------------- cache
def test_cache_holds_the_combiners_inputs_and_resumes(data, run):
    """Every input item cached; an item's images are the combination of its halves, the
    base on each and the cross regressions with the per-pixel bandwidth; a deleted file is
    recomputed alone on a rerun; a dataset is not its own replica; a folder holding another
    cache is refused, naming the difference."""
    from jaxden.data.merge import combine_buffers
    from jaxden.denoise.njs import cross_regressions, half_buffers
    from jaxden.denoise.registry import load_denoiser
    from jaxden.train.njs_cache import build_njs_cache

    cache_dir = data["root"] / "cache"
    build = lambda **kw: build_njs_cache(data["dataset"], data["replica"], "oidn", cache_dir,
                                         window=11, progress=False, **kw)
    cache = build()
    assert cache.complete and len(cache.records) == 6  # 2 crops x 3 levels
    a, b, path = item_frames(data)
    item_id = next(i for i, r in cache.records.items() if r["path"] == path)
    stored = cache.read(item_id)
    combined = combine_buffers([a, b])
    assert_allclose(stored["noisy"], combined.color, rtol=1e-6)
    assert_allclose(stored["variance"], combined.variance, rtol=1e-6)
    base = load_denoiser("oidn")
    assert_allclose(stored["denoised_a"], np.asarray(base(a)), rtol=1e-5, atol=1e-6)
    ols_a, ols_b = cross_regressions(*half_buffers(a, b, stored["denoised_a"],
                                                   stored["denoised_b"]), "pixel", window=11)
    assert_allclose(stored["ols_a"], np.asarray(ols_a), rtol=1e-5, atol=1e-6)
    assert_allclose(stored["ols_b"], np.asarray(ols_b), rtol=1e-5, atol=1e-6)

    kept = {i: r["sha256"] for i, r in cache.records.items()}
    others = {r["path"]: (cache_dir / r["path"]).stat().st_mtime_ns
              for r in cache.records.values() if r["path"] != path}
    (cache_dir / path).unlink()
    again = build()
    assert again.complete and {i: r["sha256"] for i, r in again.records.items()} == kept
    assert {p: (cache_dir / p).stat().st_mtime_ns for p in others} == others
    with pytest.raises(DatasetError, match="same render seed"):
        build_njs_cache(data["dataset"], data["dataset"], "oidn", data["root"] / "self",
                        window=11, progress=False)
    with pytest.raises(DatasetError, match="ols_ridge"):
        build(ridge=0.5)


# ----------------------------------------------------------------------------- training
def test_training_runs_by_the_generic_loop_and_the_run_is_a_whole_model(data, run):
    """Finite losses; NJS beats the combined noisy frame on the validation split; the
    checkpoint records kind, model and the base's digest and reloads; a run over other base
    weights is refused."""
    from jaxden.checkpoint import read_checkpoint_meta
    from jaxden.denoise.njs_model import (
        NJS_KIND,
        BaseMismatchError,
        NJSModelConfig,
        load_njs,
        resolve_base,
    )

    workdir, result, _ = run
    log = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    losses = [entry["loss"] for entry in log if "loss" in entry]
    assert len(losses) == 6 and all(math.isfinite(x) for x in losses)
    assert result["step"] == 6 and result["val_loss"] < result["val_baseline_loss"]
    meta = read_checkpoint_meta(workdir)
    assert (meta["kind"], meta["model"]) == (NJS_KIND, "njs")
    assert meta["model_config"]["base_sha256"] == resolve_base("oidn")[1]
    model = load_njs(workdir)
    assert model.config.widths == (4, 8, 8) and model.base.name == "oidn"
    with pytest.raises(BaseMismatchError, match="trained over base 'oidn'"):
        NJSModelConfig(base="oidn", base_sha256="0" * 64)
    with pytest.raises(ConfigError, match="odd"):
        NJSModelConfig(base="oidn", ols_window=10)


# ---------------------------------------------------------------------------- inference
def test_njs_denoise_and_the_cli(data, run, capsys):
    """njs_denoise is the network on the image-bandwidth cross regressions, clamped; `jaxden
    denoise MEAN --model RUN --buffers A B` writes the same image; without --buffers, and
    with an input that is not the halves' mean, it is one error line."""
    import jax.numpy as jnp
    from helpers import assert_one_error_line, run_cli

    from jaxden.denoise.njs import njs_apply
    from jaxden.denoise.njs_model import load_njs, njs_denoise, njs_inputs_from_halves
    from jaxden.io.exr import read_image, write_frame

    workdir = run[0]
    a, b, path = item_frames(data)
    model = load_njs(workdir)
    image, combined = njs_denoise(model, a, b)
    inputs = njs_inputs_from_halves(model.base, a, b, bandwidth="image", window=11)
    expected = njs_apply(model.params, *(jnp.asarray(x) for x in inputs[:4]),
                         model.config.njs(), clamp=True)
    assert image.shape == (32, 32, 3) and image.min() >= 0
    assert_allclose(image, np.asarray(expected), rtol=1e-5, atol=1e-6)
    assert float(combined.spp) == 16

    root = data["root"]
    write_frame(root / "mean.exr", combined)
    halves = [data["dataset"] / path, data["replica"] / path]
    out = root / "njs.exr"
    code, lines, _ = run_cli(["denoise", root / "mean.exr", "--model", workdir, "--buffers",
                              *halves, "--out", out], capsys)
    assert code == 0, lines
    assert_allclose(read_image(out), image, rtol=1e-6, atol=1e-7)
    code, lines, _ = run_cli(["denoise", root / "mean.exr", "--model", workdir, "--out", out],
                             capsys)
    assert_one_error_line(code, lines, "--buffers")
    code, lines, _ = run_cli(["denoise", halves[0], "--model", workdir, "--buffers", *halves,
                              "--out", out], capsys)
    assert_one_error_line(code, lines, "not the mean")


# ---------------------------------------------------------------------------- evaluator
def test_njs_evaluator(data, run, capsys):
    """`jaxden evaluate njs`: one row per crop and level with the combined spp and the den,
    base and mc metrics of image_errors; the tables per spp."""
    from helpers import run_cli

    from jaxden.evaluate.denoise import DENOISE_METRICS

    out = data["root"] / "eval"
    code, lines, _ = run_cli(["evaluate", "njs", "--data", data["dataset"], "--replica",
                              data["replica"], "--denoiser", run[0], "--split", "val",
                              "--spp", "2", "32", "--out", out], capsys)
    assert code == 0, lines
    result = json.loads(out.with_suffix(".json").read_text())
    rows = result["rows"]
    assert sorted(r["spp"] for r in rows) == [4, 64]
    for prefix in ("den", "base", "mc"):
        assert all(math.isfinite(r[f"{prefix}_{m}"]) for r in rows for m in DENOISE_METRICS)
    assert {"crop", "scene"} <= set(rows[0])
    assert set(result["by_spp"]) == {"4", "64"}
    assert result["provenance"]["denoiser"]["base"] == "oidn"
    assert "64 spp (combined)" in out.with_suffix(".md").read_text()
