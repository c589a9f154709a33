"""What the report shows, computed from the files :mod:`jaxden.report.discover` found.

Per scene (:func:`scene_content`): every image read from its EXR (linear, checked finite and of
the reference's size), its error maps against the reference (relative squared error, FLIP),
alpha maps where present, every metric (:func:`jaxden.report.errormaps.image_metrics`), a
convergence plot, and the automatic exposure. Per `jaxden evaluate pd` result (:func:`metric_file_content`):
the per-spp means over its crops and their plot. Per training run (:func:`run_content`): its
curves from ``metrics.jsonl`` and their plot. Pixels are stored as
:mod:`jaxden.report.encode` describes.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from jaxden.report import encode, errormaps, figures
from jaxden.report.discover import (
    REFERENCE,
    MetricFile,
    ReportError,
    RunFiles,
    SceneFiles,
    mean_rows,
)
from jaxden.report.tonemap import auto_stops, log_range

#: Error-map layers: name -> (title, colour map, scale).
ERROR_LAYERS = {"relse": ("Relative squared error", "(x - r)² / (r² + 0.01), mean over RGB",
                          "viridis", "log"),
                "flip": ("FLIP", "HDR-FLIP per pixel", "magma", "linear")}
ALPHA_LAYER = ("Mixer alpha", "mean over RGB; 1 = denoised, 0 = MC input", "viridis",
               "linear")


@dataclasses.dataclass
class SceneContent:
    """One scene of the page. ``arrays[key]``: encoded pixels, keys ``reference``,
    ``SPP/METHOD`` (images), ``relse/SPP/METHOD``, ``flip/SPP/METHOD``, ``alpha/SPP/METHOD``;
    ``layers[name]``: ``{title, detail, colormap, scale, low, high}`` of each false-colour layer."""

    name: str
    folder: str
    width: int
    height: int
    factor: int
    stops: float
    spp_levels: list[int]
    methods: list[str]
    alpha_methods: list[str]
    arrays: dict[str, dict]
    layers: dict[str, dict]
    rows: list[dict]
    plot_svg: bytes


@dataclasses.dataclass
class MetricContent:
    """A `jaxden evaluate pd` result: its per-spp means over crops (``rows``) and their plot."""

    name: str
    path: str
    note: str
    metrics: tuple[str, ...]
    rows: list[dict]
    plot_svg: bytes


@dataclasses.dataclass
class RunContent:
    """A training run: ``curves[key]`` = ``[(step, value)]`` of the train loss and every
    validation metric of its metrics.jsonl, ``last[key]`` = each curve's last value,
    ``steps``: the last step logged, and their plot (None: nothing logged yet)."""

    name: str
    folder: str
    curves: dict[str, list[tuple[int, float]]]
    last: dict[str, float]
    steps: int
    plot_svg: bytes | None


def training_curves(records: list[dict]) -> dict[str, list[tuple[int, float]]]:
    """``{key: [(step, value)]}`` of metrics.jsonl records: the train loss (``loss``) and
    every validation metric (``val_*``), finite values only, in the order logged."""
    curves: dict[str, list[tuple[int, float]]] = {}
    for record in records:
        for key, value in record.items():
            if key != "loss" and not key.startswith("val_"):
                continue
            if isinstance(value, (int, float)) and not isinstance(value, bool) \
                    and math.isfinite(value):
                curves.setdefault(key, []).append((int(record["step"]), float(value)))
    order = ["loss", *sorted(k for k in curves if k != "loss")]
    return {key: curves[key] for key in order if key in curves}


def run_content(run: RunFiles) -> RunContent:
    """A training run's curves and their plot (:func:`jaxden.report.figures.training_figure`).
    A broken metrics.jsonl is a ReportError naming the file and the line (a last line cut
    short by a kill is left out)."""
    from jaxden.fileio import read_jsonl

    records, _ = read_jsonl(run.metrics, "the metrics log", error=ReportError,
                            fields={"step": int})
    curves = training_curves(records)
    plot = None
    if curves:
        plot = figures.svg_bytes(figures.training_figure(curves, title=f"{run.name}: training"))
    return RunContent(name=run.name, folder=str(run.folder), curves=curves,
                      last={key: points[-1][1] for key, points in curves.items()},
                      steps=max((int(r["step"]) for r in records), default=0), plot_svg=plot)


def load_image(path: Path, shape: tuple[int, ...] | None = None, alpha: bool = False
               ) -> np.ndarray:
    """An image of the report, (H, W, 3) float32 (alpha maps: (H, W, C)); refuses non-finite
    values and a size other than ``shape``'s (H, W), naming the file."""
    from jaxden.io.exr import read_image

    path = Path(path)
    image = read_image(path) if alpha else read_image(path, ("R", "G", "B"))
    bad = int((~np.isfinite(image)).sum())
    if bad:
        raise ReportError(f"{path}: {bad} NaN or infinite values; the report needs finite "
                          f"images")
    if shape is not None and image.shape[:2] != tuple(shape[:2]):
        raise ReportError(f"{path}: {image.shape[1]}x{image.shape[0]} pixels, but the scene's "
                          f"reference has {shape[1]}x{shape[0]}")
    return image


def _progress(total: int, show: bool, what: str):
    from tqdm import tqdm

    return tqdm(total=total, disable=not show, desc=what, unit="image", leave=False)


def scene_content(scene: SceneFiles, max_size: int | None = 1024, progress: bool = False,
                  flip_maps=None) -> SceneContent:
    """Read, measure and encode one scene (module docstring). ``flip_maps``: FLIP already
    computed, ``{(spp, method): (mean, map (H, W))}``, used instead of computing it again."""
    flip_maps = flip_maps or {}
    reference = load_image(scene.reference)
    height, width = reference.shape[:2]
    factor = encode.display_factor(height, width, max_size)

    def shown(array):
        return encode.downsample(array, factor)

    arrays = {REFERENCE: encode.encode_array(shown(reference), "f16")}
    rows, relse_maps, flip_maps, alpha_maps = [], {}, {}, {}
    keys = sorted(scene.images, key=lambda key: (key[0], scene.methods.index(key[1])))
    with _progress(len(keys), progress, scene.name) as bar:
        for spp, method in keys:
            image = load_image(scene.images[spp, method], reference.shape)
            if (spp, method) in flip_maps:
                flip_mean, flip_values = flip_maps[spp, method]
            else:
                flip_mean, flip_values = errormaps.flip_map(image, reference)
            rows.append({"scene": scene.name, "spp": spp, "method": method,
                         **errormaps.image_metrics(image, reference, flip_mean)})
            arrays[f"{spp}/{method}"] = encode.encode_array(shown(image), "f16")
            relse_maps[spp, method] = shown(errormaps.relative_squared_error(image, reference))
            flip_maps[spp, method] = shown(flip_values)
            if (spp, method) in scene.alphas:
                alpha = load_image(scene.alphas[spp, method], reference.shape, alpha=True)
                alpha_maps[spp, method] = shown(np.mean(alpha, axis=-1))
            bar.update()
    low, high = log_range(list(relse_maps.values()))
    layers = {}
    for name, maps, (low_, high_) in (("relse", relse_maps, (low, high)),
                                      ("flip", flip_maps, (0.0, 1.0))):
        title, detail, colormap, scale = ERROR_LAYERS[name]
        layers[name] = {"title": title, "detail": detail, "colormap": colormap, "scale": scale,
                        "low": low_, "high": high_}
        for (spp, method), values in maps.items():
            arrays[f"{name}/{spp}/{method}"] = encode.encode_array(values, "f32")
    if alpha_maps:
        title, detail, colormap, scale = ALPHA_LAYER
        layers["alpha"] = {"title": title, "detail": detail, "colormap": colormap, "scale": scale,
                           "low": 0.0, "high": 1.0}
        for (spp, method), values in alpha_maps.items():
            arrays[f"alpha/{spp}/{method}"] = encode.encode_array(values, "f32")
    figure = figures.convergence_figure(rows, title=f"{scene.name}: error vs spp")
    return SceneContent(
        name=scene.name, folder=str(scene.folder), width=width // factor,
        height=height // factor, factor=factor, stops=auto_stops(reference),
        spp_levels=scene.spp_levels, methods=scene.methods,
        alpha_methods=[m for m in scene.methods if any(k[1] == m for k in alpha_maps)],
        arrays=arrays, layers=layers, rows=rows, plot_svg=figures.svg_bytes(figure))


def metric_file_content(metric_file: MetricFile) -> MetricContent:
    """The per-spp means over crops of a `jaxden evaluate pd` result, and their convergence plot."""
    rows = mean_rows(metric_file.rows, metric_file.name)
    metrics = tuple(m for m in ("rmse", "rmse_nc", "relmse", "flip") if m in metric_file.metrics)
    metrics = metrics or metric_file.metrics
    figure = figures.convergence_figure(rows, metrics=metrics,
                                        title=f"{metric_file.name}: mean over crops")
    return MetricContent(metric_file.name, str(metric_file.path), metric_file.note, metrics,
                         rows, figures.svg_bytes(figure))


__all__ = ["ALPHA_LAYER", "ERROR_LAYERS", "MetricContent", "RunContent", "SceneContent",
           "load_image", "metric_file_content", "run_content", "scene_content", "training_curves"]
