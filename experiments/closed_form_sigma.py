"""Choose the local-mean width of the closed-form mixer on training data (not the test sets).

    python experiments/closed_form_sigma.py --data data/default-chain --split all \
        --sigma 2 4 6 8 12 16 24 --mixer oidn-pd --out experiments/results/closed-form-sigma

For every sigma: the closed-form mixer (:func:`jaxden.progressive.closed_form_alpha`, Eq. 9
with Gaussian local means, no t-test) on every input of the split, with OIDN's denoised image
and SURE read from the dataset's SURE cache (``jaxden dataset sure-cache DIR --denoiser
oidn``: 4 finite-difference probes, seed 0). Reported per sigma, RMSE of the mix over OIDN's:

- geometric mean over inputs of the per-input ratio (the selection criterion: every input
  weighs the same, a single firefly crop cannot decide it);
- median of the per-input ratios;
- mean over spp of the per-spp ratio of crop-mean RMSEs (the PD reports' summary metric).

``--mixer SPEC`` lists a trained mixer beside (no t-test, its config's swap averaging); the
shipped ``oidn-pd`` was trained on data/default-chain's train split, so there it is not a
held-out comparison, only a reference for how the closed form fails.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def open_oidn_cache(data: Path):
    """The dataset's complete OIDN SURE cache and its input item ids by (crop, spp)."""
    from jaxden.pdcache import SureCache, default_cache_dir

    cache = SureCache(data, default_cache_dir(data, "oidn"))
    if not cache.complete:
        raise SystemExit(f"{data}: the OIDN SURE cache is incomplete; run `jaxden dataset "
                         f"sure-cache {data} --denoiser oidn`")
    items = {(item.crop, item.spp): item.id for item in cache.dataset.items
             if item.kind == "input"}
    return cache, items


def evaluate(data: Path, split: str, sigmas: list[float], mixers: list[str]) -> list[dict]:
    """One row per input: crop, spp, RMSE of MC, OIDN, the closed-form mix per sigma and each
    trained mixer's mix (no t-test, the mixer config's swap averaging)."""
    from jaxden.pdreport import iter_crops
    from jaxden.progressive import _inference_alpha, closed_form_alpha, load_mixer

    loaded = {spec: load_mixer(spec) for spec in mixers}

    cache, items = open_oidn_cache(data)
    rows = []
    for crop, reference, inputs in iter_crops(data, split):
        ref = np.asarray(reference.color, np.float64)

        def rmse(image):
            return float(np.sqrt(np.mean((np.asarray(image, np.float64) - ref) ** 2)))

        for spp, frame in inputs:
            cached = cache.read(items[(crop.id, spp)])
            x, var = frame.color, frame.variance
            y, sure_map = cached["denoised"], cached["sure"]
            row = {"crop": crop.id, "spp": spp, "mc": rmse(x), "oidn": rmse(y)}
            for sigma in sigmas:
                alpha = np.asarray(closed_form_alpha(x, y, var, sure_map, sigma=sigma))
                row[f"sigma={sigma:g}"] = rmse(x + alpha * (y - x))
            for spec, (params, config) in loaded.items():
                alpha = np.asarray(_inference_alpha(params, x, y, var, sure_map, config,
                                                    config.swap_average))
                row[f"mixer {spec}"] = rmse(x + alpha * (y - x))
            rows.append(row)
        print(crop.id, file=sys.stderr, flush=True)
    return rows


def ratio_summary(rows: list[dict], keys: list[str], base: str = "oidn"
                  ) -> dict[str, dict[str, float]]:
    """Per key, the error ``row[key]`` over ``row[base]``: geometric mean and median over the
    rows (inputs), and the mean over spp of the per-spp ratio of crop means."""
    spps = sorted({r["spp"] for r in rows})
    out = {}
    for key in keys:
        ratios = np.array([r[key] / r[base] for r in rows])
        per_spp = [np.mean([r[key] for r in rows if r["spp"] == s])
                   / np.mean([r[base] for r in rows if r["spp"] == s]) for s in spps]
        out[key] = {"geometric_mean": float(np.exp(np.mean(np.log(ratios)))),
                    "median": float(np.median(ratios)),
                    "mean_over_spp_of_crop_mean_ratio": float(np.mean(per_spp))}
    return out


def summarize(rows: list[dict], sigmas: list[float], mixers: list[str]
              ) -> dict[str, dict[str, float]]:
    keys = ["mc"] + [f"sigma={s:g}" for s in sigmas] + [f"mixer {m}" for m in mixers]
    return ratio_summary(rows, keys)


def markdown(summary: dict[str, dict[str, float]], rows: list[dict], worst: int = 5) -> str:
    count = len(rows)
    mixers = [k for k in summary if k.startswith("mixer ")]
    best = min((k for k in summary if k.startswith("sigma=")),
               key=lambda k: summary[k]["geometric_mean"])
    lines = [f"RMSE over OIDN's on {count} inputs (no t-test). Selection criterion: the "
             f"geometric mean; best: **{best}**.", "",
             "| mix | geometric mean | median | mean over spp of crop-mean ratio |",
             "|---|---:|---:|---:|"]
    for key, s in summary.items():
        name = ("MC (alpha = 0)" if key == "mc" else key if key.startswith("mixer")
                else f"closed form, {key}")
        lines.append(f"| {name} | {s['geometric_mean']:.4f} | {s['median']:.4f} | "
                     f"{s['mean_over_spp_of_crop_mean_ratio']:.4f} |")
    lines += ["", f"The {worst} inputs where the closed form at {best} is furthest above OIDN:", "",
              "| crop | spp | RMSE MC | RMSE OIDN | RMSE closed form | over OIDN | "
              + "".join(f"RMSE {k} | " for k in mixers),
              "|---|---:|---:|---:|---:|---:|" + "---:|" * len(mixers)]
    for r in sorted(rows, key=lambda r: r[best] / r["oidn"], reverse=True)[:worst]:
        lines.append(f"| {r['crop']} | {r['spp']} | {r['mc']:.4g} | {r['oidn']:.4g} | "
                     f"{r[best]:.4g} | {r[best] / r['oidn']:.3f} | "
                     + "".join(f"{r[k]:.4g} | " for k in mixers))
    return "\n".join(lines)


def cache_sweep_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments every sweep over a dataset's OIDN SURE cache takes: --data, --split,
    --mixer (repeatable) and --out."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True,
                        help="complete dataset folder with an OIDN SURE cache")
    parser.add_argument("--split", default="all", help="split (train, val, test, all)")
    parser.add_argument("--mixer", action="append", default=[],
                        help="a trained mixer to list beside (spec; repeatable). On its own "
                             "training data it is not a held-out comparison")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    return parser


def main(argv=None) -> int:
    parser = cache_sweep_parser(__doc__)
    parser.add_argument("--sigma", type=float, nargs="+", required=True)
    args = parser.parse_args(argv)

    from pd_report import provenance, write_report

    info = provenance(args, {"denoiser": "oidn", "sigmas": args.sigma, "mixers": args.mixer})
    rows = evaluate(args.data, args.split, args.sigma, args.mixer)
    summary = summarize(rows, args.sigma, args.mixer)
    write_report(args.out, {"provenance": info, "summary": summary, "rows": rows},
                 markdown(summary, rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
