"""The error guard's break-even factor (``tstat.guard_gamma``) image by image: what a tighter cap
buys at the top spp and costs below it.

    python experiments/pd_guard_gamma.py --data $JAXDEN_HOME/data/stress --denoiser oidn \
        --gamma 2 1.5 1 --out experiments/results/pd/pd-guard-gamma-oidn-stress

The guard caps the mix weight at ``gamma var / E[(y - x)^2]`` (jaxden.progressive.guard):
gamma = 2 is where the mix breaks even with x in expectation, gamma = 1 the squared-error
optimum when chi^2 = E[(y - x)^2] / var is known. The denoiser and its SURE run once per input
(the shipped mixer's probes, key 0); only the mix is redone per gamma, with the shipped mixer
and its t-statistic config otherwise unchanged. Errors are noise-corrected MSE (the reference's
variance of the mean subtracted) over the whole frame, as ratios: PD / min(MC, denoiser) at
every spp, PD / MC at the top spp. For the image worst at the top spp under the shipped gamma,
the script also lists the pixels that carry its excess over MC (x, y, the reference, the
standard error of x, alpha before and after the guard).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
from pathlib import Path

import numpy as np

TOP_PIXELS = 8  # pixels listed for the worst image


def _nc_mse(image, reference, reference_variance) -> float:
    return float(np.mean((image - reference) ** 2) - np.mean(reference_variance))


def measure(data: Path, denoiser: str, gammas: tuple[float, ...], split: str):
    import jax

    from jaxden.data.crops import iter_crops
    from jaxden.denoise.registry import load_denoiser
    from jaxden.progressive import load_mixer
    from jaxden.progressive.pipeline import mix_given_sure, shipped_mixer_path
    from jaxden.sure.denoiser import denoise_with_sure

    path = shipped_mixer_path(denoiser)
    if path is None:
        raise SystemExit(f"pd_guard_gamma: no mixer ships for denoiser {denoiser!r}")
    params, config = load_mixer(str(path))
    model = load_denoiser(denoiser)
    if config.tstat.guard_gamma not in gammas:
        gammas = (config.tstat.guard_gamma, *gammas)
    rows, worst = [], None
    for crop, reference, inputs in iter_crops(data, split):
        r = np.asarray(reference.color, np.float64)
        r_var = np.asarray(reference.variance, np.float64)
        for level, frame in inputs:
            result, frame = denoise_with_sure(model, frame, jax.random.PRNGKey(0),
                                              sure=config.sure)
            x = np.asarray(frame.color, np.float64)
            y = np.asarray(result.denoised, np.float64)
            mc, den = _nc_mse(x, r, r_var), _nc_mse(y, r, r_var)
            row = {"crop": crop.id, "scene": Path(str(crop.scene)).stem, "spp": level,
                   "mc_mse_nc": mc, "denoiser_mse_nc": den, "pd_mse_nc": {}}
            for gamma in gammas:
                tstat = dataclasses.replace(config.tstat, guard_gamma=gamma)
                z, alpha_prime, alpha, _ = mix_given_sure(
                    frame.color, result.denoised, frame.variance, result.sure, params, config,
                    tstat=tstat, spp=frame.spp)
                z = np.asarray(z, np.float64)
                row["pd_mse_nc"][str(gamma)] = _nc_mse(z, r, r_var)
                if gamma == config.tstat.guard_gamma:
                    detail = (x, y, r, np.asarray(frame.variance, np.float64),
                              np.asarray(alpha), np.asarray(alpha_prime), z)
            rows.append(row)
            if level == inputs[-1][0]:
                ratio = row["pd_mse_nc"][str(config.tstat.guard_gamma)] / mc
                if worst is None or ratio > worst[0]:
                    worst = (ratio, row, detail)
    return rows, _excess_pixels(worst), config.tstat.guard_gamma, gammas


def _excess_pixels(worst):
    """The pixels that carry the worst image's excess over MC at its top spp."""
    if worst is None:
        return None
    _, row, (x, y, r, var, alpha, alpha_prime, z) = worst
    excess = np.sum((z - r) ** 2, -1) - np.sum((x - r) ** 2, -1)
    order = np.argsort(excess.ravel())[::-1][:TOP_PIXELS]
    total = float(excess.sum())
    pixels = []
    for index in order:
        h, w = divmod(int(index), x.shape[1])
        pixels.append({"pixel": [h, w], "x": x[h, w].mean(), "y": y[h, w].mean(),
                       "reference": r[h, w].mean(), "std_error": float(np.sqrt(var[h, w].mean())),
                       "alpha": float(alpha[h, w].mean()),
                       "alpha_prime": float(alpha_prime[h, w].mean()),
                       "share": float(excess[h, w] / total) if total > 0 else 0.0})
    return {"crop": row["crop"], "scene": row["scene"], "spp": row["spp"],
            "excess_over_mc": total, "pixels": pixels}


def render_markdown(rows, excess, gammas, shipped, denoiser) -> str:
    heads = " | ".join(f"gamma {g:g}" for g in gammas)
    lines = [f"## The error guard's gamma, image by image ({denoiser})", "",
             f"PD / min(MC, {denoiser}) in noise-corrected MSE over the whole frame per image "
             f"and spp, for each gamma (shipped: {shipped:g}); the denoiser, its SURE and the "
             f"shipped mixer are fixed.", "",
             f"| image | scene | spp | MC / best | {heads} |",
             "|---|---|---:|---:|" + "---:|" * len(gammas)]
    for row in rows:
        best = min(row["mc_mse_nc"], row["denoiser_mse_nc"])
        cells = " | ".join(f"{row['pd_mse_nc'][str(g)] / best:.4f}" for g in gammas)
        lines.append(f"| {row['crop']} | {row['scene']} | {row['spp']} | "
                     f"{row['mc_mse_nc'] / best:.3f} | {cells} |")
    lines += ["", "Worst ratio over all spp, and PD / MC at the top spp, per gamma:", "",
              "| gamma | worst PD / best (image, spp) | worst top-spp PD / MC (image) |",
              "|---:|---|---|"]
    top = max(row["spp"] for row in rows)
    for gamma in gammas:
        key = str(gamma)
        ratios = [(row["pd_mse_nc"][key] / min(row["mc_mse_nc"], row["denoiser_mse_nc"]),
                   row) for row in rows]
        value, row = max(ratios, key=lambda item: item[0])
        tops = [(r["pd_mse_nc"][key] / r["mc_mse_nc"], r) for r in rows if r["spp"] == top]
        top_value, top_row = max(tops, key=lambda item: item[0])
        lines.append(f"| {gamma:g} | {value:.4f} ({row['scene']}, {row['spp']}) | "
                     f"{top_value:.4f} ({top_row['scene']}) |")
    if excess is not None:
        lines += ["", f"Pixels carrying the excess over MC of {excess['scene']} at "
                  f"{excess['spp']} spp (gamma {shipped:g}; channel means):", "",
                  "| pixel | x | y | reference | std. error of x | alpha | alpha' | share |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for p in excess["pixels"]:
            lines.append(f"| {p['pixel'][0]}, {p['pixel'][1]} | {p['x']:.1f} | {p['y']:.1f} | "
                         f"{p['reference']:.1f} | {p['std_error']:.2f} | {p['alpha']:.3f} | "
                         f"{p['alpha_prime']:.3f} | {p['share']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--denoiser", default="oidn")
    parser.add_argument("--split", default="all")
    parser.add_argument("--gamma", type=float, nargs="+", default=[2.0, 1.5, 1.0])
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    from jaxden.paths import portable
    from jaxden.provenance import file_sha256, package_version, run_identity, write_result

    rows, excess, shipped, gammas = measure(args.data, args.denoiser, tuple(args.gamma),
                                           args.split)
    result = {"rows": rows, "excess_pixels": excess, "denoiser": args.denoiser,
              "gammas": list(gammas), "shipped_gamma": shipped}
    result["provenance"] = {
        **run_identity(argv), "date": datetime.date.today().isoformat(),
        "dataset": {"path": portable(str(args.data)),
                    "manifest_sha256": file_sha256(args.data / "manifest.json")},
        "versions": {n: package_version(n) for n in ("pyoidn", "jax")}}
    write_result(args.out, result, render_markdown(rows, excess, gammas, shipped, args.denoiser))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
