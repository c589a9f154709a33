"""The progressive-denoising paper's Fig. 11 on jaxden's data: MC, OIDN, the Deep Combiner (DC),
PD(OIDN) and PD(DC) over 2..4096 spp on the held-out set ``data/pd-test-high``.

    python experiments/pd_fig11.py [--home $JAXDEN_HOME] [--out experiments/results/pd/pd-fig11]

Reads the ``jaxden evaluate pd`` results the queue writes under ``$JAXDEN_HOME/runs/pd-fig11``
(experiments/queue.sh, steps ``fig11-*``; each is one command):

- ``pd-oidn``: OIDN in JAX with the shipped mixer ``oidn-pd`` (PD(OIDN) as jaxden ships it);
- ``pd-oidn-closed-form`` and ``pd-dc-s{0,1}``: OIDN in JAX and DC over it (runs
  ``dc-oidn-s0``/``-s1`` of experiments/configs/train-dc.toml, seeds 0 and 1) under the same
  closed-form mixer (the paper's Eq. 9 with local means, no training: no mixer was trained on
  DC), SURE by ``jax.jvp`` from the colour covariance with one probe, per-channel t-statistic.

Writes one table per error (RMSE and relMSE, crop means, linear HDR) with a column per method
and a row per spp, the ratio of each method's RMSE to MC's at the top spp per crop, and the
paper's claims checked on these numbers: DC below PD at low spp and above MC at high spp, and
PD(DC) at or below MC at the top spp on every crop. A result that is missing is named.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
RUNS = {"pd-oidn": "PD(OIDN), shipped mixer", "pd-oidn-closed-form": "PD(OIDN), closed form",
        "pd-dc-s0": "PD(DC), seed 0", "pd-dc-s1": "PD(DC), seed 1"}
#: Columns: (label, run, column prefix of its rows).
COLUMNS = (("MC", "pd-oidn", "mc"), ("OIDN", "pd-oidn", "denoiser"),
           ("DC s0", "pd-dc-s0", "denoiser"), ("DC s1", "pd-dc-s1", "denoiser"),
           ("PD(OIDN)", "pd-oidn", "pd"), ("PD(OIDN) closed form", "pd-oidn-closed-form", "pd"),
           ("PD(DC s0)", "pd-dc-s0", "pd"), ("PD(DC s1)", "pd-dc-s1", "pd"))


def load(folder: Path) -> dict[str, list[dict]]:
    """``{run: rows}`` of the results that exist."""
    out = {}
    for run in RUNS:
        path = folder / f"{run}.json"
        if path.is_file():
            out[run] = json.loads(path.read_text())["rows"]
    return out


def means(rows: list[dict], prefix: str, metric: str) -> dict[int, float]:
    """``{spp: mean over crops}`` of ``<prefix>_<metric>``."""
    by_spp: dict[int, list[float]] = {}
    for row in rows:
        key = f"{prefix}_{metric}"
        if key in row:
            by_spp.setdefault(int(row["spp"]), []).append(float(row[key]))
    return {spp: float(np.mean(v)) for spp, v in sorted(by_spp.items())}


def error_table(runs: dict, metric: str) -> tuple[list[str], dict]:
    present = [(label, runs[run], prefix) for label, run, prefix in COLUMNS if run in runs]
    columns = {label: means(rows, prefix, metric) for label, rows, prefix in present}
    levels = sorted({spp for values in columns.values() for spp in values})
    lines = ["| spp | " + " | ".join(columns) + " |", "|---:|" + "---:|" * len(columns)]
    for spp in levels:
        cells = [f"{columns[label][spp]:.4g}" if spp in columns[label] else ""
                 for label in columns]
        lines.append(f"| {spp} | " + " | ".join(cells) + " |")
    return lines, columns


def top_ratios(runs: dict) -> tuple[list[str], dict]:
    """Per crop at the top spp: each PD's and DC's RMSE over MC's."""
    lines, data = [], {}
    for label, run, prefix in COLUMNS:
        if run not in runs or label == "MC":
            continue
        rows = runs[run]
        top = max(int(r["spp"]) for r in rows)
        ratios = {r["crop"]: r[f"{prefix}_rmse"] / r["mc_rmse"] for r in rows
                  if int(r["spp"]) == top and r["mc_rmse"] > 0}
        data[label] = {"spp": top, "ratios": ratios}
        worst = max(ratios.values())
        above = sum(v > 1.0 for v in ratios.values())
        lines.append(f"| {label} | {top} | {worst:.4f} | {above} of {len(ratios)} |")
    return (["| method | top spp | worst crop RMSE / MC | crops above MC |",
             "|---|---:|---:|---:|", *lines], data)


def claims(columns: dict, data: dict) -> list[str]:
    out = ["## The paper's claims on this data", ""]
    mc, dcs = columns.get("MC"), [c for c in ("DC s0", "DC s1") if c in columns]
    pds = [c for c in ("PD(DC s0)", "PD(DC s1)") if c in columns]
    if not mc or not dcs:
        return out + ["- not measured yet (DC runs missing)"]
    low, high = min(mc), max(mc)
    for dc, pd in zip(dcs, pds):
        out.append(f"- {dc} below PD over it at {low} spp (RMSE): "
                   f"{'yes' if columns[dc][low] < columns[pd][low] else 'no'} "
                   f"({columns[dc][low]:.4g} against {columns[pd][low]:.4g})")
        out.append(f"- {dc} above MC at {high} spp (RMSE): "
                   f"{'yes' if columns[dc][high] > mc[high] else 'no'} "
                   f"({columns[dc][high]:.4g} against MC {mc[high]:.4g})")
    for pd in pds:
        ratios = data[pd]["ratios"]
        worst = max(ratios.values())
        out.append(f"- {pd} at or below MC at the top spp ({data[pd]['spp']}) on every crop: "
                   f"{'met' if worst <= 1.0 else 'NOT met'} (worst crop {worst:.4f}x MC's "
                   f"RMSE, {len(ratios)} crops)")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--home", default=os.environ.get("JAXDEN_HOME", "~/jaxden-work"))
    parser.add_argument("--out", default=str(REPO / "experiments" / "results" / "pd" / "pd-fig11"))
    args = parser.parse_args(argv)
    home = Path(args.home).expanduser()
    runs = load(home / "runs" / "pd-fig11")
    rmse_lines, rmse = error_table(runs, "rmse")
    relmse_lines, relmse = error_table(runs, "relmse")
    ratio_lines, ratios = top_ratios(runs)
    missing = [f"`{run}` ({label})" for run, label in RUNS.items() if run not in runs]
    text = ["<!-- generated by: python experiments/pd_fig11.py -->",
            "# Progressive denoising paper Fig. 11 on jaxden's data: the Deep Combiner", "",
            "Held-out set `data/pd-test-high` (dataset-pd-test-high.toml), every spp level it "
            "has; crop means, linear HDR, against its references. DC: the single-buffer Deep "
            "Combiner over OIDN in JAX (experiments/configs/train-dc.toml, seeds 0 and 1); "
            "PD(DC) and 'PD(OIDN) closed form': the closed-form mixer (Eq. 9, local means), "
            "one jvp probe of the colour covariance, per-channel t-statistic; PD(OIDN): the "
            "shipped `oidn-pd` mixer. Inputs: `$JAXDEN_HOME/runs/pd-fig11/*.json` "
            "(experiments/queue.sh, steps `fig11-*`).", "",
            *(["Missing: " + ", ".join(missing), ""] if missing else []),
            "## RMSE", "", *rmse_lines, "", "## relMSE", "", *relmse_lines, "",
            "## At the top spp, per crop", "", *ratio_lines, "", *claims(rmse, ratios), ""]
    out = Path(args.out)
    out.with_suffix(".md").write_text("\n".join(text))
    out.with_suffix(".json").write_text(json.dumps(
        {"rmse": rmse, "relmse": relmse, "top_ratios": ratios, "missing": missing},
        indent=1, sort_keys=True))
    print(f"wrote {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
