"""The progressive-denoising pipeline end to end: mixer training through `jaxden train` on a
tiny cached dataset (experiments/configs/mixer-tiny.toml), the training batches (swaps),
progressive_denoise with OIDN, the `sure` / `progressive` / `dataset sure-cache` commands, and
bad inputs (no variance, negative variance, mismatched or wrong-kind mixer checkpoints).

Data: Mitsuba-free (jaxden.render.synthetic.synthetic_render): dataset-tiny.toml with 2 crops per
scene (12 inputs of 32 x 32 at 2, 8, 32 spp); the mixer trains 40 steps on 16 x 16 crops.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxden import cli, metrics
from jaxden import progressive as P
from jaxden.checkpoint import save_weights
from jaxden.config import load_config
from jaxden.data.builder import build_dataset
from jaxden.data.config import DatasetConfig
from jaxden.denoise.registry import load_denoiser, make_denoiser
from jaxden.errors import CheckpointError, ConfigError, FrameError
from jaxden.io.exr import read_channels, read_header, read_image, write_channels, write_frame
from jaxden.progressive.cache import SureCache
from jaxden.progressive.inputs import MIXER_FEATURES_NO_SURE
from jaxden.progressive.network import inference_alpha
from jaxden.render.synthetic import synthetic_render
from jaxden.sure.denoiser import denoise_with_sure
from jaxden.sure.settings import SureSettings
from jaxden.sure.stein import draw_probes, sure_blackbox
from jaxden.train.config import load_train_config
from jaxden.train.loop import _loaders
from jaxden.train.tasks import mixer_task

ROOT = Path(__file__).resolve().parent.parent  # the checkout: tests run from any folder
TINY_DATA = str(ROOT / "experiments" / "configs" / "dataset-tiny.toml")
TINY_MIXER = str(ROOT / "experiments" / "configs" / "mixer-tiny.toml")


# ------------------------------------------------------------------------ helpers


def run_cli(argv, capsys):
    """Run the jaxden CLI; returns (exit code, stdout, stderr)."""
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def small_frame(seed=5, size=(24, 20), spp=16):
    return synthetic_render("pipeline", spp, seed=seed, size=size).numpy()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """(dataset folder, training workdir) after `jaxden train mixer-tiny.toml` (builds the
    OIDN SURE cache on the way)."""
    root = tmp_path_factory.mktemp("pd")
    dataset = root / "tiny"
    config = load_config(TINY_DATA, DatasetConfig, ["crops_per_scene=2"])
    build_dataset(config, dataset, executor="serial", render_fn=synthetic_render, progress=False)
    workdir = root / "run"
    code = cli.main(["train", TINY_MIXER, f"data.dataset={dataset}", "--workdir", str(workdir)])
    assert code == 0
    return dataset, workdir


def train_config(dataset):
    return load_train_config(TINY_MIXER, [f"data.dataset={dataset}"])


# ------------------------------------------------------------------------ training


def test_training_lowers_the_loss_and_swap_symmetry_is_measured(trained):
    dataset, workdir = trained
    assert (dataset / "derived" / "oidn" / "sure-cache.json").is_file()
    config = train_config(dataset)
    task = mixer_task(config)
    train, val = _loaders(config, task)
    batches = [task.prepare(b) for epoch in range(3) for b in train.epoch(epoch)]
    initial = task.init(jax.random.PRNGKey(config.seed), batches[0])  # as train_and_evaluate
    params, mixer_config = P.load_mixer(workdir)
    assert mixer_config == load_config(config.model_config, P.MixerConfig)

    def mean_loss(p):
        return float(np.mean([metrics.smape(task.predict(p, b), b["reference"]) for b in batches]))

    before, after = mean_loss(initial), mean_loss(params)
    log = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    print(f"\ntraining SMAPE on {len(batches)} fixed batches: {before:.4f} -> {after:.4f}; "
          f"logged {[round(e['loss'], 4) for e in log if 'loss' in e]}")
    assert after < 0.9 * before

    # Swap symmetry on the (unswapped) validation crops. With swap averaging (inference form,
    # inference_alpha) alpha(x, y) + alpha(y, x) = 1 holds by construction: asserted to float32
    # round-off (1e-6 on values in [0, 1]). A single mixer call has no such guarantee: the gap
    # mean |alpha(x, y) - (1 - alpha(y, x))| is bounded by what was measured, with margin. The
    # centred head starts every alpha near 1/2 (output kernel scaled by 0.1), so the untrained
    # gap is small; training (the swap only encourages symmetry) moves it. Measured here:
    # init 0.081, trained 0.357 (CPU, seed 0).
    assert mixer_config.uses_sure  # so the swapped call is alpha(y, x, sure, var)
    gaps = {}
    for name, p in (("init", initial), ("trained", params)):
        values = []
        for batch in val.epoch(0):
            b = task.prepare(batch)
            x, y, var, sure = b["x"], b["y"], b["var"], b["sure"]
            values.append(P.swap_symmetry(p, mixer_config, x, y, var, sure))
            forward = np.asarray(inference_alpha(p, x, y, var, sure, mixer_config, True))
            backward = np.asarray(inference_alpha(p, y, x, sure, var, mixer_config, True))
            np.testing.assert_allclose(forward + backward, 1.0, rtol=0, atol=1e-6)
            assert np.all((forward >= 0) & (forward <= 1))
        gaps[name] = float(np.mean(values))
    print(f"swap symmetry mean |alpha(x,y) - (1 - alpha(y,x))|: {gaps}")
    assert 0 < gaps["init"] < 0.2, gaps
    assert 0.15 < gaps["trained"] < 0.6, gaps


def test_a_run_saved_before_a_new_config_field_resumes(trained, tmp_path):
    """Adding a MixerConfig field with a default (swap_average) must not make older
    checkpoints 'of another config': the stored model_config is read with today's defaults."""
    dataset, workdir = trained
    old = tmp_path / "old-run"
    shutil.copytree(workdir, old)
    for meta_file in old.glob("*/meta/metadata"):
        meta = json.loads(meta_file.read_text())
        assert meta["model_config"].pop("swap_average") is False
        meta_file.write_text(json.dumps(meta))
    config = train_config(dataset)
    from jaxden.train.loop import train_and_evaluate

    result = train_and_evaluate(config, old, progress=False)  # resumes at the last step
    assert np.isfinite(result["val_loss"])
    # ... but a real difference is still refused
    for meta_file in old.glob("*/meta/metadata"):
        meta = json.loads(meta_file.read_text())
        meta["model_config"]["width"] = 8
        meta_file.write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="another model or config"):
        train_and_evaluate(config, old, progress=False)


def test_training_batches_swap_reproducibly(trained):
    dataset, _ = trained
    config = train_config(dataset)
    task = mixer_task(config)
    train, val = _loaders(config, task)
    cache = SureCache(dataset, dataset / "derived" / "oidn")
    swapped = kept = 0
    for epoch in range(4):
        for batch in train.epoch(epoch):
            first, second = task.prepare(batch), task.prepare(batch)
            for name in first:
                np.testing.assert_array_equal(first[name], second[name])
            denoised, sure_map, _ = cache.crops_for(batch)
            x, var = batch.input.color, batch.input.variance
            for b in range(x.shape[0]):
                if np.array_equal(first["x"][b], x[b]):
                    kept += 1
                    np.testing.assert_array_equal(first["y"][b], denoised[b])
                    np.testing.assert_array_equal(first["var"][b], var[b])
                    np.testing.assert_array_equal(first["sure"][b], sure_map[b])
                else:
                    swapped += 1
                    np.testing.assert_array_equal(first["x"][b], denoised[b])
                    np.testing.assert_array_equal(first["y"][b], x[b])
                    np.testing.assert_array_equal(first["var"][b], sure_map[b])
                    np.testing.assert_array_equal(first["sure"][b], var[b])
                np.testing.assert_array_equal(first["reference"][b], batch.reference.color[b])
    # 24 samples, each swapped with probability 1/2: both kinds occur (P(not) = 2^-23).
    assert swapped > 0 and kept > 0
    for batch in val.epoch(0):
        np.testing.assert_array_equal(task.prepare(batch)["x"], batch.input.color)


# ------------------------------------------------------------------------ inference


def test_progressive_denoise_with_oidn_end_to_end(trained):
    _, workdir = trained
    params, config = P.load_mixer(workdir)
    frame = small_frame()
    key = jax.random.PRNGKey(3)
    z, alpha_prime, extras = P.progressive_denoise(frame, "oidn", params, config, key)
    assert z.shape == alpha_prime.shape == (20, 24, 3)
    oidn = make_denoiser("oidn")
    np.testing.assert_array_equal(np.asarray(extras["denoised"]), oidn(frame))
    probes = np.asarray(draw_probes(key, frame.variance, 4), np.float64)
    direct = sure_blackbox(oidn.function(), frame, probes=probes, eps=1e-2)
    np.testing.assert_array_equal(np.asarray(extras["sure"]), direct.sure)
    x, var, y = frame.color, frame.variance, direct.denoised
    alpha = np.asarray(P.mixer_alpha(params, config, x, y, var, direct.sure))
    np.testing.assert_allclose(np.asarray(extras["alpha"]), alpha, atol=1e-6)
    np.testing.assert_allclose(np.asarray(extras["mixed"]), x + alpha * (y - x), atol=1e-5)
    want = P.t_statistic_scaling(extras["alpha"], x, extras["mixed"], var, config.tstat)
    np.testing.assert_allclose(np.asarray(alpha_prime), np.asarray(want), atol=1e-6)
    a, a_prime = np.asarray(extras["alpha"]), np.asarray(alpha_prime)
    assert np.all(a_prime >= 0) and np.all(a_prime <= a + 1e-7)
    np.testing.assert_allclose(np.asarray(z), x + a_prime * (y - x), atol=1e-5)
    # Without the t-test alpha' = alpha and z' = z.
    z0, alpha0, _ = P.progressive_denoise(frame, "oidn", params, config, key, tstat=None)
    np.testing.assert_array_equal(np.asarray(alpha0), a)
    np.testing.assert_allclose(np.asarray(z0), np.asarray(extras["mixed"]), atol=1e-6)
    # swap_average: alpha is the mean of the mixer and 1 - its swapped call (y <-> x, SURE <->
    # var), and the t-test and mix use that alpha.
    z2, alpha2, extras2 = P.progressive_denoise(frame, "oidn", params, config, key,
                                                swap_average=True)
    swapped = np.asarray(P.mixer_alpha(params, config, y, x, direct.sure, var))
    np.testing.assert_allclose(np.asarray(extras2["alpha"]), 0.5 * (alpha + 1 - swapped),
                               atol=1e-6)
    assert np.abs(np.asarray(extras2["alpha"]) - alpha).max() > 1e-4  # the option did something
    want2 = P.t_statistic_scaling(extras2["alpha"], x, extras2["mixed"], var, config.tstat)
    np.testing.assert_allclose(np.asarray(alpha2), np.asarray(want2), atol=1e-6)
    np.testing.assert_allclose(np.asarray(z2), x + np.asarray(alpha2) * (y - x), atol=1e-5)
    # ... and the config's flag is the default.
    on = dataclasses.replace(config, swap_average=True)
    _, alpha3, _ = P.progressive_denoise(frame, "oidn", params, on, key)
    np.testing.assert_array_equal(np.asarray(alpha3), np.asarray(alpha2))


def test_progressive_denoise_input_errors(trained):
    _, workdir = trained
    params, config = P.load_mixer(workdir)
    frame = small_frame()
    key = jax.random.PRNGKey(0)
    with pytest.raises(FrameError, match="SURE needs the variance"):
        P.progressive_denoise(frame.replace(variance=None), "oidn", params, config, key)
    bad = frame.variance.copy()
    bad[3, 4, 1] = -0.5
    with pytest.raises(FrameError, match="variance must be >= 0"):
        P.progressive_denoise(frame.replace(variance=bad), "oidn", params, config, key)
    nan = frame.color.copy()
    nan[0, 0, 0] = np.nan
    with pytest.raises(FrameError, match="non-finite"):
        P.progressive_denoise(frame.replace(color=nan), "oidn", params, config, key)
    # The authors' repair policy: NaN -> 0, then the pipeline runs.
    z, _, _ = P.progressive_denoise(frame.replace(color=nan), "oidn", params, config, key,
                                    nonfinite="zero")
    assert np.all(np.isfinite(np.asarray(z)))


# ------------------------------------------------------------------------ command line


def test_cli_sure_writes_denoised_and_sure(tmp_path, capsys):
    frame = small_frame(seed=8)
    source = tmp_path / "in.exr"
    write_frame(source, frame)
    out = tmp_path / "sure.exr"
    code, stdout, stderr = run_cli(["sure", source, "--denoiser", "oidn", "--out", out,
                                    "--seed", 4], capsys)
    assert code == 0, stderr
    assert "image SURE" in stdout
    data, header = read_channels(out)
    assert set(data) == {"R", "G", "B", "sure.R", "sure.G", "sure.B", "divergence.R",
                         "divergence.G", "divergence.B"}
    assert header["denoiser"] == "oidn" and header["probes"] == 4
    direct, _ = denoise_with_sure("oidn", frame, jax.random.PRNGKey(4))
    np.testing.assert_array_equal(read_image(out), direct.denoised)
    np.testing.assert_array_equal(read_image(out, ("sure.R", "sure.G", "sure.B")), direct.sure)


def test_cli_sure_from_buffers(tmp_path, capsys):
    """`jaxden sure IN.exr --buffers ...`: equals sure_buffers on the same arrays; buffers
    that do not average to IN are refused by name."""
    from jaxden.sure.buffers import combine_buffers, sure_buffers

    parts = [small_frame(seed=20 + k, spp=4) for k in range(4)]
    full = combine_buffers(parts).replace(spp=None)
    full = full.replace(**{n: np.asarray(getattr(full, n), np.float32) for n in full.features()})
    source = tmp_path / "full.exr"
    write_frame(source, full)
    paths = []
    for k, part in enumerate(parts):
        paths.append(tmp_path / f"b{k}.exr")
        write_frame(paths[-1], part)
    out = tmp_path / "sure.exr"
    code, stdout, stderr = run_cli(["sure", source, "--buffers", *paths, "--denoiser", "oidn",
                                    "--out", out], capsys)
    assert code == 0, stderr
    assert "4 buffers" in stdout
    direct = sure_buffers(load_denoiser("oidn"), full, np.stack([p.color for p in parts]))
    np.testing.assert_allclose(read_image(out, ("sure.R", "sure.G", "sure.B")), direct.sure,
                               rtol=1e-5, atol=1e-9)
    assert read_header(out)["method"] == "buffers"
    code, _, stderr = run_cli(["sure", source, "--buffers", *paths, "--extrapolate",
                               "--denoiser", "oidn", "--out", tmp_path / "rx.exr"], capsys)
    assert code == 0, stderr
    extrapolated = sure_buffers(load_denoiser("oidn"), full, np.stack([p.color for p in parts]),
                                extrapolate=True)
    np.testing.assert_allclose(read_image(tmp_path / "rx.exr", ("sure.R", "sure.G", "sure.B")),
                               extrapolated.sure, rtol=1e-5, atol=1e-9)
    code, _, stderr = run_cli(["sure", source, "--extrapolate", "--denoiser", "oidn", "--out",
                               tmp_path / "x.exr"], capsys)
    assert code != 0 and "--extrapolate needs --buffers" in stderr
    code, _, stderr = run_cli(["sure", source, "--buffers", *paths[:3], "--denoiser", "oidn",
                               "--out", tmp_path / "bad.exr"], capsys)
    assert code != 0 and "not the mean" in stderr and "full.exr" in stderr
    assert not (tmp_path / "bad.exr").exists()


def test_cli_sure_reads_files_of_other_renderers(tmp_path, capsys):
    frame = small_frame(seed=9)
    plain = tmp_path / "plain.exr"  # colour + variance only: no albedo or normal
    write_channels(plain, {**{c: frame.color[..., i] for i, c in enumerate("RGB")},
                           **{f"variance.{c}": frame.variance[..., i]
                              for i, c in enumerate("RGB")}})
    code, _, stderr = run_cli(["sure", plain, "--denoiser", "oidn", "--out", tmp_path / "a.exr",
                               "--spp", 16], capsys)
    assert code == 0, stderr
    named = tmp_path / "named.exr"  # another renderer's names, per-sample variance
    write_channels(named, {**{c: frame.color[..., i] for i, c in enumerate("RGB")},
                           **{f"color_var.{c}": 16 * frame.variance[..., i]
                              for i, c in enumerate("RGB")}}, attributes={"spp": 16})
    code, _, stderr = run_cli(["sure", named, "--denoiser", "oidn", "--out", tmp_path / "b.exr",
                               "--variance-channels", "color_var.R,color_var.G,color_var.B",
                               "--sample-variance"], capsys)
    assert code == 0, stderr
    np.testing.assert_allclose(read_image(tmp_path / "b.exr", ("sure.R", "sure.G", "sure.B")),
                               read_image(tmp_path / "a.exr", ("sure.R", "sure.G", "sure.B")),
                               rtol=1e-4, atol=1e-6)


def test_cli_channels_maps_another_renderers_names(tmp_path, capsys):
    """--channels FIELD=NAMES reads a file with another renderer's names (here pbrt-v4-like)
    exactly as the same data under jaxden's names; OIDN without features is announced."""
    frame = small_frame(seed=13)
    ours = tmp_path / "ours.exr"
    write_frame(ours, frame)
    names = {"color": ("R", "G", "B"), "variance": ("Variance.R", "Variance.G", "Variance.B"),
             "albedo": ("Albedo.R", "Albedo.G", "Albedo.B"), "normal": ("Ns.X", "Ns.Y", "Ns.Z")}
    theirs = tmp_path / "theirs.exr"
    write_channels(theirs, {name: getattr(frame, field)[..., i]
                            for field, channels in names.items()
                            for i, name in enumerate(channels)}, attributes={"spp": 16})
    mapping = [arg for field in ("variance", "albedo", "normal")
               for arg in ("--channels", f"{field}={','.join(names[field])}")]
    code, _, stderr = run_cli(["progressive", ours, "--denoiser", "oidn", "--out",
                               tmp_path / "a.exr"], capsys)
    assert code == 0 and "note" not in stderr, stderr
    code, _, stderr = run_cli(["progressive", theirs, "--denoiser", "oidn", *mapping, "--out",
                               tmp_path / "b.exr"], capsys)
    assert code == 0 and "note" not in stderr, stderr
    np.testing.assert_array_equal(read_image(tmp_path / "b.exr"), read_image(tmp_path / "a.exr"))
    code, _, stderr = run_cli(["denoise", theirs, "--model", "oidn", *mapping[2:], "--out",
                               tmp_path / "c.exr"], capsys)
    assert code == 0 and "note" not in stderr, stderr
    code, _, _ = run_cli(["denoise", ours, "--model", "oidn", "--out", tmp_path / "d.exr"],
                         capsys)
    np.testing.assert_array_equal(read_image(tmp_path / "c.exr"), read_image(tmp_path / "d.exr"))
    # Without the mapping the features are not found: said on stderr, not silently dropped.
    code, _, stderr = run_cli(["sure", theirs, "--denoiser", "oidn", *mapping[:2], "--out",
                               tmp_path / "e.exr"], capsys)
    assert code == 0 and "no albedo or normal channels" in stderr and "--channels" in stderr
    # Bad specifications (argparse's usage error) and channels the file lacks are clear errors.
    for bad, message in [(["--channels", "albedo=Albedo.R,Albedo.G"], "albedo takes 3"),
                         (["--channels", "colour=A,B,C"], "FIELD one of color"),
                         (["--channels", "albedo"], "expected FIELD=NAME")]:
        with pytest.raises(SystemExit) as exit_info:
            run_cli(["sure", theirs, "--denoiser", "oidn", *bad, "--out", tmp_path / "f.exr"],
                    capsys)
        assert exit_info.value.code == 2 and message in capsys.readouterr().err, bad
    for bad, message in [(["--channels", "variance=V.R,V.G,V.B", "--variance-channels",
                           "W.R,W.G,W.B"], "given twice, differently"),
                         (["--channels", "normal=N.X,N.Y,N.Z"], "normal needs N.X, N.Y, N.Z")]:
        code, _, stderr = run_cli(["sure", theirs, "--denoiser", "oidn", *mapping[:2], *bad,
                                   "--out", tmp_path / "f.exr"], capsys)
        assert code == 2 and message in stderr, (bad, stderr)
    assert not (tmp_path / "f.exr").exists()


def test_cli_progressive_and_sure_cache(trained, tmp_path, capsys):
    dataset, workdir = trained
    frame = small_frame(seed=11)
    source = tmp_path / "in.exr"
    write_frame(source, frame)
    out, alpha = tmp_path / "out.exr", tmp_path / "alpha.exr"
    code, stdout, stderr = run_cli(["progressive", source, "--denoiser", "oidn", "--mixer",
                                    workdir, "--out", out, "--alpha", alpha, "--seed", 2], capsys)
    assert code == 0, stderr
    params, config = P.load_mixer(workdir)
    z, alpha_prime, extras = P.progressive_denoise(frame, "oidn", params, config,
                                                   jax.random.PRNGKey(2))
    np.testing.assert_allclose(read_image(out), np.asarray(z), rtol=1e-6, atol=1e-6)
    assert set(read_header(alpha)["channels"]) == {"R", "G", "B", "unscaled.R", "unscaled.G",
                                                   "unscaled.B"}
    np.testing.assert_allclose(read_image(alpha), np.asarray(alpha_prime), atol=1e-6)
    np.testing.assert_allclose(read_image(alpha, ("unscaled.R", "unscaled.G", "unscaled.B")),
                               np.asarray(extras["alpha"]), atol=1e-6)
    assert read_header(out)["swap_average"] == 0  # the tiny mixer's config
    code, stdout, stderr = run_cli(["progressive", source, "--denoiser", "oidn", "--mixer",
                                    workdir, "--out", out, "--seed", 2, "--swap-average"], capsys)
    assert code == 0, stderr
    z2, _, _ = P.progressive_denoise(frame, "oidn", params, config, jax.random.PRNGKey(2),
                                     swap_average=True)
    np.testing.assert_allclose(read_image(out), np.asarray(z2), rtol=1e-6, atol=1e-6)
    assert read_header(out)["swap_average"] == 1
    code, stdout, stderr = run_cli(["dataset", "sure-cache", dataset, "--denoiser", "oidn",
                                    "--quiet"], capsys)
    assert code == 0, stderr
    assert "SURE cache complete" in stdout and "12 items" in stdout


def test_cli_bad_inputs_are_clear_errors(trained, tmp_path, capsys):
    _, workdir = trained
    frame = small_frame(seed=12)
    no_variance = tmp_path / "novar.exr"
    write_frame(no_variance, frame.replace(variance=None))
    for command in (["sure"], ["progressive", "--mixer", workdir]):
        code, _, stderr = run_cli(command[:1] + [no_variance, "--denoiser", "oidn", "--out",
                                                 tmp_path / "o.exr"] + command[1:], capsys)
        assert code == 2 and "SURE" in stderr and "variance" in stderr and "novar.exr" in stderr

    negative = tmp_path / "negative.exr"
    variance = frame.variance.copy()
    variance[2, 3, 0] = -1.0
    write_channels(negative, {**{c: frame.color[..., i] for i, c in enumerate("RGB")},
                              **{f"variance.{c}": variance[..., i] for i, c in enumerate("RGB")}})
    code, _, stderr = run_cli(["sure", negative, "--denoiser", "oidn", "--out",
                               tmp_path / "o.exr"], capsys)
    assert code == 2 and "variance must be >= 0" in stderr and "negative.exr" in stderr

    source = tmp_path / "in.exr"
    write_frame(source, frame)
    params, config = P.load_mixer(workdir)
    mismatched = tmp_path / "mismatched.msgpack"
    P.save_mixer(mismatched, params, config)
    meta = json.loads(mismatched.with_suffix(".json").read_text())
    other = P.MixerConfig(features=MIXER_FEATURES_NO_SURE)
    meta["model_config"]["features"] = list(other.features)
    meta["layout"] = P.mixer_layout(other)
    mismatched.with_suffix(".json").write_text(json.dumps(meta))
    code, _, stderr = run_cli(["progressive", source, "--denoiser", "oidn", "--mixer", mismatched,
                               "--out", tmp_path / "o.exr"], capsys)
    assert code == 2 and "conv_in" in stderr and "18" in stderr and "12" in stderr

    denoiser_ckpt = tmp_path / "unet.msgpack"
    save_weights(denoiser_ckpt, {"w": np.zeros(2, np.float32)},
                 {"kind": "denoiser", "model": "unet", "model_config": {}})
    code, _, stderr = run_cli(["progressive", source, "--denoiser", "oidn", "--mixer",
                               denoiser_ckpt, "--out", tmp_path / "o.exr"], capsys)
    assert code == 2 and "not a mixer" in stderr and "denoiser" in stderr
    assert not (tmp_path / "o.exr").exists()  # nothing half-written


def test_train_resumes_into_the_same_run_with_the_same_cache(trained, tmp_path):
    """A second `jaxden train` with the same command finds the finished run and the cache."""
    dataset, workdir = trained
    copy = tmp_path / "run"
    shutil.copytree(workdir, copy)
    code = cli.main(["train", TINY_MIXER, f"data.dataset={dataset}", "--workdir", str(copy)])
    assert code == 0
    a, _ = P.load_mixer(workdir)
    b, _ = P.load_mixer(copy)
    for left, right in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(left), np.asarray(right))


def test_swap_symmetry_of_the_trained_mixer_on_a_frame(trained):
    _, workdir = trained
    params, config = P.load_mixer(workdir)
    frame = small_frame(seed=13)
    result, _ = denoise_with_sure("oidn", frame, jax.random.PRNGKey(0))
    x, y, var, sure = frame.color, result.denoised, frame.variance, result.sure
    gap = P.swap_symmetry(params, config, x, y, var, sure)
    per_pixel = np.asarray(P.swap_symmetry(params, config, x, y, var, sure, per_pixel=True))
    # the definition, from two direct mixer calls: the swapped call exchanges x with y and
    # var with SURE
    alpha = np.asarray(P.mixer_alpha(params, config, x, y, var, sure))
    swapped = np.asarray(P.mixer_alpha(params, config, y, x, sure, var))
    np.testing.assert_allclose(per_pixel, np.abs(alpha - (1 - swapped)), atol=1e-6)
    assert gap == pytest.approx(float(per_pixel.mean()), rel=1e-5)
    print(f"\nswap symmetry of the tiny trained mixer on a 24 x 20 frame: {gap:.4f}")
    # One call is not symmetric: measured 0.466 (CPU), bounded with margin (the mixer trained
    # 40 steps; a gap near 0 would mean the swapped call is not the swap) ...
    assert 0.2 < gap < 0.75
    # ... the swap-averaged alpha is, exactly: alpha(x, y) + alpha(y, x) = 1 per pixel, to
    # float32 round-off, both through inference_alpha and through progressive_denoise.
    forward = np.asarray(inference_alpha(params, x, y, var, sure, config, True))
    backward = np.asarray(inference_alpha(params, y, x, sure, var, config, True))
    np.testing.assert_allclose(forward + backward, 1.0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(forward, 0.5 * (alpha + 1 - swapped), atol=1e-6)


# ------------------------------------------------------------------------ reports


def test_mixer_alpha_script_matches_the_pipeline(trained):
    """experiments/mixer_alpha.py: its 'single' and 'average' PD / MC are what
    progressive_denoise gives without and with swap averaging (same SURE key)."""
    from helpers import load_script

    from jaxden.data.crops import iter_crops

    mixer_alpha = load_script("mixer_alpha")
    dataset, workdir = trained
    crop, reference, levels = next(iter_crops(dataset, "all"))
    spp, frame = levels[-1]
    rows = mixer_alpha.evaluate(dataset, [crop.id], [spp], [str(workdir)])
    assert [(r["crop"], r["spp"]) for r in rows] == [(crop.id, spp)]
    entry = rows[0]["mixers"][str(workdir)]
    params, config = P.load_mixer(workdir)
    mc = float(metrics.rmse(frame.color, reference.color))
    for swap, name in ((False, "single"), (True, "average")):
        z, _, extras = P.progressive_denoise(frame, "oidn", params, config, jax.random.PRNGKey(0),
                                             swap_average=swap)
        assert entry[name]["pd_over_mc"] == pytest.approx(
            float(metrics.rmse(np.asarray(z), reference.color)) / mc, rel=1e-4)
        if not swap:
            assert entry[name]["alpha"] == pytest.approx(float(np.mean(extras["alpha"])), rel=1e-5)
    with pytest.raises(SystemExit, match="no crop"):
        mixer_alpha.evaluate(dataset, ["s999-c000"], [spp], [str(workdir)])
    untrained, untrained_config = mixer_alpha._load(f"untrained:{workdir}")
    assert untrained_config == config
    fresh = P.mixer_init(jax.random.PRNGKey(0), config)
    for a, b in zip(jax.tree_util.tree_leaves(untrained), jax.tree_util.tree_leaves(fresh)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow  # ~9 s; the report rows themselves: test_pd_report_rows_match_direct_computation
def test_evaluate_pd_tstat_override(trained, tmp_path, capsys):
    """jaxden evaluate pd --tstat KEY=VALUE: the rows are those of the mixer with that
    t-statistic field changed, and the provenance records it; a bad key names the field."""
    from jaxden.cli.evaluate import logit_bound
    from jaxden.config import load_config
    from jaxden.evaluate import pd as pdreport

    dataset, workdir = trained
    spp = next(pdreport.iter_crops(dataset, "val"))[2][-1][0]  # the highest input spp
    out = tmp_path / "rep"
    assert cli.main(["evaluate", "pd", "--data", str(dataset), "--split", "val", "--denoiser",
                     "oidn", "--mixer", str(workdir), "--spp", str(spp), "--tstat", "c=1.0",
                     "--out", str(out)]) == 0
    result = json.loads(out.with_suffix(".json").read_text())
    assert len(result["rows"]) == 2  # the two val crops (the test's cost is per crop)
    assert result["provenance"]["tstat"]["c"] == 1.0
    params, config = P.load_mixer(workdir)
    changed = dataclasses.replace(config, tstat=load_config(config.tstat, P.TStatConfig,
                                                            overrides=["c=1.0"]))
    rows = pdreport.evaluate_progressive(dataset, "oidn", (params, changed), split="val",
                                         spp=(spp,))
    assert [r["pd_rmse"] for r in result["rows"]] == pytest.approx([r["pd_rmse"] for r in rows],
                                                                   rel=1e-6)
    default = pdreport.evaluate_progressive(dataset, "oidn", (params, config), split="val",
                                            spp=(spp,))
    assert [r["pd_rmse"] for r in default] != pytest.approx([r["pd_rmse"] for r in rows],
                                                            rel=1e-6)  # c matters here
    # Bad overrides: the message names the field, exit status 2, no report written.
    for option, value, match in (("--tstat", "sigma_mn=1", "sigma_mn"),
                                 ("--logit-bound", "3", "apply only to head"),
                                 ("--mixer-set", "closed_form_stop=1", "closed_form_stop"),
                                 ("--mixer-set", "closed_form_stops=0", "closed_form_stops")):
        assert cli.main(["evaluate", "pd", "--data", str(dataset), "--split", "all",
                         "--denoiser", "oidn", "--mixer", str(workdir), option, value, "--out",
                         str(tmp_path / "bad")]) == 2
        assert match in capsys.readouterr().err
        assert not (tmp_path / "bad.json").exists()
    for text in ("0", "-1", "nan", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected a number > 0 or 'none'"):
            logit_bound(text)
    assert logit_bound("None") == 0.0 and logit_bound("2.5") == 2.5
    # --mixer-set: the closed form with strata set on the command line is the spec with them.
    for name, argv in (("set", ["--mixer", "closed-form", "--mixer-set", "closed_form_stops=1"]),
                       ("spec", ["--mixer", "closed-form:stops=1"])):
        assert cli.main(["evaluate", "pd", "--data", str(dataset), "--split", "val",
                         "--denoiser", "oidn", "--spp", str(spp), *argv,
                         "--out", str(tmp_path / name)]) == 0
    by_set, by_spec = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("set", "spec"))
    assert by_set["provenance"]["closed_form_stops"] == 1.0
    assert [r["pd_rmse"] for r in by_set["rows"]] == [r["pd_rmse"] for r in by_spec["rows"]]


def test_evaluate_pd_keep_current_keeps_only_the_same_run(trained, tmp_path, capsys,
                                                           monkeypatch):
    """jaxden evaluate pd --keep-current keeps OUT.json only when it is what the run would write:
    the same data build, mixer and effective config; a changed mixer field, another build of
    the data or a report without a column the report now has (made before it existed) is made
    again. After the first real run the evaluation is replayed (what is kept is the point)."""
    from jaxden.evaluate import pd as pdreport

    dataset, workdir = trained
    spp = next(pdreport.iter_crops(dataset, "val"))[2][0][0]
    out = tmp_path / "rep"
    argv = ["evaluate", "pd", "--data", str(dataset), "--split", "val", "--denoiser", "oidn", "--mixer",
            str(workdir), "--spp", str(spp), "--out", str(out), "--keep-current"]

    def run(*extra) -> bool:  # True: it wrote the report
        capsys.readouterr()
        assert cli.main([*argv, *extra]) == 0
        return "is current" not in capsys.readouterr().out

    assert run()
    first = out.with_suffix(".json").read_text()
    rows = json.loads(first)["rows"]
    monkeypatch.setattr(pdreport, "evaluate_progressive", lambda *a, **k: rows)
    assert not run() and out.with_suffix(".json").read_text() == first
    assert run("--tstat", "c=3.0")  # another t-statistic: another report
    assert run() and not run()  # back to the config's own
    report = json.loads(out.with_suffix(".json").read_text())
    for row in report["rows"]:
        del row["pd_true_sure_rmse"]
    out.with_suffix(".json").write_text(json.dumps(report))
    assert run()  # a column missing: made again
    report = json.loads(out.with_suffix(".json").read_text())
    report["provenance"]["dataset"]["manifest_sha256"] = "0" * 64
    out.with_suffix(".json").write_text(json.dumps(report))
    assert run()  # another build of the data


def test_pd_report_rows_match_direct_computation(trained):
    """jaxden.evaluate's pd on the tiny dataset: one row per (crop, spp); each row's numbers equal
    progressive_denoise / metrics computed directly with the same key; the summary's ratios
    are the stated means."""
    from jaxden.data.layout import load_manifest
    from jaxden.evaluate import pd as pdreport

    dataset, workdir = trained
    params, config = P.load_mixer(workdir)
    rows = pdreport.evaluate_progressive(dataset, "oidn", (params, config), split="all", seed=3)
    manifest = load_manifest(dataset)
    inputs = [i for i in manifest.items if i.kind == "input" and i.spp >= 2]
    assert len(rows) == len(inputs) == 12
    assert [r["spp"] for r in rows[:3]] == sorted(r["spp"] for r in rows[:3])

    crop, reference, levels = next(pdreport.iter_crops(dataset, "all"))
    spp, frame = levels[1]
    row = rows[1]
    assert (row["crop"], row["spp"]) == (crop.id, spp)
    z, alpha_prime, extras = P.progressive_denoise(
        frame, "oidn", params, config, jax.random.fold_in(jax.random.PRNGKey(3), 1))
    assert row["pd_rmse"] == pytest.approx(float(metrics.rmse(np.asarray(z), reference.color)),
                                           rel=1e-5)
    assert row["mc_relmse"] == pytest.approx(float(metrics.relmse(frame.color, reference.color)),
                                             rel=1e-6)
    corrected = float(metrics.mse(frame.color, reference.color)) - float(reference.variance.mean())
    assert row["mc_mse_nc"] == pytest.approx(corrected, rel=1e-4, abs=1e-9)
    assert row["sure"] == pytest.approx(float(np.mean(np.asarray(extras["sure"]))), rel=1e-5)
    assert row["alpha_prime"] == pytest.approx(float(np.mean(np.asarray(alpha_prime))), rel=1e-5)
    z_pc, _, _ = P.progressive_denoise(
        frame, "oidn", params, config, jax.random.fold_in(jax.random.PRNGKey(3), 1),
        tstat=dataclasses.replace(config.tstat, per_channel=True))
    assert row["pd_pc_rmse"] == pytest.approx(
        float(metrics.rmse(np.asarray(z_pc), reference.color)), rel=1e-5)
    # The row of the config's own form of t is PD itself (the other one is z_pc above).
    assert not config.tstat.per_channel
    assert row["pd_shared_rmse"] == pytest.approx(row["pd_rmse"], rel=1e-6)
    # PD fed the true error of y in place of its SURE: the same pipeline with that map
    assert config.uses_sure  # the swapped call below exchanges (x, var) with (y, SURE)
    true_err = pdreport.true_error(extras["denoised"], reference)
    alpha_true = P.mixer_alpha(params, config, frame.color, extras["denoised"], frame.variance,
                               true_err)
    if config.swap_average:
        alpha_true = 0.5 * (alpha_true + 1 - P.mixer_alpha(
            params, config, extras["denoised"], frame.color, true_err, frame.variance))
    z_true = np.asarray(frame.color) + np.asarray(P.t_statistic_scaling(
        alpha_true, frame.color, frame.color + alpha_true * (extras["denoised"] - frame.color),
        frame.variance, config.tstat)) * (np.asarray(extras["denoised"]) - frame.color)
    assert row["pd_true_sure_rmse"] == pytest.approx(
        float(metrics.rmse(z_true, reference.color)), rel=1e-5)
    assert row["pd_true_sure_rmse"] != pytest.approx(row["pd_rmse"], rel=1e-4)

    summary = pdreport.summarize_progressive(rows)
    top = summary["max_spp"]
    assert top == max(r["spp"] for r in rows) and summary["crops"] == 4
    at_top = [r for r in rows if r["spp"] == top]
    assert summary["per_spp"][top]["pd_rmse"] == pytest.approx(
        np.mean([r["pd_rmse"] for r in at_top]))
    ratio = np.mean([m["pd_rmse"] / m["denoiser_rmse"] for m in summary["per_spp"].values()])
    assert summary["headline"]["pd_over_denoiser"]["rmse"] == pytest.approx(ratio)
    paper = np.mean([m["pd_rmse"] / m["denoiser_rmse"] for level, m in summary["per_spp"].items()
                     if level >= 32])
    assert summary["headline"]["pd_over_denoiser_paper_range"]["rmse"] == pytest.approx(paper)
    # the reference-fitted oracle includes alpha = 0 and 1 on every tile
    assert all(r["oracle_rmse"] <= min(r["mc_rmse"], r["denoiser_rmse"]) * (1 + 1e-5)
               for r in rows)
    # per crop: the mean over spp of the crop's own ratios, and the ratio to MC at the top spp
    crop = rows[0]["crop"]
    mine = [r for r in rows if r["crop"] == crop]
    per_crop = summary["per_crop"][crop]
    assert per_crop["pd_over_denoiser_rmse"] == pytest.approx(
        np.mean([r["pd_rmse"] / r["denoiser_rmse"] for r in mine]))
    last = next(r for r in mine if r["spp"] == top)
    assert per_crop["oracle_over_mc_rmse_at_max_spp"] == pytest.approx(
        last["oracle_rmse"] / last["mc_rmse"])
    assert per_crop["oracle_over_mc_rmse_at_max_spp"] <= 1 + 1e-5
    table = pdreport.markdown_progressive(summary)
    assert "PD(OIDN)" in table and f"| {top} | MC |" in table
    assert f"| {crop} | {per_crop['denoiser_rmse']:.5f} |" in table


def test_sure_accuracy_rows_and_summary(trained):
    """sure_accuracy's SURE equals denoise_with_sure's with the same key; SURE / MSE is the
    ratio of the crop means; an incomplete dataset is refused by name."""
    from jaxden.data.layout import load_manifest
    from jaxden.errors import DatasetError
    from jaxden.evaluate import sure as pdreport

    dataset, _ = trained
    rows = pdreport.sure_accuracy(dataset, "oidn", split="all", seed=1, spp=(8, 32))
    assert len(rows) == 8 and {r["spp"] for r in rows} == {8, 32}
    _, reference, levels = next(pdreport.iter_crops(dataset, "all", spp=(8, 32)))
    result, _ = denoise_with_sure("oidn", levels[0][1], jax.random.fold_in(jax.random.PRNGKey(1), 0))
    assert rows[0]["sure"] == pytest.approx(float(np.mean(result.sure)), rel=1e-5)
    summary = pdreport.summarize_sure(rows)
    group = [r for r in rows if r["spp"] == 32]
    assert summary["per_spp"][32]["ratio"] == pytest.approx(
        np.mean([r["sure"] for r in group]) / np.mean([r["mse_nc"] for r in group]))
    assert "| oidn | 32 |" in pdreport.markdown_sure({"oidn": summary})

    manifest = load_manifest(dataset)
    manifest.items[0].sha256 = None
    broken = dataset.parent / "incomplete"
    shutil.copytree(dataset, broken)
    manifest.save(broken)
    with pytest.raises(DatasetError, match="not complete"):
        next(pdreport.iter_crops(broken, "all"))


def test_ratio_interval_is_a_crop_bootstrap():
    """With two crops the crop bootstrap has three outcomes ({a, a}, {a, b}, {b, b}, with
    probabilities 1/4, 1/2, 1/4), so its 2.5-97.5 % interval spans the two crops' own ratios;
    every crop at ratio 1 gives [1, 1]; renders of one crop move together."""
    from jaxden.evaluate import sure as pdreport

    rows = [{"crop": "a", "sure": 2.0, "mse_nc": 1.0}, {"crop": "a", "sure": 1.0, "mse_nc": 1.0},
            {"crop": "b", "sure": 1.0, "mse_nc": 2.0}]
    low, high = pdreport.ratio_interval(rows, "sure")
    assert (low, high) == (pytest.approx(0.5), pytest.approx(1.5))  # crop b 1/2, crop a 3/2
    assert pdreport.ratio_interval(rows, "sure") == [low, high]  # seeded
    same = [{"crop": c, "sure": v, "mse_nc": v} for c, v in (("a", 1.0), ("b", 5.0), ("c", 2.0))]
    assert pdreport.ratio_interval(same, "sure") == [pytest.approx(1.0), pytest.approx(1.0)]
    summary = pdreport.summarize_sure([{**r, "spp": 64, "reference_var": 0.0} for r in rows])
    assert summary["per_spp"][64]["ratio_ci95"] == [low, high]


def test_true_error_is_unbiased_for_the_squared_error_against_the_truth():
    """true_error subtracts the reference's variance of the mean from the squared error
    against it, so over reference renders it averages (y - truth)^2: with 4000 reference
    draws of known variance the mean is within 4 standard errors of it (seed 0), while the
    raw squared error is off by the variance."""
    from types import SimpleNamespace

    from jaxden.evaluate.oracle import true_error

    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 2, (4, 5, 3))
    y = truth + rng.normal(0, 0.2, truth.shape)
    var_r = rng.uniform(0.01, 0.05, truth.shape)
    draws = np.stack([true_error(y, SimpleNamespace(
        color=truth + rng.normal(0, np.sqrt(var_r)), variance=var_r)) for _ in range(4000)])
    want = (y - truth) ** 2
    se = draws.std(axis=0) / np.sqrt(len(draws))
    assert np.all(np.abs(draws.mean(axis=0) - want) <= 4 * se + 1e-7)
    assert np.mean(draws.mean(axis=0) + var_r - want) == pytest.approx(np.mean(var_r), rel=0.05)


def test_oracle_mix_is_the_best_tile_alpha():
    """oracle_mix's alpha per tile and channel minimises the squared error against the
    reference over alpha in [0, 1]: a brute-force search on a fine grid never does better,
    and the oracle is never worse than x (alpha 0) or y (alpha 1) on any tile."""
    from jaxden.evaluate.oracle import oracle_mix

    rng = np.random.default_rng(5)
    r = rng.uniform(0, 1, (10, 13, 3))
    x = r + rng.normal(0, 0.3, r.shape)
    y = r + rng.normal(0, 0.1, r.shape) + rng.choice([-0.5, 0.0, 0.5], size=(1, 1, 3))
    z = oracle_mix(x, y, r, block=4)
    grid = np.linspace(0, 1, 1001)
    for top in range(0, 10, 4):
        for left in range(0, 13, 4):
            t = np.s_[top : top + 4, left : left + 4]
            for c in range(3):
                err = np.sum((z[t][..., c] - r[t][..., c]) ** 2)
                brute = min(np.sum((x[t][..., c] + a * (y[t][..., c] - x[t][..., c])
                                    - r[t][..., c]) ** 2) for a in grid)
                assert err <= brute + 1e-4
                assert err <= min(np.sum((x[t][..., c] - r[t][..., c]) ** 2),
                                  np.sum((y[t][..., c] - r[t][..., c]) ** 2)) + 1e-4
                assert brute <= err + 1e-3 * max(err, 1e-9) + 1e-6  # the grid finds it too


def test_sure_accuracy_buffers_rows(trained, monkeypatch):
    """sure_accuracy_buffers with a stand-in renderer: the seeds it asks for, the combined
    frame, the sub-buffer SURE equal to sure_buffers computed directly; seeds that collide
    with the dataset's are refused."""
    from jaxden.data.layout import load_manifest
    from jaxden.denoise.registry import load_denoiser
    from jaxden.errors import DatasetError
    from jaxden.evaluate import sure_buffers as pdreport
    from jaxden.sure.buffers import combine_buffers, sure_buffers

    dataset, _ = trained
    _, reference, levels = next(pdreport.iter_crops(dataset, "all", spp=(8,)))
    template = levels[0][1]
    calls = []

    def fake_render(scene, spp, seed, size, crop):
        calls.append((scene, spp, seed))
        rng = np.random.default_rng(seed)
        noise = rng.exponential(1.0, np.shape(reference.color)) - 1.0
        return template.replace(color=(reference.color * (1 + 0.3 * noise)).astype(np.float32),
                                variance=np.full(np.shape(reference.color), 0.01, np.float32),
                                spp=np.float32(spp))

    rows = pdreport.sure_accuracy_buffers(dataset, ["oidn"], buffers=4, renders=2, split="all",
                                          spp=(8, 32), render_fn=fake_render)["oidn"]
    assert len(rows) == 4 * 2 * 2  # crops x spp levels x renders
    assert [c[1] for c in calls[:8]] == [2] * 8  # 8 spp = 4 buffers of 2
    first_seeds = [c[2] for c in calls[:8]]
    assert first_seeds == [pdreport.BUFFER_SEED_BASE + k for k in range(8)]
    parts = [fake_render("x", 2, s, None, None) for s in first_seeds[:4]]
    combined = combine_buffers(parts)
    direct = sure_buffers(load_denoiser("oidn"), combined.replace(spp=None),
                          np.stack([p.color for p in parts]))
    assert rows[0]["sure_buffers"] == pytest.approx(float(np.mean(direct.sure)), rel=1e-4)
    assert rows[0]["render"] == 0 and rows[1]["render"] == 1

    used = min(i.seed for i in load_manifest(dataset).items)
    monkeypatch.setattr(pdreport, "BUFFER_SEED_BASE", used)
    with pytest.raises(DatasetError, match="collide"):
        pdreport.sure_accuracy_buffers(dataset, ["oidn"], buffers=4, split="all", spp=(8,),
                                       render_fn=fake_render)


def test_cli_progressive_closed_form_mixer(tmp_path, capsys):
    """`--mixer closed-form` needs no weights: same output as progressive_denoise with the
    closed-form config; the mixer is not tied to a denoiser (no mismatch note for denoisers
    without a shipped mixer), and it cannot be trained."""
    frame = small_frame(seed=12)
    source, out = tmp_path / "in.exr", tmp_path / "out.exr"
    write_frame(source, frame)
    code, _, stderr = run_cli(["progressive", source, "--denoiser", "oidn", "--mixer",
                                    "closed-form:sigma=4", "--out", out, "--seed", 3], capsys)
    assert code == 0, stderr
    assert "trained on the output" not in stderr
    params, config = P.load_mixer("closed-form:sigma=4")
    z, _, extras = P.progressive_denoise(frame, "oidn", params, config,
                                                   jax.random.PRNGKey(3))
    np.testing.assert_allclose(read_image(out), np.asarray(z), rtol=1e-6, atol=1e-6)
    want = P.closed_form_alpha(frame.color, extras["denoised"], frame.variance, extras["sure"],
                               sigma=4.0)
    np.testing.assert_allclose(np.asarray(extras["alpha"]), np.asarray(want), atol=1e-6)
    code, _, stderr = run_cli(["progressive", source, "--denoiser", "unet", "--out", out],
                              capsys)
    assert code == 2 and "--mixer closed-form" in stderr
    with pytest.raises(ConfigError, match="no parameters to train"):
        mixer_task(load_train_config(TINY_MIXER, ["model_config.kind='closed_form'"]))


def test_cli_progressive_tstat_overrides(tmp_path, capsys):
    """`jaxden progressive --tstat KEY=VALUE` sets fields of the mixer's TStatConfig: the
    same z as progressive_denoise with that config, recorded in the header; a wrong key or
    value, or --tstat beside --no-tstat, is a one-line error that writes nothing."""
    from jaxden.io.exr import read_header

    frame = small_frame(seed=13)
    source, out = tmp_path / "in.exr", tmp_path / "out.exr"
    write_frame(source, frame)
    words = ["c=0.5", "guard_gamma=1"]
    code, _, stderr = run_cli(["progressive", source, "--denoiser", "oidn", "--mixer",
                               "closed-form", "--out", out, "--seed", 3,
                               *(w for word in words for w in ("--tstat", word))], capsys)
    assert code == 0, stderr
    params, config = P.load_mixer("closed-form")
    tuned = dataclasses.replace(config, tstat=dataclasses.replace(
        config.tstat, c=0.5, guard_gamma=1.0))
    for cfg, same in ((tuned, True), (config, False)):
        z, _, _ = P.progressive_denoise(frame, "oidn", params, cfg, jax.random.PRNGKey(3))
        close = np.allclose(read_image(out), np.asarray(z), rtol=1e-6, atol=1e-6)
        assert close == same, cfg.tstat
    assert read_header(out)["tstat_overrides"] == " ".join(words)
    for extra, message in ((["--tstat", "guard_gama=1"], "guard_gama"),
                           (["--tstat", "guard_gamma=-1"], "guard_gamma"),
                           (["--tstat", "guard_gamma=3", "--no-tstat"], "--no-tstat")):
        target = tmp_path / "bad.exr"
        code, _, stderr = run_cli(["progressive", source, "--denoiser", "oidn", "--mixer",
                                   "closed-form", "--out", target, *extra], capsys)
        assert code == 2 and message in stderr and "Traceback" not in stderr, stderr
        assert not target.exists()


def test_probes_default_to_the_mixers_training_probes(tmp_path, capsys):
    """Without ``sure`` / --probes, PD takes as many SURE probes as the mixer was trained
    with (its ``sure.probes``: the noise level of the SURE input it learned on); an explicit
    count still wins, as a SureSettings field or the older ``num_probes`` keyword."""
    frame = small_frame(seed=13)
    params, config = P.load_mixer("closed-form:sigma=4")
    config = dataclasses.replace(config, sure=config.sure.replace(probes=2))
    key = jax.random.PRNGKey(5)
    z_default = np.asarray(P.progressive_denoise(frame, "oidn", params, config, key)[2]["sure"])
    z_two, z_four = (np.asarray(P.progressive_denoise(
        frame, "oidn", params, config, key, sure=SureSettings(probes=k))[2]["sure"])
        for k in (2, 4))
    np.testing.assert_array_equal(z_default, z_two)
    assert np.abs(z_two - z_four).max() > 1e-4
    older = P.progressive_denoise(frame, "oidn", params, config, key, num_probes=4)[2]["sure"]
    np.testing.assert_array_equal(np.asarray(older), z_four)
    params, shipped = P.load_mixer("oidn-pd")
    source, out = tmp_path / "in.exr", tmp_path / "out.exr"
    write_frame(source, frame)
    code, _, stderr = run_cli(["progressive", source, "--denoiser", "oidn", "--out", out], capsys)
    assert code == 0, stderr
    assert read_header(out)["probes"] == shipped.sure.probes
    code, _, stderr = run_cli(["progressive", source, "--denoiser", "oidn", "--out", out,
                               "--probes", 3], capsys)
    assert code == 0, stderr
    assert read_header(out)["probes"] == 3
