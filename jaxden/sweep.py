"""Sweeps: a base training config plus axes of overrides, one run folder per point.

A sweep file (TOML, e.g. ``experiments/sweeps/pd-ablations.toml``)::

    base = "../configs/mixer-oidn.toml"   # the training config, relative to this file
    mode = "grid"                          # every combination of the axes ("zip": i-th together)
    overrides = ["optim.steps=3200"]       # for every run; CLI key=value words add to these

    [axes]                                 # override key -> the values it takes
    "model_config.head" = ["f_act", "sigmoid"]
    seed = [0, 1]
    # name = [...]                         # optional: run names (no override)

    [evaluate]                             # optional
    pd = ["data/test-high"]                # mixer runs: PD report on these datasets
    spp = [64, 256, 1024]                  # only these spp levels (default: all)
    denoise = ["$JAXDEN_HOME/data/rt-test"]   # denoiser runs: PSNR, SSIM, relMSE, FLIP
    denoise_spp = [1]                      #   at these input spp (default 1)
    sequences = ["$JAXDEN_HOME/data/rt-seq"]  # denoiser runs: per frame and with temporal
                                           #   accumulation (jaxden.evaluate.denoise)

The keys of ``[evaluate]`` are those of the evaluators that run in sweeps (one that a plugin
registers too: :func:`jaxden.evaluate.registry.evaluate_table_class`): each one's name lists
its datasets, beside the settings it reads (above: ``pd`` reads ``spp``, ``split``,
``probes``, ``seed`` and ``denoiser``, ``denoise`` reads ``split`` and ``denoise_spp``), and
each one gives the summary's columns for its datasets (its ``sweep_columns``).

Paths may use ``~`` and ``$JAXDEN_HOME`` (default ``~/jaxden-work``), here and in overrides
such as ``data.dataset=$JAXDEN_HOME/data/rt``.

``jaxden sweep FILE --workdir DIR`` trains every run in ``DIR/<run name>/`` (its resolved config,
checkpoints and ``metrics.jsonl``, as ``jaxden train`` writes them), evaluates it, and writes the
run's ``result.json`` (its overrides, resolved config, final training metrics and evaluations).
``DIR/summary.json`` and ``DIR/summary.md`` tabulate all runs, with the mean and spread over
seeds when ``seed`` is an axis. A rerun skips every run whose ``result.json`` records the same
resolved config, and an interrupted run resumes from its last checkpoint, so a sweep is
resumable as a whole (a damaged ``result.json`` makes its run count as unfinished: a note
says so and the run is redone from its checkpoints). Runs go through :mod:`jaxden.executor`
(``serial`` by default: each training run already uses every core of a small machine;
``local`` / ``ray`` to spread them).

Data that several runs read (a mixer's SURE cache over the dataset) is built or confirmed once,
in the calling process, before any run is dispatched; the runs then only read it, so runs on
several workers never race to build it (:func:`jaxden.train.loop.prepare_shared_data`). Paths
reach the runs absolute (a relative ``data.dataset`` means the caller's folder, also on a Ray
node). A run name that would leave ``--workdir`` (``..``, ``.``, empty, or a summary's name) is
refused before anything runs, and so is a sweep of more than :data:`MAX_RUNS` runs unless
``allow_large`` (``--allow-large``).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
import tomllib
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

from jaxden.config import config_to_dict, load_config, toml_value
from jaxden.errors import ConfigError

__all__ = ["Run", "SweepConfig", "check_sweep", "load_sweep", "plan_runs", "run_sweep",
           "summarize"]

RESULT_NAME = "result.json"
#: A sweep of more runs is refused unless ``allow_large`` (a typo in [axes] can mean thousands).
MAX_RUNS = 200
#: Names a run folder may not take: they would be the workdir itself, its parent, or a summary.
_RESERVED_NAMES = ("", ".", "..", "summary.json", "summary.md")
#: An axis that only names runs (no override): with mode = "zip" it is the whole folder name.
NAME_AXIS = "name"


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """A sweep file without its ``[axes]`` table (kept apart: its values are any TOML value).

    ``evaluate``: what to measure after each run's training, the ``[evaluate]`` table as
    :func:`load_sweep` checks it: an instance of the dataclass that the registered evaluators
    declare (:func:`jaxden.evaluate.registry.evaluate_table_class`)."""

    base: str
    mode: Literal["grid", "zip"] = "grid"
    overrides: tuple[str, ...] = ()
    evaluate: Any = dataclasses.field(default_factory=dict)
    # Modules to import before any name resolves (jaxden.plugins): a plugin's models, losses
    # and evaluators, in this process and every worker.
    plugins: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class Run:
    """One point of the sweep: its folder name, its axis values and all its overrides."""

    name: str
    values: dict[str, Any]
    overrides: tuple[str, ...]


def load_sweep(path: str | Path, overrides: tuple[str, ...] | list[str] = ()):
    """``(SweepConfig, axes, base path)`` from a sweep file; ``overrides`` (CLI key=value
    words) are appended to the file's ``overrides`` for every run. Errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"sweep file {path} does not exist")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: not valid TOML: {error}") from None
    from jaxden.plugins import load_config_plugins

    load_config_plugins(data, str(path))
    axes = data.pop("axes", None)
    if not isinstance(axes, dict) or not axes:
        raise ConfigError(f"{path}: needs an [axes] table with at least one key = [values]")
    for key, values in axes.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{path}: [axes] {key!r} must be a non-empty list of values, got "
                              f"{values!r}")
    try:
        config = load_config(data, SweepConfig)
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None
    try:  # against the evaluators registered now (a plugin's registers when it is imported)
        evaluate = _load_evaluate(config.evaluate)
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None
    config = dataclasses.replace(config, evaluate=evaluate,
                                 overrides=(*config.overrides, *overrides))
    base = (path.parent / config.base).resolve() if not Path(config.base).is_absolute() \
        else Path(config.base)
    if not base.is_file():
        raise ConfigError(f"{path}: base = {config.base!r}: no such training config ({base})")
    if config.mode == "zip" and len({len(v) for v in axes.values()}) > 1:
        lengths = ", ".join(f"{k}: {len(v)}" for k, v in axes.items())
        raise ConfigError(f"{path}: mode = 'zip' needs axes of equal length, got {lengths}")
    return config, axes, base


def _load_evaluate(table: Any):
    """The ``[evaluate]`` table (``table``, as TOML gave it) checked into the registered
    evaluators' dataclass; ConfigError naming the key and the allowed ones."""
    from jaxden.evaluate.registry import evaluate_table_class

    cls = evaluate_table_class()
    holder = dataclasses.make_dataclass("SweepConfig", [
        ("evaluate", cls, dataclasses.field(default_factory=cls))], frozen=True)
    return load_config({"evaluate": table}, holder).evaluate


def _label(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "+".join(_label(v) for v in value)
    if isinstance(value, dict):
        return "+".join(f"{k}-{_label(v)}" for k, v in value.items())
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def plan_runs(config: SweepConfig, axes: dict[str, list[Any]]) -> list[Run]:
    """The sweep's runs in order: the grid (or zip) of the axes. A run's name is
    ``key=value`` per axis (last part of the key, lists joined by '+'), joined by '__'; an
    axis called ``name`` gives names instead of overrides (in ``zip`` mode the whole name, in
    ``grid`` mode a prefix)."""
    keys = list(axes)
    points = (itertools.product(*axes.values()) if config.mode == "grid"
              else zip(*axes.values()))
    runs, seen = [], set()
    for point in points:
        values = dict(zip(keys, point))
        named = {k: v for k, v in values.items() if k != NAME_AXIS}
        name = "__".join(filter(None, [
            _label(values[NAME_AXIS]) if NAME_AXIS in values else "",
            *(f"{k.split('.')[-1]}={_label(v)}" for k, v in named.items()
              if NAME_AXIS not in values or config.mode == "grid")]))
        name = re.sub(r"[^A-Za-z0-9_.+=-]", "-", name)[:200]
        if name in _RESERVED_NAMES:
            raise ConfigError(f"a run of the sweep ({values}) would get the folder name {name!r}, "
                              f"which is not a folder inside --workdir; choose another name or "
                              f"axis value")
        if name in seen:
            raise ConfigError(f"two runs of the sweep get the same folder name {name!r}: make "
                              f"the axis values distinct")
        seen.add(name)
        overrides = (*config.overrides, *(f"{k}={toml_value(v)}" for k, v in named.items()))
        runs.append(Run(name, values, overrides))
    return runs


def select_runs(runs: list[Run], only: Sequence[str], path) -> list[Run]:
    """The runs named in ``only`` (all when empty), in plan order; ConfigError for a name the
    sweep in ``path`` does not have."""
    if not only:
        return runs
    names = [run.name for run in runs]
    unknown = [name for name in only if name not in names]
    if unknown:
        raise ConfigError(f"{path}: no run named {', '.join(map(repr, unknown))} in the "
                          f"sweep; its runs: {', '.join(names)}")
    return [run for run in runs if run.name in only]


def _run_one(task: tuple[str, str, tuple[str, ...], dict, dict[str, Any], bool]) -> dict:
    """Train, evaluate and record one run (module level: the local executor pickles it)."""
    _worker_setup()
    from jaxden.evaluate import evaluate_run
    from jaxden.fileio import atomic_write_text
    from jaxden.train.config import load_train_config
    from jaxden.train.loop import train_and_evaluate

    run_dir, base, overrides, evaluate, values, progress = task
    run_dir = Path(run_dir)
    train_config = load_train_config(base, list(overrides))
    resolved = config_to_dict(train_config)
    result_file = run_dir / RESULT_NAME
    previous = _finished_result(result_file, resolved, evaluate, values)
    if previous is not None:
        return {**previous, "skipped": True}
    train = train_and_evaluate(train_config, run_dir, progress=progress)
    evaluations = evaluate_run(run_dir, evaluate, train_config.model)  # jaxden.evaluate
    result = {"run": run_dir.name, "values": values, "overrides": list(overrides),
              "config": resolved, "evaluate": evaluate,
              "train": {k: v for k, v in train.items() if isinstance(v, (int, float, str))},
              "evaluations": evaluations}
    atomic_write_text(result_file, json.dumps(result, indent=1, sort_keys=True))
    return {**result, "skipped": False}


#: The fields of a run's result.json that a rerun and the summary read.
_RESULT_FIELDS = {"run": str, "values": dict, "overrides": list, "config": dict,
                  "evaluate": dict, "train": dict, "evaluations": dict}
_TRAIN_FIELDS = {"step": int, "val_loss?": float, "val_baseline_loss?": float}


def _finished_result(path: Path, resolved: dict, evaluate: dict, values: dict) -> dict | None:
    """The recorded result of a finished run with this config and evaluation, else None.

    A result.json that cannot be read, is malformed or lacks what the summary shows counts as
    not finished, with a note: the run is redone, which resumes from its last checkpoint and
    only evaluates again, and its result.json is rewritten. (It is jaxden's own record,
    written atomically, so damage comes from outside; the trained model is in the
    checkpoints, so redoing is cheap, and one damaged record should not stop a sweep.)"""
    import sys

    from jaxden.errors import JaxdenError
    from jaxden.fileio import check_json_fields, read_json

    if not path.exists():
        return None
    try:
        previous = read_json(path, "the run's result", error=ConfigError, fields=_RESULT_FIELDS)
        check_json_fields(previous["train"], _TRAIN_FIELDS, f"{path}: field 'train'",
                          ConfigError)
        try:
            _metrics(previous)
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise ConfigError(f"{path}: the run's result has no readable metrics "
                              f"({type(error).__name__}: {str(error)[:60]})") from None
    except JaxdenError as error:
        print(f"jaxden: note: {error}; redoing the run (it resumes from its last checkpoint)",
              file=sys.stderr, flush=True)
        return None
    recorded = previous["config"]
    try:  # today's defaults for config fields added since the run finished (the same run)
        from jaxden.train.config import TrainConfig

        recorded = config_to_dict(load_config(recorded, TrainConfig))
    except (ConfigError, TypeError, ValueError):
        pass
    if (recorded == resolved and _same_evaluate(previous["evaluate"], evaluate)
            and previous["values"] == values):
        return previous
    return None


def _worker_setup() -> None:
    """In the process that runs a sweep's run (maybe a fresh local or Ray worker): one JAX
    device per core (before JAX starts its backend), and the persistent compilation cache
    unless this process chose one already."""
    from jaxden.distributed import use_all_cores

    use_all_cores()
    import jax

    if not jax.config.jax_compilation_cache_dir:
        from jaxden.compile_cache import enable_compilation_cache

        enable_compilation_cache()


def _absolute_overrides(train_config, overrides: tuple[str, ...]) -> tuple[str, ...]:
    """``overrides`` plus ``data.dataset=<absolute>`` when the run's dataset is relative, and
    ``init=<absolute>`` when its ``init`` is a relative path that exists here (a shipped
    model's name stays a name): a worker in another folder (a Ray node) must read the
    caller's files."""
    dataset = train_config.data.dataset
    if dataset and not Path(dataset).is_absolute():
        overrides = (*overrides, f"data.dataset={toml_value(str(Path(dataset).absolute()))}")
    init = getattr(train_config, "init", None)
    if init and not Path(init).is_absolute() and Path(init).exists():
        overrides = (*overrides, f"init={toml_value(str(Path(init).absolute()))}")
    return overrides


def check_sweep(path: str | Path, overrides=(), *, only: Sequence[str] = (),
                allow_large: bool = False):
    """Everything about a sweep that can be checked before any training, in the order a run
    would meet it: the file, its runs (count, names, ``only``), every run's resolved training
    config (axis keys, values and ranges, through the config's declarations), and every
    dataset of its ``[evaluate]`` table (exists, complete, the split not empty). The first
    problem is a ConfigError naming the file and the run, key or dataset. Returns
    ``(config, axes, base, runs, train_configs)`` (runs with absolute paths in overrides)."""
    from jaxden.train.config import load_train_config

    config, axes, base = load_sweep(path, tuple(overrides))
    runs = select_runs(plan_runs(config, axes), only, path)
    if len(runs) > MAX_RUNS and not allow_large:
        raise ConfigError(f"{path}: the sweep has {len(runs)} runs, more than {MAX_RUNS}; check "
                          f"its [axes], or pass --allow-large to run them all")
    configs = []
    for index, run in enumerate(runs):
        try:
            train_config = load_train_config(base, list(run.overrides))
            absolute = _absolute_overrides(train_config, run.overrides)
            if absolute != run.overrides:
                runs[index] = run = dataclasses.replace(run, overrides=absolute)
                train_config = load_train_config(base, list(run.overrides))
        except ConfigError as error:
            raise ConfigError(f"{path}: run {run.name}: {error}") from None
        configs.append(train_config)
    _check_evaluate_sets(path, config.evaluate)
    return config, axes, base, runs, configs


def _check_evaluate_sets(path, evaluate) -> None:
    """Each [evaluate] dataset exists and can be read as its evaluator reads it (its
    ``sweep_check``: a rendered dataset is complete with crops in the split it is read at, a
    sequence set is complete)."""
    from jaxden.errors import JaxdenError
    from jaxden.evaluate.registry import sweep_evaluators

    table = config_to_dict(evaluate)
    for evaluator in sweep_evaluators():
        for folder in getattr(evaluate, evaluator.name):
            where = f"{path}: [evaluate] {evaluator.name} = {folder!r}"
            if not Path(folder).is_dir():
                raise ConfigError(f"{where}: no such dataset folder")
            try:
                evaluator.sweep_check(folder, table)
            except JaxdenError as error:
                raise ConfigError(f"{where}: {error}") from None


def run_sweep(path: str | Path, workdir: str | Path, overrides=(), *, executor: str = "serial",
              workers: int | None = None, progress: bool = True, allow_large: bool = False,
              ray_address: str | None = None, only: Sequence[str] = ()) -> list[dict]:
    """Run (or finish) the sweep in ``path`` under ``workdir``; returns the runs' results in
    plan order and writes ``summary.json`` / ``summary.md`` there.

    ``only``: run just the runs of these names (the rest are neither run nor read), in plan
    order, and write no summary, which always covers the whole sweep: a later call without
    ``only`` finds those runs finished and writes it.

    ``executor`` / ``workers`` / ``ray_address``: see :func:`jaxden.executor.make_executor`.
    ``allow_large``: run more than :data:`MAX_RUNS` runs. With ``progress`` the run count is
    printed first. Shared data (SURE caches) is prepared here, before any run starts."""
    from jaxden.executor import make_executor
    from jaxden.fileio import atomic_write_text
    from jaxden.train.loop import prepare_shared_data, shared_data_key

    config, axes, base, runs, configs = check_sweep(path, overrides, only=only,
                                                   allow_large=allow_large)
    given_workdir, workdir = workdir, Path(workdir).absolute()
    if workdir.exists() and not workdir.is_dir():
        raise ConfigError(f"--workdir {workdir} is a file, not a folder")
    if progress:
        print(f"sweep {path}: {len(runs)} run(s) of {base} ({config.mode} over "
              f"{', '.join(axes)}) in {workdir}", flush=True)
    evaluate = _evaluate_record(config.evaluate)
    tasks = [(str(workdir / run.name), str(base), run.overrides, evaluate, run.values, progress)
             for run in runs]
    by_name = {}
    # The executor first (a Ray cluster that cannot be reached fails before any work), then
    # what several runs read, built once, here, before any of them starts.
    with make_executor(executor, workers, ray_address=ray_address) as pool:
        prepared = set()
        for train_config in configs:
            key = shared_data_key(train_config)
            if key is not None and key not in prepared:
                prepare_shared_data(train_config, progress=progress)
                prepared.add(key)
        workdir.mkdir(parents=True, exist_ok=True)
        for result in pool.map_unordered(_run_one, tasks):
            by_name[result["run"]] = result
    results = [by_name[run.name] for run in runs]
    if only:
        return results
    summary = summarize(results, list(axes))
    atomic_write_text(workdir / "summary.json", json.dumps(
        {"provenance": _provenance(path, given_workdir, overrides),
         "sweep": str(path), "base": str(base), "mode": config.mode,
         "axes": axes, "runs": [{k: v for k, v in r.items() if k != "config"} for r in results],
         "groups": summary["groups"]}, indent=1, sort_keys=True, default=str))
    prov = _provenance(path, given_workdir, overrides)
    atomic_write_text(workdir / "summary.md", f"<!-- generated by: {prov['command']} (commit "
                      f"{prov['commit']}, {prov['date']}) -->\n" + summary["markdown"] + "\n")
    return results


def _evaluate_record(evaluate) -> dict:
    """The ``[evaluate]`` table as a run records it: every key, defaults filled in, datasets
    as absolute paths (the runs may work in another folder)."""
    from jaxden.evaluate.registry import sweep_evaluators

    record = config_to_dict(evaluate)
    for evaluator in sweep_evaluators():
        record[evaluator.name] = [str(Path(p).absolute())
                                  for p in getattr(evaluate, evaluator.name)]
    return record


def _same_evaluate(recorded: dict, evaluate: dict) -> bool:
    """Whether a finished run's recorded ``[evaluate]`` is ``evaluate``: keys it lacks (an
    evaluator registered since, by jaxden or a plugin) count as their defaults."""
    from jaxden.evaluate.registry import evaluate_table_class

    defaults = config_to_dict(evaluate_table_class()())
    return {**defaults, **recorded} == evaluate


def _provenance(path, workdir, overrides) -> dict[str, str]:
    """What made a summary: the sweep command (as run from the current folder), the git commit
    of the code (:func:`jaxden.provenance.git_commit`: '+dirty' with uncommitted changes to
    tracked files outside results and weights) and the date."""
    import shlex

    from jaxden.provenance import git_commit, plugin_record, today

    command = shlex.join(["jaxden", "sweep", str(path), "--workdir", str(workdir),
                          *map(str, overrides)])
    return {"command": command, "commit": git_commit(), "date": today(), **plugin_record()}


def _metrics(result: dict) -> dict[str, float]:
    """The numbers a summary row shows: final validation loss (and the baseline's), and per
    evaluation the columns its evaluator gives (its ``sweep_columns``), each labelled by the
    dataset folder's name. ConfigError for an evaluation no registered evaluator made."""
    from jaxden.evaluate.registry import evaluator_of_sweep_key

    out = {}
    for key in ("val_loss", "val_baseline_loss"):
        if isinstance(result["train"].get(key), (int, float)):
            out[key] = float(result["train"][key])
    for name, evaluation in result.get("evaluations", {}).items():
        kind, _, path = name.partition(":")
        label = path.rstrip("/").split("/")[-1]
        columns = evaluator_of_sweep_key(kind).sweep_columns
        for column, value in (columns(evaluation) if columns is not None else {}).items():
            out[f"{label} {column}"] = value
    return out


def summarize(results: list[dict], axes: list[str]) -> dict[str, Any]:
    """A markdown table of every run (axis values and metrics) and, when ``seed`` is an axis,
    one row per setting of the other axes with the mean and the standard deviation over seeds
    (``groups`` in the returned dict)."""
    rows = [(r, _metrics(r)) for r in results]
    columns = list(dict.fromkeys(k for _, m in rows for k in m))
    lines = ["| run | " + " | ".join(axes + columns) + " |",
             "|---|" + "---|" * len(axes) + "---:|" * len(columns)]
    for result, metrics in rows:
        cells = [_label(result["values"].get(a, "")) for a in axes]
        cells += [f"{metrics[c]:.5g}" if c in metrics else "" for c in columns]
        lines.append(f"| {result['run']} | " + " | ".join(cells) + " |")
    groups = []
    if "seed" in axes:
        others = [a for a in axes if a != "seed"]
        grouped: dict[tuple, list[dict[str, float]]] = defaultdict(list)
        for result, metrics in rows:
            grouped[tuple(_label(result["values"][a]) for a in others)].append(metrics)
        lines += ["", "Mean ± standard deviation over seeds:", "",
                  "| " + " | ".join(others + ["seeds"] + columns) + " |",
                  "|" + "---|" * (len(others) + 1) + "---:|" * len(columns)]
        for key, members in grouped.items():
            stats = {}
            for c in columns:
                values = [m[c] for m in members if c in m]
                if values:
                    mean = sum(values) / len(values)
                    std = (math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))
                           if len(values) > 1 else 0.0)
                    stats[c] = (mean, std)
            groups.append({"values": dict(zip(others, key)), "seeds": len(members),
                           "metrics": {c: {"mean": m, "std": s} for c, (m, s) in stats.items()}})
            cells = list(key) + [str(len(members))]
            cells += [f"{stats[c][0]:.5g} ± {stats[c][1]:.2g}" if c in stats else ""
                      for c in columns]
            lines.append("| " + " | ".join(cells) + " |")
    return {"markdown": "\n".join(lines), "groups": groups}
