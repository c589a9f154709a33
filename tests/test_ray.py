"""The Ray executor on a real two-node Ray cluster (`jaxden dataset build|sweep --executor ray`).

The cluster (two nodes of one CPU each, ``ray.cluster_utils.Cluster``) and every process that
talks to it, including the driver part of these tests, run inside a network namespace with
nothing but loopback (``unshare -n``, then ``ip link set lo up``): Ray binds the machine's other
addresses even when told 127.0.0.1, and no packet may leave the machine. That needs root;
elsewhere those tests are skipped with the reason. The errors that start no cluster (no
address, an unreachable one) run anywhere.

What they show: a dataset built through Ray is byte-identical to the local build; a node killed
mid-build loses nothing (its task is rerun on the other node) and its workers' output stays out
of the build's; relative ``--out`` / ``--workdir`` / ``data.dataset`` mean the caller's folder;
a four-run mixer sweep over one dataset (one SURE cache) on two workers finishes; a cluster
with no free CPU gives a clear error after the stated wait, and Ctrl-C cancels the tasks and
exits 130.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest
from test_distributed import FAST_COMPILE, loopback_namespace_reason, run_in_loopback

from jaxden.cli import main
from jaxden.errors import JaxdenError
from jaxden.executor import ExecutorError, make_executor

ROOT = Path(__file__).resolve().parent.parent
TINY = ROOT / "experiments" / "configs" / "dataset-tiny.toml"

ray = pytest.importorskip("ray", reason="Ray is not installed: pip install 'jaxden[ray]'")

needs_namespace = pytest.mark.skipif(
    sys.platform != "linux" or loopback_namespace_reason() is not None,
    reason=str(loopback_namespace_reason() if sys.platform == "linux" else "Linux only"))


# ----------------------------------------------------------------- errors without a cluster
def test_ray_needs_an_address_and_never_starts_a_private_cluster(monkeypatch, tmp_path, capsys):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    with pytest.raises(ExecutorError, match=r"--ray-address HOST:PORT .* RAY_ADDRESS"):
        make_executor("ray")
    assert not ray.is_initialized()
    out = tmp_path / "ds"
    assert main(["dataset", "build", str(TINY), "--out", str(out), "--executor", "ray"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxden: error: executor 'ray' needs a Ray "
                                               "cluster"), err
    assert not out.exists()  # nothing written before the executor exists
    # An address without --executor ray is not silently ignored.
    assert main(["dataset", "build", str(TINY), "--out", str(out), "--ray-address", "local"]) == 2
    assert "--ray-address is for --executor ray" in capsys.readouterr().err


def test_unreachable_cluster_is_one_clear_line(monkeypatch, tmp_path, capsys):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'base = "{ROOT / "experiments" / "configs" / "mixer-tiny.toml"}"\n'
                     f'overrides = ["data.dataset={tmp_path}"]\n[axes]\nseed = [0]\n')
    # Port 1 on loopback: refused at once (nothing leaves the machine).
    for argv in (["dataset", "build", str(TINY), "--out", str(tmp_path / "ds")],
                 ["sweep", str(sweep), "--workdir", str(tmp_path / "w")]):
        monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:1")
        code = main([*argv, "--executor", "ray"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, err
        assert "cannot reach the Ray cluster at 127.0.0.1:1" in err[0], err
    assert main(["dataset", "build", str(TINY), "--out", str(tmp_path / "ds"), "--executor",
                 "ray", "--ray-address", "nonsense"]) == 2
    assert "expected HOST:PORT" in capsys.readouterr().err
    assert not (tmp_path / "ds").exists() and not ray.is_initialized()


def test_task_errors_keep_their_type_and_message():
    """The executor's contract, checked on the serial and local executors here (the Ray one
    re-raises a task's own exception too: see the cluster tests)."""
    for kind in ("serial", "local"):
        with make_executor(kind, workers=1) as pool, pytest.raises(JaxdenError, match="bad 3"):
            list(pool.map_unordered(_fail_on_three, [1, 2, 3]))


def _fail_on_three(value: int) -> int:
    from jaxden.errors import DatasetError

    if value == 3:
        raise DatasetError(f"bad {value}")
    return value


# ----------------------------------------------------------------- a two-node cluster
DRIVER = r'''
import hashlib, json, os, signal, subprocess, sys, threading, time
from pathlib import Path


def run():
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    root = Path(sys.argv[1]); mode = sys.argv[2]; repeats = int(sys.argv[3])
    report = {}
    from ray.cluster_utils import Cluster

    start = time.time()
    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 1, "object_store_memory": 100 * 2**20, "include_dashboard": False})
    node_a = cluster.add_node(num_cpus=1, object_store_memory=100 * 2**20)
    cluster.wait_for_nodes()
    address = cluster.address
    report["cluster_seconds"] = time.time() - start

    from jaxden.cli import main
    from jaxden.config import load_config
    from jaxden.data.builder import build_dataset
    from jaxden.render.synthetic import synthetic_render
    from jaxden.data.config import DatasetConfig
    from jaxden.data.verify import verify_dataset

    TINY = sys.argv[4]
    config = load_config(TINY, DatasetConfig, ["crops_per_scene=4"])

    def digests(folder):
        return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(Path(folder).rglob("*.exr"))}

    caller = root / "caller"
    caller.mkdir()
    os.chdir(caller)

    if mode in ("default", "build"):
        # A build through Ray (relative --out: the caller's folder) and a local one.
        start = time.time()
        build_dataset(config, "rel/ray", executor="ray", ray_address=address,
                      render_fn=synthetic_render, progress=False)
        report["ray_build_seconds"] = time.time() - start
        build_dataset(config, root / "local", executor="local", workers=2,
                      render_fn=synthetic_render, progress=False)
        report["same_bytes"] = digests(caller / "rel" / "ray") == digests(root / "local")
        report["files"] = len(digests(root / "local"))
        report["ray_verified"] = verify_dataset(caller / "rel" / "ray").ok

        # A node killed mid-build: its task is rerun elsewhere, nothing is lost, and what its
        # workers printed is not in this process's output.
        LOG = str(root / "renders.log")

        def slow_render(scene, spp, seed=0, size=None, *, crop=None):
            import time as _time

            import ray as _ray

            node = _ray.get_runtime_context().get_node_id()
            print("WORKER-OUTPUT-LINE from", node, flush=True)
            with open(LOG, "a") as log:
                log.write(f"start {node} {scene} {spp} {seed}\n")
            _time.sleep(0.4)
            frame = synthetic_render(scene, spp, seed, size, crop=crop)
            with open(LOG, "a") as log:
                log.write(f"end {node} {scene} {spp} {seed}\n")
            return frame

        def kill_when_busy():
            deadline = time.time() + 120
            while time.time() < deadline:
                lines = Path(LOG).read_text().splitlines() if Path(LOG).exists() else []
                if any(line.startswith(f"start {node_a.node_id}") for line in lines):
                    cluster.remove_node(node_a, allow_graceful=False)
                    report["killed_node"] = node_a.node_id
                    return
                time.sleep(0.05)

        killer = threading.Thread(target=kill_when_busy)
        killer.start()
        manifest = build_dataset(config, root / "killed", executor="ray", ray_address=address,
                                 render_fn=slow_render, progress=False)
        killer.join()
        report["killed_complete"] = manifest.complete and verify_dataset(root / "killed").ok
        report["killed_same_bytes"] = digests(root / "killed") == digests(root / "local")
        lines = Path(LOG).read_text().splitlines()
        started = {l.split(" ", 2)[2] for l in lines if l.startswith(f"start {node_a.node_id}")}
        ended = {l.split(" ", 2)[2] for l in lines if l.startswith(f"end {node_a.node_id}")}
        report["renders_started"] = sum(line.startswith("start") for line in lines)
        report["renders_cut_by_the_kill"] = len(started - ended)
        node_a = cluster.add_node(num_cpus=1, object_store_memory=100 * 2**20)
        cluster.wait_for_nodes()

    if mode in ("default", "sweep"):
        # Four mixer runs over one dataset (one SURE cache) on two Ray workers, through the CLI,
        # with a relative --workdir and data.dataset.
        build_dataset(load_config(TINY, DatasetConfig), "rel/tiny", executor="serial",
                      render_fn=synthetic_render, progress=False)
        sweep = root / "sweep.toml"
        sweep.write_text(
            'base = "' + sys.argv[5] + '"\n'
            'overrides = ["data.dataset=rel/tiny", "optim.steps=2", "eval_every=2", '
            '"checkpoint_every=2", "eval_batches=1", "model_config.width=8"]\n'
            "[axes]\nseed = [0, 1, 2, 3]\n")
        outcomes = []
        for index in range(repeats):
            for executor in (["ray", "--ray-address", address], ["local"]):
                if executor[0] == "local" and mode != "sweep":
                    continue
                start = time.time()
                code = main(["sweep", str(sweep), "--workdir", f"rel/sweep-{executor[0]}-{index}",
                             "--executor", executor[0], "--workers", "2", *executor[1:]])
                runs = sorted(p.parent.name for p in
                              (caller / "rel" / f"sweep-{executor[0]}-{index}").glob("*/result.json"))
                outcomes.append({"executor": executor[0], "code": code, "runs": runs,
                                 "seconds": time.time() - start})
        report["sweeps"] = outcomes

    if mode == "default":
        # No free CPU: every CPU held by other work. A clear error after the stated wait, and
        # Ctrl-C stops the command and cancels its tasks.
        import ray

        ray.init(address=address, log_to_driver=False, logging_level="ERROR")

        @ray.remote(num_cpus=1)
        def hog():
            time.sleep(600)

        hogs = [hog.remote() for _ in range(2)]
        while ray.available_resources().get("CPU", 0) > 0:
            time.sleep(0.2)
        def build_command(out):
            return [sys.executable, "-m", "jaxden.cli", "dataset", "build", TINY, "--out", str(out),
                    "--executor", "ray", "--ray-address", address]

        env = {**os.environ, "JAXDEN_RAY_WAIT_S": "4"}
        start = time.time()
        starved = subprocess.run(build_command(root / "starved"), env=env, capture_output=True,
                                 text=True, timeout=300)
        report["starved"] = {"rc": starved.returncode, "stderr": starved.stderr[-3000:],
                             "seconds": time.time() - start}
        env["JAXDEN_RAY_WAIT_S"] = "300"
        proc = subprocess.Popen(build_command(root / "interrupted"), env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        while not (root / "interrupted" / "manifest.json").exists() and proc.poll() is None:
            time.sleep(0.2)
        time.sleep(3)  # the tasks are submitted and wait for a CPU
        proc.send_signal(signal.SIGINT)
        start = time.time()
        _, stderr = proc.communicate(timeout=120)
        report["interrupted"] = {"rc": proc.returncode, "stderr": stderr[-3000:],
                                 "seconds": time.time() - start}
        for ref in hogs:
            ray.cancel(ref, force=True)
        time.sleep(5)  # were the build's tasks cancelled, they never render now
        report["rendered_after_interrupt"] = len(list((root / "interrupted").rglob("*.exr")))
        ray.shutdown()

    cluster.shutdown()
    print("REPORT " + json.dumps(report))


if __name__ == "__main__":  # the local executor's spawned workers import this file
    run()
'''


def run_cluster_driver(tmp_path: Path, mode: str, repeats: int = 1, timeout: float = 900):
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    env = {**os.environ, "JAXDEN_CACHE_DIR": str(tmp_path / "cache"), "JAX_PLATFORMS": "cpu",
           "JAXDEN_CPU_DEVICES": "1"}
    env.pop("RAY_ADDRESS", None)
    env["XLA_FLAGS"] = FAST_COMPILE
    done = run_in_loopback(driver, str(tmp_path), mode, str(repeats), str(TINY),
                           str(ROOT / "experiments" / "configs" / "mixer-tiny.toml"), env=env,
                           timeout=timeout)
    assert done.returncode == 0 and "REPORT " in done.stdout, (done.stdout[-3000:],
                                                               done.stderr[-5000:])
    report = json.loads(done.stdout.split("REPORT ", 1)[1])
    report["driver_output"] = done.stdout + done.stderr
    return report


@pytest.fixture(scope="module")
def cluster_report(tmp_path_factory):
    if sys.platform != "linux" or loopback_namespace_reason() is not None:
        pytest.skip(str(loopback_namespace_reason()))
    return run_cluster_driver(tmp_path_factory.mktemp("ray"), "default")


@pytest.mark.slow  # the module's Ray cluster driver: 115 s of setup on 2 cores
@needs_namespace
def test_ray_build_is_byte_identical_to_the_local_build(cluster_report):
    assert cluster_report["files"] == 32
    assert cluster_report["same_bytes"] and cluster_report["ray_verified"]


@pytest.mark.slow  # the module's Ray cluster driver: 115 s of setup on 2 cores
@needs_namespace
def test_a_node_killed_mid_build_loses_nothing(cluster_report):
    assert cluster_report.get("killed_node"), "the node was never busy"
    # The kill cut a task of 4 renders short: it ran again on the other node.
    assert cluster_report["renders_started"] > cluster_report["files"], cluster_report
    assert cluster_report["killed_complete"] and cluster_report["killed_same_bytes"]
    # Its workers printed a line per render, and the dead node's last log lines are sent to
    # every driver: none of it reached the build's output.
    assert "WORKER-OUTPUT-LINE" not in cluster_report["driver_output"]
    assert "Raylet is terminated" not in cluster_report["driver_output"]
    assert "(raylet)" not in cluster_report["driver_output"]


@pytest.mark.slow  # the module's Ray cluster driver: 115 s of setup on 2 cores
@needs_namespace
def test_four_run_sweep_over_one_dataset_on_two_ray_workers(cluster_report):
    (sweep,) = cluster_report["sweeps"]
    assert sweep["code"] == 0 and sweep["runs"] == [f"seed={s}" for s in range(4)], sweep


@pytest.mark.slow  # the module's Ray cluster driver: 115 s of setup on 2 cores
@needs_namespace
def test_no_free_cpu_is_an_error_and_ctrl_c_cancels(cluster_report):
    starved = cluster_report["starved"]
    lines = [line for line in starved["stderr"].splitlines() if line.startswith("jaxden:")]
    assert starved["rc"] == 2 and len(lines) == 1, starved
    assert "has had no free CPU for 4 s" in lines[0] and "Traceback" not in starved["stderr"]
    interrupted = cluster_report["interrupted"]
    assert interrupted["rc"] == 130 and interrupted["seconds"] < 30, interrupted
    assert interrupted["stderr"].strip().splitlines()[-1].startswith("jaxden: interrupted")
    assert "Traceback" not in interrupted["stderr"]
    assert cluster_report["rendered_after_interrupt"] == 0


@needs_namespace
@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_four_run_sweeps_finish_ten_times_out_of_ten(tmp_path):
    """The race of issue 23 (runs building one SURE cache at once): ten four-run sweeps over
    one dataset on two workers, through Ray and through local processes."""
    report = run_cluster_driver(tmp_path, "sweep", repeats=10, timeout=3600)
    outcomes = report["sweeps"]
    assert len(outcomes) == 20
    failed = [o for o in outcomes if o["code"] != 0 or len(o["runs"]) != 4]
    assert not failed, failed
