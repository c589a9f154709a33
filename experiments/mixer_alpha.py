"""What mixers do on given crops of any dataset: their alpha against the evidence they are fed.

    python experiments/mixer_alpha.py --data $JAXDEN_HOME/data/test-high-chain \
        --crop s006-c000 s001-c000 --spp 64 1024 4096 --mixer oidn-pd \
        --mixer untrained:oidn-pd --worst-pixels 3 --out /tmp/mixer-alpha

For every crop, spp and mixer: the mean alpha of the mixer's single call (the paper's), of its
swapped call (1 - alpha(y, x)) and of their average (``swap_average``), each before the
t-statistic scaling; RMSE over MC's of PD with each alpha (after the scaling) and of OIDN
alone (or ``--denoiser``: any registered denoiser or checkpoint that the mixers take); and
the median over pixels and channels of SURE(y) / var(x), the evidence of which
image is closer to the truth (above 1: y's estimated squared error exceeds x's variance, so
the render should win). SURE: 4 finite-difference probes, seed 0, as in the PD reports.
``--mixer untrained:SPEC`` shows where training started (SPEC's config, seed-0 init). Also
listed: the crop's mean variance, the t-test's Gaussian width sigma_s for it, and the mean
absolute first-layer weight of each network mixer on each input feature.

``--worst-pixels N`` adds, per crop, spp and mixer, the N pixels where PD (swap-averaged
alpha, after the t-test) is furthest from the reference: x, y, the reference, var and SURE
(means over the colour channels), the closed form's alpha (:func:`closed_form_alpha`, default
width) and the mixer's single, swapped and averaged alpha there. This is how a mixer that
overrides the closed form on a firefly shows itself.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def _load(spec: str):
    """``(params, config)`` of a mixer spec; ``untrained:SPEC`` is SPEC's config with freshly
    initialised parameters (seed 0), the starting point of its training."""
    import jax

    from jaxden.progressive.mixer import load_mixer, mixer_init

    if spec.startswith("untrained:"):
        _, config = load_mixer(spec.split(":", 1)[1])
        return mixer_init(jax.random.PRNGKey(0), config), config
    return load_mixer(spec)


def worst_pixels(truth, x, y, var, sure, alphas: dict, z, count: int) -> list[dict]:
    """The ``count`` pixels with the largest squared error of ``z`` (summed over channels),
    with the channel means of the inputs and of each alpha of ``alphas`` there."""
    error = np.sum((np.asarray(z, np.float64) - truth) ** 2, axis=-1)
    order = np.argsort(error, axis=None)[::-1][:count]
    pixels = []
    for flat in order:
        i, j = np.unravel_index(flat, error.shape)
        entry = {"pixel": [int(i), int(j)], "error": float(np.sqrt(error[i, j]))}
        for name, image in (("x", x), ("y", y), ("reference", truth), ("var", var),
                            ("sure", sure), *alphas.items()):
            entry[name] = float(np.mean(np.asarray(image)[i, j]))
        pixels.append(entry)
    return pixels


def evaluate(data: Path, crops, spp, mixers, denoiser: str = "oidn", seed: int = 0,
             worst: int = 0):
    import jax
    import jax.numpy as jnp

    from jaxden.data.crops import iter_crops
    from jaxden.denoise.registry import load_denoiser
    from jaxden.progressive.closed_form import closed_form_alpha
    from jaxden.progressive.network import _mixer_alpha, _mixer_swap_args
    from jaxden.progressive.tstat import _gaussian_sigma, consistent_mix
    from jaxden.sure.denoiser import denoise_with_sure

    model = load_denoiser(denoiser)
    loaded = {spec: _load(spec) for spec in mixers}
    rows, found = [], set()
    for crop, reference, inputs in iter_crops(data, "all", tuple(spp)):
        if crop.id not in crops:
            continue
        found.add(crop.id)
        truth = np.asarray(reference.color, np.float64)
        for level, frame in inputs:
            result, frame = denoise_with_sure(model, frame, jax.random.PRNGKey(seed))
            x, var = jnp.asarray(frame.color), jnp.asarray(frame.variance)
            y, sure = jnp.asarray(result.denoised), jnp.asarray(result.sure)

            def rmse(image, truth=truth):
                return float(np.sqrt(np.mean((np.asarray(image, np.float64) - truth) ** 2)))

            mc = rmse(x)
            ratio = np.asarray(sure, np.float64) / np.maximum(np.asarray(var, np.float64), 1e-20)
            row = {"crop": crop.id, "spp": level, "denoiser_over_mc": rmse(y) / mc,
                   "sure_over_var_median": float(np.median(ratio)),
                   "var_mean": float(np.mean(np.asarray(var, np.float64))), "mixers": {}}
            for spec, (params, config) in loaded.items():
                single = _mixer_alpha(params, x, y, var, sure, config)
                swapped = 1.0 - _mixer_alpha(params, *_mixer_swap_args(config, x, y, var, sure),
                                             config)
                entry = {"tstat_sigma": float(_gaussian_sigma(var, config.tstat))}
                alphas = {"single": single, "swapped": swapped, "average": (single + swapped) / 2}
                pd = {}
                for name, alpha in alphas.items():
                    pd[name], _ = consistent_mix(x, y, alpha, var, config.tstat,
                                                 spp=frame.spp)
                    entry[name] = {"alpha": float(jnp.mean(alpha)),
                                   "pd_over_mc": rmse(pd[name]) / mc}
                if worst:
                    alphas = {"closed_form": closed_form_alpha(x, y, var, sure), **alphas}
                    entry["worst_pixels"] = worst_pixels(truth, x, y, var, sure, alphas,
                                                         pd["average"], worst)
                row["mixers"][spec] = entry
            rows.append(row)
    missing = sorted(set(crops) - found)
    if missing:
        raise SystemExit(f"{data}: no crop(s) {', '.join(missing)}")
    return rows


def first_layer_weights(mixers) -> dict:
    """Mean |weight| of each network mixer's first convolution per input feature (3 channels
    each); mixers without one (the closed form) are left out."""
    import jax

    from jaxden.progressive.inputs import mixer_channel_slices

    out = {}
    for spec in mixers:
        params, config = _load(spec)
        kernel = next((np.asarray(v) for path, v in jax.tree_util.tree_leaves_with_path(params)
                       if "conv_in" in jax.tree_util.keystr(path) and np.ndim(v) == 4), None)
        if kernel is None:
            continue
        out[spec] = {name: float(np.mean(np.abs(kernel[:, :, s, :])))
                     for name, s in mixer_channel_slices(tuple(config.features)).items()}
    return out


def markdown(rows, mixers, weights=None, denoiser: str = "OIDN") -> str:
    lines = [(f"| crop | spp | {denoiser} / MC | median SURE / var | mean var | mixer | "
              "t-test sigma_s | alpha single / swapped / average | "
              "PD / MC single / swapped / average |"),
             "|---|---:|---:|---:|---:|---|---:|---|---|"]
    for row in rows:
        for spec in mixers:
            e = row["mixers"][spec]
            lines.append(
                f"| {row['crop']} | {row['spp']} | {row['denoiser_over_mc']:.3f} | "
                f"{row['sure_over_var_median']:.2f} | {row['var_mean']:.2e} | `{spec}` | "
                f"{e['tstat_sigma']:.3g} | "
                + " / ".join(f"{e[k]['alpha']:.3f}" for k in ("single", "swapped", "average"))
                + " | " + " / ".join(f"{e[k]['pd_over_mc']:.3f}"
                                     for k in ("single", "swapped", "average")) + " |")
    pixel_lines = []
    for row in rows:
        for spec in mixers:
            for p in row["mixers"][spec].get("worst_pixels", []):
                pixel_lines.append(
                    f"| {row['crop']} | {row['spp']} | `{spec}` | {p['pixel'][0]}, {p['pixel'][1]} "
                    f"| {p['error']:.3g} | {p['x']:.3g} | {p['y']:.3g} | {p['reference']:.3g} | "
                    f"{p['var']:.3g} | {p['sure']:.3g} | {p['closed_form']:.3f} | "
                    f"{p['single']:.3f} / {p['swapped']:.3f} / {p['average']:.3f} |")
    if pixel_lines:
        lines += ["", "Worst pixels of PD (swap-averaged alpha, after the t-test); channel means:",
                  "", ("| crop | spp | mixer | row, col | PD error | x | y | reference | var | "
                       "SURE | closed-form alpha | alpha single / swapped / average |"),
                  "|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---|", *pixel_lines]
    if weights:
        names = list(next(iter(weights.values())))
        lines += ["", "Mean |weight| of the first convolution, per input feature:", "",
                  "| mixer | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
        for spec, values in weights.items():
            lines.append(f"| `{spec}` | " + " | ".join(f"{values[n]:.4f}" for n in names) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="complete dataset folder")
    parser.add_argument("--crop", nargs="+", required=True, help="crop ids, e.g. s006-c000")
    parser.add_argument("--spp", type=int, nargs="+", required=True)
    parser.add_argument("--mixer", action="append", required=True,
                        help="a mixer spec (shipped name, run folder or .msgpack), or "
                             "untrained:SPEC (its config, untrained); repeatable")
    parser.add_argument("--denoiser", default="oidn",
                        help="the denoiser whose output the mixers mix (a registered name or a "
                             "checkpoint; default oidn)")
    parser.add_argument("--seed", type=int, default=0, help="SURE probe seed")
    parser.add_argument("--worst-pixels", type=int, default=0, metavar="N",
                        help="also list the N pixels with the largest PD error per input")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args(argv)

    from jaxden.evaluate import dataset_provenance
    from jaxden.provenance import result_provenance, run_identity, write_result

    info = result_provenance(run_identity(), dataset_provenance(args.data, None),
                             seed=args.seed, probes=4, mixers=args.mixer, crops=args.crop,
                             denoiser=args.denoiser)
    rows = evaluate(args.data, args.crop, args.spp, args.mixer, denoiser=args.denoiser,
                    seed=args.seed, worst=args.worst_pixels)
    weights = first_layer_weights(args.mixer)
    name = "OIDN" if args.denoiser == "oidn" else args.denoiser
    write_result(args.out, {"provenance": info, "rows": rows, "first_layer_weights": weights},
                 markdown(rows, args.mixer, weights, name))
    return 0


if __name__ == "__main__":
    sys.exit(main())
