"""Training over several processes (jax.distributed, CPU gloo collectives) and every core by
default.

The multi-process jobs run inside a network namespace with nothing but loopback
(``unshare -n``, then ``ip link set lo up``), started by a driver script that runs inside it
too: no packet of the job can leave the machine. That needs root (and ``unshare``); elsewhere
those tests are skipped with the reason.

What they show: two processes with one CPU device each train the same model as one process
with two devices (the global batch split the same way) to 1e-5 after 20 steps, each process
reading only its rows; a job whose process 1 is killed mid-run stops with one line, keeps its
last checkpoint, and resumes from it when both processes are started again.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import (
    FAST_COMPILE,
    build_tiny_dataset,
    metrics_records,
    restore_last_checkpoint,
    write_train_config,
)

from jaxden.distributed import CPU_DEVICES_ENV, FORCE_DEVICES_OPTION, use_all_cores
from jaxden.errors import ConfigError


@functools.cache
def loopback_namespace_reason() -> str | None:
    """None when ``unshare -n`` gives this test a loopback-only network, else why not."""
    if os.geteuid() != 0:
        return "needs root for `unshare -n` (a loopback-only network namespace)"
    if not shutil.which("unshare") or not shutil.which("ip"):
        return "needs `unshare` and `ip` (util-linux, iproute2)"
    probe = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up && ip -o addr"],
                           capture_output=True, text=True, timeout=30, check=False)
    if probe.returncode != 0:
        return f"`unshare -n` failed here: {probe.stderr.strip()[:200]}"
    if any("inet" in line and " lo " not in f" {line} " for line in probe.stdout.splitlines()):
        return "the namespace has a non-loopback address"
    return None


def run_in_loopback(script: Path, *args: str, env: dict, timeout: float):
    """Run ``python script args`` inside a fresh network namespace that has only loopback."""
    return subprocess.run(
        ["unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$0" "$@"', sys.executable,
         str(script), *args], env=env, capture_output=True, text=True, timeout=timeout,
        check=False)


needs_namespace = pytest.mark.skipif(
    sys.platform != "linux" or loopback_namespace_reason() is not None,
    reason=str(loopback_namespace_reason() if sys.platform == "linux" else "Linux only"))


# ------------------------------------------------------------------------- every core
def test_use_all_cores_sets_xla_flags_unless_the_user_chose():
    env = {}
    count = use_all_cores(env)
    from jaxden.distributed import cpu_count

    if cpu_count() > 1:
        assert count == cpu_count()
        assert env["XLA_FLAGS"] == f"{FORCE_DEVICES_OPTION}={cpu_count()}"
    # Other XLA flags are kept; an explicit device count is never overridden.
    env = {"XLA_FLAGS": "--xla_cpu_foo=1", CPU_DEVICES_ENV: "3"}
    assert use_all_cores(env) == 3
    assert env["XLA_FLAGS"] == f"--xla_cpu_foo=1 {FORCE_DEVICES_OPTION}=3"
    env = {"XLA_FLAGS": f"{FORCE_DEVICES_OPTION}=5", CPU_DEVICES_ENV: "3"}
    assert use_all_cores(env) is None and env["XLA_FLAGS"] == f"{FORCE_DEVICES_OPTION}=5"
    env = {CPU_DEVICES_ENV: "1"}  # the opt-out: JAX's own single device
    assert use_all_cores(env) is None and "XLA_FLAGS" not in env
    with pytest.raises(ConfigError, match=CPU_DEVICES_ENV):
        use_all_cores({CPU_DEVICES_ENV: "many"})


# `jaxden train CONFIG` / `jaxden bench NAME` with the command replaced by a report of what
# JAX sees.
CHILD_DEVICES = """
import sys
import jaxden.cli.bench as bench
import jaxden.cli.train as train

def report(args):
    import jax
    print("DEVICES", len(jax.devices()))
    return 0

bench.cmd_bench = train.cmd_train = report
from jaxden.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_cli_exposes_one_device_per_core_to_training_only(tmp_path):
    """`jaxden train|sweep` start JAX with one CPU device per core (here: what the command
    sees), JAXDEN_CPU_DEVICES=1 keeps JAX's single device, and `jaxden bench` times with
    the single device `denoise` and `progressive` run on."""
    from jaxden.distributed import cpu_count

    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", CPU_DEVICES_ENV)}
    env["JAX_PLATFORMS"] = "cpu"
    seen = []
    train = ["train", "x.toml", "--workdir", str(tmp_path / "run")]
    for words, extra in ((train, {}), (train, {CPU_DEVICES_ENV: "1"}),
                         (["bench", "render"], {})):
        out = subprocess.run([sys.executable, "-c", CHILD_DEVICES, *words],
                             env={**env, **extra}, capture_output=True, text=True,
                             timeout=120, check=False)
        assert out.returncode == 0, out.stderr[-2000:]
        seen.append(int(out.stdout.split("DEVICES")[1].split()[0]))
    assert seen == [cpu_count(), 1, 1]


# ------------------------------------------------------------------------- multi-process
#: The tiny KP model, 20 steps of batches of 4 (split over the processes or devices).
TRAIN_OPTIONS = {"steps": 20, "eval_every": 20, "eval_batches": 2, "checkpoint_every": 5,
                 "keep_checkpoints": 5, "batch_size": 4}

# Process 1 of the interrupted job: the real `jaxden train`, killed (SIGKILL, no clean-up)
# when it takes the batch of step KILL_AT.
KILLED_PROCESS = """
import os, signal, sys
import jaxden.train.loop as loop

KILL_AT = int(sys.argv[1])
real = loop.batches_from

def batches_from(loader, start_step, mesh=None):
    for index, batch in enumerate(real(loader, start_step, mesh)):
        if start_step + index == KILL_AT and loader.split == "train":
            os.kill(os.getpid(), signal.SIGKILL)
        yield batch

loop.batches_from = batches_from
from jaxden.cli import main
sys.exit(main(sys.argv[2:]))
"""

# Runs inside the namespace: one process with two devices, then the two-process job that
# loses process 1, then that job restarted; prints one JSON line.
DRIVER = """
import json, os, subprocess, sys, time
config, root, killer, mode = sys.argv[1:5]
base = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
base["XLA_FLAGS"] = os.environ["JAXDEN_TEST_FAST_COMPILE"]
jaxden = [sys.executable, "-m", "jaxden.cli"]
report = {}

def start_job(workdir, port, kill_at=None):
    procs = []
    for pid in (0, 1):
        args = ["train", config, "--workdir", workdir, "--coordinator", f"127.0.0.1:{port}",
                "--num-processes", "2", "--process-id", str(pid)]
        command = jaxden + args
        if pid == 1 and kill_at is not None:
            command = [sys.executable, killer, str(kill_at)] + args
        procs.append(subprocess.Popen(command, env={**base, "JAXDEN_CPU_DEVICES": "1"},
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    return procs


def finish(procs):
    out = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=600)
        out.append({"rc": p.returncode, "stdout": stdout[-2000:], "stderr": stderr[-3000:]})
    return out


# XLA compiles on one thread: the single-process reference and the first two-process job
# run side by side.
start = time.time()
one_log = open(f"{root}/one.log", "w+")
one = subprocess.Popen(jaxden + ["train", config, "--workdir", f"{root}/one"],
                       env={**base, "JAXDEN_CPU_DEVICES": "2"}, stdout=one_log, stderr=one_log)
if mode == "full":
    report["two"] = finish(start_job(f"{root}/two", 29411))
report["killed"] = finish(start_job(f"{root}/killed", 29412, kill_at=13))
report["checkpoints_after_kill"] = sorted(
    int(p) for p in os.listdir(f"{root}/killed") if p.isdigit())
report["leftovers"] = [p for p in os.listdir(f"{root}/killed") if "tmp" in p]
report["resumed"] = finish(start_job(f"{root}/killed", 29413))
one.wait(timeout=600)
one_log.seek(0)
report["one"] = {"rc": one.returncode, "stderr": one_log.read()[-3000:]}
report["seconds"] = time.time() - start
print("REPORT " + json.dumps(report))
"""


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return build_tiny_dataset(tmp_path_factory.mktemp("dist") / "tiny", ["crops_per_scene=4"])


def final_params(workdir: Path):
    import jax

    state, meta = restore_last_checkpoint(workdir)
    return meta["step"], jax.tree_util.tree_leaves(state["params"])


def losses(workdir: Path) -> dict[int, float]:
    return {r["step"]: r["loss"] for r in metrics_records(workdir) if "loss" in r}


def run_driver(tmp_path, dataset, mode):
    config = write_train_config(tmp_path, dataset, **TRAIN_OPTIONS)
    driver, killer = tmp_path / "driver.py", tmp_path / "killed.py"
    driver.write_text(DRIVER)
    killer.write_text(KILLED_PROCESS)
    # One compilation cache for all the processes: each program is compiled once.
    env = {**os.environ, "JAXDEN_CACHE_DIR": str(tmp_path / "cache"), "JAX_PLATFORMS": "cpu",
           "JAXDEN_TEST_FAST_COMPILE": FAST_COMPILE}
    done = run_in_loopback(driver, str(config), str(tmp_path), str(killer), mode, env=env,
                           timeout=1200)
    assert done.returncode == 0 and "REPORT " in done.stdout, (done.stdout[-2000:],
                                                               done.stderr[-4000:])
    return json.loads(done.stdout.split("REPORT ", 1)[1])


def assert_same_training(reference: Path, other: Path):
    step, want = final_params(reference)
    other_step, got = final_params(other)
    assert step == other_step == 20
    assert len(want) == len(got)
    for a, b in zip(want, got):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-5)
    mine, theirs = losses(reference), losses(other)
    assert sorted(mine) == sorted(theirs) == list(range(1, 21))  # each step logged once
    np.testing.assert_allclose([theirs[s] for s in mine], list(mine.values()), atol=1e-5)


@needs_namespace
def test_two_processes_killed_and_resumed_match_one_process_with_two_devices(tmp_path,
                                                                              tiny_dataset):
    report = run_driver(tmp_path, tiny_dataset, "kill")
    assert report["one"]["rc"] == 0, report["one"]["stderr"]
    killed = report["killed"]
    assert killed[1]["rc"] == -9  # SIGKILL at step 13
    # Process 0 notices at the next collective and stops with one line, no traceback.
    assert killed[0]["rc"] == 2, killed[0]["stderr"]
    errors = [line for line in killed[0]["stderr"].splitlines() if line.startswith("jaxden:")]
    assert len(errors) == 1 and "the distributed job stopped" in errors[0], errors
    assert "Traceback" not in killed[0]["stderr"]
    # The checkpoints before the kill are there, nothing half-written.
    assert report["checkpoints_after_kill"][-1] == 10 and not report["leftovers"]
    resumed = report["resumed"]
    assert [p["rc"] for p in resumed] == [0, 0], resumed
    # Only process 0 reports (and writes).
    assert "finished: step=20" in resumed[0]["stdout"] and "finished" not in resumed[1]["stdout"]
    # Two processes (killed at 13, resumed from 10) reach what one process with two devices
    # reaches: the same global batches split over the same two devices.
    assert_same_training(tmp_path / "one", tmp_path / "killed")


@needs_namespace
@pytest.mark.slow
def test_two_processes_match_one_process_with_two_devices(tmp_path, tiny_dataset):
    report = run_driver(tmp_path, tiny_dataset, "full")
    assert report["one"]["rc"] == 0, report["one"]["stderr"]
    assert [p["rc"] for p in report["two"]] == [0, 0], report["two"]
    assert_same_training(tmp_path / "one", tmp_path / "two")
    assert_same_training(tmp_path / "one", tmp_path / "killed")


@pytest.mark.parametrize("options, words", [
    (["--num-processes", "2", "--process-id", "1"], "need --coordinator HOST:PORT"),
    (["--coordinator", "nowhere", "--num-processes", "2", "--process-id", "0"],
     "expected HOST:PORT"),
    (["--coordinator", "127.0.0.1:1", "--num-processes", "2", "--process-id", "2"],
     "--process-id 2 must be below --num-processes 2"),
])
def test_bad_distributed_options_are_one_line(tmp_path, capsys, options, words):
    from jaxden.cli import main

    config = write_train_config(tmp_path, tmp_path, **TRAIN_OPTIONS)
    assert main(["train", str(config), "--workdir", str(tmp_path / "w"), *options]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "w").exists()
