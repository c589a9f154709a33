"""Nothing silently wrong between training runs: validation is the mean over every example
whatever the device count and batch size (also across sweep executors), a workdir left by a run
that failed before its first checkpoint takes a corrected config, and a trained model records
the features of its data, so a frame of other features is named when the model meets it."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import pytest
from helpers import (
    FAST_COMPILE,
    build_tiny_dataset,
    checkpoint_steps,
    train_toml,
    write_train_config,
)

from jaxden.data.loader import DatasetLoader
from jaxden.errors import ConfigError
from jaxden.train import loop
from jaxden.train.config import load_train_config
from jaxden.train.optim import loss_function
from jaxden.train.sharding import data_mesh, pad_to_devices, replicate
from jaxden.train.tasks import make_task

#: The tiny dataset (2 scenes, one in val) with 1 crop per scene: 3 validation examples (the
#: crop at 2, 8 and 32 spp): not a multiple of 2 devices, nor of the batch sizes 2 and 4, and
#: fewer than one batch of 4.
VAL_EXAMPLES = 3


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build_tiny_dataset(tmp_path_factory.mktemp("validation") / "tiny")


def tiny_config(folder: Path, dataset: Path, overrides=(), **options):
    """The tiny KP config of tests/helpers.py (16-pixel crops) with ``options``."""
    folder.mkdir(parents=True, exist_ok=True)
    return load_train_config(write_train_config(folder, dataset, **options), list(overrides))


def smape(x, y):
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return float(np.mean(np.abs(x - y) / (np.abs(x) + np.abs(y) + 0.01)))


def test_pad_to_devices():
    rows, weights = pad_to_devices(["a", "b", "c"], 2)
    assert rows == ["a", "b", "c", "c"] and weights.tolist() == [1, 1, 1, 0]
    rows, weights = pad_to_devices(["a"], 4)
    assert rows == ["a"] * 4 and weights.tolist() == [1, 0, 0, 0]
    rows, weights = pad_to_devices(["a", "b"], 2)
    assert rows == ["a", "b"] and weights.tolist() == [1, 1]


def test_validation_is_the_mean_over_every_example_on_one_or_two_devices(dataset, tmp_path):
    """The same val_loss / val_baseline_loss on one and two devices and for batches of 1, 2
    and 4 (3 examples: a last batch that does not split over two devices, a split smaller than
    one batch), equal to the mean of the per-example SMAPE computed here example by example.
    Before padding, two devices refused the batches of 1 and 4 ("no batch that fits the device
    count") and dropped the last example of the batches of 2."""
    assert len(jax.devices()) >= 2, "conftest sets two host devices"
    config = tiny_config(tmp_path, dataset)
    task = make_task(config)
    params = task.init(jax.random.PRNGKey(0), None)
    step = jax.jit(loop.make_eval_step(task, loss_function(config.optim.loss)))
    found = {}
    _, val = loop._loaders(config, task)
    for batch_size in (1, 2, 4):
        # the validation loader of a run with data.batch_size = batch_size (the training
        # split, of 3 examples too, takes no batch of 4)
        val = DatasetLoader(dataset, "val", batch_size, crop_size=16, seed=val.seed,
                            features=val.features, reference_features=val.reference_features,
                            augment=False, shuffle=False, drop_last=False)
        assert len(val.samples) == VAL_EXAMPLES
        for devices in (1, 2):
            mesh = data_mesh(jax.devices()[:devices])
            found[batch_size, devices] = loop.evaluate(  # 8 batches: the whole split
                step, replicate(params, mesh), val, mesh, 8, task.prepare)
    # The reference: each example alone, on the host.
    _, val = loop._loaders(config, task)
    losses, baselines = [], []
    for draw in val.plan_epoch(0):
        batch = task.prepare(val.read([draw]))
        prediction = task.predict(params, batch)
        losses.append(smape(prediction, task.target(batch)))
        baselines.append(smape(task.baseline(batch), task.target(batch)))
    want = {"val_loss": np.mean(losses), "val_baseline_loss": np.mean(baselines)}
    assert want["val_baseline_loss"] > 0.05  # a noisy input: the numbers mean something
    for key, result in found.items():
        assert result.keys() == want.keys(), key
        for name, value in want.items():
            assert result[name] == pytest.approx(value, rel=2e-6), (key, name, result)


def test_serial_and_local_sweeps_report_the_same_validation(dataset, tmp_path, monkeypatch):
    """A sweep of two runs reports the same validation numbers with the serial executor (this
    process: two devices) as with `--executor local` (its worker started with one device).
    Before padding, seed 0: val_baseline_loss 0.1112 serial (the 32-spp example dropped) vs
    0.0728 local (the mean of two batch means), val_loss 0.0688 vs 0.0548; now 0.08559 and
    0.05944 both."""
    from jaxden.sweep import run_sweep

    (tmp_path / "train.toml").write_text(train_toml(dataset, steps=2, eval_every=2,
                                                    eval_batches=8, checkpoint_every=2))
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'base = "{tmp_path / "train.toml"}"\n[axes]\nseed = [0, 1]\n')
    serial = run_sweep(sweep, tmp_path / "serial", executor="serial", progress=False)
    # The local executor's worker: one device, XLA at -O0, its own compilation cache.
    monkeypatch.setenv("XLA_FLAGS", FAST_COMPILE)
    monkeypatch.setenv("JAXDEN_CPU_DEVICES", "1")
    monkeypatch.setenv("JAXDEN_CACHE_DIR", str(tmp_path / "cache"))
    local = run_sweep(sweep, tmp_path / "local", executor="local", workers=1, progress=False)
    assert [r["run"] for r in serial] == [r["run"] for r in local] == ["seed=0", "seed=1"]
    for ours, theirs in zip(serial, local):
        train, other = ours["train"], theirs["train"]
        assert train["val_baseline_loss"] == pytest.approx(other["val_baseline_loss"], rel=1e-6)
        # trained on 2 devices here and on 1 there: the same parameters to float rounding
        assert train["val_loss"] == pytest.approx(other["val_loss"], rel=1e-5)
    assert serial[0]["train"]["val_loss"] != serial[1]["train"]["val_loss"]  # two real runs


def test_a_workdir_left_before_the_first_checkpoint_takes_a_corrected_config(
        dataset, tmp_path, monkeypatch, capsys):
    """A run that records its config and fails before its first checkpoint leaves a workdir
    that holds no work: a corrected config trains there (one line says so) and is recorded;
    once that run has checkpoints, another config is refused again. The checkpoint records the
    features of the training data."""
    from jaxden.checkpoint import read_checkpoint_meta

    workdir = tmp_path / "run"
    first = tiny_config(tmp_path / "a", dataset, steps=2, eval_every=2, checkpoint_every=2)

    def failing(*args, **kwargs):
        raise RuntimeError("the first validation failed")

    monkeypatch.setattr(loop, "evaluate", failing)
    with pytest.raises(RuntimeError, match="first validation"):
        loop.train_and_evaluate(first, workdir, progress=False)
    monkeypatch.undo()
    recorded = json.loads((workdir / "config.json").read_text())
    assert recorded["seed"] == 1 and checkpoint_steps(workdir) == []

    corrected = tiny_config(tmp_path / "b", dataset, ["seed=2"], steps=2, eval_every=2,
                            checkpoint_every=2)
    capsys.readouterr()
    result = loop.train_and_evaluate(corrected, workdir, progress=False)
    notes = [line for line in capsys.readouterr().err.splitlines() if "jaxden:" in line]
    assert notes == [(f"jaxden: note: {workdir} recorded a run with another config that saved "
                      f"no checkpoint: training there with this config")], notes
    assert result["step"] == 2
    assert json.loads((workdir / "config.json").read_text())["seed"] == 2
    assert "seed = 2" in (workdir / "config.toml").read_text()
    assert checkpoint_steps(workdir) == [2]
    meta = read_checkpoint_meta(workdir)
    assert meta["trained_features"] == {"aux": "first-hit", "feature_spp": 16}

    with pytest.raises(ConfigError, match="holds a run with another config.*seed"):
        loop.train_and_evaluate(first, workdir, progress=False)
    assert json.loads((workdir / "config.json").read_text())["seed"] == 2


# ------------------------------------------------------------------------------ features
def test_feature_records_compare_the_samples_averaged(capsys):
    from jaxden.data.features import FeatureRecord, feature_mismatch, warn_feature_mismatch

    trained = FeatureRecord("first-hit", 16)
    assert feature_mismatch(trained, FeatureRecord("first-hit", 16)) is None
    assert feature_mismatch(trained, None) is None and feature_mismatch(None, trained) is None
    # 8 spp: 8 feature samples either way, as in training at 8 spp
    assert feature_mismatch(trained, FeatureRecord("first-hit", 8), spp=8) is None
    assert feature_mismatch(trained, FeatureRecord("first-hit", 1024), spp=8) is None
    assert "feature_spp" in feature_mismatch(trained, FeatureRecord("first-hit", 64), spp=64)
    assert "differing: aux)" in feature_mismatch(trained, FeatureRecord("specular-chain"))
    # a model that reads no feature is not warned about
    assert not warn_feature_mismatch(trained, FeatureRecord("specular-chain", 64),
                                     where="x.exr", fields=("color", "variance"))
    assert FeatureRecord.from_json({"aux": 3}) is None
    assert FeatureRecord.from_json({"aux": "first-hit", "feature_spp": "many"}) == \
        FeatureRecord("first-hit", None)
    assert capsys.readouterr().err == ""


def test_a_frame_of_other_features_is_named_once(dataset, tmp_path, capsys):
    """A checkpoint trained on the tiny dataset (first-hit at 16 spp) meets a frame that
    `jaxden render` made with its defaults (specular-chain at 1024, 64 spp): one warning line
    naming both records, once per process; a frame of the training features: none."""
    from jaxden.checkpoint import Checkpointer, read_checkpoint_meta
    from jaxden.data.features import (
        dataset_features,
        header_features,
        meta_features,
        warn_frame_features,
    )
    from jaxden.io.exr import read_header, write_frame
    from jaxden.render.core import DEFAULT_AUX, DEFAULT_FEATURE_SPP, feature_attributes
    from jaxden.render.synthetic import synthetic_render

    # A checkpoint's meta as train_and_evaluate writes it (test above: from a real run).
    workdir = tmp_path / "run"
    features = dataset_features(dataset)
    with Checkpointer(workdir) as checkpointer:
        checkpointer.save(1, {"w": np.zeros(2, np.float32)},
                          {"kind": "denoiser", "model": "kp", "trained_features":
                           features.to_json()})
        checkpointer.wait()
    trained = meta_features(read_checkpoint_meta(workdir))
    assert trained == features and trained.describe() == "aux=first-hit, feature_spp=16"

    frame = synthetic_render("cornell-box", 64, seed=0, size=(8, 8))
    rendered = tmp_path / "rendered.exr"
    write_frame(rendered, frame, attributes=feature_attributes(64, DEFAULT_AUX,
                                                               DEFAULT_FEATURE_SPP))
    header = read_header(rendered)
    assert (header["aux"], header["feature_spp"]) == ("specular-chain", 64)
    assert header_features(header).describe() == "aux=specular-chain, feature_spp=64"
    capsys.readouterr()
    assert warn_frame_features(trained, rendered, model="kp", fields=("color", "albedo"))
    assert not warn_frame_features(trained, rendered, model="kp")  # once per process
    lines = capsys.readouterr().err.splitlines()
    assert lines == [(
        f"jaxden: warning: {rendered}: its features are aux=specular-chain, feature_spp=64, kp "
        f"was trained on aux=first-hit, feature_spp=16 (differing: aux, feature_spp); it sees "
        f"features unlike its training data (render the frame with --aux first-hit "
        f"--feature-spp 16, or train on a dataset of its features)")], lines
    same = tmp_path / "same.exr"
    write_frame(same, frame, attributes=feature_attributes(64, "first-hit", 16))
    unrecorded = tmp_path / "unrecorded.exr"
    write_frame(unrecorded, frame)
    assert not warn_frame_features(trained, same, model="kp")
    assert not warn_frame_features(trained, unrecorded, model="kp")
    assert capsys.readouterr().err == ""
