"""Stein SURE against sub-buffer SURE on fresh renders made of independent sub-buffers (the
``sure-buffers`` evaluator): :func:`sure_accuracy_buffers` renders, denoises and estimates;
the result's tables compare both estimators (and the extrapolated sub-buffer one) with the
noise-corrected true MSE, per spp and per crop."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from jaxden.data.crops import iter_crops
from jaxden.errors import ConfigError, DatasetError
from jaxden.evaluate.evaluator import Evaluator
from jaxden.evaluate.shared import crop_count, progress_bar
from jaxden.evaluate.sure import BOOTSTRAP_RESAMPLES, summarize_sure
from jaxden.sure.settings import UNSET, SureSettings

BUFFER_SEED_BASE = 800_000


def sure_accuracy_buffers(dataset_dir, denoisers, *, buffers: int = 16, renders: int = 1,
                          split: str = "test", sure: SureSettings | None = None,
                          spp: tuple[int, ...] | None = None, render_fn=None,
                          progress: bool = False, **options) -> dict[str, list[dict[str, Any]]]:
    """Stein SURE and sub-buffer SURE of each denoiser on the same fresh renders.

    For every crop of ``split``, spp level (levels divisible by ``buffers`` into >= 2 spp
    each) and each of ``renders`` independent renders r, renders ``buffers`` independent
    sub-buffers at spp / buffers with render seeds ``BUFFER_SEED_BASE + 1000 * level_index +
    buffers * r + k`` (refused if one collides with the dataset's seeds for that crop),
    combines them (:func:`jaxden.sure.combine_buffers`: the same image as one render of all
    the samples) and computes, for each denoiser, ``sure`` (probes:
    :func:`jaxden.sure.denoise_with_sure` under ``sure``, the
    :class:`~jaxden.sure.settings.SureSettings`, None: the defaults, the older keywords
    ``options`` (``seed=``, ``num_probes=``, ``method=``) over it; key
    ``fold_in(PRNGKey(sure.seed), index)``),
    ``sure_buffers`` (:func:`jaxden.sure.sure_buffers`) and the noise-corrected true MSE of
    the output against the dataset's reference. ``render_fn(scene, spp, seed, size, crop)``
    defaults to the dataset builder's renderer.

    Returns {denoiser name: rows}, rows as in :func:`jaxden.evaluate.sure.sure_accuracy` plus
    ``sure_buffers``, ``sure_buffers_rx`` (Richardson-extrapolated from K and K/2 merged
    pairs, as ``sure_buffers(..., extrapolate=True)``; None for odd K) and ``render`` (r); the
    summaries average over crops and renders alike.
    """
    import jax

    from jaxden import metrics
    from jaxden.data.layout import load_manifest
    from jaxden.denoise.registry import load_denoiser
    from jaxden.sure.buffers import combine_buffers, merge_buffer_pairs, sure_buffers
    from jaxden.sure.denoiser import denoise_with_sure
    from jaxden.sure.settings import resolve_settings

    if render_fn is None:
        from jaxden.render.scene_cache import render_cached

        def render_fn(scene, level, seed, size, crop):
            return render_cached(scene, level, seed=seed, size=size, crop=crop).numpy()

    if not isinstance(buffers, int) or buffers < 2:
        raise ConfigError(f"buffers must be an integer >= 2, got {buffers!r}")
    if not isinstance(renders, int) or renders < 1 or buffers * renders > 1000:
        raise ConfigError(f"renders must be an integer >= 1 with buffers * renders <= 1000, "
                          f"got {renders!r}")
    models = [load_denoiser(d) if isinstance(d, str) else d for d in denoisers]
    manifest = load_manifest(dataset_dir)
    size = tuple(manifest.config["size"])
    settings = resolve_settings(sure, **options)
    base = jax.random.PRNGKey(settings.seed)
    rows: dict[str, list[dict[str, Any]]] = {m.name: [] for m in models}
    index = 0
    crops = iter_crops(dataset_dir, split, spp)
    for crop, reference, inputs in progress_bar(crops, crop_count(dataset_dir, split), progress,
                                                f"buffer SURE ({buffers} buffers)"):
        used = {item.seed for item in manifest.items_of(crop.id)}
        for level_index, (level, _) in enumerate(inputs):
            if level % buffers or level // buffers < 2:
                continue
            for r in range(renders):
                seeds = [BUFFER_SEED_BASE + 1000 * level_index + buffers * r + k
                         for k in range(buffers)]
                if used & set(seeds):
                    raise DatasetError(f"buffer render seeds {seeds[0]}.. collide with the "
                                       f"dataset's seeds for {crop.id}")
                parts = [render_fn(crop.scene, level // buffers, s, size, crop.window)
                         for s in seeds]
                frame = combine_buffers(parts).replace(spp=None)
                frame = frame.replace(**{name: np.asarray(getattr(frame, name), np.float32)
                                         for name in frame.features()})
                colours = np.stack([np.asarray(p.color, np.float64) for p in parts])
                for model in models:
                    result, _ = denoise_with_sure(model, frame, jax.random.fold_in(base, index),
                                                  sure=settings)
                    jk = sure_buffers(model, frame, colours)
                    rx = None
                    if buffers % 2 == 0 and buffers >= 4:  # Richardson in 1/K: 2 S_K - S_K/2
                        half = sure_buffers(model, frame, merge_buffer_pairs(colours))
                        rx = 2.0 * float(np.mean(jk.sure)) - float(np.mean(half.sure))
                    y = np.asarray(result.denoised, np.float32)
                    rows[model.name].append({
                        "crop": crop.id, "scene": crop.scene, "spp": level, "buffers": buffers,
                        "render": r,
                        "sure": float(np.mean(np.asarray(result.sure))),
                        "sure_buffers": float(np.mean(jk.sure)),
                        "sure_buffers_rx": rx,
                        "mse_nc": float(metrics.noise_corrected_mse(y, reference.color,
                                                                    reference.variance)),
                        "mse_raw": float(metrics.mse(y, reference.color)),
                        "reference_var": float(np.mean(reference.variance)),
                    })
                index += 1
    return rows


#: The estimators a sub-buffer result compares: its name -> the row field.
ESTIMATES = {"stein": "sure", "buffers": "sure_buffers", "extrapolated": "sure_buffers_rx"}
_ESTIMATE_NAMES = {"stein": "Stein (probes)", "buffers": "sub-buffers",
                   "extrapolated": "sub-buffers extrapolated in 1/K"}


def _estimates(rows: dict) -> dict[str, str]:
    """The estimators every row has a value of (the extrapolation needs an even K)."""
    return {k: v for k, v in ESTIMATES.items()
            if all(row.get(v) is not None for r in rows.values() for row in r)}


def summarize_buffers(rows: dict, provenance: dict | None = None) -> dict:
    """``{"summary": {denoiser: {estimator: summarize_sure(...)}}}``."""
    keys = _estimates(rows)
    return {"summary": {name: {kind: summarize_sure(r, key=key) for kind, key in keys.items()}
                        for name, r in rows.items()}}


def markdown_buffers(summaries: dict, rows: dict, buffers: int, renders: int) -> str:
    """The tables: per denoiser and spp the estimators' ratios to the true MSE (of means, the
    bootstrap interval, of the median crop-render, the share within ±10 %), then per crop."""
    keys = _estimates(rows)
    names = " / ".join(_ESTIMATE_NAMES[k] for k in keys)
    lines = [(f"{renders} fresh render(s) per crop and spp, each the mean of {buffers} "
              "independent sub-buffers. Estimate / noise-corrected true MSE: of the means over "
              "all crop-renders, of the median crop-render, and the share of crop-renders "
              f"within ±10 % ({names}); the 95 % interval of the ratio of means is a crop "
              f"bootstrap ({BOOTSTRAP_RESAMPLES} resamples of the crops with all their "
              "renders, seed 0)."), "",
             ("| denoiser | spp | true MSE | ratio of means | 95 % interval | median | "
              "within ±10 % |"),
             "|---|---:|---:|---:|---:|---:|---:|"]

    def cells(per, field, fmt):
        return " / ".join(format(per[kind][field], fmt) for kind in keys)

    def intervals(per):
        return " / ".join("{:.2f}..{:.2f}".format(*per[kind]["ratio_ci95"]) for kind in keys)

    for name, by_kind in summaries.items():
        for level in by_kind["stein"]["per_spp"]:
            per = {kind: by_kind[kind]["per_spp"][level] for kind in keys}
            lines.append(f"| {name} | {level} | {per['stein']['mse_nc']:.4g} | "
                         f"{cells(per, 'ratio', '.3f')} | {intervals(per)} | "
                         f"{cells(per, 'median_crop_ratio', '.3f')} | "
                         f"{cells(per, 'within_10pct', '.0%')} |")
    crops = sorted({r["crop"] for r in next(iter(rows.values()))})
    lines += ["", f"Per crop, all spp and renders pooled (ratio of means, {names}):",
              "", "| denoiser | " + " | ".join(crops) + " |",
              "|---|" + "---:|" * len(crops)]
    for name, r in rows.items():
        crop_cells = []
        for crop in crops:
            group = [row for row in r if row["crop"] == crop]
            true = sum(row["mse_nc"] for row in group)
            crop_cells.append(" / ".join(f"{sum(row[key] for row in group) / true:.2f}"
                                         for key in keys.values()))
        lines.append(f"| {name} | " + " | ".join(crop_cells) + " |")
    return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class SureBuffersOptions:
    """``buffers``: independent sub-buffers per render (spp / buffers each); ``renders``:
    independent renders per crop and spp; the rest (``sure``: the Stein SURE's settings) as
    :class:`~jaxden.evaluate.sure.SureOptions`."""

    denoisers: tuple[str, ...] = ("oidn",)
    split: str = "test"
    sure: SureSettings = UNSET
    spp: tuple[int, ...] | None = None
    buffers: int = 16
    renders: int = 1


def _run(data, options: SureBuffersOptions, *, progress: bool = False) -> dict[str, list]:
    return sure_accuracy_buffers(data, list(options.denoisers), buffers=options.buffers,
                                 renders=options.renders, split=options.split,
                                 sure=options.sure, spp=options.spp, progress=progress)


def _provenance(options: SureBuffersOptions) -> dict:
    from jaxden.evaluate.shared import weights_identity

    settings = options.sure.resolved()
    return {"denoisers": [weights_identity(spec) for spec in options.denoisers],
            "seed": settings.seed, "probes": settings.probes, "sure": settings.given(),
            "buffers": options.buffers, "renders": options.renders,
            "render_seed_base": BUFFER_SEED_BASE}


EVALUATOR = Evaluator(
    name="sure-buffers",
    description="Stein SURE against sub-buffer SURE on fresh renders of independent "
                "sub-buffers",
    options=SureBuffersOptions,
    run=_run,
    summarize=summarize_buffers,
    table=lambda fields, rows, provenance: markdown_buffers(
        fields["summary"], rows, provenance["buffers"],
        provenance.get("renders", 1)),
    provenance=_provenance,
)
