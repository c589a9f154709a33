"""Evaluators by name, and the evaluation of a sweep's trained run by its ``[evaluate]`` table.

The names are those of ``jaxden evaluate NAME`` and of the dataset lists in a sweep's
``[evaluate]`` table (``pd = [...]``, ``denoise = [...]``, ``sequences = [...]``); a new
evaluator is one more :class:`~jaxden.evaluate.evaluator.Evaluator` in :data:`EVALUATORS`.
The keys a sweep's ``[evaluate]`` table allows are those the registered evaluators declare
(:func:`evaluate_table_class`), so an evaluator registered by a plugin runs in sweeps too.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from jaxden.errors import ConfigError
from jaxden.evaluate import denoise, oracle, pd, sure, sure_buffers
from jaxden.evaluate.evaluator import Evaluator

EVALUATORS: dict[str, Evaluator] = {e.name: e for e in (
    pd.EVALUATOR, oracle.EVALUATOR, sure.EVALUATOR, sure_buffers.EVALUATOR, denoise.DENOISE,
    denoise.SEQUENCES)}


def get_evaluator(name: str) -> Evaluator:
    """The evaluator called ``name``; ConfigError listing the names if there is none."""
    if name not in EVALUATORS:
        raise ConfigError(f"no evaluator named {name!r}; the evaluators: "
                          f"{', '.join(EVALUATORS)}")
    return EVALUATORS[name]


def make_options(name: str, **options):
    """The options of evaluator ``name`` from keyword values (its options dataclass; an
    unknown key is a ConfigError naming it and the allowed ones)."""
    import dataclasses

    evaluator = get_evaluator(name)
    fields = [f.name for f in dataclasses.fields(evaluator.options)]
    unknown = sorted(set(options) - set(fields))
    if unknown:
        raise ConfigError(f"evaluator {name!r}: unknown option(s) {', '.join(unknown)}; "
                          f"allowed: {', '.join(fields)}")
    return evaluator.options(**options)


def evaluate_run(run_dir, table: dict, model: str) -> dict[str, dict]:
    """The evaluations of one trained sweep run: for every evaluator whose name lists datasets
    in the sweep's ``[evaluate]`` ``table`` (a dict, as the sweep records it), its summary on
    each dataset, under ``"<sweep_key>:<dataset>"``. ``model``: the model the run trains (an
    evaluator that needs the other kind, a mixer or a denoiser, is a ConfigError)."""
    from jaxden.train.tasks import get_trainable

    run_dir = Path(run_dir)
    trains = get_trainable(model).kind  # "mixer" or "denoiser"
    chosen = [e for e in sweep_evaluators() if table.get(e.name)]
    for evaluator in chosen:
        if evaluator.trains != trains:
            what = "trains a mixer (use pd)" if trains == "mixer" else f"trains {model!r}"
            raise ConfigError(f"[evaluate] {evaluator.name} needs {evaluator.trains} runs; run "
                              f"{run_dir.name} {what}")
    evaluations = {}
    for evaluator in chosen:
        for dataset in table[evaluator.name]:
            rows = evaluator.run(dataset, evaluator.sweep_options(run_dir, table))
            evaluations[f"{evaluator.sweep_key}:{dataset}"] = (
                evaluator.summarize(rows, {})["summary"])
    return evaluations


def sweep_evaluators() -> list[Evaluator]:
    """The registered evaluators that run in sweeps (they have ``sweep_options``), in order."""
    return [e for e in EVALUATORS.values() if e.sweep_options is not None]


def evaluator_of_sweep_key(key: str) -> Evaluator:
    """The sweep evaluator whose entries in a run's ``result.json`` are ``KEY:<dataset>``;
    ConfigError when none is registered (a plugin's evaluator whose plugin is not loaded)."""
    for evaluator in sweep_evaluators():
        if evaluator.sweep_key == key:
            return evaluator
    raise ConfigError(f"no evaluator records sweep results as {key!r}:...; the evaluators "
                      f"that run in sweeps: {', '.join(e.name for e in sweep_evaluators())}")


def evaluate_table_class() -> type:
    """The frozen dataclass ``EvaluateConfig`` of a sweep's ``[evaluate]`` table: for every
    evaluator of :func:`sweep_evaluators`, its name (a tuple of dataset folders, ``~`` and
    ``$JAXDEN_HOME`` expanded; default none) and its ``sweep_settings``, in registry order.
    ValueError (an evaluator's definition is wrong, not a user's file) for a name that is not
    a Python identifier or two declarations of one key that differ."""
    evaluators = sweep_evaluators()
    declared: dict[str, tuple[Any, Any, str]] = {}  # key -> (type, default, declared by)

    def declare(key: str, tp: Any, default: Any, by: str) -> None:
        if not key.isidentifier():
            raise ValueError(f"evaluator {by!r} declares the [evaluate] key {key!r}, which is "
                             f"not a Python identifier")
        if key in declared and declared[key][:2] != (tp, default):
            raise ValueError(f"evaluators {declared[key][2]!r} and {by!r} declare the "
                             f"[evaluate] key {key!r} differently: {declared[key][:2]} and "
                             f"{(tp, default)}")
        declared.setdefault(key, (tp, default, by))

    datasets = [evaluator.name for evaluator in evaluators]
    for evaluator in evaluators:
        declare(evaluator.name, tuple[str, ...], (), evaluator.name)
        for key, tp, default in evaluator.sweep_settings:
            if key in datasets:
                raise ValueError(f"evaluator {evaluator.name!r} declares the [evaluate] key "
                                 f"{key!r}, the name of an evaluator")
            declare(key, tp, default, evaluator.name)

    def expand_datasets(self) -> None:
        from jaxden.paths import expand_path

        for name in datasets:
            object.__setattr__(self, name, tuple(expand_path(p) for p in getattr(self, name)))

    return dataclasses.make_dataclass(
        "EvaluateConfig",
        [(key, tp, dataclasses.field(default=default)) for key, (tp, default, _) in
         declared.items()],
        frozen=True, namespace={"__post_init__": expand_datasets,
                                "__doc__": "A sweep's [evaluate] table (jaxden.sweep)."})
