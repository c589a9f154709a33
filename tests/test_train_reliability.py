"""Training runs that fail safely: a diverged state is never checkpointed, Ctrl-C leaves a
resumable workdir and one line, and two runs cannot write one workdir."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from helpers import (
    build_tiny_dataset,
    checkpoint_steps,
    cli_env,
    metrics_records,
    sigint_default,
    write_train_config,
)

from jaxden.cli import main
from jaxden.errors import JaxdenError
from jaxden.fileio import folder_lock
from jaxden.train import loop
from jaxden.train.config import load_train_config
from jaxden.train.workdir import TRAIN_LOCK


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build_tiny_dataset(tmp_path_factory.mktemp("reliability") / "tiny")


def write_config(folder: Path, dataset: Path, steps=6, checkpoint_every=2, log_every=100) -> Path:
    return write_train_config(folder, dataset, steps=steps, log_every=log_every,
                              eval_every=steps, checkpoint_every=checkpoint_every,
                              keep_checkpoints=3)


def test_a_diverged_state_is_never_checkpointed(tmp_path, dataset, monkeypatch):
    """The parameters turn NaN after step 3 while the loss is only checked at step 100: the
    check before the checkpoint of step 4 stops the run, naming the step and the array, and
    keeps the checkpoint of step 2."""
    real = loop.make_train_step

    def poisoned(task, optimizer, loss_fn):
        step = real(task, optimizer, loss_fn)

        def train_step(state, batch):
            state, metrics = step(state, batch)
            params = jax.tree_util.tree_map(
                lambda x: jnp.where(state.step >= 3, jnp.nan, x), state.params)
            return loop.TrainState(params, state.opt_state, state.step), metrics

        return train_step

    monkeypatch.setattr(loop, "make_train_step", poisoned)
    config = load_train_config(write_config(tmp_path, dataset))
    workdir = tmp_path / "run"
    with pytest.raises(JaxdenError, match=r"diverged by step 4: params\['params'\]\['block0'\].* NaN or inf, so "
                                          r"checkpoint 4 was not written \(the last checkpoint "
                                          r"\(step 2\) is kept\)") as info:
        loop.train_and_evaluate(config, workdir, progress=False)
    assert "\n" not in str(info.value)
    assert checkpoint_steps(workdir) == [2]


def test_a_second_run_on_a_locked_workdir_is_one_line(tmp_path, dataset, capsys):
    config = write_config(tmp_path, dataset, steps=2)
    workdir = tmp_path / "run"
    workdir.mkdir()
    with folder_lock(workdir, TRAIN_LOCK, "training run"):
        assert main(["train", str(config), "--workdir", str(workdir)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another training run is writing into" in err[0], err
    assert checkpoint_steps(workdir) == []


STEPS = 40  # the SIGINT comes after 8 logged steps; 40 leave room to stop mid-run


def test_ctrl_c_finishes_the_checkpoint_and_prints_one_line(tmp_path, dataset):
    """SIGINT while checkpoints are written every step: exit 130 with the 'interrupted' line
    and no traceback, no temporary checkpoint folder; the same command then resumes and
    finishes."""
    config = write_config(tmp_path, dataset, steps=STEPS, checkpoint_every=1, log_every=1)
    workdir = tmp_path / "run"
    env = cli_env(tmp_path / "cache")
    command = [sys.executable, "-m", "jaxden.cli", "train", str(config), "--workdir",
               str(workdir)]
    proc = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=sigint_default)
    metrics = workdir / "metrics.jsonl"
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if metrics.exists() and len(metrics.read_text().splitlines()) > 8:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-3000:]
    assert stderr.replace("\r", "\n").strip().splitlines()[-1] == (
        "jaxden: interrupted (finished work is kept; run the same command to resume)")
    assert "Traceback" not in stderr and "orbax" not in stderr.lower()
    assert not [p for p in workdir.iterdir() if "tmp" in p.name]
    stopped = checkpoint_steps(workdir)[-1]
    assert 0 < stopped < STEPS
    # The same command resumes from the last checkpoint and finishes.
    finish = subprocess.run(command, env=env, capture_output=True, text=True, timeout=300,
                            check=False)
    assert finish.returncode == 0, finish.stderr[-3000:]
    assert checkpoint_steps(workdir)[-1] == STEPS
    records = metrics_records(workdir)
    # Every step logged once: none lost, none repeated.
    assert [r["step"] for r in records if "loss" in r] == list(range(1, STEPS + 1))


def test_a_batch_that_does_not_split_uses_fewer_devices(tmp_path, dataset, capsys):
    """batch_size 3 on two devices: one device trains (a note says so) instead of an error."""
    if len(jax.devices()) != 2:
        pytest.skip("needs exactly two devices (conftest gives the CPU two)")
    config = load_train_config(write_config(tmp_path, dataset, steps=1, checkpoint_every=1),
                               ["data.batch_size=3"])
    result = loop.train_and_evaluate(config, tmp_path / "run", progress=True)
    assert result["step"] == 1
    assert "splits evenly over 1 of the 2 JAX devices" in capsys.readouterr().err
