"""Which part of the error guard costs PD(OIDN) its low-spp gain on textured scenes, and whether
the option that removes it (``tstat.guard_cap_spp``) holds against today's guard everywhere else.

    python experiments/pd_guard_textured.py --run --out experiments/results/pd/pd-guard-textured

PD(OIDN) is OIDN in JAX (``oidn-jax``) with the shipped mixer ``oidn-pd``, as the queue's
``pd_eval`` runs it. ``--run`` first runs every evaluation that is missing or out of date
(``jaxden evaluate pd ... --keep-current``: a current one is kept) into ``--work`` (default
``$JAXDEN_HOME/runs/pd-guard-textured/SET/VARIANT.json``); without it the tables come from what
``--work`` holds (a missing file is named). The sets:

- ``ood-low``: the seven Mitsuba XML scenes of ``data/ood`` (bump maps, bitmap textures, a normal
  map; none made by jaxden's procedural generator) at 4, 8 and 16 spp. A build of
  ``dataset-ood.toml`` with ``spp=[4,8,16]`` is these very files: every render's seed is derived
  from (dataset seed, scene, crop, spp), not from the spp list or the name, and the 4-spp input
  re-renders bit for bit; so the existing build is read with ``--spp 4 8 16``.
- ``pd-test-high`` and ``test-chain`` (the held-out procedural crops, all their spp) and
  ``stress`` (8 frames with tiny lamps, glints and caustics, 4..4096 spp): today's guard against
  the option.
- small-lights (the built-in scene, 96 x 96, seed 1801, against the 8192-spp reference of seed
  999, as ``experiments/pd_lamps.py`` renders it into ``$JAXDEN_HOME/runs/pd-lamps``) at 8 and
  1024 spp: PD / MC in noise-corrected MSE for every variant (one SURE per frame, the mix redone
  per variant).

It also measures the mechanism on ood-low at 4 spp: where today's guard adds squared error over
the t-test alone, split by the cap's chi^2, and on the pixels with chi^2 in [2, 3) how far the
render's own local variance and x's realized squared error are from the truth (the variance of
the 1024-spp render of the same scene times 1024 / 4 standing for the true variance).
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
#: variant -> (what it is, --tstat overrides of the shipped oidn-pd's t-statistic config).
VARIANTS = {
    "today": ("the shipped guard (gamma 2, sigma 1, variance bound 2, per-channel chi)", []),
    "t-test only": ("no guard (the paper's t-test alone)", ["guard=false"]),
    "cap off": ("the significance factor alone (gamma 1000: the cap never binds)",
                ["guard_gamma=1000"]),
    "no variance bound": ("guard_confidence 0: the variance taken as exact",
                          ["guard_confidence=0"]),
    "variance bound 4": ("guard_confidence 4 (twice the bound)", ["guard_confidence=4"]),
    "gamma 4": ("cap at twice break-even", ["guard_gamma=4"]),
    "gamma 1": ("cap at the squared-error optimum", ["guard_gamma=1"]),
    "noise strata": ("guard_strata 1 (significance also over noise strata)",
                     ["guard_strata=1"]),
    "sigma 2": ("guard window sigma 2 px", ["guard_sigma=2"]),
    "cap spp 16": (("the option: below 16 spp the cap also reads a wider window and takes "
                    "the looser cap"), ["guard_cap_spp=16"]),
}
#: Columns that today's evaluation already holds: row prefix -> what it is.
DERIVED = {"mixed": "no t-test, no guard (the mixer's alpha)",
           "pd_shared": "t and guard chi summed over R, G, B (per_channel false)"}
OPTION = "cap spp 16"
#: set -> (dataset folder under $JAXDEN_HOME/data, --spp levels or None for all, variants,
#: further options of `evaluate pd`). ood-low-seed1: other SURE probes (the mixer's 4 normal
#: probes per image; their draw moves single scene-spp cells by up to ~0.5 %).
SETS = {
    "ood-low": ("ood", (4, 8, 16), tuple(VARIANTS), ()),
    "ood-low-seed1": ("ood", (4, 8, 16), ("today", "t-test only", OPTION), ("--seed", "1")),
    "pd-test-high": ("pd-test-high", None, ("today", OPTION), ()),
    "test-chain": ("test-chain", None, ("today", OPTION), ()),
    # and the simplest other fix of ood-low, a looser variance bound, for what it costs there
    "stress": ("stress", None, ("today", OPTION, "variance bound 4"), ()),
}
#: The target on ood-low: PD / OIDN within this in RMSE and relMSE, every scene, at these spp.
TARGET, TARGET_SPP = 1.01, (4, 16)
LAMPS = {"size": (96, 96), "seed": 1801, "reference_spp": 8192, "reference_seed": 999,
         "spp": (8, 1024)}


def _jaxden_home() -> Path:
    from jaxden.paths import expand_path

    return Path(expand_path("$JAXDEN_HOME"))


def evaluate(set_name: str, variant: str, work: Path) -> Path:
    """Run (or keep, when current) ``jaxden evaluate pd`` of ``variant`` on ``set_name``."""
    data, spp, _, extra = SETS[set_name]
    out = work / set_name / variant.replace(" ", "-")
    out.parent.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "jaxden.cli", "evaluate", "pd",
               "--data", str(_jaxden_home() / "data" / data), "--denoiser", "oidn-jax",
               "--mixer", "oidn-pd", "--keep-current", "--out", str(out)]
    if spp:
        command += ["--spp", *map(str, spp)]
    command += list(extra)
    for override in VARIANTS[variant][1]:
        command += ["--tstat", override]
    print("+", " ".join(command), flush=True)
    subprocess.run(command, cwd=REPO, check=True)
    return out.with_suffix(".json")


def load_rows(work: Path) -> dict:
    """``{set: {variant: rows}}`` of the evaluations in ``work``."""
    import json

    found, missing = {}, []
    for set_name, (_, _, variants, _) in SETS.items():
        for variant in variants:
            path = work / set_name / f"{variant.replace(' ', '-')}.json"
            if path.is_file():
                found.setdefault(set_name, {})[variant] = json.loads(path.read_text())["rows"]
            else:
                missing.append(str(path))
    if missing:
        raise SystemExit("pd_guard_textured: missing evaluations (run with --run):\n  "
                         + "\n  ".join(missing))
    return found


def _scene(row) -> str:
    return Path(str(row.get("scene", row["crop"]))).stem


def _method_rows(rows_by_variant: dict) -> dict:
    """``{variant: rows as (prefix 'pd')}``, the derived columns of today's rows added as
    variants of their own."""
    out = {v: [(r, "pd") for r in rows] for v, rows in rows_by_variant.items()}
    if "today" in rows_by_variant:
        for prefix in DERIVED:
            out[prefix] = [(r, prefix) for r in rows_by_variant["today"]]
    return out


def cell_ratios(rows_by_variant: dict) -> dict:
    """``{variant: {(crop, scene, spp): (RMSE ratio, relMSE ratio)}}``: PD / OIDN per image."""
    table = {}
    for variant, rows in _method_rows(rows_by_variant).items():
        table[variant] = {(r["crop"], _scene(r), r["spp"]): (
            r[f"{p}_rmse"] / r["denoiser_rmse"], r[f"{p}_relmse"] / r["denoiser_relmse"])
            for r, p in rows}
    return table


def set_summary(rows_by_variant: dict) -> dict:
    """Per variant: per spp the ratio of crop means (PD / OIDN, RMSE and relMSE) and the worst
    image's; their means over spp (the reports' headline form); PD / MC (noise-corrected MSE)
    at the top spp per image with the row's noise margin."""
    out = {}
    for variant, rows in _method_rows(rows_by_variant).items():
        levels = sorted({r["spp"] for r, _ in rows})
        per_spp = {}
        for level in levels:
            group = [(r, p) for r, p in rows if r["spp"] == level]
            entry = {}
            for metric in ("rmse", "relmse"):
                pd = np.mean([r[f"{p}_{metric}"] for r, p in group])
                den = np.mean([r[f"denoiser_{metric}"] for r, _ in group])
                entry[metric] = float(pd / den)
                entry[f"worst_{metric}"] = float(max(r[f"{p}_{metric}"] / r[f"denoiser_{metric}"]
                                                     for r, p in group))
            per_spp[level] = entry
        top = levels[-1]
        top_rows = [(r, p) for r, p in rows if r["spp"] == top]
        out[variant] = {
            "per_spp": per_spp,
            "mean_rmse": float(np.mean([e["rmse"] for e in per_spp.values()])),
            "mean_relmse": float(np.mean([e["relmse"] for e in per_spp.values()])),
            "top_spp": top,
            # the margin is PD's (today's z); for the derived columns it is left out
            "top_pd_over_mc": {r["crop"]: (r[f"{p}_mse_nc"] / r["mc_mse_nc"],
                                           (r.get("pd_vs_mc_margin", 0.0) / r["mc_mse_nc"]
                                            if p == "pd" else float("nan")))
                               for r, p in top_rows},
        }
    return out


# ------------------------------------------------------------------------ small-lights
def _lamp_render(work: Path, spp: int, seed: int):
    """The small-lights frame as experiments/pd_lamps.py renders and caches it."""
    from jaxden.io.exr import read_frame, write_frame
    from jaxden.render.core import render_frame

    path = work / f"small-lights-{spp}spp-seed{seed}.exr"
    if not path.is_file():
        work.mkdir(parents=True, exist_ok=True)
        write_frame(path, render_frame("small-lights", spp, seed=seed, size=LAMPS["size"]),
                    attributes={"seed": seed})
    return read_frame(path)


def small_lights() -> dict:
    """``{variant: {spp: {pd_over_mc, pd_over_den_relmse, pd_over_den_rmse}}}`` on the whole
    small-lights frame (noise-corrected MSE against the reference's variance)."""
    import dataclasses

    import jax

    from jaxden.config import load_config
    from jaxden.denoise.registry import load_denoiser
    from jaxden.evaluate.pd import PDOptions, resolve_mixer
    from jaxden.progressive.pipeline import mix_given_sure, progressive_denoise
    from jaxden.progressive.tstat import TStatConfig

    work = _jaxden_home() / "runs" / "pd-lamps"
    reference = _lamp_render(work, LAMPS["reference_spp"], LAMPS["reference_seed"])
    ref = np.asarray(reference.color, np.float64)
    ref_var = np.asarray(reference.variance, np.float64)
    params, config = resolve_mixer(PDOptions(mixer="oidn-pd"))
    model = load_denoiser("oidn-jax")

    def errors(image):
        squared = (np.asarray(image, np.float64) - ref) ** 2
        return (float(squared.mean() - ref_var.mean()), float(np.sqrt(squared.mean())),
                float((squared / (ref ** 2 + 0.01)).mean()))

    out: dict = {}
    for spp in LAMPS["spp"]:
        frame = _lamp_render(work, spp, LAMPS["seed"])
        _, _, extras = progressive_denoise(frame, model, params, config, jax.random.PRNGKey(0))
        mc, den = errors(frame.color), errors(extras["denoised"])
        for variant, (_, overrides) in VARIANTS.items():
            tstat = load_config(config.tstat, TStatConfig, overrides=list(overrides))
            z, *_ = mix_given_sure(frame.color, extras["denoised"], frame.variance,
                                   extras["sure"], params,
                                   dataclasses.replace(config, tstat=tstat), spp=frame.spp,
                                   variance_dof=frame.variance_dof)
            pd = errors(z)
            out.setdefault(variant, {})[spp] = {
                "pd_over_mc": pd[0] / mc[0], "pd_over_den_rmse": pd[1] / den[1],
                "pd_over_den_relmse": pd[2] / den[2]}
    return out


# --------------------------------------------------------------------------- mechanism
def mechanism(level: int = 4, reference_level: int = 1024) -> list[dict]:
    """Per ood scene at ``level`` spp: today's guard against the t-test alone (PD / OIDN), the
    share of the guard's excess squared error on pixels by the cap's chi^2, and on the pixels
    with chi^2 in [2, 3) medians of: local variance of the render / true local variance, local
    (x - ref)^2 / true local variance, (y - ref)^2 / (x - ref)^2 (local means over the guard's
    window; the true variance is the ``reference_level`` render's times reference_level /
    level)."""
    import jax
    import jax.numpy as jnp

    from jaxden.data.crops import iter_crops
    from jaxden.data.layout import load_manifest
    from jaxden.denoise.registry import load_denoiser
    from jaxden.evaluate.pd import PDOptions, resolve_mixer
    from jaxden.io.exr import read_frame
    from jaxden.progressive import guard
    from jaxden.progressive.closed_form import blur_2d, gaussian_taps
    from jaxden.progressive.heads import mix_unchecked
    from jaxden.progressive.pipeline import progressive_denoise
    from jaxden.progressive.tstat import _scale_alpha, _t_statistic

    data = _jaxden_home() / "data" / "ood"
    manifest = load_manifest(data)
    params, config = resolve_mixer(PDOptions(mixer="oidn-pd"))
    tstat = config.tstat
    model = load_denoiser("oidn-jax")
    taps = jnp.asarray(gaussian_taps(tstat.guard_sigma), jnp.float32)
    bands = ((0, 2), (2, 3), (3, 10), (10, math.inf))
    out = []
    levels = SETS["ood-low"][1]
    base = jax.random.PRNGKey(config.sure.seed)
    for number, (crop, reference, inputs) in enumerate(iter_crops(data, "test", (level,))):
        (_, frame), = inputs
        # the SURE probes of this image in the ood-low evaluation (evaluate pd's fold_in)
        key = jax.random.fold_in(base, number * len(levels) + levels.index(level))
        high = [i for i in manifest.items_of(crop.id)
                if i.kind == "input" and i.spp == reference_level]
        true_var = jnp.asarray(np.asarray(read_frame(data / high[0].path).variance)
                               * (reference_level / level), jnp.float32)
        _, _, extras = progressive_denoise(frame, model, params, config, key)
        x, var = jnp.asarray(frame.color), jnp.asarray(frame.variance)
        y, alpha = extras["denoised"], extras["alpha"]
        ref = np.asarray(reference.color, np.float64)
        alpha_t = _scale_alpha(alpha, _t_statistic(x, mix_unchecked(x, y, alpha), var, tstat),
                               tstat)
        alpha_g = guard.guard_alpha(alpha_t, x, y, var, tstat, jnp.asarray(float(level)))
        chi2, _ = guard._guard_chi2(x, y, var, guard.variance_inflation(float(level), tstat),
                                    tstat)
        err = {name: (np.asarray(mix_unchecked(x, y, a), np.float64) - ref) ** 2
               for name, a in (("t", alpha_t), ("guard", alpha_g))}
        excess = err["guard"] - err["t"]
        den_err = (np.asarray(y, np.float64) - ref) ** 2
        chi2 = np.broadcast_to(np.asarray(chi2), excess.shape)
        local = lambda a: np.asarray(blur_2d(jnp.asarray(a, jnp.float32), taps), np.float64)
        band = (chi2 >= 2) & (chi2 < 3)
        local_var, local_true = local(var), np.maximum(local(true_var), 1e-30)
        local_x = local((np.asarray(x, np.float64) - ref) ** 2)
        local_y = local(den_err)
        rmse = lambda e: math.sqrt(e.mean())
        relmse = lambda e, r=ref: float((e / (r ** 2 + 0.01)).mean())
        out.append({
            "crop": crop.id, "scene": Path(str(crop.scene)).stem, "spp": level,
            "t_only_over_den": (rmse(err["t"]) / rmse(den_err), relmse(err["t"]) / relmse(den_err)),
            "guard_over_den": (rmse(err["guard"]) / rmse(den_err),
                               relmse(err["guard"]) / relmse(den_err)),
            "excess_over_den_sse": float(excess.sum() / den_err.sum()),
            "band_share": {f"[{lo}, {hi})": {"pixels": float(((chi2 >= lo) & (chi2 < hi)).mean()),
                                             "excess_over_den_sse": float(
                                                 excess[(chi2 >= lo) & (chi2 < hi)].sum()
                                                 / den_err.sum())}
                           for lo, hi in bands},
            "band_2_3": ({"var_over_true": float(np.median(local_var[band] / local_true[band])),
                          "x_err_over_true": float(np.median(local_x[band] / local_true[band])),
                          "y_err_over_x_err": float(np.median(
                              local_y[band] / np.maximum(local_x[band], 1e-30)))}
                         if band.any() else None),
        })
    return out


# ------------------------------------------------------------------------------ tables
def _fmt(value: float, digits: int = 3) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def verdicts(summary: dict, cells: dict, lamps: dict) -> dict:
    """What the option does against today's guard, set by set."""
    result = {"ood_low_target": {}}
    for set_name in ("ood-low", "ood-low-seed1"):
        for variant, by_cell in cells[set_name].items():
            over = [f"{scene} {spp} spp ({r:.3f} / {q:.3f})" for (_, scene, spp), (r, q)
                    in sorted(by_cell.items(), key=lambda kv: (kv[0][2], kv[0][1]))
                    if spp in TARGET_SPP and (r > TARGET or q > TARGET)]
            result["ood_low_target"][f"{set_name}: {variant}"] = over
    for set_name in ("pd-test-high", "test-chain", "stress"):
        today, option = summary[set_name]["today"], summary[set_name][OPTION]
        top = [crop for crop, (ratio, _) in option["top_pd_over_mc"].items()
               if ratio > today["top_pd_over_mc"][crop][0]]
        result[set_name] = {
            "mean_rmse": (today["mean_rmse"], option["mean_rmse"]),
            "mean_relmse": (today["mean_relmse"], option["mean_relmse"]),
            "top_spp_worse_than_today": top}
    result["small_lights_1024"] = {v: lamps[v][1024]["pd_over_mc"] for v in lamps}
    return result


def table(result: dict) -> str:
    cells, summary, lamps = result["cells"], result["summary"], result["small_lights"]
    names = {**{v: d for v, (d, _) in VARIANTS.items()}, **DERIVED}
    lines = [("## Error guard variants on textured scenes at low spp (ood-low) and the sets it "
              "must not hurt"), "",
             ("PD(OIDN): `oidn-jax` with the shipped `oidn-pd` (per-channel t, error guard), "
              "as `jaxden evaluate pd` runs it; one variant of the guard at a time through "
              "`--tstat`. Ratios PD / OIDN; set columns: ratio of the crop means per spp; "
              "'worst': the worst scene's ratio."), "",
             "| variant | what | " + " | ".join(
                 f"{s} spp RMSE (worst) | {s} spp relMSE (worst)" for s in (4, 8, 16))
             + f" | scene-spp cells over {TARGET} at {' and '.join(map(str, TARGET_SPP))} spp |",
             "|---|---|" + "---:|" * 6 + "---:|"]
    target = result["verdicts"]["ood_low_target"]
    for set_name in ("ood-low", "ood-low-seed1"):
        for variant, entry in summary[set_name].items():
            row = []
            for level in (4, 8, 16):
                e = entry["per_spp"][level]
                row += [f"{e['rmse']:.4f} ({e['worst_rmse']:.3f})",
                        f"{e['relmse']:.4f} ({e['worst_relmse']:.3f})"]
            bold = "**" if variant == OPTION else ""
            label = variant if set_name == "ood-low" else f"{variant}, SURE seed 1"
            lines.append(f"| {bold}{label}{bold} | {names[variant]} | " + " | ".join(row)
                         + f" | {len(target[f'{set_name}: {variant}'])} |")
    lines += ["", "Per scene, PD / OIDN RMSE / relMSE:", "",
              "| variant | scene | 4 spp | 8 spp | 16 spp |", "|---|---|---:|---:|---:|"]
    for variant, by_cell in cells["ood-low"].items():
        for scene in sorted({s for _, s, _ in by_cell}):
            values = {spp: v for (_, s, spp), v in by_cell.items() if s == scene}
            lines.append(f"| {variant} | {scene} | " + " | ".join(
                f"{values[s][0]:.3f} / {values[s][1]:.3f}" for s in (4, 8, 16)) + " |")
    lines += ["", "## Mechanism (ood-low, 4 spp; today's guard against the t-test alone)", "",
              ("Excess: the guard's squared error over the t-test alone's, summed over the "
               "frame, over OIDN's. On the pixels whose cap chi^2 is in [2, 3) (just past "
               "gamma / alpha'): medians of the render's local variance over the true one, x's "
               "local squared error over the true variance, and y's squared error over x's."),
              "",
              ("| scene | t only / OIDN | guard / OIDN | excess | chi^2 < 2 | [2, 3) | [3, 10) "
               "| >= 10 | [2, 3): var / true | (x - ref)^2 / true var | (y - ref)^2 / (x - ref)^2 "
               "|"),
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for m in result["mechanism"]:
        band = m["band_2_3"] or {}
        shares = " | ".join(f"{b['excess_over_den_sse']:+.4f} ({100 * b['pixels']:.1f} %)"
                            for b in m["band_share"].values())
        lines.append(
            f"| {m['scene']} | {m['t_only_over_den'][0]:.3f} / {m['t_only_over_den'][1]:.3f} | "
            f"{m['guard_over_den'][0]:.3f} / {m['guard_over_den'][1]:.3f} | "
            f"{m['excess_over_den_sse']:+.4f} | {shares} | "
            f"{_fmt(band.get('var_over_true'), 2)} | {_fmt(band.get('x_err_over_true'), 2)} | "
            f"{_fmt(band.get('y_err_over_x_err'), 3)} |")
    lines += ["", (f"## Today's guard against the option (`{VARIANTS[OPTION][1][0]}`) on the "
                   "held-out and stress sets (on stress also a looser variance bound)"), "",
              ("Mean over spp of PD / OIDN (ratio of crop means per spp), per spp, and PD / MC "
               "in noise-corrected MSE at the top spp per image (with its noise margin)."), "",
              ("| set | variant | mean RMSE | mean relMSE | per spp RMSE / relMSE (worst image) "
               "| top spp PD / MC per image (margin) |"), "|---|---|---:|---:|---|---|"]
    for set_name in ("pd-test-high", "test-chain", "stress"):
        for variant in SETS[set_name][2]:
            e = summary[set_name][variant]
            per = "; ".join(f"{s}: {v['rmse']:.4f} / {v['relmse']:.4f} ({v['worst_rmse']:.3f} / "
                            f"{v['worst_relmse']:.3f})" for s, v in e["per_spp"].items())
            top = ", ".join(f"{c[:4]} {r:.4f} ({m:.4f})"
                            for c, (r, m) in e["top_pd_over_mc"].items())
            lines.append(f"| {set_name} | {variant} | {e['mean_rmse']:.5f} | "
                         f"{e['mean_relmse']:.5f} | {per} | {top} |")
    lines += ["", "## Small-lights (whole 96 x 96 frame, lamps included)", "",
              "| variant | " + " | ".join(f"{s} spp PD / MC | {s} spp PD / OIDN RMSE | "
                                           f"{s} spp PD / OIDN relMSE" for s in LAMPS["spp"])
              + " |", "|---|" + "---:|" * (3 * len(LAMPS["spp"]))]
    for variant, by_spp in lamps.items():
        lines.append(f"| {variant} | " + " | ".join(
            f"{by_spp[s]['pd_over_mc']:.4f} | {by_spp[s]['pd_over_den_rmse']:.4f} | "
            f"{by_spp[s]['pd_over_den_relmse']:.4f}" for s in LAMPS["spp"]) + " |")
    v = result["verdicts"]
    lines += ["", "## Verdict", ""]
    for key, over in v["ood_low_target"].items():
        if key.split(": ")[1] in ("today", OPTION, "t-test only"):
            variant = key
            lines.append(f"- {variant}: {len(over)} scene-spp cells over {TARGET} "
                         f"at {' and '.join(map(str, TARGET_SPP))} spp"
                         + (f" ({'; '.join(over)})" if over else ""))
    for set_name in ("pd-test-high", "test-chain", "stress"):
        s = v[set_name]
        lines.append(f"- {set_name}: mean PD / OIDN RMSE {s['mean_rmse'][0]:.5f} today, "
                     f"{s['mean_rmse'][1]:.5f} with the option; relMSE {s['mean_relmse'][0]:.5f}"
                     f", {s['mean_relmse'][1]:.5f}; top spp worse than today on "
                     f"{len(s['top_spp_worse_than_today'])} image(s)"
                     + (f" ({', '.join(s['top_spp_worse_than_today'])})"
                        if s["top_spp_worse_than_today"] else ""))
    lines.append(f"- small-lights at 1024 spp, PD / MC: today "
                 f"{v['small_lights_1024']['today']:.4f}, option "
                 f"{v['small_lights_1024'][OPTION]:.4f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from jaxden.provenance import package_version, run_identity, write_result

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="store_true",
                        help="run the missing or out-of-date evaluations first")
    parser.add_argument("--work", type=Path, default=None,
                        help="evaluations folder (default $JAXDEN_HOME/runs/pd-guard-textured)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    work = args.work or _jaxden_home() / "runs" / "pd-guard-textured"
    if args.run:
        for set_name, (_, _, variants, _) in SETS.items():
            for variant in variants:
                evaluate(set_name, variant, work)
    rows = load_rows(work)
    summary = {name: set_summary(by_variant) for name, by_variant in rows.items()}
    cells = {name: cell_ratios(rows[name]) for name in ("ood-low", "ood-low-seed1")}
    lamps = small_lights()
    result = {
        "variants": {v: {"what": d, "tstat": o} for v, (d, o) in VARIANTS.items()},
        "derived": DERIVED,
        "summary": summary,
        "cells": {name: {v: [{"crop": c, "scene": s, "spp": spp, "rmse": r, "relmse": q}
                             for (c, s, spp), (r, q) in by.items()]
                         for v, by in table_.items()}
                  for name, table_ in cells.items()},
        "small_lights": lamps,
        "mechanism": mechanism(),
    }
    result["verdicts"] = verdicts(summary, cells, lamps)
    result["provenance"] = {
        **run_identity(argv), "date": datetime.date.today().isoformat(),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
        "versions": {n: package_version(n) for n in ("jax", "mitsuba")},
        "work": str(work), "denoiser": "oidn-jax", "mixer": "oidn-pd", "lamps": LAMPS}
    # The table reads the cells as {(crop, scene, spp): ...}; the JSON holds them as lists.
    text = table({**result, "cells": cells})
    write_result(args.out, result, text)


if __name__ == "__main__":
    main()
