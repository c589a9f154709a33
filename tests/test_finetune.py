"""Fine-tuning (``init`` in the training config, jaxden.train.finetune): a run from a shipped
model starts from exactly its parameters with a fresh optimiser state, and so does a run from
another run's folder; weights of another model, config or shape, and a missing or corrupt
source, are refused in one line before anything is written; a resume continues from the run's
own checkpoints (the source may be gone) and refuses a source that changed since the start.

Data: the Mitsuba-free tiny dataset and a one-layer KP model (tests/helpers.py)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil

import jax
import numpy as np
import pytest
from helpers import assert_one_error_line, build_tiny_dataset, run_cli, write_train_config

from jaxden.checkpoint import Checkpointer, save_weights
from jaxden.denoise.registry import WEIGHTS_DIR
from jaxden.errors import CheckpointError, ConfigError
from jaxden.train import loop, tensorboard
from jaxden.train.config import load_train_config
from jaxden.train.tasks import make_task

SHIPPED = "wskp-3"  # model "wskp3", deployed: the smallest shipped denoiser


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build_tiny_dataset(tmp_path_factory.mktemp("finetune") / "tiny")


def leaves(tree) -> dict[str, np.ndarray]:
    return {jax.tree_util.keystr(p): np.asarray(v)
            for p, v in jax.tree_util.tree_leaves_with_path(tree)}


def start_of(monkeypatch, config, workdir):
    """The run's state and optimiser as the loop receives them at its start (no step runs)."""
    seen = {}

    def capture(config, workdir, task, loss_fn, optimizer, train, val, mesh, state, **options):
        seen.update(state=state, optimizer=optimizer)
        return {}

    with monkeypatch.context() as patch:
        patch.setattr(loop, "_train", capture)
        loop.train_and_evaluate(config, workdir, progress=False)
    return seen["state"], seen["optimizer"]


def shipped_toml(folder, dataset, model="wskp3", model_config="deploy = true", init=SHIPPED):
    path = folder / "config.toml"
    path.write_text(f'model = "{model}"\ninit = "{init}"\neval_batches = 1\n[model_config]\n'
                    f'{model_config}\n[data]\ndataset = "{dataset}"\ncrop_size = 16\n'
                    f'batch_size = 2\n[optim]\nsteps = 2\n')
    return path


def test_a_run_from_a_shipped_model_starts_from_its_parameters(dataset, tmp_path, monkeypatch):
    from flax import serialization

    config = load_train_config(shipped_toml(tmp_path, dataset))
    state, optimizer = start_of(monkeypatch, config, tmp_path / "run")
    file = WEIGHTS_DIR / f"{SHIPPED}.msgpack"
    shipped = leaves(serialization.msgpack_restore(file.read_bytes()))
    started = leaves(state.params)
    assert started.keys() == shipped.keys() and len(shipped) == 3  # 3 deployed convs
    for name, value in shipped.items():
        assert started[name].dtype == np.float32
        np.testing.assert_array_equal(started[name], value, err_msg=name)
    fresh = leaves(optimizer.init(state.params))  # Adam's moments at zero, count 0
    assert leaves(state.opt_state).keys() == fresh.keys()
    for name, value in leaves(state.opt_state).items():
        np.testing.assert_array_equal(value, fresh[name], err_msg=name)
    assert int(state.step) == 0
    record = json.loads((tmp_path / "run" / "config.json").read_text())["init_source"]
    assert record["sha256"] == hashlib.sha256(file.read_bytes()).hexdigest()
    assert (record["spec"], record["step"]) == (SHIPPED, None)
    # A config built in Python (no load_train_config) is refused by the run itself.
    other = dataclasses.replace(config, model="wskp")
    with pytest.raises(CheckpointError, match="holds the denoiser 'wskp3'.*trains 'wskp'"):
        loop.train_and_evaluate(other, tmp_path / "other", progress=False)
    assert not (tmp_path / "other").exists()


def _copy_shipped(folder, edit_meta=None, cut=False):
    """wskp-3's weights copied into ``folder`` (meta edited, weights truncated)."""
    target = folder / "copy.msgpack"
    shutil.copy(WEIGHTS_DIR / f"{SHIPPED}.msgpack", target)
    meta = json.loads((WEIGHTS_DIR / f"{SHIPPED}.json").read_text())
    if edit_meta:
        edit_meta(meta)
    target.with_suffix(".json").write_text(json.dumps(meta))
    if cut:
        target.write_bytes(target.read_bytes()[:1000])
    return target


REFUSED = {
    "other-model": (lambda f: {"model": "wskp", "model_config": "deploy = true"},
                    ["'wskp3'", "'wskp'"]),
    "other-config": (lambda f: {"model_config": "deploy = false"},
                     ["another [model_config]", "deploy: true -> false"]),
    "mixer-into-denoiser": (lambda f: {"init": "wskp-6-pd"}, ["holds a mixer", "a denoiser"]),
    "denoiser-into-mixer": (lambda f: {"model": "mixer", "model_config": ""},
                            ["holds a denoiser", "trains a mixer"]),
    "missing": (lambda f: {"init": "wskp-7"}, ["no such file or folder", "wskp-6"]),
    "not-weights": (lambda f: {"init": str(WEIGHTS_DIR / f"{SHIPPED}.json")}, [".msgpack"]),
    "corrupt": (lambda f: {"init": str(_copy_shipped(f, cut=True))}, ["corrupt weights"]),
    "shapes": (lambda f: {"init": str(_copy_shipped(
        f, lambda m: m["model_config"].update(width=8))),
        "model_config": "deploy = true\nwidth = 8"}, ["has shape", "the model needs"]),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_weights_of_another_model_or_a_bad_source_are_refused(case, dataset, tmp_path, capsys):
    change, words = REFUSED[case]
    config = shipped_toml(tmp_path, dataset, **change(tmp_path))
    code, lines, _ = run_cli(["train", config, "--workdir", tmp_path / "run"], capsys)
    assert_one_error_line(code, lines, "init = ", *words)
    assert not (tmp_path / "run").exists()


def test_a_resume_continues_from_its_own_checkpoints(dataset, tmp_path, monkeypatch):
    plain = load_train_config(write_train_config(tmp_path, dataset, steps=2, checkpoint_every=1))
    task = make_task(plain)
    source = tmp_path / "source.msgpack"
    params = task.init(jax.random.PRNGKey(7), None)
    save_weights(source, params, task.meta)
    config = dataclasses.replace(plain, init=str(source))

    loop.train_and_evaluate(config, tmp_path / "straight", progress=False)
    loop.train_and_evaluate(config, tmp_path / "resumed", progress=False, stop_after=1)
    save_weights(source, jax.tree_util.tree_map(lambda x: 2 * x, params), task.meta)
    with pytest.raises(ConfigError, match="has changed since"):
        loop.train_and_evaluate(config, tmp_path / "resumed", progress=False)
    source.unlink()  # a resume never reads the source: gone is fine
    source.with_suffix(".json").unlink()
    assert loop.train_and_evaluate(config, tmp_path / "resumed", progress=False)["step"] == 2
    # its TensorBoard files: one per start, together every scalar of metrics.jsonl
    first, second = tensorboard.event_files(tmp_path / "resumed")
    logged = {(r["step"], k): np.float32(v) for r in map(json.loads, (
        tmp_path / "resumed" / "metrics.jsonl").read_text().splitlines())
        for k, v in r.items() if k != "step"}
    events = tensorboard.read_events(first) + tensorboard.read_events(second)
    assert {(e["step"], k): v for e in events for k, v in e.get("scalars", {}).items()} == logged
    assert tensorboard.read_events(second)[1]["session_status"] == tensorboard.SESSION_START
    with Checkpointer(tmp_path / "straight") as a, Checkpointer(tmp_path / "resumed") as b:
        (straight, _), (resumed, _) = a.restore(), b.restore()
    assert int(straight["step"]) == int(resumed["step"]) == 2
    for name, value in leaves(straight["params"]).items():
        np.testing.assert_allclose(leaves(resumed["params"])[name], value, rtol=1e-6, atol=1e-7)
    with pytest.raises(ConfigError, match="no such file or folder"):  # a new run needs it
        loop.train_and_evaluate(config, tmp_path / "new", progress=False)

    # A run folder as the source: its newest checkpoint's parameters, exactly.
    from_run = dataclasses.replace(plain, init=str(tmp_path / "straight"))
    state, _ = start_of(monkeypatch, from_run, tmp_path / "from-run")
    started = leaves(state.params)
    for name, value in leaves(straight["params"]).items():
        np.testing.assert_array_equal(started[name], value, err_msg=name)
    record = json.loads((tmp_path / "from-run" / "config.json").read_text())["init_source"]
    assert record["step"] == 2 and len(record["sha256"]) == 64
