"""Faults during `jaxden train` and `jaxden sweep`: SIGKILL mid-run and a full disk.

What must hold: a killed run or sweep resumes with the same command, loses no finished
checkpoint or run (their files are untouched: bytes and mtimes), redoes no finished run, and
ends where an uninterrupted one ends; a full disk is one line ``jaxden: error: ... No space
left on device`` with exit status 2, leaves no partial file (no temporary file, no half
checkpoint, no cut metrics line), and the same command resumes once there is space.

The commands run in subprocesses (what a user sees on stderr) through a small hook script
that, at a chosen checkpoint of a chosen run folder, SIGKILLs its own process right after
the save starts (orbax is then writing the checkpoint in the background) or fills the disk
just before the save, so every fault hits the same point each time. The disk is a small
tmpfs (root only; skipped otherwise). Data: the tiny Mitsuba-free dataset; model: a 4-step
KP of one layer. Other faults are covered elsewhere: Ctrl-C and a locked workdir in
test_train_reliability.py, a killed dataset build in test_dataset.py, full-disk denoise and
render in test_adversarial.py.
"""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

import pytest
from helpers import (
    assert_no_partial_files,
    assert_one_error_line,
    assert_same_state,
    build_tiny_dataset,
    checkpoint_steps,
    files,
    hooked_env,
    logged_steps,
    run_jaxden,
    small_tmpfs,
    write_sweep,
    write_train_config,
)

# Runs `jaxden ARGS` with one fault. JAXDEN_TEST_FAULT is "kill:<run folder>:<step>" (SIGKILL
# right after the save of that checkpoint starts) or "fill:<run folder>:<step>:<filler file>"
# (fill the disk just before that save; step 0: when that run starts, before its first file).
HOOK = """
import os, signal, sys
from pathlib import Path
from jaxden import checkpoint
from jaxden.cli import main
from jaxden.train import loop

kind, name, step, *rest = os.environ["JAXDEN_TEST_FAULT"].split(":")
step = int(step)

def fill():
    with open(rest[0], "wb", buffering=0) as handle:
        try:
            while True:
                handle.write(b"\\0" * 4096)
        except OSError:
            pass

real_save = checkpoint.Checkpointer.save
real_train = loop.train_and_evaluate

def save(self, at, state, meta):
    hit = self.directory.name == name and int(at) == step
    if hit and kind == "fill":
        self.wait()  # earlier checkpoints finish first: only this one meets the full disk
        fill()
    real_save(self, at, state, meta)
    if hit and kind == "kill":
        os.kill(os.getpid(), signal.SIGKILL)

def train_and_evaluate(config, workdir, **options):
    if Path(workdir).name == name and step == 0 and kind == "fill":
        fill()
    return real_train(config, workdir, **options)

checkpoint.Checkpointer.save = save
loop.train_and_evaluate = train_and_evaluate
sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """(folder with the hook, the dataset and the training config, subprocess env)."""
    folder = tmp_path_factory.mktemp("faults")
    dataset = build_tiny_dataset(folder / "tiny")
    write_train_config(folder, dataset, eval_every=4, keep_checkpoints=3, steps=4)
    return folder, hooked_env(folder, HOOK)


def jaxden(setup, *argv, fault: str | None = None) -> subprocess.CompletedProcess:
    folder, env = setup
    return run_jaxden(folder, env, argv, hook_var="JAXDEN_TEST_FAULT", hook_value=fault)


def error_lines(stderr: str) -> list[str]:
    """stderr without the progress bar: what is left must be the one error line."""
    lines = [line.strip() for line in stderr.replace("\r", "\n").splitlines()]
    return [line for line in lines if line and not line.startswith("train kp")]


def assert_sweep_resumes(setup, sweep: Path, workdir: Path) -> None:
    """The same `jaxden sweep` again, after its run 'b' was stopped: it skips the finished run
    'a' without touching any of its files, finishes 'b' and leaves nothing partial."""
    finished = files(workdir / "a")
    done = jaxden(setup, "sweep", sweep, "--workdir", workdir)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "(1 run now, 1 already finished)" in done.stdout
    assert files(workdir / "a") == finished
    assert_no_partial_files(workdir)


# ------------------------------------------------------------------------------ SIGKILL
@pytest.mark.slow  # ~21 s; Ctrl-C during a checkpoint stays in the default suite
def test_training_killed_while_checkpointing_resumes(setup, tmp_path):
    """SIGKILL while checkpoint 4 is being written: checkpoint 2 is kept untouched, the rerun
    removes the unfinished save, resumes from 2 and finishes; every step is logged once."""
    folder, _ = setup
    workdir = tmp_path / "run"
    killed = jaxden(setup, "train", folder / "train.toml", "--workdir", workdir,
                    fault="kill:run:4")
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    # The kill cuts the save short (it leaves orbax's temporary folder, never taken for a
    # checkpoint), unless a descheduled main thread let orbax finish first.
    assert checkpoint_steps(workdir) == [2] and (workdir / "4.orbax-checkpoint-tmp").is_dir() \
        or checkpoint_steps(workdir) == [2, 4]
    kept = files(workdir / "2")
    done = jaxden(setup, "train", folder / "train.toml", "--workdir", workdir)
    assert done.returncode == 0, done.stderr[-3000:]
    assert checkpoint_steps(workdir) == [2, 4]
    assert files(workdir / "2") == kept
    assert_no_partial_files(workdir)
    assert logged_steps(workdir) == ([1, 2, 3, 4], [0, 4])


@pytest.mark.slow  # ~20 s: a sweep killed mid-run; test_interrupts and test_sweep cover resuming sweeps
def test_sweep_killed_mid_run_redoes_no_finished_run(setup, tmp_path):
    """SIGKILL in the second run of a sweep (while its checkpoint 4 is written): the rerun
    skips the finished run without touching any of its files, resumes the killed one from its
    checkpoint 2, and that run ends exactly where the finished one (the same config) did:
    same parameters, same validation loss, the same steps logged once."""
    folder, _ = setup
    sweep = write_sweep(folder, tmp_path)
    workdir = tmp_path / "w"
    killed = jaxden(setup, "sweep", sweep, "--workdir", workdir, fault="kill:b:4")
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    assert (workdir / "a" / "result.json").is_file()
    assert not (workdir / "b" / "result.json").exists()
    assert_sweep_resumes(setup, sweep, workdir)
    a, b = (json.loads((workdir / r / "result.json").read_text()) for r in ("a", "b"))
    assert b["train"]["step"] == a["train"]["step"] == 4
    assert b["train"]["val_loss"] == pytest.approx(a["train"]["val_loss"], rel=1e-6)
    assert logged_steps(workdir / "b") == logged_steps(workdir / "a") == ([1, 2, 3, 4], [0, 4])
    assert_same_state(workdir / "a", workdir / "b")
    summary = json.loads((workdir / "summary.json").read_text())
    assert [r["run"] for r in summary["runs"]] == ["a", "b"]


# ---------------------------------------------------------------------------- full disk
@pytest.fixture()
def small_disk(tmp_path):
    """A 4 MiB tmpfs (root only; skipped otherwise), unmounted afterwards."""
    with small_tmpfs(tmp_path / "disk", "4m") as folder:
        yield folder


def assert_one_disk_full_line(result: subprocess.CompletedProcess) -> None:
    assert_one_error_line(result.returncode, error_lines(result.stderr),
                          "No space left on device")


@pytest.mark.slow  # ~20 s; the sweep's case below fills the disk at a training checkpoint too
def test_full_disk_while_training_is_one_line_and_resumes(setup, small_disk):
    """The disk fills up just before checkpoint 4: one line, exit 2, checkpoint 2 and the
    metrics log whole, nothing partial; with space again the same command finishes."""
    folder, _ = setup
    workdir = small_disk / "run"
    filler = small_disk / "filler"
    full = jaxden(setup, "train", folder / "train.toml", "--workdir", workdir,
                  fault=f"fill:run:4:{filler}")
    assert_one_disk_full_line(full)
    filler.unlink()
    assert checkpoint_steps(workdir) == [2]
    assert_no_partial_files(workdir)
    kept = files(workdir / "2")
    done = jaxden(setup, "train", folder / "train.toml", "--workdir", workdir)
    assert done.returncode == 0, done.stderr[-3000:]
    assert checkpoint_steps(workdir) == [2, 4] and files(workdir / "2") == kept
    assert_no_partial_files(workdir)
    assert logged_steps(workdir) == ([1, 2, 3, 4], [0, 4])


@pytest.mark.parametrize("step", [pytest.param(0, id="before-run-b", marks=pytest.mark.slow),
                                  pytest.param(4, id="checkpoint-of-run-b")])
def test_full_disk_during_a_sweep_is_one_line_and_resumes(setup, small_disk, tmp_path, step):
    """The disk fills up during the sweep's second run (before its first file, or just before
    its checkpoint 4): one line, exit 2, nothing partial, the first run untouched; with space
    again the same command skips the first run and finishes the second where the first
    ended."""
    folder, _ = setup
    sweep = write_sweep(folder, tmp_path)
    workdir = small_disk / "w"
    filler = small_disk / "filler"
    full = jaxden(setup, "sweep", sweep, "--workdir", workdir, fault=f"fill:b:{step}:{filler}")
    assert_one_disk_full_line(full)
    filler.unlink()
    assert (workdir / "a" / "result.json").is_file()
    assert not (workdir / "b" / "result.json").exists()
    assert not (workdir / "summary.json").exists()
    assert_no_partial_files(workdir)
    assert_sweep_resumes(setup, sweep, workdir)
    assert logged_steps(workdir / "b") == ([1, 2, 3, 4], [0, 4])
    assert_same_state(workdir / "a", workdir / "b")
