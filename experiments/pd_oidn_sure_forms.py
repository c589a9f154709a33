"""Progressive denoising of OIDN with its two forms of SURE side by side: finite differences of
the C++ OIDN (4 probes, 5 pyoidn calls) and the exact divergence by ``jax.jvp`` of OIDN-JAX
(K = 1 and 4 normal probes, K = 1 Rademacher probe), the shipped ``oidn-pd`` mixer over each,
and one Rademacher probe into a mixer trained on such SURE, on the same held-out sets.

    python experiments/pd_oidn_sure_forms.py [--results experiments/results/pd]
        [--out experiments/results/pd/pd-oidn-sure-forms]

Reads the ``jaxden evaluate pd`` reports (``REPORT.json``) named in :data:`SETS` from
``--results`` (``experiments/queue.sh`` makes the jvp ones, steps ``pd-oidnjax-*``) and writes
one table per set: per spp, the RMSE and relMSE of OIDN and of PD with each SURE form, then the
headline ratios over spp (PD / OIDN, averaged as the reports average them) and PD / MC at the
top spp (crop mean and worst crop). OIDN-JAX's output is within 4e-6 relative RMSE of pyoidn's
(``oidn/oidn-jax-closeness.md``), so the denoiser columns are the same image to the digits
shown and the PD columns differ by SURE alone. A report of another dataset build than its
set's first is refused: the forms must be compared on one build.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
#: The last form: one Rademacher jvp probe into a mixer trained on such SURE
#: (configs/mixer-oidnjax-k1.toml, with oidn-pd's inference overrides), not oidn-pd.
K1_MIXER = "jvp, OIDN-JAX, K = 1 Rademacher, mixer trained on it"
K1_RADEMACHER = "jvp, OIDN-JAX, K = 1 Rademacher"
#: (set label, [(SURE form label, report stem)]): the first report of a set is the reference.
SETS = (
    ("test (8 crops, 2..1024 spp)", (
        ("finite differences, C++ OIDN, K = 4", "pd-oidn-test-shipped"),
        ("jvp, OIDN-JAX, K = 4", "pd-oidnjax-test"),
        ("jvp, OIDN-JAX, K = 1", "pd-oidnjax-k1-test"),
        (K1_RADEMACHER, "pd-oidnjax-k1rad-test"),
        (K1_MIXER, "pd-oidnjax-k1mixer-test"))),
    ("test-high (8 crops, 32..4096 spp)", (
        ("finite differences, C++ OIDN, K = 4", "pd-oidn-test-high-shipped"),
        ("jvp, OIDN-JAX, K = 4", "pd-oidnjax-test-high"),
        ("jvp, OIDN-JAX, K = 1", "pd-oidnjax-k1-test-high"),
        (K1_RADEMACHER, "pd-oidnjax-k1rad-test-high"),
        (K1_MIXER, "pd-oidnjax-k1mixer-test-high"))),
)


def spp_means(report: dict, key: str) -> dict[int, float]:
    """Crop mean of ``key`` per spp level."""
    sums: dict[int, list[float]] = {}
    for row in report["rows"]:
        sums.setdefault(int(row["spp"]), []).append(float(row[key]))
    return {spp: sum(values) / len(values) for spp, values in sorted(sums.items())}


def worst_crop_at_top(report: dict) -> float:
    """The largest PD / MC RMSE over crops at the report's top spp."""
    return max(crop["pd_over_mc_rmse_at_max_spp"]
               for crop in report["summary"]["per_crop"].values())


def load(results: Path, stem: str) -> dict | None:
    path = results / f"{stem}.json"
    return json.loads(path.read_text()) if path.exists() else None


def set_table(label: str, forms, reports: dict) -> tuple[list[str], dict]:
    present = [(name, stem) for name, stem in forms if reports.get(stem)]
    lines = [f"## {label}", ""]
    if not present:
        return lines + ["No report yet.", ""], {}
    first = reports[present[0][1]]
    build = first["provenance"]["dataset"]["manifest_sha256"]
    for name, stem in present[1:]:
        other = reports[stem]["provenance"]["dataset"]["manifest_sha256"]
        if other != build:
            raise SystemExit(f"{stem}.json was measured on another build of "
                             f"{first['provenance']['dataset']['dir']} than "
                             f"{present[0][1]}.json ({other[:12]} vs {build[:12]})")
    missing = [stem for _, stem in forms if not reports.get(stem)]
    den = {m: spp_means(first, f"denoiser_{m}") for m in ("rmse", "relmse")}
    pd = {stem: {m: spp_means(reports[stem], f"pd_{m}") for m in ("rmse", "relmse")}
          for _, stem in present}
    header = "| spp | OIDN RMSE | " + " | ".join(f"PD RMSE: {n}" for n, _ in present) + \
        " | OIDN relMSE | " + " | ".join(f"PD relMSE: {n}" for n, _ in present) + " |"
    lines += [header, "|---:|" + "---:|" * (2 + 2 * len(present))]
    for spp in den["rmse"]:
        cells = [f"{den['rmse'][spp]:.5f}"] + [f"{pd[s]['rmse'][spp]:.5f}" for _, s in present]
        cells += [f"{den['relmse'][spp]:.5f}"] + [f"{pd[s]['relmse'][spp]:.5f}"
                                                   for _, s in present]
        lines.append(f"| {spp} | " + " | ".join(cells) + " |")
    lines += ["", "| SURE form | PD / OIDN: RMSE | relMSE | FLIP | PD / MC RMSE at the top "
              "spp: crop mean | worst crop | report |", "|---|---:|---:|---:|---:|---:|---|"]
    summary = {}
    for name, stem in present:
        head = reports[stem]["summary"]["headline"]
        ratio = head["pd_over_denoiser"]
        top = head["pd_over_mc_at_max_spp"]["rmse"]
        worst = worst_crop_at_top(reports[stem])
        summary[stem] = {"form": name, "pd_over_denoiser": ratio, "pd_over_mc_at_max_spp": top,
                         "worst_crop_pd_over_mc_at_max_spp": worst,
                         "probes": reports[stem]["provenance"]["probes"],
                         "denoiser": reports[stem]["provenance"]["denoiser"],
                         "commit": reports[stem]["provenance"]["commit"]}
        lines.append(f"| {name} | {ratio['rmse']:.3f} | {ratio['relmse']:.3f} | "
                     f"{ratio['flip']:.3f} | {top:.3f} | {worst:.4f} | `pd/{stem}` |")
    if missing:
        lines += ["", "Not measured yet: " + ", ".join(f"`{m}`" for m in missing) + "."]
    return lines + [""], {"dataset": first["provenance"]["dataset"], "forms": summary,
                          "missing": missing}


def main(argv: list[str] | None = None) -> int:
    from jaxden.provenance import run_identity, write_result

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, default=REPO / "experiments/results/pd")
    parser.add_argument("--out", type=Path,
                        default=REPO / "experiments/results/pd/pd-oidn-sure-forms")
    args = parser.parse_args(argv)
    lines = ["# PD(OIDN): SURE by finite differences of the C++ OIDN against SURE by jvp of "
             "OIDN-JAX", "",
             "The shipped `oidn-pd` mixer (its inference overrides: closed_form_stops = 1, "
             "per-channel t) over OIDN with HDR + albedo + normal; crop means over 8 held-out "
             "crops per spp. PD / OIDN: the reports' headline ratio over spp; K: SURE probes "
             "per image (the mixer was trained with K = 4 finite-difference probes).", ""]
    result = {}
    for label, forms in SETS:
        reports = {stem: load(args.results, stem) for _, stem in forms}
        table, summary = set_table(label, forms, reports)
        lines += table
        result[label] = summary
    write_result(args.out, {"sets": result, "provenance": run_identity(argv)},
                 "\n".join(lines).rstrip())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
