"""Time a 48-item dataset build on a two-node Ray cluster against the local executor, on the
same machine, in one run (docs/scaling.md, "What Ray costs on one machine").

    unshare -n sh -c 'ip link set lo up && .venv/bin/python docs/scaling_bench.py'

(``unshare -n`` keeps the cluster on loopback; without root run it plainly.) The cluster is two
Ray nodes of ``--cpus-per-node`` CPUs on this machine (``ray.cluster_utils.Cluster``: the same
GCS and raylet processes that ``ray start`` runs); the local executor gets as many worker
processes as the cluster has CPUs. The dataset is ``experiments/configs/dataset-tiny.toml``
with 6 crops per scene: 2 scenes x 6 crops x (3 input spp + 1 reference) = 48 renders of
32 x 32 pixels, rendered by Mitsuba. A first, untimed build fills Mitsuba's kernel cache; then
local and Ray builds alternate (``--repeats`` pairs, each into a fresh folder) and the script
prints one JSON object: the seconds of every build and the Ray / local ratio of the medians.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2, help="local/Ray build pairs")
    parser.add_argument("--cpus-per-node", type=int, default=1)
    parser.add_argument("--crops-per-scene", type=int, default=6)
    args = parser.parse_args()

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    from ray.cluster_utils import Cluster

    from jaxden.config import load_config
    from jaxden.data.builder import build_dataset
    from jaxden.data.config import DatasetConfig

    config = load_config(ROOT / "experiments" / "configs" / "dataset-tiny.toml", DatasetConfig,
                         [f"crops_per_scene={args.crops_per_scene}"])
    work = Path(tempfile.mkdtemp(prefix="jaxden-scaling-"))
    start = time.perf_counter()
    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": args.cpus_per_node, "include_dashboard": False,
        "object_store_memory": 200 * 2**20})
    cluster.add_node(num_cpus=args.cpus_per_node, object_store_memory=200 * 2**20)
    cluster.wait_for_nodes()
    cluster_seconds = time.perf_counter() - start
    workers = 2 * args.cpus_per_node
    try:
        warm = build_dataset(config, work / "warm-up", executor="local", workers=workers,
                             progress=False)
        items = len(warm.items)
        seconds: dict[str, list[float]] = {"local": [], "ray": []}
        for repeat in range(args.repeats):
            for kind in ("local", "ray"):
                out = work / f"{kind}-{repeat}"
                start = time.perf_counter()
                build_dataset(config, out, executor=kind, workers=workers, progress=False,
                              ray_address=cluster.address if kind == "ray" else None)
                seconds[kind].append(round(time.perf_counter() - start, 2))
                shutil.rmtree(out)
    finally:
        cluster.shutdown()
        shutil.rmtree(work, ignore_errors=True)
    local, ray = statistics.median(seconds["local"]), statistics.median(seconds["ray"])
    print(json.dumps({
        "items": items, "nodes": 2, "cpus_per_node": args.cpus_per_node,
        "local_workers": workers, "cluster_start_seconds": round(cluster_seconds, 2),
        "seconds": seconds, "ray_over_local": round(ray / local, 3),
        "cpu_count": os.cpu_count(), "load_average": [round(x, 2) for x in os.getloadavg()],
    }))


if __name__ == "__main__":
    main()
