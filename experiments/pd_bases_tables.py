"""The progressive-denoising paper's Tables 1, 2 and 4 and its convergence plots on jaxden's
data, from the PD-bases sweeps' results.

    python experiments/pd_bases_tables.py [--home $JAXDEN_HOME] [--out experiments/results/pd]

Reads ``runs/sweeps/pd-mixers/*/result.json`` under ``$JAXDEN_HOME`` (whatever runs have
finished; missing ones are listed as such): one mixer per base of
``experiments/sweeps/pd-bases.toml`` and its PD report on ``data/pd-test-high`` (32..4096 spp,
crop means per spp), and writes:

- ``pd-table1.md`` / ``.json``: Table 1: each U-Net feature set, den against PD: RMSE,
  noise-corrected RMSE, relMSE and FLIP averaged over spp, and PD / den in the paper's form
  (the ratio of the spp-averaged errors) and as the mean of the per-spp ratios; KP (Table 2)
  and WSKP-6 with the same columns; whether PD is at or below MC at the top spp on every crop;
- ``pd-table4.md``: Table 4: RMSE per spp of the mixer of the full-feature U-Net with the
  paper's f_act head, without SURE, without f_act, without the t-test, with our
  closed_form_logit head, the denoiser alone and MC;
- ``pd-convergence-bases.svg`` / ``.json``: RMSE against spp (log-log) of MC, each base and
  PD over it.

Targets (issue text): PD(U-Net) RMSE at most 0.6 of the U-Net's own averaged over 32..4096
spp for every feature set (paper: 0.40-0.57), PD(KP) reported, PD at or below MC's RMSE at
the top spp for every crop and base.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
SWEEP = "pd-mixers"
#: The same mixers with SURE from the colour covariance (pd-mixers-cov.toml): extra PD rows.
SWEEP_COV = "pd-mixers-cov"
#: Eq. 9 alone (the closed-form mixer, no network) over each base with SURE from the colour
#: covariance: `jaxden evaluate pd` results under $JAXDEN_HOME/runs/pd-closed-form (queue.sh).
CLOSED_FORM = "runs/pd-closed-form"
#: (run name, inputs / base label, table) of the bases, in the paper's order.
BASES = (("unet-hdr", "U-Net: HDR", 1), ("unet-hdr-var", "U-Net: HDR, VAR", 1),
         ("unet-hdr-alb-nrm", "U-Net: HDR, ALB, NRM", 1),
         ("unet-hdr-alb-nrm-var", "U-Net: HDR, ALB, NRM, VAR", 1),
         ("kp5", "KP, 5 x 5 kernels (the paper's KPCN)", 2),
         ("wskp6", "WSKP-6 (trained on PD data)", 2))
#: Table 4's rows: (label, run, method key in the report).
TABLE4 = (("w/o SURE (f_act head)", "t4-no-sure", "pd"),
          ("w/o f_act (sigmoid alpha)", "t4-no-f_act", "pd"),
          ("w/o t-test (f_act head)", "t4-full", "mixed"),
          ("pro-den (f_act head, the paper's)", "t4-full", "pd"),
          ("pro-den (closed_form_logit head, ours)", "unet-hdr-alb-nrm-var", "pd"),
          ("den (U-Net: HDR, ALB, NRM, VAR)", "same-base", "denoiser"),
          ("mc-render", "same-base", "mc"))
#: The runs over Table 4's base: any of them gives its den and MC rows (same base, same data).
SAME_BASE = ("unet-hdr-alb-nrm-var", "t4-full", "t4-no-sure", "t4-no-f_act")
METRICS = (("rmse", "RMSE"), ("rmse_nc", "RMSE (noise-corr.)"), ("relmse", "relMSE"),
           ("flip", "FLIP"))
TARGET_RATIO = 0.6
#: The mixers over each base: (key in pd-table1.json, row label, where their evaluations are).
VARIANTS = (("pd", "PD", SWEEP), ("covariance_sure", "PD, covariance SURE", SWEEP_COV),
            ("closed_form", "Eq. 9 alone, covariance SURE", CLOSED_FORM))


def load_results(home: Path, sweep: str = SWEEP) -> dict[str, dict]:
    """``{run name: its PD evaluation}`` for every finished run of the pd-mixers sweep (the
    first ``pd:`` evaluation of its result.json)."""
    out = {}
    for path in sorted((home / "runs" / "sweeps" / sweep).glob("*/result.json")):
        result = json.loads(path.read_text())
        for name, value in result.get("evaluations", {}).items():
            if name.startswith("pd:"):
                out[result["run"]] = {**value, "dataset": name[3:]}
                break
    return out


def load_reports(home: Path, folder: str = CLOSED_FORM) -> dict[str, dict]:
    """``{base run name: the summary of its `jaxden evaluate pd` JSON}`` for the reports in
    ``home / folder`` (named after the base's run)."""
    out = {}
    for path in sorted((home / folder).glob("*.json")):
        report = json.loads(path.read_text())
        dataset = report["provenance"]["dataset"]
        out[path.stem] = {**report["summary"], "dataset": str(
            dataset.get("path") if isinstance(dataset, dict) else dataset)}
    return out


def _levels(evaluation: dict) -> list[tuple[int, dict]]:
    return sorted((int(level), means) for level, means in evaluation["per_spp"].items())


def averaged(evaluation: dict, method: str, metric: str) -> float:
    """The crop-mean error of ``method`` averaged over the spp levels (the paper's Table 1)."""
    return float(np.mean([m[f"{method}_{metric}"] for _, m in _levels(evaluation)]))


def base_row(evaluation: dict) -> dict:
    """Table 1's numbers for one base: den and PD averaged over spp, the two ratio forms, and
    the worst crop's PD / MC RMSE at the top spp."""
    row = {}
    for metric, _ in METRICS:
        den, pd = averaged(evaluation, "denoiser", metric), averaged(evaluation, "pd", metric)
        row[metric] = {"den": den, "pd": pd, "ratio_of_averages": pd / den,
                       "mean_ratio": evaluation["headline"]["pd_over_denoiser"][metric]}
    crops = evaluation.get("per_crop", {})
    row["worst_crop_pd_over_mc_at_top"] = (
        max(c["pd_over_mc_rmse_at_max_spp"] for c in crops.values()) if crops else None)
    row["pd_over_mc_at_top"] = evaluation["headline"]["pd_over_mc_at_max_spp"]["rmse"]
    row["spp"] = [level for level, _ in _levels(evaluation)]
    row["crops"] = evaluation["crops"]
    # Bounds, RMSE as mean per-spp ratios to den (reports from before a row existed lack it):
    # PD fed the true error of den in place of SURE, and the 8 x 8-tile oracle mix.
    headline = evaluation["headline"]
    row["bounds"] = {key: headline[f"{key}_over_denoiser"]["rmse"]
                     for key in ("pd", "pd_true_sure", "oracle")
                     if f"{key}_over_denoiser" in headline}
    return row


def bounds_lines(data: dict[str, dict]) -> list[str]:
    """What a perfect SURE and the oracle would give, per base and mixer: RMSE over den (mean
    of the per-spp ratios) and the share of the oracle's gain over den that PD reaches."""
    rows = [(label, name, data[run][key]["bounds"]) for run, label, _ in BASES if run in data
            for key, name, _ in VARIANTS
            if key in data[run] and {"pd", "oracle"} <= set(data[run][key]["bounds"])]
    if not rows:
        return []
    lines = ["", "## Against the bounds", "",
             ("RMSE over den, mean of the per-spp ratios. PD fed the true error: the same mixer "
              "and t-statistic with the reference's per-pixel squared error of den (less the "
              "reference's variance) in place of SURE, i.e. what a perfect SURE would give. "
              "Oracle: one alpha per 8 x 8 tile and channel fitted to the reference. Both read "
              "the reference: bounds, not methods."), "",
             ("| base | mixer | PD | PD fed the true error | oracle | PD's share of the "
              "oracle's gain |"),
             "|---|---|---:|---:|---:|---:|"]
    for label, name, b in rows:
        true = b.get("pd_true_sure")
        gain = 1.0 - b["oracle"]
        share = (1.0 - b["pd"]) / gain if gain > 0 else float("nan")
        lines.append(f"| {label} | {name} | {b['pd']:.3f} | "
                     + ("-" if true is None else f"{true:.3f}")
                     + f" | {b['oracle']:.3f} | {share:.0%} |")
    return lines


def _verdict(value: float, target: float, better: str = "<=") -> str:
    ok = value <= target if better == "<=" else value >= target
    return "met" if ok else "NOT met"


def pd_line(table: int, model: str, row: dict, den_row: dict) -> str:
    """A PD row of Table 1: each metric's spp-averaged PD error, its ratio to ``den_row``'s
    den (the paper's form) and the mean per-spp ratio; PD / MC at the top spp."""
    worst = row["worst_crop_pd_over_mc_at_top"]
    return (f"| {table} | | {model} | "
            + " | ".join(f"{row[m]['pd']:.5f} ({row[m]['pd'] / den_row[m]['den']:.3f}x; "
                         f"{row[m]['mean_ratio']:.3f}x)" for m, _ in METRICS)
            + f" | {row['pd_over_mc_at_top']:.3f}; "
            + ("-" if worst is None else f"{worst:.4f}") + " |")


def variant_targets(data: dict[str, dict]) -> list[str]:
    """The issue's targets, judged for each mixer over the bases it has run on."""
    targets = []
    unets = [run for run, _, table in BASES if table == 1]
    for key, name, _ in VARIANTS:
        done = [run for run in unets if key in data.get(run, {})]
        if done:
            worst = max(data[run][key]["rmse"]["ratio_of_averages"] for run in done)
            targets.append(f"- {name}: PD(U-Net) RMSE at most {TARGET_RATIO} of the U-Net's "
                           f"own, averaged over 32..4096 spp, for every feature set (paper: "
                           f"0.40-0.57): worst {worst:.3f} over {len(done)} of {len(unets)} "
                           f"feature sets: {_verdict(worst, TARGET_RATIO)}"
                           + ("" if len(done) == len(unets) else " so far") + ".")
        tops = [(run, data[run][key]["worst_crop_pd_over_mc_at_top"]) for run in data
                if key in data[run] and data[run][key]["worst_crop_pd_over_mc_at_top"] is not None]
        if tops:
            run, worst = max(tops, key=lambda t: t[1])
            targets.append(f"- {name}: PD at or below MC's RMSE at the top spp for every crop "
                           f"and base: worst crop {worst:.4f} (base {run}) over {len(tops)} of "
                           f"{len(BASES)} bases: {_verdict(worst, 1.0)}"
                           + ("" if len(tops) == len(BASES) else " so far") + ".")
        if key in data.get("kp5", {}):
            targets.append(f"- {name}: PD(KP) reported: PD / den RMSE "
                           f"{data['kp5'][key]['rmse']['ratio_of_averages']:.3f}.")
    return targets


def table1(sources: dict[str, dict[str, dict]]) -> tuple[str, dict]:
    """Table 1 (and 2) from ``sources``: ``{variant key: {base run: PD evaluation}}``, for the
    keys of :data:`VARIANTS`; a base is listed with whatever mixers have run over it."""
    lines = [(f"<!-- generated by: python experiments/pd_bases_tables.py "
              f"(from $JAXDEN_HOME/runs/sweeps/{SWEEP}/*/result.json, "
              f"$JAXDEN_HOME/runs/sweeps/{SWEEP_COV}/*/result.json and "
              f"$JAXDEN_HOME/{CLOSED_FORM}/*.json) -->"),
             "# PD paper Tables 1 and 2 on our data: den against PD per base",
             "",
             ("Each base is trained on `data/pd-rt` (2..1024 spp, 4000 steps, "
              "`experiments/sweeps/pd-bases.toml`) and mixed by its own mixer, trained on "
              "`data/pd-rt4k` (2..4096 spp) with the `wskp-6-pd` recipe (jvp SURE with one "
              "probe, width 16, closed_form_logit head). \"PD\": the paper's per-channel SURE "
              "(`experiments/sweeps/pd-mixers.toml`); \"PD, covariance SURE\": SURE from the "
              "colour covariance (`pd-mixers-cov.toml`); \"Eq. 9 alone\": the closed-form "
              "mixer, no network (the paper's Eq. 9 with local means, sigma 12, per-channel t), "
              "on SURE from the covariance (`$JAXDEN_HOME/runs/pd-closed-form`, steps "
              "`pd-closed-form-BASE` of `queue.sh`). Errors on `data/pd-test-high` (8 held-out "
              "procedural crops of 96 x 96, 32..4096 spp, 8192-spp references), crop means "
              "averaged over spp. PD / den: the ratio of the spp-averaged errors (the paper's "
              "table form) and, in brackets, the mean of the per-spp ratios. The MC row (the "
              "noisy input, the same for every base) tells how much each base gains before "
              "mixing: a base near MC leaves PD little to do but also makes PD / den easy."),
             "",
             "| table | base | model | " + " | ".join(label for _, label in METRICS)
             + " | PD / MC, RMSE at the top spp (crop mean; worst crop) |",
             "|---|---|---|" + "---:|" * len(METRICS) + "---:|"]
    data, missing = {}, []
    available = [ev for key, _, _ in VARIANTS for ev in sources.get(key, {}).values()]
    if available:  # MC is the same input for every base: any evaluation gives it
        lines.append("| | MC (the input) | MC | "
                     + " | ".join(f"{averaged(available[0], 'mc', m):.5f}" for m, _ in METRICS)
                     + " | 1 |")
    for run, label, table in BASES:
        evaluations = [(key, name, sources[key][run]) for key, name, _ in VARIANTS
                       if run in sources.get(key, {})]
        if not evaluations:
            missing.append(run)
            lines.append(f"| {table} | {label} | not run |" + " |" * len(METRICS) + " |")
            continue
        # den is the base alone on the same data: the same in every evaluation of the base
        den = {m: {"den": averaged(evaluations[0][2], "denoiser", m)} for m, _ in METRICS}
        data[run] = {"den": {m: den[m]["den"] for m, _ in METRICS}}
        lines.append(f"| {table} | {label} | den | "
                     + " | ".join(f"{den[m]['den']:.5f}" for m, _ in METRICS) + " | |")
        for key, name, evaluation in evaluations:
            row = data[run][key] = base_row(evaluation)
            lines.append(pd_line(table, name, row, den))
    lines += bounds_lines(data)
    targets = variant_targets(data)
    lines += ["", "## Targets", ""] + (targets or ["- no run has finished yet"])
    if missing:
        lines += ["", "Not run yet: " + ", ".join(missing) + "."]
    return "\n".join(lines) + "\n", {"rows": data, "missing": missing, "targets": targets}


def table4(results: dict[str, dict]) -> str:
    lines = [(f"<!-- generated by: python experiments/pd_bases_tables.py "
              f"(from $JAXDEN_HOME/runs/sweeps/{SWEEP}/*/result.json) -->"),
             "# PD paper Table 4 on our data: ablations per spp (RMSE, crop mean)",
             "",
             ("The U-Net with HDR, ALB, NRM and VAR as the base (`pd-bases.toml`), mixers "
              "trained with the paper's f_act head (t4-* rows of `pd-mixers.toml`; w/o SURE drops "
              "SURE and its divergence from the inputs; w/o f_act predicts alpha through a "
              "sigmoid); w/o t-test is the f_act mixer's output before the t-statistic scaling. "
              "`data/pd-test-high`, 8 crops.")]
    done = [run for run in SAME_BASE if run in results]
    if not done:
        return "\n".join(lines + ["", "No run has finished yet."]) + "\n"
    levels = [level for level, _ in _levels(results[done[0]])]
    lines += ["", "| | " + " | ".join(str(s) for s in levels) + " |",
              "|---|" + "---:|" * len(levels)]
    for label, run, method in TABLE4:
        run = done[0] if run == "same-base" else run
        if run not in results:
            lines.append(f"| {label} | not run |" + " |" * (len(levels) - 1))
            continue
        means = dict(_levels(results[run]))
        lines.append(f"| {label} | " + " | ".join(f"{means[s][f'{method}_rmse']:.5f}"
                                                 for s in levels) + " |")
    return "\n".join(lines) + "\n"


def convergence(sources: dict[str, dict[str, dict]]) -> tuple[str, dict]:
    """One log-log RMSE panel per base with any mixer: MC, the base, PD over it per mixer."""
    from jaxden.evaluate.plot import svg_plot

    legends = {"pd": ("PD(base)", "#d62728"),
               "covariance_sure": ("PD(base), covariance SURE", "#2ca02c"),
               "closed_form": ("Eq. 9 alone over the base, covariance SURE", "#9467bd")}
    curves, panels, shown = {}, [], set()
    for run, label, _ in BASES:
        evaluations = {key: sources[key][run] for key, _, _ in VARIANTS
                       if run in sources.get(key, {})}
        if not evaluations:
            continue
        levels = _levels(next(iter(evaluations.values())))
        curves[run] = {key: [(s, m[f"{key}_rmse"]) for s, m in levels]
                       for key in ("mc", "denoiser")}
        for key, _, _ in VARIANTS:
            curves[run][key] = ([(s, m["pd_rmse"]) for s, m in _levels(evaluations[key])]
                                if key in evaluations else [])
        shown |= set(evaluations)
        panels.append((run, label.split(" (")[0]))
    methods = (("mc", "MC", "#7f7f7f"), ("denoiser", "den (the base)", "#1f77b4"),
               *((key, *legends[key]) for key, _, _ in VARIANTS if key in shown))
    if not panels:
        return "", curves
    return svg_plot(curves, "RMSE against spp on pd-test-high (crop means)", panels=panels,
                    methods=methods, dashed=()), curves


def main(argv=None) -> int:
    from jaxden.fileio import atomic_write_text
    from jaxden.paths import jaxden_home

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--home", type=Path, default=None, help="default $JAXDEN_HOME")
    parser.add_argument("--out", type=Path, default=REPO / "experiments" / "results" / "pd")
    args = parser.parse_args(argv)
    home = args.home or jaxden_home()
    results = load_results(home)
    sources = {"pd": results, "covariance_sure": load_results(home, SWEEP_COV),
               "closed_form": load_reports(home)}
    args.out.mkdir(parents=True, exist_ok=True)
    text, data = table1(sources)
    atomic_write_text(args.out / "pd-table1.md", text)
    atomic_write_text(args.out / "pd-table1.json", json.dumps(
        {**data, "sources": {key: where for key, _, where in VARIANTS},
         "datasets": sorted({r["dataset"] for runs in sources.values() for r in runs.values()})},
        indent=1) + "\n")
    if any(run in results for run in SAME_BASE):  # else the current file stays as it is
        atomic_write_text(args.out / "pd-table4.md", table4(results))
    svg, curves = convergence(sources)
    if svg:
        atomic_write_text(args.out / "pd-convergence-bases.svg", svg)
        atomic_write_text(args.out / "pd-convergence-bases.json",
                          json.dumps({"curves": curves}, indent=1) + "\n")
    table4_written = any(run in results for run in SAME_BASE)
    print(f"wrote pd-table1.md{', pd-table4.md' if table4_written else ''}"
          f"{', pd-convergence-bases.svg' if svg else ''} "
          f"into {args.out} from " + ", ".join(f"{len(sources[key])} {name!r}"
                                              for key, name, _ in VARIANTS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
