"""What a report is made of: the file naming convention, and finding the files under a path.

A report reads a folder laid out like ``jaxden demo``'s output::

    DIR/SCENE/reference.exr            the reference image of SCENE (required, one per scene)
    DIR/SCENE/sppN.exr                 the Monte Carlo input at N samples per pixel (method "mc")
    DIR/SCENE/sppN.METHOD.exr          METHOD's result at N spp (METHOD: letters, digits, _ or -)
    DIR/SCENE/sppN.METHOD.alpha.exr    optional: the mixer's alpha map behind METHOD at N spp
                                       (1 = METHOD's denoiser, 0 = the MC input)
    DIR/*.json                         optional: jaxden evaluate results (metrics only)
    DIR/RUN/metrics.jsonl              optional: a training run (`jaxden train` or a sweep's
                                       run folder): its loss curves

N may be zero-padded (``spp00004``). Images are read as R,G,B (alpha maps: R,G,B or their one
channel), linear HDR. ``DIR`` may itself be one scene folder (it holds ``reference.exr``), one training run's
folder (it holds ``metrics.jsonl``), or a single `jaxden evaluate pd` result file. Other files are ignored (``.exr`` files that do not follow the
convention are listed in :attr:`Discovery.ignored`, so a typo does not go unnoticed).
"""

from __future__ import annotations

import dataclasses
import json
import re
from collections import defaultdict
from pathlib import Path

import numpy as np

from jaxden.errors import JaxdenError

REFERENCE = "reference"
MC = "mc"
CONVENTION = ("SCENE/reference.exr, SCENE/sppN.exr (MC input), SCENE/sppN.METHOD.exr, "
              "optional SCENE/sppN.METHOD.alpha.exr")
_IMAGE_NAME = re.compile(r"^spp0*(?P<spp>[1-9][0-9]*)(?:\.(?P<method>[A-Za-z0-9_-]+))?"
                         r"(?P<alpha>\.alpha)?\.exr$", re.IGNORECASE)


class ReportError(JaxdenError, ValueError):
    """The input of a report is unusable: nothing to show, no reference, a clash of names."""


@dataclasses.dataclass(frozen=True)
class SceneFiles:
    """The EXR files of one scene: ``images[(spp, method)]`` and ``alphas[(spp, method)]``."""

    name: str
    folder: Path
    reference: Path
    images: dict[tuple[int, str], Path]
    alphas: dict[tuple[int, str], Path]

    @property
    def spp_levels(self) -> list[int]:
        return sorted({spp for spp, _ in self.images})

    @property
    def methods(self) -> list[str]:
        """Every method of the scene: ``mc`` first, then by name."""
        return order_methods({method for _, method in self.images})


@dataclasses.dataclass(frozen=True)
class MetricFile:
    """Metrics without images (a `jaxden evaluate pd` result): long-form ``rows`` of
    ``{scene, spp, method, <metric>: value}``, one per crop, spp and method."""

    name: str
    path: Path
    rows: list[dict]
    metrics: tuple[str, ...]
    note: str


@dataclasses.dataclass(frozen=True)
class RunFiles:
    """A training run's folder: its ``metrics.jsonl`` (:class:`jaxden.train.workdir.MetricsLog`)."""

    name: str
    folder: Path
    metrics: Path


@dataclasses.dataclass(frozen=True)
class Discovery:
    root: Path
    scenes: tuple[SceneFiles, ...]
    metric_files: tuple[MetricFile, ...]
    ignored: tuple[Path, ...]
    runs: tuple[RunFiles, ...] = ()


def order_methods(methods) -> list[str]:
    """``mc`` first, then the others by name."""
    methods = set(methods)
    return ([MC] if MC in methods else []) + sorted(methods - {MC})


def parse_image_name(name: str) -> tuple[int, str, bool] | None:
    """``sppN[.METHOD][.alpha].exr`` -> ``(N, METHOD or "mc", is_alpha)``; None otherwise."""
    match = _IMAGE_NAME.match(name)
    if match is None:
        return None
    method = match["method"] or MC
    if method.lower() == "alpha" and not match["alpha"]:
        return None  # "spp4.alpha.exr" names no method
    return int(match["spp"]), method, bool(match["alpha"])


def scan_scene(folder: Path, name: str | None = None) -> tuple[SceneFiles | None, list[Path]]:
    """The scene in ``folder`` (None if it holds no file of the convention) and the .exr files
    it ignored. Raises :class:`ReportError` for a scene without reference or images, and for two
    files naming the same image (``spp4.exr`` and ``spp0004.exr``)."""
    images: dict[tuple[int, str], Path] = {}
    alphas: dict[tuple[int, str], Path] = {}
    reference, ignored = None, []
    for path in sorted(folder.iterdir()):
        if not path.is_file() or path.suffix.lower() != ".exr" or path.name.startswith("."):
            continue
        if path.name.lower() == "reference.exr":
            reference = path
            continue
        parsed = parse_image_name(path.name)
        if parsed is None:
            ignored.append(path)
            continue
        spp, method, is_alpha = parsed
        table = alphas if is_alpha else images
        if method == REFERENCE:
            ignored.append(path)
            continue
        if (spp, method) in table:
            raise ReportError(f"{path}: names the same image as {table[spp, method].name} "
                              f"({method} at {spp} spp); remove one")
        table[spp, method] = path
    if reference is None and not images and not alphas:
        return None, ignored
    if reference is None:
        raise ReportError(f"{folder}: has sppN images but no reference.exr (every scene needs "
                          f"its reference; convention: {CONVENTION})")
    if not images:
        raise ReportError(f"{folder}: has reference.exr but no sppN[.METHOD].exr images "
                          f"(convention: {CONVENTION})")
    for key, path in alphas.items():
        if key not in images:
            raise ReportError(f"{path}: an alpha map without its image "
                              f"spp{key[0]}.{key[1]}.exr")
    return SceneFiles(name or folder.name, folder, reference, images, alphas), ignored


def pd_report_rows(data) -> tuple[list[dict], tuple[str, ...]] | None:
    """Long-form rows of a `jaxden evaluate pd` result (``{"rows": [{crop, spp, mc_rmse, ...}]}``) and its
    metrics; None when ``data`` is no such result."""
    rows = data.get("rows") if isinstance(data, dict) else None
    if not isinstance(rows, list) or not rows or not isinstance(rows[0], dict):
        return None
    first = rows[0]
    if not {"crop", "spp"} <= set(first) or "mc_rmse" not in first:
        return None
    methods = [key[:-len("_rmse")] for key in first if key.endswith("_rmse")]
    metrics = tuple(key[len("mc_"):] for key in first if key.startswith("mc_"))
    long_rows = []
    for row in rows:
        for method in methods:
            values = {metric: row.get(f"{method}_{metric}") for metric in metrics}
            long_rows.append({"scene": row["crop"], "spp": int(row["spp"]), "method": method,
                              **{k: float(v) for k, v in values.items() if v is not None}})
    return long_rows, metrics


def read_metric_file(path: Path, required: bool) -> MetricFile | None:
    """A `jaxden evaluate pd` result as a :class:`MetricFile`; None (or, if ``required``, an error) when
    ``path`` is not one."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        if not required:
            return None
        reason = error.msg if isinstance(error, json.JSONDecodeError) else error
        raise ReportError(f"{path}: cannot be read as JSON: {reason}") from None
    parsed = pd_report_rows(data)
    if parsed is None:
        if required:
            raise ReportError(f"{path}: not a result of jaxden evaluate pd (expected "
                              f"'rows' with crop, spp and mc_rmse, ...)")
        return None
    rows, metrics = parsed
    source = data.get("provenance", {}) if isinstance(data, dict) else {}
    crops = len({row["scene"] for row in rows})
    note = (f"jaxden evaluate result: mean over {crops} crops; "
            f"denoiser = {source.get('denoiser', '?')}; command: {source.get('command', '?')}")
    return MetricFile(path.stem, path, rows, metrics, note)


RUN_LOG = "metrics.jsonl"


def find_runs(root: Path) -> list[RunFiles]:
    """The training runs of ``root``: itself, or each of its folders, holding ``metrics.jsonl``."""
    if (root / RUN_LOG).is_file():
        return [RunFiles(root.resolve().name, root, root / RUN_LOG)]
    return [RunFiles(folder.name, folder, folder / RUN_LOG)
            for folder in sorted(p for p in root.iterdir() if p.is_dir()
                                 and not p.name.startswith("."))
            if (folder / RUN_LOG).is_file()]


def discover(path) -> Discovery:
    """The scenes, metric files and training runs under ``path`` (module docstring: the
    convention).

    Raises :class:`ReportError` naming the path when there is nothing to show."""
    root = Path(path)
    if not root.exists():
        raise ReportError(f"{root}: no such file or folder")
    if root.is_file():
        if root.suffix.lower() == ".json":
            return Discovery(root.parent, (), (read_metric_file(root, required=True),), ())
        raise ReportError(f"{root}: give a folder of EXRs ({CONVENTION}) or a `jaxden evaluate pd` result")
    scenes, ignored = [], []
    scene, skipped = scan_scene(root)
    if scene is not None:  # DIR is one scene folder
        scenes.append(scene)
        ignored += skipped
    else:
        ignored += skipped
        for folder in sorted(p for p in root.iterdir() if p.is_dir()
                             and not p.name.startswith(".")):
            scene, skipped = scan_scene(folder)
            ignored += skipped
            if scene is not None:
                scenes.append(scene)
    metric_files = [m for m in (read_metric_file(p, required=False)
                                for p in sorted(root.glob("*.json"))) if m is not None]
    runs = find_runs(root)
    if not scenes and not metric_files and not runs:
        what = "is empty" if not any(root.iterdir()) else "has nothing a report can show"
        raise ReportError(f"{root}: {what}: expected scene folders ({CONVENTION}), "
                          f"jaxden evaluate JSON files or training runs (RUN/{RUN_LOG})")
    return Discovery(root, tuple(scenes), tuple(metric_files), tuple(ignored), tuple(runs))


def mean_rows(rows: list[dict], scene: str) -> list[dict]:
    """Rows averaged over their scenes (crops) per spp and method, renamed ``scene``."""
    groups: dict[tuple[int, str], list[dict]] = defaultdict(list)
    for row in rows:
        groups[row["spp"], row["method"]].append(row)
    out = []
    for (spp, method), group in sorted(groups.items(), key=lambda item: item[0][0]):
        keys = [k for k in group[0] if k not in ("scene", "spp", "method")]
        out.append({"scene": scene, "spp": spp, "method": method,
                    **{k: float(np.mean([r[k] for r in group if k in r])) for k in keys}})
    return out
