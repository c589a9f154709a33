"""Evaluators by name, and the evaluation of a sweep's trained run by its ``[evaluate]`` table.

The names are those of ``jaxden evaluate NAME`` and of the dataset lists in a sweep's
``[evaluate]`` table (``pd = [...]``, ``denoise = [...]``, ``sequences = [...]``); a new
evaluator is one more :class:`~jaxden.evaluate.evaluator.Evaluator` in :data:`EVALUATORS`.
"""

from __future__ import annotations

from pathlib import Path

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
    chosen = [e for e in EVALUATORS.values()
              if e.sweep_options is not None and table.get(e.name)]
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
