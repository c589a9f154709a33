"""How much a bound on the closed_form_logit correction costs: the tile oracle, bounded.

    python experiments/cflogit_bound.py --data data/default-chain --split train \
        --out experiments/results/cflogit-bound-train

The ``closed_form_logit`` mixer head computes alpha = sigmoid(logit(alpha_cf) + c), with
alpha_cf Eq. 9 with local means (:func:`jaxden.progressive.closed_form_alpha`) and c the
network's correction; ``MixerConfig.logit_bound = B`` limits c to B tanh(raw / B), so that
no input (a low-spp firefly fed as linear radiance, say) can move alpha's logit more than B
from Eq. 9's. This script measures what such a bound costs at best: per input of the split it
takes the reference-fitted alpha of 8^2 tiles (:func:`jaxden.pdreport.oracle_alpha`, an upper
bound on any mixer), the correction c* = logit(oracle) - logit(alpha_cf) per pixel, and mixes
with sigmoid(logit(alpha_cf) + clip(c*, -B, B)) for each B (no t-test; logits of values
clipped to [1e-4, 1 - 1e-4]). B = 0 is the closed form, B = inf the tile oracle. Reported as
in the PD reports: RMSE and relMSE over OIDN's (mean over spp of the per-spp ratio of crop
means), over MC at the highest spp, and the worst crop there; plus the quantiles of |c*|.

Needs the dataset's OIDN SURE cache (``jaxden dataset sure-cache DIR --denoiser oidn``).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

BOUNDS = (0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 6.0, math.inf)
EPS = 1e-4
QUANTILES = (0.5, 0.75, 0.9, 0.95, 0.99)


def bound_name(bound: float) -> str:
    return "B=inf (oracle)" if math.isinf(bound) else f"B={bound:g}"


def logit(a):
    a = np.clip(np.asarray(a, np.float64), EPS, 1.0 - EPS)
    return np.log(a) - np.log1p(-a)


def bounded_alphas(alpha_cf, alpha_oracle, bounds=BOUNDS) -> dict[float, np.ndarray]:
    """sigmoid(logit(alpha_cf) + clip(logit(alpha_oracle) - logit(alpha_cf), -B, B)) per B."""
    base = logit(alpha_cf)
    wanted = logit(alpha_oracle) - base
    return {b: 1.0 / (1.0 + np.exp(-(base + np.clip(wanted, -b, b)))) for b in bounds}


def evaluate(data: Path, split: str) -> tuple[list[dict], np.ndarray]:
    """One row per input (crop, spp, (RMSE, relMSE) of MC, OIDN and each bound), and a
    subsample of |c*| over all pixels."""
    from closed_form_sigma import open_oidn_cache

    from jaxden import metrics
    from jaxden.pdreport import iter_crops, oracle_alpha
    from jaxden.progressive import closed_form_alpha

    cache, items = open_oidn_cache(data)
    rows, corrections = [], []
    rng = np.random.default_rng(0)
    for crop, reference, inputs in iter_crops(data, split):
        ref = np.asarray(reference.color)

        def errors(image, ref=ref):
            image = np.asarray(image, np.float32)
            return [float(metrics.rmse(image, ref)), float(metrics.relmse(image, ref))]

        for spp, frame in inputs:
            cached = cache.read(items[(crop.id, spp)])
            x = np.asarray(frame.color, np.float64)
            y = np.asarray(cached["denoised"], np.float64)
            alpha_cf = np.broadcast_to(np.asarray(closed_form_alpha(
                frame.color, cached["denoised"], frame.variance, cached["sure"]), np.float64),
                x.shape)
            alpha_oracle = oracle_alpha(x, y, ref)
            wanted = np.abs(logit(alpha_oracle) - logit(alpha_cf)).ravel()
            corrections.append(rng.choice(wanted, size=min(4096, wanted.size), replace=False))
            row = {"crop": crop.id, "spp": spp, "mc": errors(x), "oidn": errors(y)}
            for bound, alpha in bounded_alphas(alpha_cf, alpha_oracle).items():
                row[bound_name(bound)] = errors(x + alpha * (y - x))
            rows.append(row)
        print(crop.id, file=sys.stderr, flush=True)
    return rows, np.concatenate(corrections)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True,
                        help="complete dataset folder with an OIDN SURE cache")
    parser.add_argument("--split", default="test")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args(argv)

    from mix_combinations import markdown, summarize
    from pd_report import provenance, write_report

    info = provenance(args, {"denoiser": "oidn", "block": 8, "eps": EPS})
    rows, corrections = evaluate(args.data, args.split)
    names = [bound_name(b) for b in BOUNDS]
    summary = summarize(rows, names)
    quantiles = {f"q{q:g}": float(np.quantile(corrections, q)) for q in QUANTILES}
    text = (markdown(summary) + "\n\n|c*| = |logit(oracle) - logit(closed form)| over pixels "
            "(4096 per input): " + ", ".join(f"{k} {v:.2f}" for k, v in quantiles.items()))
    write_report(args.out, {"provenance": info, "summary": summary,
                            "correction_quantiles": quantiles, "rows": rows}, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
