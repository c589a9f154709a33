"""Why no local rule can meet the stress set's every-spp target at 4..16 spp: pixels whose
local statistics say the same thing while their truths are opposite.

    python experiments/pd_guard_ambiguity.py --data $JAXDEN_HOME/data/stress --denoiser oidn \
        --spp 4 8 16 --out experiments/results/pd/pd-guard-ambiguity

A progressive-denoising mixer (and the error guard after it) sees, per pixel, x, its variance,
the denoised y and their neighbourhoods. Take the pixels where those disagree most sharply:
y is more than 10 of the pixel's own standard errors off x (own chi^2 = sum_c (y - x)^2 /
sum_c var > 100, or var = 0 with y != x), while over the guard's window (Gaussian, sigma 1 px,
3-sigma support) y is within the noise (spatial chi^2 < 2, the guard's break-even). These are
the pixels the spatial guard keeps and the noise-strata option (tstat.guard_strata) cuts.
For each image the script reports how many there are, their share of the squared error of
keeping y there, and the alpha that would be best on them with the reference known,
alpha* = sum (r - x)(y - x) / sum (y - x)^2 (0: y is wrong, keep x; 1: y is right).

If alpha* is near 0 on some images and near 1 on others, the class is ambiguous: any rule
that is a function of these local statistics gives the class one answer, and must lose on one
kind of image or the other. On the stress set at 4 spp with OIDN it is both (the result file).
"""

from __future__ import annotations

import argparse
import datetime
from pathlib import Path

import numpy as np

OWN_CHI2 = 100.0  # y more than 10 of the pixel's own standard errors off x
SPATIAL_CHI2 = 2.0  # within the guard's break-even over its window
RELMSE_EPS = 0.01  # jaxden.metrics.relmse's eps


def local_sum(image: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """Zero-padded Gaussian local sum over a 3-sigma square (the guard's window), (H, W)."""
    radius = max(1, int(np.ceil(3 * sigma)))
    offsets = np.arange(-radius, radius + 1)
    taps = np.exp(-offsets ** 2 / (2 * sigma ** 2))
    padded = np.pad(image, radius)
    rows = sum(t * padded[k:k + image.shape[0], :] for k, t in enumerate(taps))
    return sum(t * rows[:, k:k + image.shape[1]] for k, t in enumerate(taps))


def classify(x, y, var):
    """Boolean (H, W): own chi^2 > OWN_CHI2 and spatial chi^2 < SPATIAL_CHI2."""
    residual = np.sum((y - x) ** 2, axis=-1)
    variance = np.sum(var, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        own = np.where(variance > 0, residual / variance, np.where(residual > 0, np.inf, 0))
        spatial = local_sum(residual) / local_sum(variance)
    return (own > OWN_CHI2) & (spatial < SPATIAL_CHI2)


def measure(data: Path, denoiser: str, spp: tuple[int, ...]) -> list[dict]:
    from jaxden.data.crops import iter_crops
    from jaxden.denoise.registry import load_denoiser

    model = load_denoiser(denoiser)
    rows = []
    for crop, reference, inputs in iter_crops(data, "all", spp):
        r = np.asarray(reference.color, np.float64)
        for level, frame in inputs:
            x = np.asarray(frame.color, np.float64)
            var = np.asarray(frame.variance, np.float64)
            y = np.asarray(model(frame), np.float64)
            mask = classify(x, y, var)
            d, e = (y - x)[mask], (r - x)[mask]
            weight = 1.0 / (r[mask] ** 2 + RELMSE_EPS)  # relMSE's per-value weight
            keep_y = float(np.sum((y - r) ** 2))
            keep_y_rel = float(np.sum((y - r) ** 2 / (r ** 2 + RELMSE_EPS)))
            rows.append({
                "crop": crop.id, "scene": Path(str(crop.scene)).stem, "spp": level,
                "pixels": int(mask.sum()),
                "share_of_denoiser_error": float(np.sum((y - r)[mask] ** 2) / keep_y)
                if keep_y > 0 else 0.0,
                "best_alpha": float(np.sum(d * e) / np.sum(d * d)) if mask.any() else None,
                "share_of_denoiser_relmse": float(np.sum(((y - r) ** 2 / (r ** 2 + RELMSE_EPS))[
                    mask]) / keep_y_rel) if keep_y_rel > 0 else 0.0,
                "best_alpha_relmse": float(np.sum(weight * d * e) / np.sum(weight * d * d))
                if mask.any() else None,
                "median_reference_over_x": float(np.median(
                    (np.mean(r, -1)[mask] + 1e-3) / (np.mean(x, -1)[mask] + 1e-3)))
                if mask.any() else None,
            })
    return rows


def render_markdown(rows: list[dict], denoiser: str) -> str:
    lines = [f"## Pixels the local statistics cannot decide ({denoiser})", "",
             f"Pixels where y is > 10 of the pixel's own standard errors off x (own chi^2 > "
             f"{OWN_CHI2:g}) but within the noise over the guard's window (spatial chi^2 < "
             f"{SPATIAL_CHI2:g}). alpha* is the best single alpha on them with the reference "
             f"known (0: keep x, 1: keep y), for squared error and for relMSE; share: of the "
             f"denoiser's whole-frame error that these pixels carry.", "",
             "| image | scene | spp | pixels | share (MSE) | alpha* (MSE) | share (relMSE) "
             "| alpha* (relMSE) | median r / x |", "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        alpha = "-" if row["best_alpha"] is None else f"{row['best_alpha']:.2f}"
        alpha_rel = ("-" if row["best_alpha_relmse"] is None
                     else f"{row['best_alpha_relmse']:.2f}")
        ratio = ("-" if row["median_reference_over_x"] is None
                 else f"{row['median_reference_over_x']:.3g}")
        lines.append(f"| {row['crop']} | {row['scene']} | {row['spp']} | {row['pixels']} | "
                     f"{row['share_of_denoiser_error']:.3f} | {alpha} | "
                     f"{row['share_of_denoiser_relmse']:.3f} | {alpha_rel} | {ratio} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--denoiser", default="oidn")
    parser.add_argument("--spp", type=int, nargs="+", default=[4, 8, 16])
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    from jaxden.paths import portable
    from jaxden.provenance import file_sha256, package_version, run_identity, write_result

    rows = measure(args.data, args.denoiser, tuple(args.spp))
    result = {"rows": rows, "denoiser": args.denoiser, "own_chi2": OWN_CHI2,
              "spatial_chi2": SPATIAL_CHI2}
    result["provenance"] = {
        **run_identity(argv), "date": datetime.date.today().isoformat(),
        "dataset": {"path": portable(str(args.data)),
                    "manifest_sha256": file_sha256(args.data / "manifest.json")},
        "versions": {n: package_version(n) for n in ("pyoidn", "jax")}}
    write_result(args.out, result, render_markdown(rows, args.denoiser))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
