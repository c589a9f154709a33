"""Measurements of progressive denoising on a rendered dataset (the paper's Table 3 / Fig. 10
and the SURE accuracy table, on our data).

Every error is measured against the dataset's high-spp reference of the same crop, which is
itself noisy; besides the raw metrics each row carries the *noise-corrected* MSE,
``mse(x, r) - mean(var_r)`` (:func:`jaxden.metrics.noise_corrected_mse`), an unbiased
estimate of the MSE against the true image.

- :func:`evaluate_progressive`: per crop and spp, RMSE / relMSE / FLIP / noise-corrected MSE
  of MC (the input), the denoiser (y), the mixer before the t-test (x + alpha (y - x)) and
  PD (z'), plus the image-level SURE of y, the mean alpha / alpha' and the mixer's swap
  symmetry gap.
- :func:`sure_accuracy`: per crop and spp, the image mean of SURE next to the noise-corrected
  true MSE of a denoiser's output (jvp for JAX denoisers, finite differences for OIDN).
- :func:`summarize_progressive`, :func:`summarize_sure`: per-spp means over crops and the
  headline ratios; :func:`markdown_progressive`, :func:`markdown_sure`: tables.
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.data.crops import iter_crops
from jaxden.errors import ConfigError, DatasetError

PD_METHODS = ("mc", "denoiser", "mixed", "pd", "pd_pc", "pd_shared", "pd_true_sure", "oracle")
#: The methods whose ratios to the denoiser the summaries report (the oracles included).
RATIO_METHODS = ("pd", "pd_pc", "pd_shared", "mixed", "pd_true_sure", "oracle")
ORACLE_BLOCK = 8
PAPER_MIN_SPP = 32  # the paper averages its Table 3 over 32..8192 spp
PD_METRICS = ("rmse", "rmse_nc", "relmse", "flip", "mse_nc")


def _errors(image, reference) -> dict[str, float]:
    from jaxden import metrics

    image = np.asarray(image, np.float32)
    mse_nc = float(metrics.noise_corrected_mse(image, reference.color, reference.variance))
    return {
        "rmse": float(metrics.rmse(image, reference.color)),
        "rmse_nc": math.sqrt(max(mse_nc, 0.0)),
        "relmse": float(metrics.relmse(image, reference.color)),
        "flip": float(metrics.flip(image, reference.color, "HDR")),
        "mse_nc": mse_nc,
    }


def noise_margin(image, x, variance, reference) -> float:
    """Twice the standard deviation that the noise of the render x and of the reference puts
    into the difference of two noise-corrected MSEs scored against the same reference,
    MSE(image) - MSE(x), in MSE units (mean over pixels and channels). Per pixel
    (image - r)^2 - (x - r)^2 = (image - x)(image + x - 2 r); with image - x held fixed, its
    noise is 2 (image - x)((x - mu) - (r - mu)), of variance 4 (image - x)^2 (var_x + var_r).
    Within the margin, image and x are equally far from the truth as far as one render and
    one reference can tell (a pixel mixed at Eq. 9's break-even alpha is such a pixel); a
    bias shows beyond it, its excess growing with (image - x)^2 and the margin with its square
    root."""
    image, x = (np.asarray(a, np.float64) for a in (image, x))
    spread = np.sum((image - x) ** 2 * (np.asarray(variance, np.float64)
                                        + np.asarray(reference.variance, np.float64)))
    return float(4.0 * math.sqrt(spread) / image.size)


def oracle_alpha(x, y, reference, block: int = ORACLE_BLOCK) -> np.ndarray:
    """The alpha of :func:`oracle_mix`: one value in [0, 1] per channel and per ``block`` x
    ``block`` tile, the least-squares fit of ``x + alpha (y - x)`` to the reference, spread over
    the tile's pixels; (H, W, C) float64."""
    x, y, r = (np.asarray(a, np.float64) for a in (x, y, reference))
    h, w = x.shape[:2]
    out = np.empty_like(x)
    for top in range(0, h, block):
        for left in range(0, w, block):
            tile = np.s_[top : top + block, left : left + block]
            d = (y - x)[tile]
            num = np.sum((r - x)[tile] * d, axis=(0, 1))
            den = np.sum(d * d, axis=(0, 1))
            out[tile] = np.clip(np.divide(num, den, out=np.zeros_like(num), where=den > 0), 0, 1)
    return out


def true_error(y, reference) -> np.ndarray:
    """What SURE estimates, read off the reference: the per-pixel squared error of ``y``
    against the reference frame's colour less the variance of the reference's pixel mean
    (unbiased for the squared error against the true image, as SURE is); (H, W, C) float32.
    Fed to a mixer in place of SURE it measures what a perfect SURE would give."""
    y = np.asarray(y, np.float64)
    err = (y - np.asarray(reference.color, np.float64)) ** 2
    return (err - np.asarray(reference.variance, np.float64)).astype(np.float32)


def oracle_mix(x, y, reference, block: int = ORACLE_BLOCK) -> np.ndarray:
    """The best mix ``x + alpha (y - x)`` with one alpha in [0, 1] per channel and per
    ``block`` x ``block`` tile, fitted by least squares to the reference: an upper bound on
    what a mixer whose alpha varies on that scale can reach (it sees the reference, so it is
    not a method). Tiles at the right/bottom edge may be smaller."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return (x + oracle_alpha(x, y, reference, block) * (y - x)).astype(np.float32)


def _progress(iterable, total: int | None, show: bool, what: str):
    if not show:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=what, unit="crop")


def _crop_count(dataset_dir, split) -> int:
    from jaxden.data.layout import load_manifest

    manifest = load_manifest(dataset_dir)
    return len(manifest.crops_in(split))


def evaluate_progressive(dataset_dir, denoiser, mixer, *, split: str = "test",
                         seed: int = 0, num_probes: int | None = None,
                         spp: tuple[int, ...] | None = None,
                         progress: bool = False) -> list[dict[str, Any]]:
    """One row per (crop, spp): errors of MC, the denoiser, the mixer without the t-test, PD,
    PD with the per-channel t-statistic (``pd_pc``: the mixer's config with
    ``tstat.per_channel = True``, same alpha) and with the shared one (``pd_shared``: the
    authors' form, ``per_channel = False``; one of the two equals ``pd``), PD with SURE
    replaced by the true error (``pd_true_sure``: the mixer and t-statistic fed
    :func:`true_error` of y instead of its SURE, what a perfect SURE would give; an oracle,
    since it reads the reference) and the reference-fitted :func:`oracle_mix` bound, each as ``{method}_{metric}`` (metrics
    :data:`PD_METRICS`), plus ``sure`` (image mean
    of y's SURE), ``alpha`` / ``alpha_prime`` (means) and ``swap_gap`` (mean |alpha(x, y) -
    (1 - alpha(y, x))|).

    ``denoiser``: a spec or :class:`jaxden.denoise.Denoiser`; ``mixer``: a spec for
    :func:`jaxden.progressive.load_mixer` or a ``(params, config)`` pair. SURE probes of item
    ``i`` come from ``fold_in(PRNGKey(seed), i)``; ``num_probes`` None: the mixer's
    ``sure_probes`` (what it was trained with).
    """
    import dataclasses

    import jax

    from jaxden.denoise.registry import load_denoiser
    from jaxden.progressive.heads import mix
    from jaxden.progressive.mixer import load_mixer, swap_symmetry
    from jaxden.progressive.pipeline import mix_given_sure, progressive_denoise
    from jaxden.progressive.tstat import consistent_mix

    model = load_denoiser(denoiser) if isinstance(denoiser, str) else denoiser
    params, config = load_mixer(mixer) if isinstance(mixer, (str, Path)) else mixer
    per_channel = dataclasses.replace(config.tstat, per_channel=True)
    shared = dataclasses.replace(config.tstat, per_channel=False)
    base = jax.random.PRNGKey(seed)
    rows, index = [], 0
    crops = iter_crops(dataset_dir, split, spp)
    for crop, reference, inputs in _progress(crops, _crop_count(dataset_dir, split), progress,
                                             "PD report"):
        for level, frame in inputs:
            z, alpha_prime, extras = progressive_denoise(
                frame, model, params, config, jax.random.fold_in(base, index),
                num_probes=num_probes)
            index += 1
            alpha_pc, alpha_shared = (
                consistent_mix(frame.color, extras["denoised"], extras["alpha"],
                               frame.variance, tstat, spp=frame.spp)[1]
                for tstat in (per_channel, shared))
            z_true, *_ = mix_given_sure(frame.color, extras["denoised"], frame.variance,
                                        true_error(extras["denoised"], reference), params,
                                        config, spp=frame.spp)
            images = {"mc": frame.color, "denoiser": extras["denoised"],
                      "mixed": extras["mixed"], "pd": z,
                      "pd_pc": mix(frame.color, extras["denoised"], alpha_pc),
                      "pd_shared": mix(frame.color, extras["denoised"], alpha_shared),
                      "pd_true_sure": z_true,
                      "oracle": oracle_mix(frame.color, extras["denoised"], reference.color)}
            row: dict[str, Any] = {"crop": crop.id, "scene": crop.scene, "spp": level}
            for method, image in images.items():
                row |= {f"{method}_{k}": v for k, v in _errors(image, reference).items()}
            row["pd_vs_mc_margin"] = noise_margin(z, frame.color, frame.variance, reference)
            row["sure"] = float(np.mean(np.asarray(extras["sure"])))
            row["alpha"] = float(np.mean(np.asarray(extras["alpha"])))
            row["alpha_prime"] = float(np.mean(np.asarray(alpha_prime)))
            row["swap_gap"] = swap_symmetry(params, config, frame.color, extras["denoised"],
                                            frame.variance, extras["sure"])
            rows.append(row)
    return rows


def sure_accuracy(dataset_dir, denoiser, *, split: str = "test", seed: int = 0,
                  num_probes: int = 4, method: str = "auto", spp: tuple[int, ...] | None = None,
                  progress: bool = False) -> list[dict[str, Any]]:
    """One row per (crop, spp): ``sure`` (image mean of the per-pixel SURE of the denoiser's
    output), ``mse_nc`` (its noise-corrected true MSE against the reference), ``mse_raw``
    (uncorrected), ``reference_var`` (mean variance of the reference's pixel mean), and the
    same for the input: ``input_var`` (the mean variance of its pixel mean, the unbiased
    estimate of its MSE) and ``input_mse_nc`` (its noise-corrected true MSE). On frames with
    a colour covariance ``sure`` draws its probes from it and ``sure_diag`` is the paper's
    per-channel form on the same normals (:mod:`jaxden.sure.stein`)."""
    import jax

    from jaxden import metrics
    from jaxden.denoise.registry import load_denoiser
    from jaxden.sure.denoiser import denoise_with_sure

    model = load_denoiser(denoiser) if isinstance(denoiser, str) else denoiser
    base = jax.random.PRNGKey(seed)
    rows, index = [], 0
    crops = iter_crops(dataset_dir, split, spp)
    for crop, reference, inputs in _progress(crops, _crop_count(dataset_dir, split), progress,
                                             f"SURE accuracy ({model.name})"):
        for level, frame in inputs:
            key = jax.random.fold_in(base, index)
            result, _ = denoise_with_sure(model, frame, key, num_probes=num_probes,
                                          method=method)
            index += 1
            y = np.asarray(result.denoised, np.float32)
            extra = {}
            if frame.covariance is not None:
                diag, _ = denoise_with_sure(model, frame.replace(covariance=None), key,
                                            num_probes=num_probes, method=method)
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


BUFFER_SEED_BASE = 800_000


def sure_accuracy_buffers(dataset_dir, denoisers, *, buffers: int = 16, renders: int = 1,
                          split: str = "test",
                          seed: int = 0, num_probes: int = 4, method: str = "auto",
                          spp: tuple[int, ...] | None = None, render_fn=None,
                          progress: bool = False) -> dict[str, list[dict[str, Any]]]:
    """Stein SURE and sub-buffer SURE of each denoiser on the same fresh renders.

    For every crop of ``split``, spp level (levels divisible by ``buffers`` into >= 2 spp
    each) and each of ``renders`` independent renders r, renders ``buffers`` independent
    sub-buffers at spp / buffers with render seeds ``BUFFER_SEED_BASE + 1000 * level_index +
    buffers * r + k`` (refused if one collides with the dataset's seeds for that crop), combines them (:func:`jaxden.sure.combine_buffers`: the same image
    as one render of all the samples) and computes, for each denoiser, ``sure`` (probes:
    :func:`jaxden.sure.denoise_with_sure`, key ``fold_in(PRNGKey(seed), index)``),
    ``sure_buffers`` (:func:`jaxden.sure.sure_buffers`) and the noise-corrected true MSE of
    the output against the dataset's reference. ``render_fn(scene, spp, seed, size, crop)``
    defaults to the dataset builder's renderer.

    Returns {denoiser name: rows}, rows as in :func:`sure_accuracy` plus ``sure_buffers``,
    ``sure_buffers_rx`` (Richardson-extrapolated from K and K/2 merged pairs, as
    ``sure_buffers(..., extrapolate=True)``; None for odd K) and ``render`` (r); the summaries
    average over crops and renders alike.
    """
    import jax

    from jaxden import metrics
    from jaxden.data.layout import load_manifest
    from jaxden.denoise.registry import load_denoiser
    from jaxden.sure.buffers import combine_buffers, merge_buffer_pairs, sure_buffers
    from jaxden.sure.denoiser import denoise_with_sure

    if render_fn is None:
        from jaxden.data.builder import render_cached

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
    base = jax.random.PRNGKey(seed)
    rows: dict[str, list[dict[str, Any]]] = {m.name: [] for m in models}
    index = 0
    crops = iter_crops(dataset_dir, split, spp)
    for crop, reference, inputs in _progress(crops, _crop_count(dataset_dir, split), progress,
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
                                                  num_probes=num_probes, method=method)
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


def _by_spp(rows) -> dict[int, list[dict]]:
    groups: dict[int, list[dict]] = defaultdict(list)
    for row in rows:
        groups[row["spp"]].append(row)
    return dict(sorted(groups.items()))


def summarize_progressive(rows) -> dict[str, Any]:
    """Per-spp means over crops of every ``{method}_{metric}`` (and sure, alpha, swap_gap);
    the ratios PD / denoiser and PD / MC per spp; and the headline numbers:

    - ``pd_over_denoiser[metric]``: mean over spp of the per-spp ratio of crop-mean errors
      (RMSE: of crop-mean RMSE; relMSE: of crop-mean relMSE), the paper's Table 3 form;
      ``pd_over_denoiser_paper_range``: the same over spp >= 32 only (the paper's range);
      ``mixed_*`` and ``oracle_*``: the same for the mix without t-test and the oracle;
    - ``pd_over_mc_at_max_spp[metric]``: the same ratio against MC at the highest spp;
    - ``per_crop[crop]``: RMSE of PD and of the oracle over the denoiser's (mean over spp of the
      per-spp ratio) and over MC at the highest spp, and the denoiser's mean RMSE over spp
      (how much the crop weighs in the crop-mean headline): where the gains are lost.
    """
    per_spp = {}
    for level, group in _by_spp(rows).items():
        keys = [k for k in group[0] if k not in ("crop", "scene", "spp")]
        per_spp[level] = {k: float(np.mean([r[k] for r in group])) for k in keys}
        per_spp[level]["crops"] = len(group)
    ratios: dict[str, dict[str, float]] = defaultdict(dict)
    top = max(per_spp)
    for metric in ("rmse", "rmse_nc", "relmse", "flip"):
        for method in RATIO_METHODS:
            if f"{method}_{metric}" not in per_spp[top]:
                continue  # a report from before the row existed
            for suffix, low in (("", 0), ("_paper_range", PAPER_MIN_SPP)):
                per = [m[f"{method}_{metric}"] / m[f"denoiser_{metric}"]
                       for level, m in per_spp.items()
                       if level >= low and m[f"denoiser_{metric}"] > 0]
                ratios[f"{method}_over_denoiser{suffix}"][metric] = (
                    float(np.mean(per)) if per else float("nan"))
        mc = per_spp[top][f"mc_{metric}"]
        for method in ("pd", "pd_pc", "pd_shared"):
            if f"{method}_{metric}" not in per_spp[top]:
                continue
            ratios[f"{method}_over_mc_at_max_spp"][metric] = (
                per_spp[top][f"{method}_{metric}"] / mc if mc > 0 else float("nan"))
    for level, m in per_spp.items():
        m["pd_over_denoiser_rmse"] = m["pd_rmse"] / m["denoiser_rmse"]
        m["pd_over_mc_rmse"] = m["pd_rmse"] / m["mc_rmse"]
    per_crop = {}
    for crop in dict.fromkeys(r["crop"] for r in rows):
        group = [r for r in rows if r["crop"] == crop]
        at_top = [r for r in group if r["spp"] == top]
        entry = {"denoiser_rmse": float(np.mean([r["denoiser_rmse"] for r in group]))}
        for method in ("pd", "oracle"):
            entry[f"{method}_over_denoiser_rmse"] = float(np.mean(
                [r[f"{method}_rmse"] / r["denoiser_rmse"] for r in group]))
            entry[f"{method}_over_mc_rmse_at_max_spp"] = (
                float(at_top[0][f"{method}_rmse"] / at_top[0]["mc_rmse"]) if at_top
                else float("nan"))
        per_crop[crop] = entry
    return {"per_spp": per_spp, "headline": dict(ratios), "max_spp": top,
            "crops": len({r["crop"] for r in rows}), "per_crop": per_crop}


#: Crop-bootstrap resamples of :func:`ratio_interval`.
BOOTSTRAP_RESAMPLES = 2000


def summarize_sure(rows, key: str = "sure") -> dict[str, Any]:
    """Per spp: ``sure`` and ``mse_nc`` means over crops, ``ratio`` = mean SURE / mean true MSE
    (noise-corrected), ``median_crop_ratio`` and the mean reference variance relative to the
    true MSE (how much the correction matters); ``within_10pct``: the share of rows (images)
    whose own ratio is within ±10 %; ``ratio_ci95``: a crop-bootstrap 95 % interval of the
    ratio (:func:`ratio_interval`). ``key``: the row field holding the estimate
    (``sure_buffers`` for the sub-buffer estimator)."""
    per_spp = {}
    for level, group in _by_spp(rows).items():
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


def markdown_progressive(summary: dict[str, Any], denoiser: str = "OIDN") -> str:
    """Table 3 / Fig. 10 on our data: per spp, mean over crops."""
    names = {"mc": "MC", "denoiser": denoiser, "mixed": "mix w/o t-test",
             "pd": f"PD({denoiser})", "pd_pc": f"PD({denoiser}), per-channel t",
             "pd_shared": f"PD({denoiser}), shared t (authors')",
             "pd_true_sure": f"PD({denoiser}) fed the true error for SURE (oracle)",
             "oracle": f"oracle mix ({ORACLE_BLOCK}² tiles)"}
    lines = ["| spp | method | RMSE | RMSE (noise-corr.) | relMSE | FLIP |",
             "|---:|---|---:|---:|---:|---:|"]
    for level, m in summary["per_spp"].items():
        for method in PD_METHODS:
            if f"{method}_rmse" not in m:
                continue  # reports from before the oracle was added
            lines.append(f"| {level} | {names[method]} | {m[f'{method}_rmse']:.5f} | "
                         f"{m[f'{method}_rmse_nc']:.5f} | {m[f'{method}_relmse']:.5f} | "
                         f"{m[f'{method}_flip']:.4f} |")
    lines.append("")
    lines.append("| ratio | RMSE | RMSE (noise-corr.) | relMSE | FLIP |")
    lines.append("|---|---:|---:|---:|---:|")
    labels = {}
    for method in RATIO_METHODS:
        name = names[method]
        labels[f"{method}_over_denoiser"] = f"{name} / {denoiser}, mean over spp"
        labels[f"{method}_over_denoiser_paper_range"] = (
            f"{name} / {denoiser}, mean over spp >= {PAPER_MIN_SPP}")
    for method in ("pd", "pd_pc", "pd_shared"):
        labels[f"{method}_over_mc_at_max_spp"] = f"{names[method]} / MC at {summary['max_spp']} spp"
    for key, label in labels.items():
        if key not in summary["headline"]:
            continue
        r = summary["headline"][key]
        lines.append(f"| {label} | {r['rmse']:.3f} | {r['rmse_nc']:.3f} | {r['relmse']:.3f} | "
                     f"{r['flip']:.3f} |")
    lines.append("")
    lines.append("| spp | mean alpha | mean alpha' | swap gap mean abs(alpha - (1 - alpha_swapped)) |")
    lines.append("|---:|---:|---:|---:|")
    for level, m in summary["per_spp"].items():
        lines.append(f"| {level} | {m['alpha']:.3f} | {m['alpha_prime']:.3f} | "
                     f"{m['swap_gap']:.3f} |")
    if summary.get("per_crop"):
        top = summary["max_spp"]
        lines += ["", f"Per crop, RMSE: {names['pd']} and the oracle over {denoiser} (mean over "
                  f"spp of the per-spp ratio), {denoiser}'s mean RMSE (its weight in the "
                  f"crop-mean ratios above), and PD and the oracle over MC at {top} spp.", "",
                  f"| crop | {denoiser} RMSE | PD / {denoiser} | oracle / {denoiser} | "
                  f"PD / MC at {top} | oracle / MC at {top} |",
                  "|---|---:|---:|---:|---:|---:|"]
        for crop, c in summary["per_crop"].items():
            lines.append(f"| {crop} | {c['denoiser_rmse']:.5f} | "
                         f"{c['pd_over_denoiser_rmse']:.3f} | "
                         f"{c['oracle_over_denoiser_rmse']:.3f} | "
                         f"{c['pd_over_mc_rmse_at_max_spp']:.3f} | "
                         f"{c['oracle_over_mc_rmse_at_max_spp']:.3f} |")
    return "\n".join(lines)


def markdown_sure(summaries: dict[str, dict[str, Any]]) -> str:
    """One table: per denoiser and spp, mean SURE vs noise-corrected true MSE."""
    lines = ["| denoiser | spp | mean SURE | true MSE (noise-corr.) | SURE / MSE | 95 % interval "
             "(crop bootstrap) | median crop ratio | ref. var / MSE |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, summary in summaries.items():
        for level, m in summary["per_spp"].items():
            low, high = m.get("ratio_ci95", (float("nan"), float("nan")))
            lines.append(f"| {name} | {level} | {m['sure']:.4g} | {m['mse_nc']:.4g} | "
                         f"{m['ratio']:.3f} | {low:.2f}..{high:.2f} | "
                         f"{m['median_crop_ratio']:.3f} | {m['reference_var_over_mse']:.3f} |")
    return "\n".join(lines)
