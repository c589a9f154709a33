"""Progressive denoising's promise, checked image by image on finished PD reports
(jaxden evaluate pd ... --out X): at the top spp PD is at or below MC, and at every
spp PD is at most a factor above the better of MC and its denoiser.

    python experiments/pd_targets.py experiments/results/pd/pd-stress-oidn.json ... \
        --out experiments/results/pd/pd-targets

Per report and image (a crop of the test set; on the stress set a whole frame):
- top spp: PD's noise-corrected MSE against MC's, passing when PD <= MC + the noise margin of
  the row (``pd_vs_mc_margin``: twice the standard deviation that the noise of the render and
  of the reference puts into the difference of the two errors,
  :func:`jaxden.evaluate.pd.noise_margin`);
- every spp: PD / min(MC, denoiser) in RMSE (from the noise-corrected MSE) and in relMSE; the
  worst spp is listed, passing at <= --factor (1.05).
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from pathlib import Path


def _rmse(row: dict, method: str) -> float:
    return math.sqrt(max(row[f"{method}_mse_nc"], 0.0))


def check(report: dict, factor: float) -> list[dict]:
    """One dict per image of ``report`` (its rows grouped by crop)."""
    by_crop = defaultdict(list)
    for row in report["rows"]:
        by_crop[row["crop"]].append(row)
    images = []
    for crop, rows in by_crop.items():
        rows = sorted(rows, key=lambda r: r["spp"])
        top = rows[-1]
        margin = top.get("pd_vs_mc_margin", 0.0)
        entry = {"crop": crop, "scene": top.get("scene", ""), "top_spp": top["spp"],
                 "top_pd_over_mc": top["pd_mse_nc"] / top["mc_mse_nc"],
                 "top_margin_over_mc": margin / top["mc_mse_nc"],
                 "top_ok": top["pd_mse_nc"] <= top["mc_mse_nc"] + margin}
        for metric, value in (("rmse", _rmse), ("relmse", lambda r, m: r[f"{m}_relmse"])):
            ratios = [(value(r, "pd") / max(min(value(r, "mc"), value(r, "denoiser")), 1e-30),
                       r["spp"]) for r in rows]
            worst, spp = max(ratios)
            entry[f"worst_{metric}"] = worst
            entry[f"worst_{metric}_spp"] = spp
            entry[f"{metric}_ok"] = worst <= factor
        images.append(entry)
    return images


def table(results: dict[str, list[dict]], factor: float) -> str:
    lines = [
        "## Progressive denoising, image by image: ends at or below MC, never far above the "
        "better of MC and the denoiser",
        "",
        "Top spp: PD / MC in noise-corrected MSE, with the noise margin (twice the standard "
        "deviation the render's and the reference's noise put into the difference), as a fraction "
        f"of MC's MSE. Every spp: the worst PD / min(MC, denoiser), in RMSE (noise-corrected) "
        f"and relMSE, with its spp; target <= {factor}.",
        "",
        "| report | image | scene | top spp | PD / MC | margin | ok | worst RMSE ratio (spp) "
        "| ok | worst relMSE ratio (spp) | ok |",
        "|---|---|---|---:|---:|---:|---|---:|---|---:|---|",
    ]
    mark = {True: "yes", False: "**no**"}
    for name, images in results.items():
        for i in images:
            lines.append(
                f"| {name} | {i['crop']} | {Path(i['scene']).stem} | {i['top_spp']} | "
                f"{i['top_pd_over_mc']:.4f} | {i['top_margin_over_mc']:.4f} | "
                f"{mark[i['top_ok']]} | {i['worst_rmse']:.3f} ({i['worst_rmse_spp']}) | "
                f"{mark[i['rmse_ok']]} | {i['worst_relmse']:.3f} ({i['worst_relmse_spp']}) | "
                f"{mark[i['relmse_ok']]} |")
    lines.append("")
    for name, images in results.items():
        lines.append(
            f"- {name}: top spp at or below MC on {sum(i['top_ok'] for i in images)} of "
            f"{len(images)} images; within {factor}x of the better of MC and the denoiser at "
            f"every spp on {sum(i['rmse_ok'] for i in images)} (RMSE) and "
            f"{sum(i['relmse_ok'] for i in images)} (relMSE) of {len(images)}.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from jaxden.provenance import run_identity, write_result

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", type=Path, nargs="+", help="PD report .json files")
    parser.add_argument("--factor", type=float, default=1.05)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    results, sources = {}, {}
    for path in args.reports:
        report = json.loads(path.read_text())
        results[path.stem] = check(report, args.factor)
        sources[path.stem] = {"file": str(path), "commit": report["provenance"]["commit"],
                              "command": report["provenance"]["command"]}
    write_result(args.out, {"images": results,
                            "provenance": {**run_identity(argv), "reports": sources}},
                 table(results, args.factor))


if __name__ == "__main__":
    main()
