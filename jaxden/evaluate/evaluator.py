"""The one shape of an evaluator, and how a result is measured and written.

An :class:`Evaluator` measures one thing on a held-out set: ``run(data, options, progress=)``
gives the rows (one per crop and spp, or per frame), ``summarize(rows, provenance)`` the
result's fields (``summary`` and whatever else it keeps) and ``table(fields, rows,
provenance)`` the Markdown table. ``options`` is a frozen dataclass of everything else the
numbers depend on; ``provenance(options)`` is what the result records of it. ``jaxden evaluate
NAME`` and a sweep's ``[evaluate]`` table build the options and call these; neither branches on
the name.

An evaluator that runs in sweeps declares what a sweep needs of it: the ``[evaluate]`` keys it
reads (its name, a list of datasets, and ``sweep_settings``), how a dataset is checked before
any training (``sweep_check``), and the columns of the sweep's summary (``sweep_columns``).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any


def dataset_provenance(data, split: str | None) -> dict:
    """The ``dataset`` entry of a result measured on the dataset folder ``data`` (checked:
    a folder that is not a dataset is a DatasetError naming it)."""
    from jaxden.data.layout import load_manifest, manifest_path
    from jaxden.provenance import dataset_identity

    manifest = load_manifest(data)
    return dataset_identity(data, manifest_path(data), manifest.config, split)


def check_dataset(data, table: dict) -> None:
    """The default ``sweep_check``: ``data`` is a complete rendered dataset with crops in the
    split ``table["split"]`` (when the table has one); a JaxdenError saying what is wrong."""
    from jaxden.data.layout import load_manifest
    from jaxden.errors import DatasetError

    manifest = load_manifest(data)
    if not manifest.complete:
        raise DatasetError("the dataset is not complete; finish `jaxden dataset build` first")
    split = table.get("split")
    if split is not None and not manifest.crops_in(split):
        raise DatasetError(f"no crops in split {split!r} (splits: {manifest.split_counts()})")


@dataclasses.dataclass(frozen=True)
class Evaluator:
    """One evaluation, by name (see the module's docstring for the functions' roles).

    ``dataset(data, split)``: the provenance of the data (default: a rendered dataset);
    ``is_current(out, provenance)``: whether the result at ``out`` is what this run would
    write (``keep_current`` of :func:`write_evaluation`), None when there is no such test.

    Sweeps (:mod:`jaxden.sweep`; ``name`` is then a Python identifier, the ``[evaluate]`` key
    listing its datasets): ``sweep_options(run_dir, table)``: the options for a sweep run's
    trained model from the sweep's ``[evaluate]`` table (a dict holding every key of the table,
    defaults filled in), None when sweeps do not run it; ``sweep_settings``: the other keys of
    ``[evaluate]`` it reads, as ``(key, type, default)`` (an evaluator that shares a key with
    another declares the same type and default); ``sweep_check(dataset, table)``: raises a
    JaxdenError saying why ``dataset`` (an existing folder) cannot be read (default: a
    complete rendered dataset with crops in ``table["split"]``); ``sweep_key``: the prefix of
    its entries in a run's ``result.json`` (``KEY:<dataset>``); ``sweep_columns(summary)``:
    ``{column label: number}`` that the sweep's summary tabulates per dataset from one entry's
    ``summary`` (labelled ``<dataset name> <column label>``; None: no columns); ``trains``:
    what a sweep run must train for it ("mixer" or "denoiser")."""

    name: str
    description: str
    options: type
    run: Callable[..., list]
    summarize: Callable[[Any, dict], dict]
    table: Callable[[dict, Any, dict], str]
    provenance: Callable[[Any], dict]
    dataset: Callable[[Any, str | None], dict] = dataset_provenance
    sweep_options: Callable[[Path, dict], Any] | None = None
    sweep_settings: tuple[tuple[str, Any, Any], ...] = ()
    sweep_check: Callable[[Any, dict], None] = check_dataset
    sweep_key: str = ""
    sweep_columns: Callable[[dict], dict[str, float]] | None = None
    trains: str = "denoiser"
    is_current: Callable[[Path, dict], bool] | None = None


def evaluation_provenance(evaluator: Evaluator, data, options, identity: dict) -> dict:
    """A result's provenance: the run's ``identity`` (command, commit), date, machine,
    versions, the data's build, the probes' ``seed`` and ``probes`` (4 unless the options
    hold another count), and what the evaluator records of its options."""
    from jaxden.provenance import result_provenance

    extra = {"seed": getattr(options, "seed", None),
             "probes": getattr(options, "probes", None) or 4, **evaluator.provenance(options)}
    return result_provenance(identity, evaluator.dataset(data, getattr(options, "split", None)),
                             **extra)


def write_evaluation(evaluator: Evaluator, data, options, out, *, identity: dict,
                     from_json=None, keep_current: bool = False,
                     progress: bool = True) -> bool:
    """Measure ``evaluator`` on ``data`` with ``options`` and write OUT.json (the fields of
    its summary, the rows and the provenance) and OUT.md (its table); False when
    ``keep_current`` finds OUT.json current and keeps it. ``from_json``: tabulate the rows and
    provenance of a finished result instead of measuring (``data`` and ``options`` unused)."""
    from jaxden.provenance import write_result

    if from_json:
        previous = json.loads(Path(from_json).read_text())
        rows, source = previous["rows"], previous["provenance"]
    else:
        source = evaluation_provenance(evaluator, data, options, identity)
        if keep_current and evaluator.is_current is not None and evaluator.is_current(
                Path(out), source):
            print(f"jaxden evaluate {evaluator.name}: {out}.json is current (same data and "
                  f"options); kept")
            return False
        rows = evaluator.run(data, options, progress=progress)
    fields = evaluator.summarize(rows, source)
    result = {**fields, "rows": rows, "provenance": source}
    write_result(Path(out), result, evaluator.table(fields, rows, source))
    return True
