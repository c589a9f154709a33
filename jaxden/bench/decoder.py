"""Benchmark ``decoder``: the WSKP kernel decoder, production (box) form vs reference (unfold).

Problem: :func:`jaxden.denoise.kernels.decode` on a 1280 x 720 x 3 image with six kernels of sizes
3, 5, ..., 13 (``quick``: 320 x 180), random colour, importance and fusion logits (seeded).

Memory is XLA's *compiled* memory analysis of each jitted function
(``jit(f).lower(...).compile().memory_analysis()``): ``temp_size_in_bytes +
output_size_in_bytes``, i.e. the buffers XLA allocates for the computation beyond its inputs
(the inputs are identical for both forms). It is exact for what XLA plans and needs no
allocation, so the unfold form's forward+backward (tens of GB at 720p) can be measured
without running it; it does not see allocator fragmentation or the Python process.

Time: wall-clock and process CPU time per call, both forms compiled first, the median of
``repeats`` calls timed alternately (drift of a shared machine hits both alike). The unfold
form takes tens of seconds per call at 720p, so it gets fewer repeats.

``box_over_windowed`` (and ``backward_box_over_windowed``): the box form's global-shift path,
which these inputs take (importance ~ N(0, 2^2)), over its per-window path alone.

Keys: ``memory_ratio`` (box / unfold, forward; target <= 0.25), ``time_ratio`` (box / unfold
wall time, forward; target <= 1.0), ``cpu_time_ratio``, the raw numbers, and the same for
forward+backward (gradient w.r.t. colour, importance and logits): memory for both forms,
time for the box form (and the unfold form only in ``quick`` mode, where it is cheap).
"""

from __future__ import annotations

import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.denoise import kernels

try:
    from jaxden.bench import register
except ImportError:  # pragma: no cover - the registry is optional for importing this module

    def register(name):
        return lambda fn: fn


KERNEL_SIZES = kernels.DEFAULT_KERNEL_SIZES
FULL_SIZE = (720, 1280)
QUICK_SIZE = (180, 320)  # (height, width) of ``quick``; the tests make it smaller still
QUICK_REPEATS = 3


def _inputs(height: int, width: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    count = len(KERNEL_SIZES)
    color = rng.gamma(1.0, 1.0, (height, width, 3)).astype(np.float32)
    importance = (2.0 * rng.standard_normal((height, width, count))).astype(np.float32)
    logits = rng.standard_normal((height, width, count)).astype(np.float32)
    return jnp.asarray(color), jnp.asarray(importance), jnp.asarray(logits)


def _decoder(form: str):
    """'box' and 'unfold' are the public forms; 'windowed' is the box form's per-window path
    alone (what 'box' falls back to for importance ranges >= 64; these inputs take the
    global-shift path)."""
    if form == "windowed":
        return lambda c, i, a: kernels._decode_windowed(c, i, a, KERNEL_SIZES)
    return lambda c, i, a: kernels.decode(c, i, a, KERNEL_SIZES, form)


def _forward(form: str):
    return jax.jit(_decoder(form))


def _backward(form: str):
    decode = _decoder(form)

    def loss(c, i, a):
        return jnp.sum(decode(c, i, a))

    return jax.jit(jax.grad(loss, argnums=(0, 1, 2)))


def _compiled_bytes(fn, args) -> int:
    stats = fn.lower(*args).compile().memory_analysis()
    return int(stats.temp_size_in_bytes + stats.output_size_in_bytes)


def _time(fns: dict, args, repeats: dict) -> tuple[dict, dict]:
    """Median wall and CPU seconds per call; each fn is warmed up (compiled) first."""
    for fn in fns.values():
        jax.block_until_ready(fn(*args))
    wall = {name: [] for name in fns}
    cpu = {name: [] for name in fns}
    for round_ in range(max(repeats.values())):
        for name, fn in fns.items():
            if round_ >= repeats[name]:
                continue
            start, start_cpu = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(*args))
            wall[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
    return (
        {name: statistics.median(v) for name, v in wall.items()},
        {name: statistics.median(v) for name, v in cpu.items()},
    )


def measure(size: tuple[int, int] = FULL_SIZE, repeats: int = 5, unfold_repeats: int = 3,
            time_unfold_backward: bool = False) -> dict:
    """All numbers for one image size; see the module docstring."""
    args = _inputs(*size)
    forward = {form: _forward(form) for form in ("box", "unfold")}
    backward = {form: _backward(form) for form in ("box", "unfold")}
    memory = {form: _compiled_bytes(fn, args) for form, fn in forward.items()}
    memory_bwd = {form: _compiled_bytes(fn, args) for form, fn in backward.items()}

    agreement = float(
        jnp.max(jnp.abs(forward["box"](*args) - forward["unfold"](*args)))
        / jnp.max(jnp.abs(forward["unfold"](*args)))
    )
    forward["windowed"] = _forward("windowed")
    wall, cpu = _time(forward, args,
                      {"box": repeats, "windowed": repeats, "unfold": unfold_repeats})
    timed_bwd = {"box": backward["box"], "windowed": _backward("windowed")}
    if time_unfold_backward:
        timed_bwd["unfold"] = backward["unfold"]
    wall_bwd, cpu_bwd = _time(timed_bwd, args,
                              {"box": repeats, "windowed": repeats, "unfold": unfold_repeats})

    result = {
        "memory_ratio": memory["box"] / memory["unfold"],
        "time_ratio": wall["box"] / wall["unfold"],
        "cpu_time_ratio": cpu["box"] / cpu["unfold"],
        "size": f"{size[1]}x{size[0]}x3",
        "kernel_sizes": ",".join(map(str, KERNEL_SIZES)),
        "memory": "XLA compiled memory analysis: temp + output bytes",
        "box_mb": memory["box"] / 2**20,
        "unfold_mb": memory["unfold"] / 2**20,
        "box_s": wall["box"],
        "unfold_s": wall["unfold"],
        "box_cpu_s": cpu["box"],
        "unfold_cpu_s": cpu["unfold"],
        "max_rel_difference": agreement,
        "backward_memory_ratio": memory_bwd["box"] / memory_bwd["unfold"],
        "backward_box_mb": memory_bwd["box"] / 2**20,
        "backward_unfold_mb": memory_bwd["unfold"] / 2**20,
        "backward_box_s": wall_bwd["box"],
        "backward_box_cpu_s": cpu_bwd["box"],
        "windowed_s": wall["windowed"],
        "box_over_windowed": wall["box"] / wall["windowed"],
        "backward_windowed_s": wall_bwd["windowed"],
        "backward_box_over_windowed": wall_bwd["box"] / wall_bwd["windowed"],
    }
    if time_unfold_backward:
        result["backward_unfold_s"] = wall_bwd["unfold"]
        result["backward_time_ratio"] = wall_bwd["box"] / wall_bwd["unfold"]
    return result


@register("decoder")
def bench_decoder(quick: bool) -> dict:
    """Box vs unfold decoder at 1280 x 720 (quick: 320 x 180); see the module docstring."""
    if quick:
        return measure(QUICK_SIZE, repeats=QUICK_REPEATS, unfold_repeats=2,
                       time_unfold_backward=True)
    return measure(FULL_SIZE, repeats=5, unfold_repeats=2)
