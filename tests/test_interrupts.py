"""Ctrl-C (SIGINT) during `jaxden dataset build` and `jaxden sweep`.

What must hold: exit status 130, the last stderr line ``jaxden: interrupted ...`` and no
traceback; nothing partial left (no temporary file, every JSON, JSONL and EXR reads whole);
the work finished before Ctrl-C untouched by the rerun (bytes and mtimes); and the same command
then finishes with the result of an uninterrupted one.

The commands run in subprocesses, each in its own session (process group), through a small
hook script (as in test_faults.py) that sends SIGINT to that whole group at a chosen point, as
a terminal's Ctrl-C does (the dataset's render worker gets it too): right after the build has
recorded its first finished crop, or right after the checkpoint of a chosen step of a chosen
sweep run starts saving. Ctrl-C of `jaxden train` is in test_train_reliability.py; SIGKILL and
a full disk in test_faults.py and test_dataset.py.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from helpers import (
    ROOT,
    assert_no_partial_files,
    assert_same_state,
    build_tiny_dataset,
    checkpoint_steps,
    files,
    hooked_env,
    logged_steps,
    run_jaxden,
    write_sweep,
    write_train_config,
)

INTERRUPTED = "jaxden: interrupted (finished work is kept; run the same command to resume)"

# Runs `jaxden ARGS`, sending SIGINT to its process group once. JAXDEN_TEST_SIGINT is
# "result:<n>" (when a map of the executor is asked for its result after the n-th: the
# caller has recorded n results) or "save:<run folder>:<step>" (right after the save of that
# checkpoint starts). Under __main__: the dataset's spawned workers import this script.
HOOK = """
import os, signal, sys

def interrupt():
    # The whole group, as a terminal's Ctrl-C; only this process if it leads no group of its
    # own (never the test runner's).
    if os.getpgid(0) == os.getpid():
        os.killpg(0, signal.SIGINT)
    else:
        os.kill(os.getpid(), signal.SIGINT)

if __name__ == "__main__":
    from jaxden import checkpoint, executor
    from jaxden.cli import main

    kind, *where = os.environ["JAXDEN_TEST_SIGINT"].split(":")

    if kind == "result":
        real_map = executor.LocalExecutor.map_unordered

        def map_unordered(self, fn, items):
            for count, result in enumerate(real_map(self, fn, items), 1):
                yield result
                if count == int(where[0]):
                    interrupt()

        executor.LocalExecutor.map_unordered = map_unordered
    else:
        real_save = checkpoint.Checkpointer.save

        def save(self, at, state, meta):
            real_save(self, at, state, meta)
            if self.directory.name == where[0] and int(at) == int(where[1]):
                interrupt()

        checkpoint.Checkpointer.save = save
    sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """(folder with the hook, subprocess env)."""
    folder = tmp_path_factory.mktemp("interrupts")
    return folder, hooked_env(folder, HOOK)


def jaxden(setup, *argv, sigint: str | None = None) -> subprocess.CompletedProcess:
    """``jaxden ARGV`` in its own session; with ``sigint``, through the hook (see HOOK)."""
    folder, env = setup
    return run_jaxden(folder, env, argv, hook_var="JAXDEN_TEST_SIGINT", hook_value=sigint,
                      start_new_session=True)


def assert_interrupted(result: subprocess.CompletedProcess) -> None:
    """Exit 130, the 'interrupted' line last (after the progress bar), no traceback."""
    assert result.returncode == 130, result.stderr[-3000:]
    lines = [line for line in result.stderr.replace("\r", "\n").splitlines() if line.strip()]
    assert lines and lines[-1].startswith("jaxden: interrupted"), lines[-5:]
    assert lines[-1] == INTERRUPTED
    assert "Traceback" not in result.stderr, result.stderr[-3000:]


def exrs(folder: Path) -> dict[str, tuple[bytes, int]]:
    return {path: state for path, state in files(folder).items() if path.endswith(".exr")}


def test_ctrl_c_of_a_dataset_build_keeps_finished_items_and_resumes(setup, tmp_path):
    """Mitsuba builds dataset-tiny.toml (two crops of 4 renders) with one worker process;
    Ctrl-C right after the first crop is recorded (the worker has started the second): the
    manifest records the first crop's items, every file left is whole, the rerun renders the
    rest without touching the files already there, and its EXRs are byte for byte those of an
    uninterrupted build."""
    pytest.importorskip("mitsuba")
    config = ROOT / "experiments" / "configs" / "dataset-tiny.toml"
    out = tmp_path / "tiny"
    stopped = jaxden(setup, "dataset", "build", config, "--out", out, sigint="result:1")
    assert_interrupted(stopped)
    assert_no_partial_files(out)
    manifest = json.loads((out / "manifest.json").read_text())
    recorded = [item for item in manifest["items"] if item["sha256"]]
    assert len(recorded) == 4 and len({item["crop"] for item in recorded}) == 1, recorded
    assert len(recorded) < len(manifest["items"])
    finished = exrs(out)
    assert {item["path"] for item in recorded} <= set(finished)

    done = jaxden(setup, "dataset", "build", config, "--out", out)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "dataset complete" in done.stdout
    assert_no_partial_files(out)
    after = exrs(out)
    assert {path: after[path] for path in finished} == finished
    assert len(after) == len(manifest["items"])

    fresh = tmp_path / "fresh"
    clean = jaxden(setup, "dataset", "build", config, "--out", fresh)
    assert clean.returncode == 0, clean.stderr[-3000:]
    assert {p: b for p, (b, _) in after.items()} == {p: b for p, (b, _) in exrs(fresh).items()}


def test_ctrl_c_of_a_sweep_keeps_the_finished_run_and_resumes(setup, tmp_path):
    """Ctrl-C in the second run of a sweep, while its checkpoint 2 is being written: the
    checkpoint is finished (no temporary folder), the first run's files are untouched, the
    rerun skips the first run, resumes the second from step 2, and that run ends where the
    first (the same config, uninterrupted) ended."""
    dataset = build_tiny_dataset(tmp_path / "data")
    write_train_config(tmp_path, dataset, eval_every=4, keep_checkpoints=3, steps=4)
    sweep = write_sweep(tmp_path, tmp_path)
    workdir = tmp_path / "w"
    stopped = jaxden(setup, "sweep", sweep, "--workdir", workdir, sigint="save:b:2")
    assert_interrupted(stopped)
    assert (workdir / "a" / "result.json").is_file()
    assert not (workdir / "b" / "result.json").exists()
    assert not (workdir / "summary.json").exists()
    assert checkpoint_steps(workdir / "b") == [2]
    assert_no_partial_files(workdir)
    finished = files(workdir / "a")

    done = jaxden(setup, "sweep", sweep, "--workdir", workdir)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "(1 run now, 1 already finished)" in done.stdout
    assert files(workdir / "a") == finished
    assert_no_partial_files(workdir)
    a, b = (json.loads((workdir / r / "result.json").read_text()) for r in ("a", "b"))
    assert b["train"]["step"] == a["train"]["step"] == 4
    assert b["train"]["val_loss"] == pytest.approx(a["train"]["val_loss"], rel=1e-6)
    assert logged_steps(workdir / "b") == logged_steps(workdir / "a") == ([1, 2, 3, 4], [0, 4])
    assert_same_state(workdir / "a", workdir / "b")
    summary = json.loads((workdir / "summary.json").read_text())
    assert [r["run"] for r in summary["runs"]] == ["a", "b"]
