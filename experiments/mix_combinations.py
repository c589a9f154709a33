"""Combine a trained mixer's alpha with the closed form's at inference, on a held-out set.

    python experiments/mix_combinations.py --data data/test-high-chain --mixer oidn-pd \
        --out experiments/results/mix-combinations-high

Per input of the split: OIDN's denoised image y and SURE from the dataset's SURE cache
(``jaxden dataset sure-cache DIR --denoiser oidn``), the mixer's alpha (its config's swap
averaging), the closed form's (:func:`jaxden.progressive.closed_form_alpha`, default width),
and two combinations of them: the per-pixel minimum (the more conservative of the two; it
takes more of the render) and the mean. Each alpha then goes through the t-statistic scaling
of the mixer's config, as in ``jaxden progressive``. Reported as in the PD reports: RMSE and
relMSE over OIDN's (mean over spp of the per-spp ratio of crop means), PD over MC at the
highest spp (crop mean), and the worst crop there.

The SURE draws are the cache's (item seeds), not the PD reports' (``fold_in(seed, index)``),
so the "mixer" and "closed form" rows can differ from those reports in the third digit.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

COMBINATIONS = ("mixer", "closed form", "min", "mean")


def evaluate(data: Path, split: str, mixer: str) -> list[dict]:
    """One row per input: crop, spp and (RMSE, relMSE) of MC, OIDN and each combination."""
    import jax.numpy as jnp
    from closed_form_sigma import open_oidn_cache

    from jaxden import metrics
    from jaxden.pdreport import iter_crops
    from jaxden.progressive import (
        _inference_alpha,
        closed_form_alpha,
        load_mixer,
        mix,
        t_statistic_scaling,
    )

    params, config = load_mixer(mixer)
    cache, items = open_oidn_cache(data)
    rows = []
    for crop, reference, inputs in iter_crops(data, split):
        ref = np.asarray(reference.color)

        def errors(image, ref=ref):
            return [float(metrics.rmse(image, ref)), float(metrics.relmse(image, ref))]

        for spp, frame in inputs:
            cached = cache.read(items[(crop.id, spp)])
            x, var = jnp.asarray(frame.color), jnp.asarray(frame.variance)
            y, sure_map = jnp.asarray(cached["denoised"]), jnp.asarray(cached["sure"])
            learned = _inference_alpha(params, x, y, var, sure_map, config, config.swap_average)
            closed = closed_form_alpha(x, y, var, sure_map)
            alphas = dict(zip(COMBINATIONS, (learned, closed, jnp.minimum(learned, closed),
                                             0.5 * (learned + closed))))
            row = {"crop": crop.id, "spp": spp, "mc": errors(x), "oidn": errors(y)}
            for name, alpha in alphas.items():
                scaled = t_statistic_scaling(alpha, x, mix(x, y, alpha), var, config.tstat)
                row[name] = errors(mix(x, y, scaled))
            rows.append(row)
        print(crop.id, file=sys.stderr, flush=True)
    return rows


def summarize(rows: list[dict], names=COMBINATIONS) -> dict[str, dict]:
    """Per name of ``names`` (a key of every row): RMSE and relMSE over OIDN, over MC at the
    highest spp, and the worst crop there."""
    spps = sorted({r["spp"] for r in rows})
    top = spps[-1]

    def crop_mean(name, metric, spp):
        return float(np.mean([r[name][metric] for r in rows if r["spp"] == spp]))

    out = {}
    for name in names:
        over_oidn = [float(np.mean([crop_mean(name, m, s) / crop_mean("oidn", m, s)
                                    for s in spps])) for m in (0, 1)]
        per_crop = {r["crop"]: r[name][0] / r["mc"][0] for r in rows if r["spp"] == top}
        worst = max(per_crop, key=per_crop.get)
        out[name] = {"rmse_over_oidn": over_oidn[0], "relmse_over_oidn": over_oidn[1],
                     "rmse_over_mc_at_max_spp": crop_mean(name, 0, top) / crop_mean("mc", 0, top),
                     "worst_crop": worst, "worst_crop_over_mc": per_crop[worst],
                     "crops_above_mc": sum(v > 1 for v in per_crop.values()),
                     "max_spp": top, "crops": len(per_crop)}
    return out


def markdown(summary: dict[str, dict]) -> str:
    top = next(iter(summary.values()))["max_spp"]
    header = (f"| alpha | RMSE / OIDN | relMSE / OIDN | PD / MC at {top} spp "
              f"| worst crop, PD / MC at {top} | crops above MC |")
    lines = [header, "|---|---:|---:|---:|---:|---:|"]
    for name, s in summary.items():
        lines.append(f"| {name} | {s['rmse_over_oidn']:.3f} | {s['relmse_over_oidn']:.3f} | "
                     f"{s['rmse_over_mc_at_max_spp']:.3f} | {s['worst_crop_over_mc']:.3f} "
                     f"({s['worst_crop']}) | {s['crops_above_mc']} of {s['crops']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True,
                        help="complete dataset folder with an OIDN SURE cache")
    parser.add_argument("--split", default="test")
    parser.add_argument("--mixer", default="oidn-pd", help="trained mixer spec")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args(argv)

    from pd_report import provenance, write_report

    info = provenance(args, {"denoiser": "oidn", "mixer": args.mixer})
    rows = evaluate(args.data, args.split, args.mixer)
    summary = summarize(rows)
    write_report(args.out, {"provenance": info, "summary": summary, "rows": rows},
                 markdown(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
