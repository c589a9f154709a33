"""The table of consistent denoisers: MC, OIDN, PD(OIDN), WSKP-6, PD(WSKP-6), the Deep Combiner
and PD(DC) (two seeds), StatMC and its Moon-CI test, on the same images: the held-out crops
(``pd-test-high-stats``), the stress frames (``stress-stats``) and whole 256 x 256 frames
(``frames-stats``), 4..4096 spp (whole frames: 4..1024), every set rendered with StatMC's
per-pixel statistics (``Frame.boxcox``) from the same samples as the colour.

    python experiments/consistent_table.py [--home $JAXDEN_HOME] \
        [--out experiments/results/consistent/consistent-table]

Reads what the queue writes under ``$JAXDEN_HOME/runs/consistent/<set>/`` (experiments/
queue.sh, steps ``consistent-*``; each one command): ``jaxden evaluate pd`` of OIDN in JAX with
the shipped ``oidn-pd`` mixer (MC, OIDN, PD(OIDN)), of WSKP-6 with ``wskp-6-pd``, of the Deep
Combiner runs ``dc-oidn-s{0,1}`` under the closed-form mixer (Eq. 9 alone: no mixer was
trained on DC); ``jaxden evaluate denoise`` of ``statmc``, ``statmc-moon`` and of WSKP-6 with
the lamps taken out before the filter (``wskp-6:emission=separate``); ``jaxden evaluate njs``
of the neural James-Stein combiner runs ``njs-oidn-s{0,1}`` over OIDN in JAX
(``train-njs.toml``; ``njs-wskp6-s{0,1}`` over WSKP-6 on the crops and the stress frames),
whose row at 2s spp combines the set's and its replica's s-spp items (the same number of
samples as MC's row at 2s, from other renders). Times at 1280 x 720 come from the committed
benchmarks (``bench-denoisers.json``, ``bench-progressive.json``), each a ratio to OIDN
measured in the same run.

Writes, per set: RMSE, relMSE and FLIP per spp (means over the images, linear HDR); each
method's RMSE over MC's at the top spp per image (worst, and how many images are above 1);
the every-spp ratio to the better of MC and OIDN (and, for PD(X), of MC and X) per image,
worst over images and spp, in RMSE and relMSE: the bar PD's guard cannot reach (1.05x). A
result that is missing is named, never filled in.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
SETS = {"pd-test-high-stats": "held-out crops (pd-test-high, 8 procedural scenes, 96 x 96)",
        "stress-stats": "stress frames (8 scenes: small lamps, glints, caustics; 96 x 96)",
        "frames-stats": "whole frames (8 scenes of the offline table, 256 x 256)"}
#: Columns: (label, result file, column prefix of its rows, base label for PD's bar or None).
METHODS = (("MC", "pd-oidn", "mc", None), ("OIDN", "pd-oidn", "denoiser", None),
           ("PD(OIDN)", "pd-oidn", "pd", "OIDN"),
           ("WSKP-6", "pd-wskp6", "denoiser", None),
           ("WSKP-6 (emission separate)", "wskp6-separate", "den", None),
           ("PD(WSKP-6)", "pd-wskp6", "pd", "WSKP-6"),
           ("DC s0", "pd-dc-s0", "denoiser", None), ("PD(DC s0)", "pd-dc-s0", "pd", "DC s0"),
           ("DC s1", "pd-dc-s1", "denoiser", None), ("PD(DC s1)", "pd-dc-s1", "pd", "DC s1"),
           ("StatMC", "statmc", "den", None), ("StatMC (Moon CI)", "statmc-moon", "den", None),
           ("NJS(OIDN) s0", "njs-s0", "den", "OIDN"), ("NJS(OIDN) s1", "njs-s1", "den", "OIDN"),
           ("NJS(WSKP-6) s0", "njs-wskp6-s0", "den", "WSKP-6"),
           ("NJS(WSKP-6) s1", "njs-wskp6-s1", "den", "WSKP-6"))
METRICS = (("rmse", "RMSE"), ("relmse", "relMSE"), ("flip", "FLIP"))
#: Not measured on these sets yet, with why (named in every table's notes).
NOT_RUN = {"Neural kernel regression (SIGGRAPH Asia 2024)":
           "only its abstract is public (no code, architecture, bandwidth constraint or "
           "training recipe; docs/results.md, \"Consistent denoisers\")"}


def load(folder: Path) -> dict[str, list[dict]]:
    """``{result: rows}`` of the result files that exist in ``folder``."""
    out = {}
    for name in dict.fromkeys(m[1] for m in METHODS):
        path = folder / f"{name}.json"
        if path.is_file():
            out[name] = json.loads(path.read_text())["rows"]
    return out


def per_image(rows: list[dict], prefix: str, metric: str) -> dict[tuple[str, int], float]:
    """``{(crop, spp): value}`` of ``<prefix>_<metric>``."""
    return {(r["crop"], int(r["spp"])): float(r[f"{prefix}_{metric}"]) for r in rows
            if r.get(f"{prefix}_{metric}") is not None}


def method_values(results: dict, metric: str) -> dict[str, dict[tuple[str, int], float]]:
    """``{method: {(crop, spp): value}}`` for the methods whose results exist. MC comes from
    the first ``evaluate pd`` result present, else StatMC's ``evaluate denoise`` (every one
    scores the same noisy input)."""
    out = {}
    for label, name, prefix, _ in METHODS:
        if label == "MC":
            for source in ("pd-oidn", "pd-wskp6", "pd-dc-s0", "pd-dc-s1", "statmc"):
                values = per_image(results.get(source, []), "mc", metric)
                if values:
                    out[label] = values
                    break
            continue
        if name in results:
            values = per_image(results[name], prefix, metric)
            if values:
                out[label] = values
    return out


def fmt(value: float | None) -> str:
    if value is None or not np.isfinite(value):
        return "-"
    return f"{value:.4g}"


def spp_table(values: dict, metric_label: str) -> list[str]:
    levels = sorted({spp for v in values.values() for _, spp in v})
    labels = list(values)
    lines = [f"| spp | {' | '.join(labels)} |", "|---:|" + "---:|" * len(labels)]
    for spp in levels:
        cells = []
        row_means = {}
        for label in labels:
            got = [v for (c, s), v in values[label].items() if s == spp]
            row_means[label] = float(np.mean(got)) if got else None
        best = min((v for v in row_means.values() if v is not None), default=None)
        for label in labels:
            text = fmt(row_means[label])
            cells.append(f"**{text}**" if row_means[label] is not None
                         and row_means[label] == best else text)
        lines.append(f"| {spp} | {' | '.join(cells)} |")
    return [f"{metric_label}, mean over the images:", "", *lines, ""]


def top_spp_ratios(values: dict) -> dict[str, dict]:
    """Each method's value over MC's at the top spp, per image: worst and count above 1."""
    mc = values.get("MC", {})
    top = max((s for _, s in mc), default=None)
    out = {}
    for label, vals in values.items():
        if label == "MC" or top is None:
            continue
        ratios = [vals[(c, s)] / mc[(c, s)] for (c, s) in mc if s == top and (c, s) in vals
                  and mc[(c, s)] > 0]
        if ratios:
            out[label] = {"top_spp": top, "worst": max(ratios), "above": sum(r > 1 for r in ratios),
                          "images": len(ratios)}
    return out


def every_spp_bar(values: dict, label: str, base: str) -> dict | None:
    """``label``'s worst ratio over images and spp to min(MC, ``base``) of the same image."""
    mc, own, ref = values.get("MC"), values.get(label), values.get(base)
    if not (mc and own and ref):
        return None
    ratios = {key: own[key] / min(mc[key], ref[key]) for key in own
              if key in mc and key in ref and min(mc[key], ref[key]) > 0}
    if not ratios:
        return None
    worst = max(ratios, key=ratios.get)
    return {"worst": ratios[worst], "at": list(worst),
            "over_1_05": sum(r > 1.05 for r in ratios.values()), "cells": len(ratios)}


def timings() -> dict[str, float]:
    """``{method: seconds over OIDN's}`` at 1280 x 720 from the committed benchmarks."""
    out: dict[str, float] = {}
    bench = REPO / "experiments/results/bench"
    denoisers = bench / "bench-denoisers.json"
    if denoisers.is_file():
        d = json.loads(denoisers.read_text())
        oidn = d.get("oidn_s") or (d["wskp6_s"] * d["oidn_over_wskp6"]
                                   if "oidn_over_wskp6" in d else None)
        for label, key in (("WSKP-6", "wskp6_s"), ("DC s0", "dc_s"), ("StatMC", "statmc_s"),
                           ("StatMC (Moon CI)", "statmc_moon_s"),
                           ("NJS(OIDN), per image of two half buffers", "njs_s")):
            if oidn and key in d:
                out[label] = d[key] / oidn
    progressive = bench / "bench-progressive.json"
    if progressive.is_file():
        d = json.loads(progressive.read_text())
        if "pd_oidnjax_over_oidn" in d:
            out["PD(OIDN)"] = d["pd_oidnjax_over_oidn"]
        if "pd_wskp6_s" in d and "oidn_s" in d:
            out["PD(WSKP-6)"] = d["pd_wskp6_s"] / d["oidn_s"]
    out["OIDN"] = 1.0
    return out


def report(home: Path) -> tuple[str, dict]:
    lines = ["<!-- generated by: python experiments/consistent_table.py -->",
             "## Consistent denoisers on one data: MC, OIDN, PD, the Deep Combiner, StatMC", ""]
    summary: dict = {"sets": {}, "times_over_oidn": timings(), "not_run": NOT_RUN}
    for name, description in SETS.items():
        folder = home / "runs" / "consistent" / name
        results = load(folder)
        lines += [f"### {description} (`{name}`)", ""]
        missing = [label for label, result, _, _ in METHODS
                   if label != "MC" and result not in results]
        if not results:
            lines += [(f"No results yet under `{folder}` (experiments/queue.sh, steps "
                       f"`consistent-{name}-*`)."), ""]
            summary["sets"][name] = {"missing": "all"}
            continue
        entry: dict = {"missing": missing}
        for metric, label in METRICS:
            values = method_values(results, metric)
            lines += spp_table(values, label)
            entry[metric] = {"top_spp_over_mc": top_spp_ratios(values),
                             "every_spp_over_min_mc_oidn": {
                                 m: every_spp_bar(values, m, "OIDN") for m in values
                                 if m not in ("MC", "OIDN")},
                             "every_spp_over_min_mc_base": {
                                 m: every_spp_bar(values, m, base)
                                 for m, _, _, base in METHODS if base and m in values}}
        lines += ["Top spp, RMSE over MC's per image (worst; images above 1):", "",
                  "| method | worst | above 1 |", "|---|---:|---:|"]
        for m, r in entry["rmse"]["top_spp_over_mc"].items():
            lines.append(f"| {m} | {r['worst']:.4f} | {r['above']} of {r['images']} |")
        lines += ["", ("Every spp, worst ratio per image to the better of MC and the base "
                       "(RMSE / relMSE; cells above 1.05):"), "",
                  "| method | vs min(MC, OIDN) | vs min(MC, its base) |", "|---|---:|---:|"]
        for m in entry["rmse"]["every_spp_over_min_mc_oidn"]:
            cells = []
            for key in ("every_spp_over_min_mc_oidn", "every_spp_over_min_mc_base"):
                parts = []
                for metric in ("rmse", "relmse"):
                    bar = entry[metric][key].get(m)
                    parts.append("-" if bar is None else
                                 f"{bar['worst']:.3f} ({bar['over_1_05']}/{bar['cells']})")
                cells.append(" / ".join(parts))
            lines.append(f"| {m} | {cells[0]} | {cells[1]} |")
        if missing:
            lines += ["", f"Not in this set yet: {', '.join(missing)}."]
        lines.append("")
        summary["sets"][name] = entry
    times = summary["times_over_oidn"]
    lines += ["### Time at 1280 x 720, over OIDN's (CPU, each ratio from one benchmark run)", "",
              "| method | time / OIDN |", "|---|---:|"]
    lines += [f"| {m} | {t:.3g} |" for m, t in times.items()]
    lines += ["", "Not run: " + "; ".join(f"{k}: {v}" for k, v in NOT_RUN.items()) + ".", ""]
    return "\n".join(lines), summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--home", default=os.environ.get("JAXDEN_HOME",
                                                         str(Path.home() / "jaxden-work")))
    parser.add_argument("--out", default=str(REPO / "experiments/results/consistent/"
                                             "consistent-table"))
    args = parser.parse_args(argv)
    text, summary = report(Path(args.home))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(text)
    out.with_suffix(".json").write_text(json.dumps(summary, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
