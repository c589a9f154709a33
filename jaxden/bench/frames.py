"""Frame-size benchmarks: ``jaxden bench progressive --size WxH[,WxH...]`` and
``jaxden bench denoisers --size ...``: wall time and peak memory of the commands users run,
per megapixel, at whole-frame sizes (the issue's 1280x720, 1920x1080, 3840x2160, 7680x4320).

The commands (:data:`COMMANDS`): ``progressive``: ``oidn`` (``jaxden denoise --model oidn``,
the peer), ``pd_oidn`` (``jaxden progressive --denoiser oidn``) and ``pd_wskp6`` (``jaxden
progressive --denoiser wskp-6 --mixer wskp-6-pd``); ``denoisers``:
``oidn``, ``wskp6``, ``oidnjax``, ``statmc`` and ``statmc_moon`` (``jaxden denoise --model
wskp-6``, ``--model oidn-jax``, ``--model statmc``, ``--model statmc-moon``).

What is measured, and how: each command runs in its own child process exactly as a user types
it (``python -m jaxden.cli denoise IN.exr --model oidn --out OUT.exr``, ...), so the numbers
cover the whole command, as ``/usr/bin/time -v`` reports it: process start, imports, JAX's
compiles, reading and writing the EXR files and the denoising itself. Wall time is
``time.perf_counter`` around the child; its peak resident memory is ``ru_maxrss`` of
``os.wait4`` (KiB on Linux; reported in GB = 10^9 bytes) and its CPU time ``ru_utime +
ru_stime``. The child is forked by a bare interpreter (:data:`STARTER`), not by the bench: Linux
counts the forking process's memory in the child's ``ru_maxrss``. Host memory only: on a GPU
the device memory (which JAX preallocates) is not in it.
The children get the bench's environment with two changes: no
``--xla_force_host_platform_device_count`` in ``XLA_FLAGS`` (a user's, or one left by
``jaxden train``'s environment; ``jaxden denoise`` and ``jaxden progressive`` run with JAX's
default devices) and a fresh compilation cache (``$JAXDEN_CACHE_DIR`` in the temporary folder).
Each command runs :data:`RUNS` times in a row (:data:`QUICK_RUNS` with ``--quick``): the first
run compiles (a first-time user), later runs load the compiled programs from that cache (every
later frame of the same size); the reported ``_s`` and ``_gb`` are the last run's and
``_first_s`` / ``_first_gb`` the first's when there are several.

The input of each size is one EXR frame written by the bench into a temporary folder:
``$JAXDEN_BENCH_FRAME`` if set (any size), else the Cornell box at 4 spp, seed 1, rendered
once by ``jaxden render`` (a child too) at the largest requested size capped at
:data:`BASE_SIZE`, else (no Mitsuba) :func:`jaxden.render.synthetic.synthetic_render`; tiled
(whole copies, then cropped) up to each requested size, with every channel the source has
(colour, variance, albedo, normal, depth, ...), float32 as ``jaxden render`` writes it.
``frame_source`` in the result says which. The commands of :data:`STATISTICS_COMMANDS`
(StatMC) read a second file, the same frame with Box-Cox statistics (``boxcox``): the
source's own, else approximated from its colour and variance
(:func:`jaxden.bench.denoisers.with_statistics`); the others' file stays as it was.

Keys (``SIZE`` as measured, e.g. ``1920x1080``; ``CMD`` as in :data:`COMMANDS`):
``CMD_SIZE_s``, ``_gb``, ``_s_per_mp``, ``_gb_per_mp``, ``_cpu_s``, ``_status`` (the exit
status; a failing command is recorded with ``_error``, its last stderr line, and gets no
per-megapixel numbers or ratios); ``CMD_over_oidn_time_SIZE`` and ``CMD_over_oidn_memory_SIZE``
against ``jaxden denoise --model oidn`` (the peer, ``oidn``) at the same size; and, when
:data:`REFERENCE_SIZE` (1920x1080) and a larger size were both measured,
``CMD_time_per_mp_LARGEST_over_1920x1080`` and ``CMD_memory_per_mp_LARGEST_over_1920x1080``
(1 = cost linear in the pixel count); with two sizes or more,
``CMD_marginal_s_per_mp_SMALLEST_to_LARGEST`` and ``CMD_marginal_gb_per_mp_...``: the
difference between the largest and the smallest size over their difference in megapixels, the
cost of one more megapixel without the fixed cost of starting Python and JAX (which dominates
small frames' per-megapixel numbers). Also the machine: ``cpus``, ``ram_gb``, ``gpu`` (from
``nvidia-smi``, if any) and ``JAXDEN_MEMORY_LIMIT`` when set.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from jaxden.bench import BENCH_FRAME_ENV, register_sizes

Size = tuple[int, int]
#: A command: (input .exr, output .exr) -> argv.
Command = Callable[[str, str], list[str]]

JAXDEN = [sys.executable, "-m", "jaxden.cli"]


def _denoise(model: str) -> Command:
    return lambda source, out: [*JAXDEN, "denoise", source, "--model", model, "--out", out]


def _progressive(*options: str) -> Command:
    return lambda source, out: [*JAXDEN, "progressive", source, *options, "--out", out]


#: The peer of every ratio: ``jaxden denoise --model oidn``.
PEER = "oidn"
#: Commands of each benchmark, by key; the peer first. ``--quick`` leaves out QUICK_SKIP (none:
#: it runs each command once).
COMMANDS: dict[str, dict[str, Command]] = {
    "progressive": {
        PEER: _denoise("oidn"),
        "pd_oidn": _progressive("--denoiser", "oidn"),
        "pd_wskp6": _progressive("--denoiser", "wskp-6", "--mixer", "wskp-6-pd"),
    },
    "denoisers": {
        PEER: _denoise("oidn"),
        "wskp6": _denoise("wskp-6"),
        "oidnjax": _denoise("oidn-jax"),
        "statmc": _denoise("statmc"),
        "statmc_moon": _denoise("statmc-moon"),
    },
}
#: Commands that read the frame with its Box-Cox statistics (``Frame.boxcox``).
STATISTICS_COMMANDS = {"statmc"}
QUICK_SKIP: set[str] = set()
#: Runs of each command (the first compiles; the last is reported).
RUNS, QUICK_RUNS = 2, 1
#: The size whose time per megapixel the largest size's is compared with.
REFERENCE_SIZE: Size = (1920, 1080)
#: The largest frame rendered as the tile (larger sizes are tiled from it).
BASE_SIZE: Size = (1280, 720)
#: Seconds a command may run before it is stopped and recorded as failed (None: no limit).
TIMEOUT_S: float | None = None


def size_name(size: Size) -> str:
    return f"{size[0]}x{size[1]}"


def megapixels(size: Size) -> float:
    return size[0] * size[1] / 1e6


# ---------------------------------------------------------------------------- children
def child_env(cache: Path | None = None) -> dict[str, str]:
    """The children's environment: this one's without a forced XLA CPU device count, and with
    ``cache`` as ``$JAXDEN_CACHE_DIR`` if given."""
    from jaxden.distributed import FORCE_DEVICES_OPTION

    env = dict(os.environ)
    flags = [flag for flag in env.get("XLA_FLAGS", "").split()
             if not flag.startswith(FORCE_DEVICES_OPTION)]
    if flags:
        env["XLA_FLAGS"] = " ".join(flags)
    else:
        env.pop("XLA_FLAGS", None)
    if cache is not None:
        env["JAXDEN_CACHE_DIR"] = str(cache)
    return env


#: The starter of every measured command, run as ``python -S -c STARTER RESULT ARGV...``:
#: it forks, execs ARGV, waits for it with ``os.wait4`` and writes wall seconds, exit status
#: and rusage to the JSON file RESULT. Linux counts the memory of the process that forks a
#: child (at the fork, kept through exec) in the child's ``ru_maxrss``: forked from the bench
#: itself (JAX imported, frames in memory), every command would show at least the bench's
#: size. The starter is a bare interpreter (~10 MB), below any jaxden command's own peak.
STARTER = """
import json, os, sys, time
result, argv = sys.argv[1], sys.argv[2:]
start = time.perf_counter()
pid = os.fork()
if pid == 0:
    try:
        os.execvp(argv[0], argv)
    except OSError as error:
        os.write(2, f"cannot run {argv[0]}: {error}\\n".encode())
        os._exit(127)
_, status, usage = os.wait4(pid, 0)
wall = time.perf_counter() - start
with open(result, "w") as handle:
    json.dump({"s": wall, "status": os.waitstatus_to_exitcode(status),
               "maxrss_kib": usage.ru_maxrss, "cpu_s": usage.ru_utime + usage.ru_stime}, handle)
"""


def measure(argv: Sequence[str], env: dict[str, str], log: Path,
            timeout: float | None = None) -> dict:
    """Run ``argv`` as a child process (through :data:`STARTER`): ``{"s": wall seconds,
    "gb": peak RSS (GB), "cpu_s": user + system seconds, "status": exit status, "error": last
    output line (failures)}``. Its stdout and stderr go to ``log``; after ``timeout`` seconds
    it is stopped (status -9)."""
    record = log.with_suffix(".rusage.json")
    record.unlink(missing_ok=True)
    with open(log, "wb") as output:
        start = time.perf_counter()
        # Its own process group, so that a timeout or Ctrl-C stops the command with it.
        process = subprocess.Popen([sys.executable, "-S", "-c", STARTER, str(record), *argv],
                                   stdin=subprocess.DEVNULL, stdout=output,
                                   stderr=subprocess.STDOUT, env=env, start_new_session=True)
        try:
            process.wait(timeout=timeout)
            stopped = None
        except subprocess.TimeoutExpired:
            stopped = f"stopped after {timeout:g} s (TIMEOUT_S)"
        except BaseException:  # Ctrl-C: stop the command, then stop
            _stop(process)
            raise
        if stopped:
            _stop(process)
        wall = time.perf_counter() - start
    try:
        import json

        measured = json.loads(record.read_text())
    except (OSError, ValueError):
        measured = None
    if measured is None:  # the starter itself was stopped or failed
        result = {"s": wall, "gb": 0.0, "cpu_s": 0.0,
                  "status": process.returncode if process.returncode else -9}
    else:
        result = {"s": measured["s"], "gb": measured["maxrss_kib"] * 1024 / 1e9,
                  "cpu_s": measured["cpu_s"], "status": measured["status"]}
    if result["status"] != 0:
        lines = [line.strip() for line in log.read_text(errors="replace").splitlines()
                 if line.strip()]
        result["error"] = stopped or (lines[-1] if lines else
                                      "(no output)" if result["status"] > 0 else
                                      f"killed by signal {-result['status']}")
    return result


def _stop(process: subprocess.Popen) -> None:
    """SIGKILL the process group of ``process`` (the starter and the command) and reap it."""
    import signal

    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    process.wait()


# -------------------------------------------------------------------------- the frames
def base_frame(largest: Size, folder: Path):
    """(Frame, description): the tile the benchmark frames are made of (module docstring)."""
    from jaxden.io.exr import read_frame

    need = ("color", "variance", "albedo", "normal")
    path = os.environ.get(BENCH_FRAME_ENV)
    if path:
        frame = read_frame(path, require=need)
        return frame, f"${BENCH_FRAME_ENV} = {path} ({frame.width}x{frame.height}), tiled"
    size = (min(largest[0], BASE_SIZE[0]), min(largest[1], BASE_SIZE[1]))
    out = folder / "base.exr"
    argv = [*JAXDEN, "render", "cornell-box", "--spp", "4", "--seed", "1", "--size",
            size_name(size), "--out", str(out)]
    done = measure(argv, child_env(), folder / "render.log")
    if done["status"] == 0:
        return (read_frame(out, require=need),
                f"cornell-box, 4 spp, seed 1, rendered at {size_name(size)}, tiled")
    from jaxden.render.synthetic import synthetic_render

    return (synthetic_render("bench", 4, seed=1, size=size),
            f"synthetic {size_name(size)}, tiled (jaxden render failed: {done['error']})")


def tiled(frame, size: Size):
    """``frame`` repeated whole (np.tile) to cover ``size`` = (width, height), then cropped."""
    import numpy as np

    from jaxden.frame import IMAGE_FIELDS

    width, height = size
    reps = (math.ceil(height / frame.height), math.ceil(width / frame.width), 1)
    changes = {}
    for name in IMAGE_FIELDS:
        array = getattr(frame, name)
        if array is not None:
            changes[name] = np.ascontiguousarray(np.tile(np.asarray(array), reps)[:height, :width])
    return frame.replace(**changes)


def write_bench_frame(frame, size: Size, path: Path) -> None:
    from jaxden.io.exr import write_frame

    write_frame(path, tiled(frame, size), attributes={"scene": "jaxden bench frame"})


# ----------------------------------------------------------------------- the benchmark
def parse_sizes(text: str) -> list[Size]:
    """'WxH[,WxH...]' -> [(W, H), ...] in order, without repeats; ValueError for a bad one."""
    sizes: list[Size] = []
    for part in text.split(","):
        pieces = part.strip().lower().split("x")
        try:
            width, height = (int(p) for p in pieces)
        except ValueError:
            raise ValueError(f"sizes must look like 1280x720 or 1280x720,1920x1080 (WxH), "
                             f"got {part.strip()!r}"
                             + (f" in {text!r}" if "," in text else "")) from None
        if width <= 0 or height <= 0:
            raise ValueError(f"sizes must be positive, got {part.strip()!r}")
        if (width, height) not in sizes:
            sizes.append((width, height))
    return sizes


def machine() -> dict:
    """CPUs, RAM, the GPU (nvidia-smi) and JAXDEN_MEMORY_LIMIT, for the result."""
    from jaxden.limits import ENV_LIMIT, physical_memory

    info: dict = {"cpus": os.cpu_count() or 0, "ram_gb": physical_memory() / 1e9}
    if hasattr(os, "sched_getaffinity"):
        info["cpus_usable"] = len(os.sched_getaffinity(0))
    if shutil.which("nvidia-smi"):
        try:
            done = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total",
                                   "--format=csv,noheader"], capture_output=True, text=True,
                                  timeout=30, check=False)
            if done.returncode == 0 and done.stdout.strip():
                info["gpu"] = "; ".join(line.strip() for line in done.stdout.splitlines()
                                        if line.strip())
        except (OSError, subprocess.SubprocessError):
            pass
    if os.environ.get(ENV_LIMIT):
        info[ENV_LIMIT] = os.environ[ENV_LIMIT]
    return info


def frame_bench(name: str, quick: bool, sizes: Sequence[Size]) -> dict:
    """Run benchmark ``name``'s :data:`COMMANDS` on a frame of each size (module docstring)."""
    commands = {key: command for key, command in COMMANDS[name].items()
                if not (quick and key in QUICK_SKIP)}
    runs = QUICK_RUNS if quick else RUNS
    sizes = list(dict.fromkeys(tuple(s) for s in sizes))
    result: dict = {"sizes": ",".join(size_name(s) for s in sizes),
                    "commands": ",".join(commands), "runs": runs, "peer": PEER}
    with tempfile.TemporaryDirectory(prefix="jaxden-bench-frames-") as temp:
        folder = Path(temp)
        env = child_env(folder / "cache")
        result["xla_flags"] = env.get("XLA_FLAGS", "")
        largest = (max(s[0] for s in sizes), max(s[1] for s in sizes))
        tile, result["frame_source"] = base_frame(largest, folder)
        for size in sizes:
            source, out = folder / f"{size_name(size)}.exr", folder / "out.exr"
            write_bench_frame(tile, size, source)
            statistics = folder / f"{size_name(size)}-statistics.exr"
            for key, command in commands.items():
                if key in STATISTICS_COMMANDS and not statistics.exists():
                    from jaxden.bench.denoisers import with_statistics

                    write_bench_frame(with_statistics(tile), size, statistics)
                argv = command(str(statistics if key in STATISTICS_COMMANDS else source),
                               str(out))
                measured = [measure(argv, env, folder / f"{key}.log", TIMEOUT_S)
                            for _ in range(runs)]
                _record(result, key, size, measured)
                out.unlink(missing_ok=True)
            source.unlink(missing_ok=True)
            statistics.unlink(missing_ok=True)
    _ratios(result, commands, sizes)
    result.update(machine())
    return result


def _record(result: dict, key: str, size: Size, measured: list[dict]) -> None:
    last, first = measured[-1], measured[0]
    prefix = f"{key}_{size_name(size)}"
    for metric in ("s", "gb", "cpu_s", "status"):
        result[f"{prefix}_{metric}"] = last[metric]
    failed = next((m for m in measured if m["status"] != 0), None)
    if failed is not None:
        result[f"{prefix}_status"] = failed["status"]
        result[f"{prefix}_error"] = failed["error"]
    else:
        result[f"{prefix}_s_per_mp"] = last["s"] / megapixels(size)
        result[f"{prefix}_gb_per_mp"] = last["gb"] / megapixels(size)
    if len(measured) > 1:
        result[f"{prefix}_first_s"], result[f"{prefix}_first_gb"] = first["s"], first["gb"]
    done = "ok" if failed is None else f"exit {failed['status']}: {failed['error']}"
    print(f"jaxden bench: {size_name(size)} {key}: {last['s']:.2f} s, {last['gb']:.3f} GB "
          f"peak RSS ({done})", file=sys.stderr, flush=True)


def _ok(result: dict, key: str, size: Size) -> bool:
    return f"{key}_{size_name(size)}_s_per_mp" in result


def _ratios(result: dict, commands, sizes: list[Size]) -> None:
    for size in sizes:
        if not _ok(result, PEER, size):
            continue
        peer = f"{PEER}_{size_name(size)}"
        for key in commands:
            if key != PEER and _ok(result, key, size):
                own = f"{key}_{size_name(size)}"
                result[f"{key}_over_{PEER}_time_{size_name(size)}"] = (
                    result[f"{own}_s"] / result[f"{peer}_s"])
                result[f"{key}_over_{PEER}_memory_{size_name(size)}"] = (
                    result[f"{own}_gb"] / result[f"{peer}_gb"])
    for key in commands:  # the slope: what one more megapixel costs, start-up excluded
        measured = sorted((s for s in sizes if _ok(result, key, s)), key=megapixels)
        if len(measured) >= 2 and megapixels(measured[-1]) > megapixels(measured[0]):
            small, big = (f"{key}_{size_name(s)}" for s in (measured[0], measured[-1]))
            pixels = megapixels(measured[-1]) - megapixels(measured[0])
            tail = f"{size_name(measured[0])}_to_{size_name(measured[-1])}"
            result[f"{key}_marginal_s_per_mp_{tail}"] = (
                (result[f"{big}_s"] - result[f"{small}_s"]) / pixels)
            result[f"{key}_marginal_gb_per_mp_{tail}"] = (
                (result[f"{big}_gb"] - result[f"{small}_gb"]) / pixels)
    reference = tuple(REFERENCE_SIZE)
    if reference not in sizes:
        return
    for key in commands:
        measured = [s for s in sizes if _ok(result, key, s)]
        if reference not in measured:
            continue
        largest = max(measured, key=lambda s: s[0] * s[1])
        if largest[0] * largest[1] <= reference[0] * reference[1]:
            continue
        big, ref = f"{key}_{size_name(largest)}", f"{key}_{size_name(reference)}"
        tail = f"{size_name(largest)}_over_{size_name(reference)}"
        result[f"{key}_time_per_mp_{tail}"] = result[f"{big}_s_per_mp"] / result[f"{ref}_s_per_mp"]
        result[f"{key}_memory_per_mp_{tail}"] = (result[f"{big}_gb_per_mp"]
                                                 / result[f"{ref}_gb_per_mp"])


def table(result: dict) -> list[str]:
    """The result as a table, one row per size and command, then the ratios and settings."""
    sizes = parse_sizes(result["sizes"])
    commands = result["commands"].split(",")
    named = max([9, *(len(key) for key in commands)])
    header = (f"  {'size':<10} {'command':<{named}} {'wall s':>8} {'peak GB':>8} {'s/MP':>8} "
              f"{'GB/MP':>7} {'cpu s':>8} {'t/' + PEER:>7} {'m/' + PEER:>7}  exit")
    lines = [header]

    def cell(key: str, width: int, digits: int) -> str:
        value = result.get(key)
        return f"{'-' if value is None else f'{value:.{digits}f}':>{width}}"

    for size in sizes:
        for key in commands:
            prefix = f"{key}_{size_name(size)}"
            if f"{prefix}_s" not in result:
                continue
            status = result[f"{prefix}_status"]
            exit_ = "0" if status == 0 else f"{status}: {result.get(prefix + '_error', '')}"
            lines.append(
                f"  {size_name(size):<10} {key:<{named}} {cell(prefix + '_s', 8, 2)} "
                f"{cell(prefix + '_gb', 8, 3)} {cell(prefix + '_s_per_mp', 8, 2)} "
                f"{cell(prefix + '_gb_per_mp', 7, 3)} {cell(prefix + '_cpu_s', 8, 1)} "
                f"{cell(f'{key}_over_{PEER}_time_{size_name(size)}', 7, 2)} "
                f"{cell(f'{key}_over_{PEER}_memory_{size_name(size)}', 7, 2)}  {exit_}")
    scaling = sorted(k for k in result if "_per_mp_" in k)
    other = ("peer", "runs", "frame_source", "xla_flags", "cpus", "cpus_usable", "ram_gb",
             "gpu", "JAXDEN_MEMORY_LIMIT")
    width = max(len(k) for k in (*scaling, *other))
    for key in (*scaling, *other):
        if key in result:
            value = result[key]
            text = f"{value:.4g}" if isinstance(value, float) else str(value) or "(none)"
            lines.append(f"  {key:<{width}}  {text}")
    return lines


@register_sizes("progressive", table=table)
def bench_progressive_frames(quick: bool, sizes: Sequence[Size]) -> dict:
    return frame_bench("progressive", quick, sizes)


@register_sizes("denoisers", table=table)
def bench_denoisers_frames(quick: bool, sizes: Sequence[Size]) -> dict:
    return frame_bench("denoisers", quick, sizes)
