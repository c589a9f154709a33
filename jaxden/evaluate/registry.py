"""Evaluators by name, and the evaluation of a sweep's trained run by its ``[evaluate]`` table.

The names are those of ``jaxden evaluate NAME`` and of the dataset lists in a sweep's
``[evaluate]`` table (``pd = [...]``, ``denoise = [...]``, ``sequences = [...]``). Every
evaluator, jaxden's own and a plugin's (:mod:`jaxden.plugins`), is one
:class:`~jaxden.evaluate.evaluator.Evaluator` added to :data:`EVALUATORS` by
:func:`register_evaluator`; a name that jaxden or another module holds is refused in one line.
The keys a sweep's ``[evaluate]`` table allows are those the registered evaluators declare
(:func:`evaluate_table_class`), so an evaluator registered by a plugin runs in sweeps too, and
``jaxden evaluate NAME`` gives it a sub-command made from its options dataclass (one flag a
field: :mod:`jaxden.cli.evaluate`).
"""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Any

from jaxden.errors import ConfigError
from jaxden.evaluate import denoise, njs, oracle, pd, sure, sure_buffers
from jaxden.evaluate.evaluator import Evaluator
from jaxden.registry import Registry

#: Every evaluator by name: jaxden's own and those of plugins (:func:`register_evaluator`).
EVALUATORS: Registry = Registry("evaluator")
_REGISTER_PLUMBING = True  # registrations through this module belong to their caller

#: Option names an evaluator's options dataclass may not use: the flags of ``jaxden evaluate
#: NAME`` itself (``--data``, ``--out``, ``--from-json``, ``--keep-current``, ``--plugin``,
#: ``--help``), which a field's flag would shadow.
RESERVED_OPTIONS = ("data", "out", "from_json", "keep_current", "plugin", "help")


def register_evaluator(evaluator: Evaluator, *, owner: str | None = None) -> Evaluator:
    """Add ``evaluator`` under its name; ``owner``: the registering module (default: the
    caller's). Then ``jaxden evaluate NAME`` runs it (a sub-command with one flag per field of
    its ``options`` dataclass) and, when it has ``sweep_options``, a sweep's ``[evaluate]``
    table lists datasets for it. A name that jaxden or another module holds is refused in one
    line (:class:`jaxden.registry.PluginClashError`); so is an evaluator whose options are not
    a dataclass, whose options' fields take the command's own flags
    (:data:`RESERVED_OPTIONS`, and SureSettings' fields beside a SureSettings field), or that
    runs in sweeps under a name that is not a Python identifier (the ``[evaluate]`` key)."""
    from jaxden.registry import caller_module

    if not isinstance(evaluator, Evaluator):
        raise ConfigError(f"register_evaluator() takes a jaxden.evaluate.Evaluator, got "
                          f"{type(evaluator).__name__}")
    owner = owner or caller_module()
    where = f"evaluator {evaluator.name!r} from module '{owner}'"
    if not (isinstance(evaluator.options, type) and dataclasses.is_dataclass(evaluator.options)):
        raise ConfigError(f"{where}: options must be a dataclass (the fields are its options), "
                          f"got {evaluator.options!r}")
    taken = _flag_clashes(evaluator.options)
    if taken:
        raise ConfigError(f"{where}: option(s) {', '.join(taken)} would shadow flags of "
                          f"`jaxden evaluate {evaluator.name}` itself; rename them")
    if evaluator.sweep_options is not None and not evaluator.name.isidentifier():
        raise ConfigError(f"{where} runs in sweeps (it has sweep_options), so its name is an "
                          f"[evaluate] key and must be a Python identifier (e.g. "
                          f"{evaluator.name.replace('-', '_')!r})")
    return EVALUATORS.add(evaluator.name, evaluator, owner)


def _flag_clashes(options: type) -> list[str]:
    """The fields of ``options`` whose flags are taken: :data:`RESERVED_OPTIONS`, and the
    fields of SureSettings (their flags, ``--probes`` ...) beside a SureSettings field."""
    from jaxden.sure.settings import SureSettings

    fields = [f.name for f in dataclasses.fields(options)]
    taken = [name for name in fields if name in RESERVED_OPTIONS]
    try:
        hints = typing.get_type_hints(options)
    except Exception:  # noqa: BLE001 - unresolvable annotations: the CLI skips those fields
        hints = {}
    sure_fields = [name for name in fields if SureSettings in (
        hints.get(name), *typing.get_args(hints.get(name)))]
    if sure_fields:
        flags = {f.name for f in dataclasses.fields(SureSettings)}
        taken += [name for name in fields if name in flags]
        if len(sure_fields) > 1:
            taken += sure_fields[1:]
    return taken


def get_evaluator(name: str) -> Evaluator:
    """The evaluator called ``name`` (plugins named by ``JAXDEN_PLUGINS`` or entry points are
    imported first); ConfigError listing the names if there is none."""
    if EVALUATORS.find(name) is None:
        raise ConfigError(f"no evaluator named {name!r}; the evaluators: "
                          f"{', '.join(EVALUATORS)} (an evaluator of your own: "
                          f"jaxden.evaluate.register_evaluator in a plugin module named with "
                          f"--plugin, JAXDEN_PLUGINS or plugins = [...], docs/your-denoiser.md)")
    return EVALUATORS[name]


for _module, _evaluator in ((pd, pd.EVALUATOR), (oracle, oracle.EVALUATOR),
                           (sure, sure.EVALUATOR), (sure_buffers, sure_buffers.EVALUATOR),
                           (denoise, denoise.DENOISE), (denoise, denoise.SEQUENCES),
                           (njs, njs.EVALUATOR)):
    register_evaluator(_evaluator, owner=_module.__name__)
del _module, _evaluator


def make_options(name: str, **options):
    """The options of evaluator ``name`` from keyword values (its options dataclass; an
    unknown key is a ConfigError naming it and the allowed ones)."""
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
    for attempt in range(2):
        for evaluator in sweep_evaluators():
            if evaluator.sweep_key == key:
                return evaluator
        if attempt == 0:
            from jaxden.plugins import load_ambient

            load_ambient()
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
