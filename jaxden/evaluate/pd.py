"""Progressive denoising on a rendered test set: the paper's Table 3 / Fig. 10 on our data.

Every error is measured against the dataset's high-spp reference of the same crop, which is
itself noisy; besides the raw metrics each row carries the *noise-corrected* MSE,
``mse(x, r) - mean(var_r)`` (:func:`jaxden.metrics.noise_corrected_mse`), an unbiased
estimate of the MSE against the true image.

- :func:`evaluate_progressive`: per crop and spp, RMSE / relMSE / FLIP / noise-corrected MSE
  of MC (the input), the denoiser (y), the mixer before the t-test (x + alpha (y - x)), PD
  (z'), PD with either t-statistic form, PD fed the true error for SURE and the tile oracle
  (:mod:`jaxden.evaluate.oracle`), plus the image-level SURE of y, the mean alpha / alpha'
  and the mixer's swap symmetry gap.
- :func:`summarize_progressive`: per-spp means over crops and the headline ratios;
  :func:`markdown_progressive`: the tables.
- :data:`EVALUATOR` (``pd``): the above with a mixer and its inference overrides as options
  (:class:`PDOptions`), and the test of ``--keep-current`` (:func:`result_is_current`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.data.crops import iter_crops
from jaxden.errors import ConfigError
from jaxden.evaluate.evaluator import Evaluator
from jaxden.evaluate.oracle import ORACLE_BLOCK, oracle_mix, true_error
from jaxden.evaluate.shared import by_spp, crop_count, denoiser_label, progress_bar
from jaxden.sure.settings import UNSET, SureSettings

PD_METHODS = ("mc", "denoiser", "mixed", "pd", "pd_pc", "pd_shared", "pd_true_sure", "oracle")
#: The methods whose ratios to the denoiser the summaries report (the oracles included).
RATIO_METHODS = ("pd", "pd_pc", "pd_shared", "mixed", "pd_true_sure", "oracle")
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


def evaluate_progressive(dataset_dir, denoiser, mixer, *, split: str = "test",
                         sure: SureSettings | None = None,
                         spp: tuple[int, ...] | None = None,
                         progress: bool = False, **options) -> list[dict[str, Any]]:
    """One row per (crop, spp): errors of MC, the denoiser, the mixer without the t-test, PD,
    PD with the per-channel t-statistic (``pd_pc``: the mixer's config with
    ``tstat.per_channel = True``, same alpha) and with the shared one (``pd_shared``: the
    authors' form, ``per_channel = False``; one of the two equals ``pd``), PD with SURE
    replaced by the true error (``pd_true_sure``: the mixer and t-statistic fed
    :func:`~jaxden.evaluate.oracle.true_error` of y instead of its SURE, what a perfect SURE
    would give; an oracle, since it reads the reference) and the reference-fitted
    :func:`~jaxden.evaluate.oracle.oracle_mix` bound, each as ``{method}_{metric}`` (metrics
    :data:`PD_METRICS`), plus ``sure`` (image mean of y's SURE), ``alpha`` / ``alpha_prime``
    (means) and ``swap_gap`` (mean |alpha(x, y) - (1 - alpha(y, x))|).

    ``denoiser``: a spec or :class:`jaxden.denoise.Denoiser`; ``mixer``: a spec for
    :func:`jaxden.progressive.load_mixer` or a ``(params, config)`` pair. ``sure``: the
    :class:`~jaxden.sure.settings.SureSettings`, unset fields the mixer's (what it was trained
    with; the older keywords ``options``, ``seed=`` and ``num_probes=``, override it where
    given). SURE probes of item ``i`` come from ``fold_in(PRNGKey(sure.seed), i)``.
    """
    import jax

    from jaxden.denoise.registry import load_denoiser
    from jaxden.progressive.heads import mix
    from jaxden.progressive.mixer_checkpoints import load_mixer
    from jaxden.progressive.network import swap_symmetry
    from jaxden.progressive.pipeline import mix_given_sure, progressive_denoise
    from jaxden.progressive.tstat import consistent_mix
    from jaxden.sure.settings import resolve_settings

    model = load_denoiser(denoiser) if isinstance(denoiser, str) else denoiser
    params, config = load_mixer(mixer) if isinstance(mixer, (str, Path)) else mixer
    settings = resolve_settings(sure, config.sure, **options)
    per_channel = dataclasses.replace(config.tstat, per_channel=True)
    shared = dataclasses.replace(config.tstat, per_channel=False)
    base = jax.random.PRNGKey(settings.seed)
    rows, index = [], 0
    crops = iter_crops(dataset_dir, split, spp)
    for crop, reference, inputs in progress_bar(crops, crop_count(dataset_dir, split), progress,
                                                "PD report"):
        for level, frame in inputs:
            z, alpha_prime, extras = progressive_denoise(
                frame, model, params, config, jax.random.fold_in(base, index), sure=settings)
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
    for level, group in by_spp(rows).items():
        keys = [k for k in group[0] if k not in ("crop", "scene", "spp")]
        per_spp[level] = {k: float(np.mean([r[k] for r in group])) for k in keys}
        per_spp[level]["crops"] = len(group)
    ratios: dict[str, dict[str, float]] = defaultdict(dict)
    top = max(per_spp)
    for metric in ("rmse", "rmse_nc", "relmse", "flip"):
        for method in RATIO_METHODS:
            if f"{method}_{metric}" not in per_spp[top]:
                continue  # a result from before the row existed
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
                continue  # results from before the oracle was added
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
        lines += ["", (f"Per crop, RMSE: {names['pd']} and the oracle over {denoiser} (mean over "
                  f"spp of the per-spp ratio), {denoiser}'s mean RMSE (its weight in the "
                  f"crop-mean ratios above), and PD and the oracle over MC at {top} spp."), "",
                  (f"| crop | {denoiser} RMSE | PD / {denoiser} | oracle / {denoiser} | "
                  f"PD / MC at {top} | oracle / MC at {top} |"),
                  "|---|---:|---:|---:|---:|---:|"]
        for crop, c in summary["per_crop"].items():
            lines.append(f"| {crop} | {c['denoiser_rmse']:.5f} | "
                         f"{c['pd_over_denoiser_rmse']:.3f} | "
                         f"{c['oracle_over_denoiser_rmse']:.3f} | "
                         f"{c['pd_over_mc_rmse_at_max_spp']:.3f} | "
                         f"{c['oracle_over_mc_rmse_at_max_spp']:.3f} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the evaluator
@dataclasses.dataclass(frozen=True)
class PDOptions:
    """What a PD result depends on besides the data. ``denoiser``: a spec (empty: the mixer's
    own base denoiser); ``mixer``: a spec for :func:`jaxden.progressive.load_mixer`;
    ``sure``: the :class:`~jaxden.sure.settings.SureSettings` of its SURE (probes, their
    distribution, the probes' seed, ...; unset fields: the mixer's, what it was trained
    with); ``spp``: only these input spp levels (None: all). Inference overrides of the
    mixer's config: ``swap_average``, ``tstat`` (KEY=VALUE words of its TStatConfig),
    ``logit_bound`` (0.0: no bound) and ``mixer_set`` (KEY=VALUE words of its MixerConfig,
    applied last)."""

    denoiser: str = ""
    mixer: str = "oidn-pd"
    split: str = "test"
    sure: SureSettings = UNSET
    spp: tuple[int, ...] | None = None
    swap_average: bool | None = None
    tstat: tuple[str, ...] = ()
    logit_bound: float | None = None
    mixer_set: tuple[str, ...] = ()


def resolve_mixer(options: PDOptions):
    """``(params, config)`` of the options' mixer with their inference overrides applied, its
    ``sure`` the options' over the mixer's (ConfigError naming a bad key or value). Read
    afresh at each call: a sweep evaluates the checkpoint its run has just written."""
    from jaxden.config import load_config
    from jaxden.progressive.mixer_checkpoints import load_mixer
    from jaxden.progressive.mixer_config import MixerConfig, with_tstat_overrides

    params, config = load_mixer(options.mixer)
    if options.swap_average is not None:
        config = dataclasses.replace(config, swap_average=options.swap_average)
    config = with_tstat_overrides(config, options.tstat)
    if options.logit_bound is not None:
        config = dataclasses.replace(config, logit_bound=options.logit_bound or None)
    config = dataclasses.replace(config, sure=options.sure.over(config.sure))
    if options.mixer_set:
        config = load_config(config, MixerConfig, overrides=list(options.mixer_set))
    return params, config


def _run(data, options: PDOptions, *, progress: bool = False) -> list[dict[str, Any]]:
    params, config = resolve_mixer(options)
    return evaluate_progressive(data, options.denoiser or config.denoiser, (params, config),
                                split=options.split, spp=options.spp, progress=progress)


def _provenance(options: PDOptions) -> dict:
    from jaxden.config import config_to_dict
    from jaxden.evaluate.shared import weights_identity

    _, config = resolve_mixer(options)
    return {"denoiser": options.denoiser or config.denoiser,
            "mixer": weights_identity(options.mixer),
            "swap_average": config.swap_average, "logit_bound": config.logit_bound,
            "mixer_overrides": list(options.mixer_set),
            "closed_form_stops": config.closed_form_stops,
            "tstat": config_to_dict(config.tstat), "mixer_config": config_to_dict(config),
            "spp": None if options.spp is None else list(options.spp),
            "seed": config.sure.seed, "probes": config.sure.probes,
            "probe_dist": config.sure.probe_dist}


#: What a PD result must share with a new run to stand for it (``--keep-current``).
SAME_RUN = ("denoiser", "mixer", "mixer_config", "seed", "probes", "spp")


def result_is_current(out: Path, source: dict) -> bool:
    """Whether OUT.json is what this run would write: made on the same build of the dataset
    (manifest hash) and split, with the same denoiser, mixer weights, effective mixer config,
    probe seed, probes and spp, and with a column for every method the result now has."""
    try:
        old = json.loads(Path(out).with_suffix(".json").read_text())
        made = old["provenance"]
        columns = old["rows"][0] if old["rows"] else {}
    except (OSError, ValueError, KeyError, TypeError):
        return False
    now = json.loads(json.dumps(source, sort_keys=True, default=float))  # as it would be saved
    for entry in (made, now):  # weights by their content, wherever the file lies
        if isinstance(entry.get("mixer"), dict):
            entry["mixer"] = {k: entry["mixer"].get(k) for k in ("spec", "sha256")}
        entry["mixer_config"] = _as_today(entry.get("mixer_config"))
    same_data = all(made.get("dataset", {}).get(k) == now["dataset"][k]
                    for k in ("manifest_sha256", "split"))
    return (same_data and all(made.get(k) == now.get(k) for k in SAME_RUN)
            and all(f"{m}_rmse" in columns for m in PD_METHODS))


def _as_today(mixer_config):
    """A recorded mixer config in today's form (older flat SURE keys moved, today's defaults
    filled in), so that a result from before is still current; as recorded if it no longer
    loads."""
    from jaxden.config import config_to_dict, load_config
    from jaxden.progressive.mixer_config import MixerConfig, upgrade_mixer_config

    try:
        return config_to_dict(load_config(upgrade_mixer_config(mixer_config), MixerConfig))
    except (ConfigError, TypeError, ValueError):
        return mixer_config


def _sweep_options(run_dir, table: dict) -> PDOptions:
    spp = table.get("spp")
    return PDOptions(denoiser=table.get("denoiser") or "", mixer=str(run_dir),
                     split=table["split"],
                     sure=SureSettings(probes=table["probes"], seed=table["seed"]),
                     spp=None if spp is None else tuple(spp))


def _sweep_columns(summary: dict) -> dict[str, float]:
    """A sweep summary's columns of one PD evaluation: PD / denoiser (RMSE, relMSE), the same
    mixer without the t-test / denoiser (RMSE, when measured) and PD / MC at the top spp."""
    head = summary["headline"]
    columns = {"PD/den RMSE": head["pd_over_denoiser"]["rmse"],
               "PD/den relMSE": head["pd_over_denoiser"]["relmse"]}
    if "mixed_over_denoiser" in head:
        columns["no-t/den RMSE"] = head["mixed_over_denoiser"]["rmse"]
    columns[f"PD/MC RMSE@{summary['max_spp']}"] = head["pd_over_mc_at_max_spp"]["rmse"]
    return columns


EVALUATOR = Evaluator(
    name="pd",
    description="progressive denoising against MC, the denoiser and the oracles, per spp",
    options=PDOptions,
    run=_run,
    summarize=lambda rows, provenance: {"summary": summarize_progressive(rows)},
    table=lambda fields, rows, provenance: markdown_progressive(
        fields["summary"], denoiser_label(provenance["denoiser"])),
    provenance=_provenance,
    sweep_options=_sweep_options,
    sweep_settings=(("spp", tuple[int, ...] | None, None), ("split", str, "test"),
                    ("probes", int, 4), ("seed", int, 0), ("denoiser", str, "")),
    sweep_key="pd",
    sweep_columns=_sweep_columns,
    trains="mixer",
    is_current=result_is_current,
)
