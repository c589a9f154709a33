"""SURE accuracy on a rendered test set: the image mean of a denoiser's SURE against the
noise-corrected true MSE of its output, per crop and spp (the ``sure`` evaluator).

- :func:`sure_accuracy`: the rows (jvp SURE for JAX denoisers, finite differences for OIDN);
- :func:`summarize_sure`: per-spp means, the ratio, its crop-bootstrap interval
  (:func:`ratio_interval`) and the share of images within ±10 %; :func:`markdown_sure`;
- :func:`median_crop_checks`: the accuracy target, the median crop's ratio within
  :data:`MEDIAN_CROP_TOLERANCE` at every spp from :data:`MIN_SPP` on.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from typing import Any

import numpy as np

from jaxden.data.crops import iter_crops
from jaxden.evaluate.evaluator import Evaluator
from jaxden.evaluate.shared import by_spp, crop_count, progress_bar
from jaxden.sure.settings import UNSET, SureSettings

#: Crop-bootstrap resamples of :func:`ratio_interval`.
BOOTSTRAP_RESAMPLES = 2000
#: The accuracy target for SURE: the median crop's SURE / noise-corrected true MSE within this
#: tolerance at every spp level from MIN_SPP on.
MEDIAN_CROP_TOLERANCE, MIN_SPP = 0.05, 64


def sure_accuracy(dataset_dir, denoiser, *, split: str = "test",
                  sure: SureSettings | None = None, spp: tuple[int, ...] | None = None,
                  progress: bool = False, **options) -> list[dict[str, Any]]:
    """One row per (crop, spp): ``sure`` (image mean of the per-pixel SURE of the denoiser's
    output), ``mse_nc`` (its noise-corrected true MSE against the reference), ``mse_raw``
    (uncorrected), ``reference_var`` (mean variance of the reference's pixel mean), and the
    same for the input: ``input_var`` (the mean variance of its pixel mean, the unbiased
    estimate of its MSE) and ``input_mse_nc`` (its noise-corrected true MSE). On frames with
    a colour covariance (and ``sure.covariance`` on) ``sure`` draws its probes from it and
    ``sure_diag`` is the paper's per-channel form on the same normals
    (:mod:`jaxden.sure.stein`). ``sure``: the :class:`~jaxden.sure.settings.SureSettings`
    (None: the defaults; the older keywords ``options``, ``seed=``, ``num_probes=``,
    ``method=``, ``probe_dist=``, override it where given); item ``i``'s probes come from
    ``fold_in(PRNGKey(sure.seed), i)``."""
    import jax

    from jaxden import metrics
    from jaxden.denoise.registry import load_denoiser
    from jaxden.sure.denoiser import denoise_with_sure
    from jaxden.sure.settings import resolve_settings

    settings = resolve_settings(sure, **options)
    model = load_denoiser(denoiser) if isinstance(denoiser, str) else denoiser
    base = jax.random.PRNGKey(settings.seed)
    rows, index = [], 0
    crops = iter_crops(dataset_dir, split, spp)
    for crop, reference, inputs in progress_bar(crops, crop_count(dataset_dir, split), progress,
                                                f"SURE accuracy ({model.name})"):
        for level, frame in inputs:
            key = jax.random.fold_in(base, index)
            result, _ = denoise_with_sure(model, frame, key, sure=settings)
            index += 1
            y = np.asarray(result.denoised, np.float32)
            extra = {}
            if frame.covariance is not None and settings.covariance:
                diag, _ = denoise_with_sure(model, frame, key,
                                            sure=settings.replace(covariance=False))
                extra["sure_diag"] = float(np.mean(np.asarray(diag.sure)))
            rows.append({
                "crop": crop.id, "scene": crop.scene, "spp": level, **extra,
                "sure": float(np.mean(np.asarray(result.sure))),
                "mse_nc": float(metrics.noise_corrected_mse(y, reference.color,
                                                            reference.variance)),
                "mse_raw": float(metrics.mse(y, reference.color)),
                "reference_var": float(np.mean(reference.variance)),
                "input_var": float(np.mean(frame.variance)),
                "input_mse_nc": float(metrics.noise_corrected_mse(
                    np.asarray(frame.color, np.float32), reference.color, reference.variance)),
            })
    return rows


def summarize_sure(rows, key: str = "sure") -> dict[str, Any]:
    """Per spp: ``sure`` and ``mse_nc`` means over crops, ``ratio`` = mean SURE / mean true MSE
    (noise-corrected), ``median_crop_ratio`` and the mean reference variance relative to the
    true MSE (how much the correction matters); ``within_10pct``: the share of rows (images)
    whose own ratio is within ±10 %; ``ratio_ci95``: a crop-bootstrap 95 % interval of the
    ratio (:func:`ratio_interval`). ``key``: the row field holding the estimate
    (``sure_buffers`` for the sub-buffer estimator)."""
    per_spp = {}
    for level, group in by_spp(rows).items():
        sure = np.array([r[key] for r in group])
        true = np.array([r["mse_nc"] for r in group])
        ref_var = np.array([r["reference_var"] for r in group])
        per_spp[level] = {
            "sure": float(sure.mean()), "mse_nc": float(true.mean()),
            "ratio": float(sure.mean() / true.mean()) if true.mean() > 0 else float("nan"),
            "median_crop_ratio": float(np.median(sure / np.where(true > 0, true, np.nan))),
            "within_10pct": float(np.mean(np.abs(sure / np.where(true > 0, true, np.nan) - 1)
                                          <= 0.1)),
            "reference_var_over_mse": float(ref_var.mean() / true.mean())
            if true.mean() > 0 else float("nan"),
            "ratio_ci95": ratio_interval(group, key),
            "crops": len(group),
        }
    return {"per_spp": per_spp, "crops": len({r["crop"] for r in rows})}


def ratio_interval(rows, key: str = "sure", *, resamples: int = BOOTSTRAP_RESAMPLES,
                   seed: int = 0) -> list[float]:
    """95 % interval of the ratio of means (sum of ``key`` / sum of ``mse_nc``) by a crop
    bootstrap: draw the crops with replacement (each with all its renders), ``resamples``
    times with ``default_rng(seed)``; percentiles 2.5 and 97.5. Renders of one crop share its
    content, so crops, not renders, are the independent units."""
    crops: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for row in rows:
        crops[row["crop"]].append((row[key], row["mse_nc"]))
    sums = np.array([[sum(v for v, _ in pairs), sum(t for _, t in pairs)]
                     for pairs in crops.values()])
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(sums), size=(resamples, len(sums)))
    totals = sums[draws].sum(axis=1)
    ratios = totals[:, 0] / np.where(totals[:, 1] > 0, totals[:, 1], np.nan)
    low, high = np.nanpercentile(ratios, [2.5, 97.5])
    return [float(low), float(high)]


def markdown_sure(summaries: dict[str, dict[str, Any]]) -> str:
    """One table: per denoiser and spp, mean SURE vs noise-corrected true MSE."""
    lines = [("| denoiser | spp | mean SURE | true MSE (noise-corr.) | SURE / MSE | 95 % interval "
             "(crop bootstrap) | median crop ratio | ref. var / MSE |"),
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, summary in summaries.items():
        for level, m in summary["per_spp"].items():
            low, high = m.get("ratio_ci95", (float("nan"), float("nan")))
            lines.append(f"| {name} | {level} | {m['sure']:.4g} | {m['mse_nc']:.4g} | "
                         f"{m['ratio']:.3f} | {low:.2f}..{high:.2f} | "
                         f"{m['median_crop_ratio']:.3f} | {m['reference_var_over_mse']:.3f} |")
    return "\n".join(lines)


def median_crop_checks(summaries: dict, tolerance: float = MEDIAN_CROP_TOLERANCE,
                       min_spp: int = MIN_SPP) -> dict:
    """Per denoiser: the spp level (>= ``min_spp``) where the median crop's ratio is farthest
    from 1, that ratio, and whether every level is within ``tolerance``."""
    checks = {}
    for name, summary in summaries.items():
        levels = {int(level): m["median_crop_ratio"] for level, m in summary["per_spp"].items()
                  if int(level) >= min_spp}
        if not levels:
            continue
        worst = max(levels, key=lambda level: abs(levels[level] - 1.0))
        checks[name] = {"worst_spp": worst, "worst_ratio": levels[worst],
                        "within": all(abs(r - 1.0) <= tolerance for r in levels.values()),
                        "tolerance": tolerance, "min_spp": min_spp}
    return checks


def markdown_checks(checks: dict) -> str:
    lines = [(f"\nMedian crop's SURE / true MSE within ±{MEDIAN_CROP_TOLERANCE:.0%} at every spp "
              f">= {MIN_SPP}:\n")]
    for name, c in checks.items():
        lines.append(f"- {name}: {'yes' if c['within'] else 'NO'} (farthest from 1: "
                     f"{c['worst_ratio']:.3f} at {c['worst_spp']} spp)")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- the evaluator
@dataclasses.dataclass(frozen=True)
class SureOptions:
    """``denoisers``: specs (``oidn``, a shipped name, a checkpoint folder), each measured on
    the same probes; ``sure``: the :class:`~jaxden.sure.settings.SureSettings` (unset fields:
    the defaults, 4 normal probes with seed 0, ...); ``spp``: only these levels."""

    denoisers: tuple[str, ...] = ("oidn",)
    split: str = "test"
    sure: SureSettings = UNSET
    spp: tuple[int, ...] | None = None


def _run(data, options: SureOptions, *, progress: bool = False) -> dict[str, list]:
    from jaxden.paths import portable

    return {portable(spec): sure_accuracy(data, spec, split=options.split, sure=options.sure,
                                          spp=options.spp, progress=progress)
            for spec in options.denoisers}


def _summarize(rows: dict, provenance: dict) -> dict:
    summaries = {spec: summarize_sure(r) for spec, r in rows.items()}
    # Frames with a colour covariance: SURE from it, and the paper's per-channel form beside
    for spec, r in rows.items():
        if r and all("sure_diag" in row for row in r):
            summaries[f"{spec} (per-channel, the paper's)"] = summarize_sure(r, key="sure_diag")
    return {"summary": summaries, "checks": median_crop_checks(summaries)}


def _provenance(options: SureOptions) -> dict:
    from jaxden.evaluate.shared import weights_identity

    settings = options.sure.resolved()
    return {"denoisers": [weights_identity(spec) for spec in options.denoisers],
            "seed": settings.seed, "probes": settings.probes, "sure": settings.given()}


EVALUATOR = Evaluator(
    name="sure",
    description="image-mean SURE against the noise-corrected true MSE, per denoiser and spp",
    options=SureOptions,
    run=_run,
    summarize=_summarize,
    table=lambda fields, rows, provenance: (markdown_sure(fields["summary"]) + "\n"
                                      + markdown_checks(fields["checks"])),
    provenance=_provenance,
)
