"""Benchmarks: speed and memory as ratios to a peer measured in the same run.

A benchmark is a function ``fn(quick: bool) -> dict`` registered with ``@register("name")`` in
any module of this package (modules are discovered and imported on first use). Its dict holds
at least one ratio key (e.g. ``"ratio"``: jaxden's time / the peer's time) and any times or
settings worth printing. :func:`run` prints a readable table on stdout or, with ``as_json``,
on stderr, stdout then holding one JSON object alone (for scripts and CI: ``json.loads`` of
the whole output).

A benchmark may also measure whole frames of given sizes (``jaxden bench NAME --size
WxH[,WxH...]``): ``fn(quick, sizes) -> dict`` registered with ``@register_sizes("name")``
under a name that ``@register`` also has (:mod:`jaxden.bench.frames`); ``run(name,
sizes=[...])`` runs it instead, and refuses a name without one.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import pkgutil
import sys
from collections.abc import Callable

from jaxden.errors import JaxdenError

BenchFn = Callable[[bool], dict]
SizedBenchFn = Callable[[bool, list[tuple[int, int]]], dict]
_REGISTRY: dict[str, BenchFn] = {}
#: name -> (fn(quick, sizes), table(result) -> lines or None): the frame-size benchmarks.
_SIZED: dict[str, tuple[SizedBenchFn, Callable[[dict], list[str]] | None]] = {}
_discovered = False


def register(name: str) -> Callable[[BenchFn], BenchFn]:
    """Decorator: register ``fn(quick: bool) -> dict`` as benchmark ``name``."""

    def decorate(fn: BenchFn) -> BenchFn:
        if name in _REGISTRY and _REGISTRY[name] is not fn:
            raise ValueError(f"benchmark {name!r} is registered twice")
        _REGISTRY[name] = fn
        return fn

    return decorate


def register_sizes(name: str, table: Callable[[dict], list[str]] | None = None
                   ) -> Callable[[SizedBenchFn], SizedBenchFn]:
    """Decorator: register ``fn(quick: bool, sizes: list[(width, height)]) -> dict`` as the
    frame-size form of benchmark ``name`` (``jaxden bench NAME --size ...``); ``table(result)``
    gives the lines printed instead of the default key / value listing."""

    def decorate(fn: SizedBenchFn) -> SizedBenchFn:
        if name in _SIZED and _SIZED[name][0] is not fn:
            raise ValueError(f"benchmark {name!r} with sizes is registered twice")
        _SIZED[name] = (fn, table)
        return fn

    return decorate


def _discover() -> None:
    global _discovered
    if not _discovered:
        for module in pkgutil.iter_modules(__path__):
            importlib.import_module(f"{__name__}.{module.name}")
        _discovered = True


def median_times(runners: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Median wall-clock seconds of each runner: every runner is called once first (compile,
    warm-up), then all are timed alternately ``repeats`` times (so a slow phase of the machine
    hits them alike). Runners' results are waited for with ``jax.block_until_ready``."""
    import statistics
    import time

    import jax

    for run in runners.values():
        jax.block_until_ready(run())
    times: dict[str, list[float]] = {name: [] for name in runners}
    for _ in range(repeats):
        for name, run in runners.items():
            start = time.perf_counter()
            jax.block_until_ready(run())
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(values) for name, values in times.items()}


#: Environment variable naming an EXR frame that :func:`bench_frame` reads instead of rendering
#: (for machines without Mitsuba, e.g. a GPU machine: render it elsewhere with
#: ``jaxden render cornell-box --spp 4 --seed 1 --size 1280x720 --half --out F.exr``).
BENCH_FRAME_ENV = "JAXDEN_BENCH_FRAME"


def bench_frame(size: tuple[int, int]):
    """The benchmarks' input: the Cornell box at 4 spp, seed 1, ``size`` = (width, height),
    rendered, or read from the EXR that ``$JAXDEN_BENCH_FRAME`` names (it must have that size,
    colour and variance)."""
    import os

    path = os.environ.get(BENCH_FRAME_ENV)
    if not path:
        from jaxden.render.core import render_frame

        return render_frame("cornell-box", 4, seed=1, size=size)
    from jaxden.io.exr import read_frame

    frame = read_frame(path, require=("color", "variance"))
    height, width = frame.color.shape[:2]
    if (width, height) != tuple(size):
        raise JaxdenError(f"${BENCH_FRAME_ENV} = {path}: the frame is {width}x{height}, the "
                          f"benchmark needs {size[0]}x{size[1]}")
    return frame


def names() -> list[str]:
    """Names of all registered benchmarks, sorted."""
    _discover()
    return sorted(_REGISTRY)


def _format(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def sized_names() -> list[str]:
    """Names of the benchmarks that take sizes (``--size``), sorted."""
    _discover()
    return sorted(_SIZED)


def run(name: str, as_json: bool = False, quick: bool = False,
        sizes: list[tuple[int, int]] | None = None) -> dict:
    """Run benchmark ``name``, print a table, return its dict.

    The table goes to stdout; with ``as_json`` it goes to stderr, and stdout holds the dict as
    one JSON object and nothing else (what the benchmark itself prints goes to stderr too).
    ``quick`` asks the benchmark for a smaller problem (for smoke tests). ``sizes``, a list of
    (width, height), runs its frame-size form instead (:func:`register_sizes`). Raises
    JaxdenError for an unknown name, listing the valid ones, and for sizes given to a benchmark
    that takes none.
    """
    _discover()
    if name not in _REGISTRY:
        raise JaxdenError(f"unknown benchmark {name!r}; valid: {', '.join(names()) or 'none'}")
    table = None
    if sizes is not None:
        if name not in _SIZED:
            raise JaxdenError(f"benchmark {name!r} takes no sizes; those that do: "
                              f"{', '.join(sized_names()) or 'none'}")
        if not sizes:
            raise JaxdenError(f"benchmark {name!r}: sizes names no size")
    shown = sys.stderr if as_json else sys.stdout
    with contextlib.redirect_stdout(shown):
        if sizes is not None:
            fn, table = _SIZED[name]
            result = dict(fn(quick, [tuple(size) for size in sizes]))
        else:
            result = dict(_REGISTRY[name](quick))
        result.setdefault("bench", name)
        where = (f" (sizes {', '.join(f'{w}x{h}' for w, h in sizes)})" if sizes is not None
                 else "")
        print(f"benchmark {name}{where}{' (quick)' if quick else ''}")
        if table is not None:
            for line in table(result):
                print(line)
        else:
            width = max(len(str(key)) for key in result)
            for key, value in result.items():
                print(f"  {key!s:<{width}}  {_format(value)}")
    if as_json:
        print(json.dumps(result, sort_keys=True, default=str), flush=True)
    return result
