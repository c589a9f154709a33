"""Benchmark ``sharding``: a data-parallel training step on 2 host devices / on 1 device.

Runs in subprocesses with ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (the flag
must be set before JAX starts) and times the same jitted train step (batch 8 of 128 x 128
synthetic frames, SMAPE, Adam) with the batch on a 1-device mesh and split over a 2-device
mesh, alternating, after compiling both; for the U-Net (``unet_ratio``) and WSKP-6
(``wskp_ratio``). ``ratio`` is the U-Net's (target <= 0.6).

Why two: on a 2-core CPU a single XLA device keeps only about one core busy on convolution-heavy
steps, so splitting the batch over two devices nearly halves the U-Net's step; WSKP-6's step is
dominated by the kernel decoder's element-wise passes, which XLA already spreads over both
cores from one device, so sharding it brings nothing on this CPU (it is for several GPUs).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

from jaxden.bench import register
from jaxden.errors import JaxdenError

#: (batch, size, repeats) of ``quick`` (the tests make it smaller still).
QUICK = (4, 64, 3)

CHILD = r"""
import json, statistics, sys, time
import jax, jax.numpy as jnp, numpy as np
from jaxden.frame import Frame
from jaxden.train.config import OptimConfig, TrainConfig
from jaxden.train.loop import TrainState, make_train_step
from jaxden.train.optim import loss_function, make_optimizer
from jaxden.train.sharding import data_mesh, replicate, shard_batch
from jaxden.train.tasks import make_task

batch_size, size, repeats, model = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
rng = np.random.default_rng(0)
shape = (batch_size, size, size)
normal = rng.normal(size=shape + (3,)).astype(np.float32)
frame = Frame(color=rng.gamma(1.0, 0.5, shape + (3,)).astype(np.float32),
              variance=rng.uniform(0, 0.1, shape + (3,)).astype(np.float32),
              albedo=rng.uniform(0, 1, shape + (3,)).astype(np.float32),
              normal=normal / np.linalg.norm(normal, axis=-1, keepdims=True),
              depth=rng.uniform(1, 4, shape + (1,)).astype(np.float32))
batch = {"input": frame, "reference": rng.gamma(1.0, 0.5, shape + (3,)).astype(np.float32)}
config = TrainConfig(model=model)
task = make_task(config)
optimizer = make_optimizer(OptimConfig(schedule="constant"))
step = jax.jit(make_train_step(task, optimizer, loss_function("smape")))
params = task.init(jax.random.PRNGKey(0), batch)
runs = {}
for count in (1, 2):
    mesh = data_mesh(jax.devices()[:count])
    state = replicate(TrainState(params, optimizer.init(params), jnp.int32(0)), mesh)
    runs[count] = [state, shard_batch(batch, mesh), []]
    for _ in range(2):
        state, metrics = step(runs[count][0], runs[count][1])
        jax.block_until_ready(metrics["loss"])
        runs[count][0] = state
for _ in range(repeats):
    for count in (1, 2):
        state, data, times = runs[count]
        start = time.perf_counter()
        state, metrics = step(state, data)
        jax.block_until_ready(metrics["loss"])
        times.append(time.perf_counter() - start)
        runs[count][0] = state
one, two = statistics.median(runs[1][2]), statistics.median(runs[2][2])
print(json.dumps({"ratio": two / one, "step_1_device_s": one, "step_2_devices_s": two,
                  "devices": len(jax.devices()), "batch": batch_size, "size": size,
                  "repeats": repeats}))
"""


@register("sharding")
def bench_sharding(quick: bool) -> dict:
    batch, size, repeats = QUICK if quick else (8, 128, 9)
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    out: dict = {}
    for model in ("unet", "wskp"):
        result = subprocess.run(
            [sys.executable, "-c", CHILD, str(batch), str(size), str(repeats), model],
            env=env, capture_output=True, text=True,
        )
        if result.returncode != 0:
            raise JaxdenError(f"sharding benchmark ({model}) failed: "
                              f"{result.stderr.strip().splitlines()[-1:]}")
        measured = json.loads(result.stdout.strip().splitlines()[-1])
        out[f"{model}_ratio"] = measured["ratio"]
        out[f"{model}_step_1_device_s"] = measured["step_1_device_s"]
        out[f"{model}_step_2_devices_s"] = measured["step_2_devices_s"]
    out["ratio"] = out["unet_ratio"]
    out.update({"batch": batch, "size": size, "repeats": repeats, "devices": 2})
    return out
