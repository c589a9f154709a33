"""Progressive denoising on small bright lights: every shipped or documented mixer on the built-in
small-lights scene (whole frame, lamps included), with the error guard and without it (the
paper's t-statistic scaling alone), and what the t-test sees on the lamp pixels.

    python experiments/pd_lamps.py --out experiments/results/pd/pd-small-lights

Renders small-lights at 96 x 96 (seed 1801) at each --spp and an 8192-spp reference (seed 999)
into --work (reused when there), then per mixer and spp: the noise-corrected MSE, RMSE,
relMSE and HDR FLIP of MC, the denoiser and PD, the share of PD's squared error on the lamp
pixels (reference > 5), and for the worst lamp pixels x, its standard error, y, alpha, t, the
Gaussian width s of the t-test, the largest variance in the t-test's window (what M_p adds),
alpha' (the t-test), chi (the guard's local deviation of y from x in standard errors) and
alpha'' (after the guard).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
from pathlib import Path

import numpy as np

#: mixer spec -> denoiser: the shipped mixers and the closed form (Eq. 9 alone) with per-channel
#: t, with and without SURE from the colour covariance.
MIXERS = {
    "wskp-6-pd": "wskp-6",
    "closed-form": "wskp-6",
    "closed-form:covariance=true": "wskp-6",
    "oidn-pd": "oidn",
}
LAMP_THRESHOLD = 5.0  # reference radiance (channel mean) above which a pixel is a lamp pixel
SIZE = (96, 96)


def render(work: Path, spp: int, seed: int):
    """The small-lights frame at ``spp`` (cached as an EXR in ``work``)."""
    from jaxden.io.exr import read_frame, write_frame
    from jaxden.render.core import render_frame

    path = work / f"small-lights-{spp}spp-seed{seed}.exr"
    if not path.is_file():
        work.mkdir(parents=True, exist_ok=True)
        write_frame(path, render_frame("small-lights", spp, seed=seed, size=SIZE),
                    attributes={"seed": seed})
    return read_frame(path)


def load(spec: str, denoiser: str):
    """(params, MixerConfig) of a mixer spec; the closed form gets the per-channel t."""
    from jaxden.progressive.mixer import CLOSED_FORM_SPEC, closed_form_mixer, load_mixer
    from jaxden.progressive.pipeline import shipped_mixer_path

    if spec.startswith(CLOSED_FORM_SPEC):
        params, config = closed_form_mixer(spec)
        return params, dataclasses.replace(
            config, denoiser=denoiser, tstat=dataclasses.replace(config.tstat, per_channel=True))
    path = shipped_mixer_path(denoiser) if spec in ("wskp-6-pd", "oidn-pd") else spec
    return load_mixer(str(path))


def errors(image, reference, lamp) -> dict:
    from jaxden import metrics

    image = np.asarray(image, np.float32)
    ref, ref_var = np.asarray(reference.color), np.asarray(reference.variance)
    squared = (image.astype(np.float64) - ref) ** 2 - ref_var
    return {"mse_nc": float(squared.mean()),
            "rmse": float(metrics.rmse(image, ref)),
            "relmse": float(metrics.relmse(image, ref)),
            "flip": float(metrics.flip(image, ref, "HDR")),
            "lamp_share": float(squared[lamp].sum() / max(squared.sum(), 1e-30))}


def lamp_pixels(frame, reference, lamp, extras, alpha_t, alpha_g, config, z, count: int):
    """What the t-test and the guard see on the ``count`` lamp pixels where PD without the
    guard errs most."""
    import jax.numpy as jnp
    from scipy.ndimage import maximum_filter

    from jaxden.progressive.closed_form import blur_2d as _blur_2d
    from jaxden.progressive.closed_form import gaussian_taps as _gaussian_taps
    from jaxden.progressive.tstat import _gaussian_sigma, t_statistic

    x, var = np.asarray(frame.color), np.asarray(frame.variance)
    y, alpha = np.asarray(extras["denoised"]), np.asarray(extras["alpha"])
    t = np.asarray(t_statistic(x, np.asarray(extras["mixed"]), var, config.tstat))
    window_max = maximum_filter(var, size=(config.tstat.window, config.tstat.window, 1),
                                mode="constant", cval=0.0)
    taps = jnp.asarray(_gaussian_taps(config.tstat.guard_sigma))
    residual = ((y - x) ** 2).sum(-1, keepdims=True)
    local = np.asarray(_blur_2d(np.concatenate([var.sum(-1, keepdims=True), residual], -1),
                                taps))
    with np.errstate(divide="ignore", invalid="ignore"):
        chi = np.sqrt(local[..., 1] / local[..., 0])
    ref = np.asarray(reference.color)
    error = ((np.asarray(z) - ref) ** 2).sum(-1)
    order = [i for i in np.argsort(error.ravel())[::-1] if lamp.ravel()[i]][:count]
    rows = []
    for index in order:
        r, c = divmod(int(index), x.shape[1])
        rows.append({"pixel": [r, c], "reference": float(ref[r, c].mean()),
                     "x": float(x[r, c].mean()), "std_error": float(np.sqrt(var[r, c].mean())),
                     "y": float(y[r, c].mean()), "alpha": float(alpha[r, c].mean()),
                     "t": float(t[r, c].mean()),
                     "s": float(_gaussian_sigma(var, config.tstat)),
                     "window_max_std_error": float(np.sqrt(window_max[r, c].mean())),
                     "alpha_t": float(np.asarray(alpha_t)[r, c].mean()),
                     "chi": float(chi[r, c]), "alpha_guard": float(np.asarray(alpha_g)[r, c].mean()),
                     "error_t": float(error[r, c]),
                     "error_mc": float(((x[r, c] - ref[r, c]) ** 2).sum())})
    return rows


def run(args) -> dict:
    import jax

    from jaxden.denoise.registry import load_denoiser
    from jaxden.progressive.pipeline import mix_given_sure, progressive_denoise

    reference = render(args.work, args.reference_spp, args.reference_seed)
    lamp = np.asarray(reference.color).mean(-1) > LAMP_THRESHOLD
    rows, pixels = [], []
    for spec, denoiser in MIXERS.items():
        model = load_denoiser(denoiser)
        params, config = load(spec, denoiser)
        paper = dataclasses.replace(config, tstat=dataclasses.replace(config.tstat, guard=False))
        for spp in args.spp:
            frame = render(args.work, spp, args.seed)
            z, alpha_g, extras = progressive_denoise(frame, model, params, config,
                                                     jax.random.PRNGKey(args.probe_seed))
            z_t, alpha_t, _, _ = mix_given_sure(frame.color, extras["denoised"], frame.variance,
                                                extras["sure"], params, paper)
            row = {"mixer": spec, "denoiser": denoiser, "spp": spp,
                   "mc": errors(frame.color, reference, lamp),
                   "denoised": errors(extras["denoised"], reference, lamp),
                   "pd_t_test_only": errors(z_t, reference, lamp),
                   "pd": errors(z, reference, lamp)}
            rows.append(row)
            print(f"{spec:28s} {spp:5d} spp  PD/MC {row['pd']['mse_nc'] / row['mc']['mse_nc']:.3f}"
                  f" (t-test only {row['pd_t_test_only']['mse_nc'] / row['mc']['mse_nc']:.3f})")
            if spp in (min(args.spp), max(args.spp)):
                pixels += [{"mixer": spec, "spp": spp, **p} for p in lamp_pixels(
                    frame, reference, lamp, extras, alpha_t, alpha_g, config, z_t, 3)]
    return {"rows": rows, "lamp_pixels": pixels, "lamp_pixel_count": int(lamp.sum())}


def table(result: dict) -> str:
    lines = [
        "## Small-lights, whole 96 x 96 frame (lamps included): PD with the error guard and with "
        "the t-test alone",
        "",
        f"{result['lamp_pixel_count']} lamp pixels (reference > {LAMP_THRESHOLD}). Ratios of "
        "noise-corrected MSE to MC's; relMSE and FLIP (HDR) as they are; 'lamp share': the "
        "part of PD's squared error on the lamp pixels.",
        "",
        "| mixer | spp | MC MSE | den / MC | PD / MC, t-test only | **PD / MC** | MC relMSE | "
        "den relMSE | PD relMSE, t-test only | **PD relMSE** | MC FLIP | den FLIP | **PD FLIP** "
        "| lamp share (t-test only / guard) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["rows"]:
        mc = r["mc"]["mse_nc"]
        lines.append(
            f"| {r['mixer']} | {r['spp']} | {mc:.4g} | {r['denoised']['mse_nc'] / mc:.3g} | "
            f"{r['pd_t_test_only']['mse_nc'] / mc:.3f} | **{r['pd']['mse_nc'] / mc:.3f}** | "
            f"{r['mc']['relmse']:.3g} | {r['denoised']['relmse']:.3g} | "
            f"{r['pd_t_test_only']['relmse']:.3g} | **{r['pd']['relmse']:.3g}** | "
            f"{r['mc']['flip']:.3f} | {r['denoised']['flip']:.3f} | **{r['pd']['flip']:.3f}** | "
            f"{r['pd_t_test_only']['lamp_share']:.2f} / {r['pd']['lamp_share']:.2f} |")
    lines += [
        "",
        "## The lamp pixels where PD with the t-test alone errs most",
        "",
        "x and y: channel means of the render and the denoised image; se: the standard error of "
        "x; t: the t-statistic of the mix; s: the t-test's Gaussian width (pixels); window se: "
        "the largest standard error in the t-test's window (its M_p term); alpha', alpha'': "
        "after the t-test and after the guard; chi: the guard's local |y - x| in standard "
        "errors; errors summed over R, G, B.",
        "",
        "| mixer | spp | pixel | reference | x | se | y | alpha | t | s | window se | alpha' | "
        "chi | alpha'' | error, t-test only | MC's error |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for p in result["lamp_pixels"]:
        lines.append(
            f"| {p['mixer']} | {p['spp']} | {tuple(p['pixel'])} | {p['reference']:.1f} | "
            f"{p['x']:.1f} | {p['std_error']:.3g} | {p['y']:.1f} | {p['alpha']:.3f} | "
            f"{p['t']:.2f} | {p['s']:.2f} | {p['window_max_std_error']:.3g} | "
            f"{p['alpha_t']:.3f} | {p['chi']:.3g} | {p['alpha_guard']:.2g} | "
            f"{p['error_t']:.3g} | {p['error_mc']:.3g} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from jaxden.paths import expand_path
    from jaxden.provenance import package_version, run_identity, write_result

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--spp", type=int, nargs="+", default=[8, 64, 1024, 4096])
    parser.add_argument("--seed", type=int, default=1801)
    parser.add_argument("--reference-spp", type=int, default=8192)
    parser.add_argument("--reference-seed", type=int, default=999)
    parser.add_argument("--probe-seed", type=int, default=0)
    parser.add_argument("--work", type=Path,
                        default=Path(expand_path("$JAXDEN_HOME/runs/pd-lamps")),
                        help="where the renders are kept (default $JAXDEN_HOME/runs/pd-lamps)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    result = run(args)
    result["provenance"] = {
        **run_identity(argv), "date": datetime.date.today().isoformat(),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
        "versions": {n: package_version(n) for n in ("pyoidn", "mitsuba", "jax")},
        "scene": "small-lights", "size": list(SIZE), "seed": args.seed, "spp": args.spp,
        "reference_spp": args.reference_spp, "reference_seed": args.reference_seed,
        "probe_seed": args.probe_seed}
    write_result(args.out, result, table(result))


if __name__ == "__main__":
    main()
