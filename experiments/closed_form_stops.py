"""Choose the brightness strata of the range-aware closed form on training data.

    python experiments/closed_form_stops.py --data data/default-chain --split all \
        --stops none 0.5 1 2 4 --mixer oidn-pd --out experiments/results/closed-form-stops

For every ``stops`` value (``none``: plain Gaussian local means): the closed-form mixer
(:func:`jaxden.progressive.closed_form_alpha`, sigma 12, no t-test) on every input of the
split, OIDN's denoised image and SURE read from the dataset's SURE cache (``jaxden dataset
sure-cache DIR --denoiser oidn``: 4 finite-difference probes, seed 0). Reported per value, for
RMSE and for relMSE (eps 0.01) of the mix over OIDN's: the geometric mean over inputs of the
per-input ratio, its median, and the mean over spp of the per-spp ratio of crop means (the PD
reports' summary metric).

Selection criterion: the lowest mean of the two geometric means (RMSE and relMSE count alike;
every input weighs the same). ``--mixer SPEC`` lists trained mixers beside (no t-test, their
configs' swap averaging); on their own training data that is not a held-out comparison.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from closed_form_sigma import cache_sweep_parser, open_oidn_cache, ratio_summary

SIGMA = 12.0


def parse_stops(text: str) -> float | None:
    if text.lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0 or 'none', got {text!r}")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0 or 'none', got {text!r}")
    return value


def stops_key(stops: float | None) -> str:
    return "stops=none" if stops is None else f"stops={stops:g}"


def evaluate(data: Path, split: str, stops: list[float | None], mixers: list[str]) -> list[dict]:
    """One row per input: crop, spp, ``{key: [RMSE, relMSE]}`` for MC, OIDN, each stops value
    and each trained mixer."""
    from jaxden import metrics
    from jaxden.pdreport import iter_crops
    from jaxden.progressive import _inference_alpha, closed_form_alpha, load_mixer

    loaded = {spec: load_mixer(spec) for spec in mixers}
    cache, items = open_oidn_cache(data)
    rows = []
    for crop, reference, inputs in iter_crops(data, split):
        ref = np.asarray(reference.color, np.float64)

        def errors(image, ref=ref):
            image = np.asarray(image, np.float64)
            return [float(np.sqrt(np.mean((image - ref) ** 2))),
                    float(metrics.relmse(image, ref))]

        for spp, frame in inputs:
            cached = cache.read(items[(crop.id, spp)])
            x, var = frame.color, frame.variance
            y, sure_map = cached["denoised"], cached["sure"]
            row = {"crop": crop.id, "spp": spp, "mc": errors(x), "oidn": errors(y)}
            for value in stops:
                alpha = np.asarray(closed_form_alpha(x, y, var, sure_map, sigma=SIGMA,
                                                     stops=value))
                row[stops_key(value)] = errors(x + alpha * (y - x))
            for spec, (params, config) in loaded.items():
                alpha = np.asarray(_inference_alpha(params, x, y, var, sure_map, config,
                                                    config.swap_average))
                row[f"mixer {spec}"] = errors(x + alpha * (y - x))
            rows.append(row)
        print(crop.id, file=sys.stderr, flush=True)
    return rows


def summarize(rows: list[dict], keys: list[str]) -> dict[str, dict[str, dict[str, float]]]:
    """``{metric: ratio_summary}`` for metric RMSE (index 0) and relMSE (index 1)."""
    out = {}
    for index, metric in enumerate(("rmse", "relmse")):
        flat = [{"spp": r["spp"], **{k: r[k][index] for k in ["oidn", *keys]}} for r in rows]
        out[metric] = ratio_summary(flat, keys)
    return out


def best_stops(summary: dict, keys: list[str]) -> str:
    candidates = [k for k in keys if k.startswith("stops=")]
    return min(candidates, key=lambda k: (summary["rmse"][k]["geometric_mean"]
                                          + summary["relmse"][k]["geometric_mean"]) / 2)


def markdown(summary: dict, keys: list[str], count: int) -> str:
    best = best_stops(summary, keys)
    lines = [(f"Closed form (sigma {SIGMA:g}, no t-test) over OIDN on {count} inputs. Selection "
             f"criterion: the mean of the RMSE and relMSE geometric means; best: **{best}**."), "",
             ("| mix | RMSE geo. mean | RMSE median | RMSE mean over spp | relMSE geo. mean | "
              "relMSE median | relMSE mean over spp |"),
             "|---|---:|---:|---:|---:|---:|---:|"]
    for key in keys:
        name = "MC (alpha = 0)" if key == "mc" else key if key.startswith("mixer") else \
            f"closed form, {key}"
        cells = [f"{summary[m][key][s]:.4f}" for m in ("rmse", "relmse")
                 for s in ("geometric_mean", "median", "mean_over_spp_of_crop_mean_ratio")]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = cache_sweep_parser(__doc__)
    parser.add_argument("--stops", type=parse_stops, nargs="+", required=True,
                        help="stratum widths in stops, or 'none' for plain local means")
    args = parser.parse_args(argv)

    from pd_report import provenance, write_report

    info = provenance(args, {"denoiser": "oidn", "sigma": SIGMA, "stops": args.stops,
                             "mixers": args.mixer})
    rows = evaluate(args.data, args.split, args.stops, args.mixer)
    keys = ["mc", *(stops_key(v) for v in args.stops), *(f"mixer {m}" for m in args.mixer)]
    summary = summarize(rows, keys)
    write_report(args.out, {"provenance": info, "summary": summary,
                            "best": best_stops(summary, keys), "rows": rows},
                 markdown(summary, keys, len(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
