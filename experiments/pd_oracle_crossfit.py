"""How much of the 8 x 8-tile oracle's gain a mixer could reach at all: the oracle's tile alphas
fitted on an independent render of the same crop at the same noise level, then applied to the
render being denoised.

    python experiments/pd_oracle_crossfit.py --data $JAXDEN_HOME/data/test-high-chain \
        --report experiments/results/pd-oidn-test-high-shipped.json \
        --out experiments/results/pd-oidn-oracle-crossfit-test-high
    python experiments/pd_oracle_crossfit.py --data $JAXDEN_HOME/data/test-chain \
        --report experiments/results/pd-oidn-test-shipped.json \
        --out experiments/results/pd-oidn-oracle-crossfit-test

The oracle of the PD reports (:func:`jaxden.progressive.report.oracle_alpha`) fits one alpha per
channel and 8 x 8 tile to the reference *and to this render's own noise*: it sees where this
render's fireflies and noise happen to fall, which no estimator can. The cross-fitted oracle
keeps everything else (the reference, the tile, the least-squares fit) but fits on an
independent render x' of the same crop with the same per-pixel variance, and applies the
alphas to the render x being measured (and the other way round; both directions are averaged).
It is what a mixer could reach if it knew, per tile, the best alpha in expectation up to the
noise of one render: a fair bound where the oracle is not.

The dataset's spp levels are independent renders (their own sampler seeds), but none has a twin
at the same spp. For level N with levels N/2 and 2N both present, x' = w x_2N + (1 - w) x_N/2 with
w in [0, 1] the root of w^2 / 2N + (1 - w)^2 / (N / 2) = 1 / N: unbiased, independent of x_N,
with exactly x_N's per-pixel variance (its noise is a blend of two sample counts rather than one,
so its tails differ a little). Features, variance and covariance are blended the same way
(variance and covariance with w^2 and (1 - w)^2). The denoiser runs on x' as on x.

Writes OUT.md and OUT.json: per spp, the mean over crops of RMSE over the denoiser's for the
oracle, the cross-fitted oracle and PD (from ``--report``, the same crops and spp), and the share
of the oracle's gain (1 - ratio) / (1 - oracle ratio) each reaches, over spp.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def blend_weight(n: int, low: int, high: int) -> float:
    """w in [0, 1] with w^2 / high + (1 - w)^2 / low = 1 / n (variance of the blend equals that
    of an n-spp render, for low < n < high)."""
    a, b, c = 1.0 / high + 1.0 / low, -2.0 / low, 1.0 / low - 1.0 / n
    disc = b * b - 4 * a * c
    roots = [(-b - math.sqrt(disc)) / (2 * a), (-b + math.sqrt(disc)) / (2 * a)]
    inside = [r for r in roots if 0.0 <= r <= 1.0]
    if not inside:
        raise ValueError(f"no blend of {low} and {high} spp has the variance of {n} spp")
    return inside[0]


def blend_frames(high_frame, low_frame, w: float):
    """w * high + (1 - w) * low, field by field (variance with the squared weights)."""
    changes = {}
    for name in ("color", "albedo", "normal", "depth"):
        a, b = getattr(high_frame, name), getattr(low_frame, name)
        if a is not None and b is not None:
            changes[name] = (w * np.asarray(a, np.float64)
                             + (1 - w) * np.asarray(b, np.float64)).astype(np.float32)
    for name in ("variance", "covariance"):  # of the mean: squared weights (independent)
        a, b = getattr(high_frame, name), getattr(low_frame, name)
        if a is not None and b is not None:
            changes[name] = (w * w * np.asarray(a, np.float64)
                             + (1 - w) ** 2 * np.asarray(b, np.float64)).astype(np.float32)
        elif name == "covariance":
            changes[name] = None
    return low_frame.replace(**changes)


def evaluate(data, denoiser_spec: str, split: str) -> list[dict]:
    from jaxden import metrics
    from jaxden.data.crops import iter_crops
    from jaxden.denoise.registry import load_denoiser
    from jaxden.progressive.report import oracle_alpha

    model = load_denoiser(denoiser_spec)
    denoise = model.function()
    rows = []
    for crop, reference, inputs in iter_crops(data, split):
        frames = dict(inputs)
        for n in sorted(frames):
            if n // 2 not in frames or 2 * n not in frames:
                continue
            w = blend_weight(n, n // 2, 2 * n)
            x = frames[n]
            twin = blend_frames(frames[2 * n], frames[n // 2], w)
            pair = [(np.asarray(f.color, np.float64), np.asarray(denoise(f), np.float64))
                    for f in (x, twin)]
            r = np.asarray(reference.color, np.float64)
            alphas = [oracle_alpha(px, py, r) for px, py in pair]
            row = {"crop": crop.id, "spp": n, "blend_weight": w}
            def rmse(image, target=reference.color):
                return float(metrics.rmse(image.astype(np.float32), target))

            for side, (px, py) in enumerate(pair):  # side 0: the dataset's render, 1: its twin
                other = alphas[1 - side]
                row[f"denoiser_rmse_{side}"] = rmse(py)
                row[f"mc_rmse_{side}"] = rmse(px)
                row[f"oracle_rmse_{side}"] = rmse(px + alphas[side] * (py - px))
                row[f"crossfit_rmse_{side}"] = rmse(px + other * (py - px))
            rows.append(row)
            print(f"{crop.id} {n} spp: oracle {row['oracle_rmse_0'] / row['denoiser_rmse_0']:.3f}"
                  f" cross-fit {row['crossfit_rmse_0'] / row['denoiser_rmse_0']:.3f} of the "
                  f"denoiser", flush=True)
    return rows


def summarize(rows: list[dict], report: dict | None) -> dict:
    pd_rows = {}
    if report is not None:
        pd_rows = {(r["crop"], r["spp"]): r["pd_rmse"] / r["denoiser_rmse"]
                   for r in report["rows"]}
    per_spp = {}
    for n in sorted({r["spp"] for r in rows}):
        cell = [r for r in rows if r["spp"] == n]
        entry = {}
        for method in ("oracle", "crossfit"):
            ratios = [r[f"{method}_rmse_{s}"] / r[f"denoiser_rmse_{s}"] for r in cell
                      for s in (0, 1)]
            entry[method] = float(np.mean(ratios))
        pd = [pd_rows[(r["crop"], n)] for r in cell if (r["crop"], n) in pd_rows]
        entry["pd"] = float(np.mean(pd)) if len(pd) == len(cell) else None
        per_spp[n] = entry
    means = {m: float(np.mean([e[m] for e in per_spp.values()])) for m in ("oracle", "crossfit")}
    if all(e["pd"] is not None for e in per_spp.values()):
        means["pd"] = float(np.mean([e["pd"] for e in per_spp.values()]))
    gain = 1.0 - means["oracle"]
    shares = {m: (1.0 - v) / gain for m, v in means.items() if m != "oracle"}
    return {"per_spp": {str(k): v for k, v in per_spp.items()}, "mean_over_spp": means,
            "share_of_oracle_gain": shares}


def report_label(report: dict | None) -> str:
    """The PD column's name: the report's mixer spec and its overrides."""
    if report is None:
        return "PD"
    source = report.get("provenance", {})
    spec = source.get("mixer", {}).get("spec", "?")
    overrides = source.get("mixer_overrides") or []
    return f"PD (mixer {spec}{''.join(f', {o}' for o in overrides)})"


def markdown(summary: dict, denoiser: str, label: str = "PD") -> str:
    lines = [(f"RMSE over {denoiser}'s (mean over crops; the oracle and the cross-fitted oracle "
              f"also over both renders of each pair):"), "",
             f"| spp | 8 x 8 oracle | cross-fitted oracle | {label} |",
             "|---:|---:|---:|---:|"]
    for n, e in summary["per_spp"].items():
        pd = "" if e["pd"] is None else f"{e['pd']:.3f}"
        lines.append(f"| {n} | {e['oracle']:.3f} | {e['crossfit']:.3f} | {pd} |")
    m, s = summary["mean_over_spp"], summary["share_of_oracle_gain"]
    pd = f"{m['pd']:.3f}" if "pd" in m else ""
    lines.append(f"| mean | {m['oracle']:.3f} | {m['crossfit']:.3f} | {pd} |")
    lines += ["", ("Share of the 8 x 8 oracle's RMSE gain, (1 - ratio) / (1 - oracle ratio), "
                   "mean ratios over spp:"), ""]
    lines += [f"- {name}: {value:.0%}" for name, value in
              (("cross-fitted oracle", s["crossfit"]), ("PD", s.get("pd")))
              if value is not None]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="complete dataset folder (test split)")
    parser.add_argument("--denoiser", default="oidn")
    parser.add_argument("--split", default="test")
    parser.add_argument("--report", default=None,
                        help="a PD report .json on the same data: its PD rows are compared")
    parser.add_argument("--out", required=True, help="output path without suffix")
    args = parser.parse_args(argv)
    from pd_report import provenance, write_report

    source = provenance(args, {"denoiser": args.denoiser, "report": args.report})
    report = json.loads(Path(args.report).read_text()) if args.report else None
    rows = evaluate(args.data, args.denoiser, args.split)
    if not rows:
        raise SystemExit(f"{args.data}: no spp level N with N/2 and 2N both present")
    summary = summarize(rows, report)
    write_report(Path(args.out), {"provenance": source, "rows": rows, "summary": summary},
                 markdown(summary, args.denoiser, report_label(report)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
