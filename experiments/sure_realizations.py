"""Is a denoiser's SURE unbiased *in expectation* on real Monte Carlo noise? Renders one crop
of a dataset R times at the same spp with independent seeds, and compares the mean over the
renders of the image-mean SURE with the mean of the noise-corrected true MSE against the
dataset's reference (rendered with other seeds, so independent of every render here).

    python experiments/sure_realizations.py --data data/test-high --crop s002-c000 --spp 64 \
        --renders 32 --out experiments/results/sure-realizations-s002-64

Reports the per-render SURE / MSE ratios (their spread is what one image-level estimate can
be off by) and the ratio of means with a 95 % interval from the per-render differences
(normal approximation over R renders). Writes OUT.json and OUT.md.

``--buffers K``: each render is the mean of K independent sub-buffers at spp / K (render seeds
SEED_BASE + K i + k), and the sub-buffer SURE (jaxden.sure.sure_buffers) is reported next to
the probe (Stein) SURE on the same renders.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SEED_BASE = 900_000  # render seeds SEED_BASE + i; checked against the dataset's seeds


def crop_renders(data, crop_id: str, spp: int, renders: int):
    """``(crop, reference_frame, frames)`` for crop ``crop_id`` of dataset ``data``: the
    reference as stored, and a generator of ``renders`` new renders at ``spp`` with seeds
    SEED_BASE + i (refused if any is a seed the dataset used for this crop)."""
    from jaxden.data.builder import render_cached
    from jaxden.data.layout import load_manifest
    from jaxden.errors import DatasetError
    from jaxden.io.exr import read_frame

    manifest = load_manifest(data)
    crops = {c.id: c for c in manifest.crops}
    if crop_id not in crops:
        raise DatasetError(f"{data}: no crop {crop_id!r} (crops: {sorted(crops)})")
    crop = crops[crop_id]
    items = manifest.items_of(crop.id)
    used = {i.seed for i in items}
    seeds = [SEED_BASE + i for i in range(renders)]
    if used & set(seeds):
        raise DatasetError(f"render seeds {SEED_BASE}.. collide with the dataset's {sorted(used)}")
    reference = next(i for i in items if i.kind == "reference")
    size = tuple(manifest.config["size"])
    frames = (render_cached(crop.scene, spp, seed=seed, size=size, crop=crop.window).numpy()
              for seed in seeds)
    return crop, read_frame(Path(data) / reference.path), frames


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="complete dataset folder")
    parser.add_argument("--crop", required=True, help="crop id, e.g. s002-c000")
    parser.add_argument("--spp", type=int, required=True)
    parser.add_argument("--renders", type=int, default=32)
    parser.add_argument("--denoiser", default="oidn")
    parser.add_argument("--probes", type=int, default=4)
    parser.add_argument("--buffers", type=int, default=1,
                        help="sub-buffers per render (1: plain renders, Stein SURE only)")
    parser.add_argument("--seed", type=int, default=0, help="probe seed")
    parser.add_argument("--out", required=True, help="output path without suffix")
    args = parser.parse_args(argv)

    import jax
    from pd_report import provenance, write_report

    from jaxden import metrics
    from jaxden.denoisers import load_denoiser
    from jaxden.pdcache import denoise_with_sure
    from jaxden.sure import combine_buffers, sure_buffers

    k = args.buffers
    if k < 1 or args.spp % k or (k > 1 and args.spp // k < 2):
        raise SystemExit(f"--buffers {k} must divide --spp {args.spp} into >= 2 spp each")
    crop, ref, parts = crop_renders(args.data, args.crop, args.spp // k, args.renders * k)
    reference_spp = int(np.asarray(ref.spp)) if ref.spp is not None else "?"
    model = load_denoiser(args.denoiser)
    base = jax.random.PRNGKey(args.seed)
    source = provenance(args, {"denoiser": args.denoiser, "crop": args.crop, "spp": args.spp,
                               "buffers": k,
                               "render_seeds": [SEED_BASE, SEED_BASE + args.renders * k - 1]})
    rows = []
    for index in range(args.renders):
        buffers = [next(parts) for _ in range(k)]
        if k > 1:
            frame = combine_buffers(buffers).replace(spp=None)
            frame = frame.replace(**{n: np.asarray(getattr(frame, n), np.float32)
                                     for n in frame.features()})
        else:
            frame = buffers[0]
        result, _ = denoise_with_sure(model, frame, jax.random.fold_in(base, index),
                                      num_probes=args.probes)
        y = np.asarray(result.denoised, np.float32)
        row = {"seed": SEED_BASE + index * k, "sure": float(np.mean(np.asarray(result.sure))),
               "mse_nc": float(metrics.noise_corrected_mse(y, ref.color, ref.variance))}
        if k > 1:
            colours = np.stack([np.asarray(b.color, np.float64) for b in buffers])
            row["sure_buffers"] = float(np.mean(sure_buffers(model, frame, colours).sure))
        rows.append(row)
        print(f"render {index + 1}/{args.renders}: " + ", ".join(
            f"{key} {value:.4g}" for key, value in row.items() if key != "seed"), flush=True)
    true = np.array([r["mse_nc"] for r in rows])
    estimators = {"Stein (probes)": "sure"} | ({"sub-buffers": "sure_buffers"} if k > 1 else {})
    summaries = {name: summarize(np.array([r[key] for r in rows]), true)
                 for name, key in estimators.items()}
    summary = summaries["Stein (probes)"] | {"by_estimator": summaries}
    lines = [
        f"{args.crop} ({crop.scene}) at {args.spp} spp, {args.denoiser}, {len(rows)} independent "
        f"renders (seeds {SEED_BASE}..)" + (f", each of {k} sub-buffers" if k > 1 else "")
        + f", reference {reference_spp} spp:",
        "",
        ("| estimator | mean SURE | mean true MSE (noise-corr.) | ratio of means | 95 % interval "
         "| per-render ratio 5/50/95 % | renders within ±10 % |"),
        "|---|---:|---:|---:|---|---|---:|",
    ]
    for name, m in summaries.items():
        q = m["per_render_ratio_quantiles"]
        lines.append(
            f"| {name} | {m['mean_sure']:.4g} | {m['mean_mse_nc']:.4g} | "
            f"{m['ratio_of_means']:.3f} | {m['ratio_of_means_95'][0]:.3f}.."
            f"{m['ratio_of_means_95'][1]:.3f} | {q['0.05']:.2f} / {q['0.5']:.2f} / "
            f"{q['0.95']:.2f} | {m['per_render_within_10pct']:.0%} |")
    table = "\n".join(lines)
    write_report(Path(args.out), {"summary": summary, "rows": rows, "provenance": source}, table)
    return 0


def summarize(sure: np.ndarray, true: np.ndarray) -> dict:
    """Ratio of means with a 95 % interval (normal approximation of the per-render
    differences), per-render ratio quantiles and the share of renders within ±10 %."""
    diff = sure - true
    half = 1.96 * diff.std(ddof=1) / np.sqrt(len(diff))
    return {
        "renders": len(sure), "mean_sure": float(sure.mean()), "mean_mse_nc": float(true.mean()),
        "ratio_of_means": float(sure.mean() / true.mean()),
        "ratio_of_means_95": [float((sure.mean() - half) / true.mean()),
                              float((sure.mean() + half) / true.mean())],
        "per_render_ratio_quantiles": {q: float(np.quantile(sure / true, float(q)))
                                       for q in ("0.05", "0.25", "0.5", "0.75", "0.95")},
        "per_render_within_10pct": float(np.mean(np.abs(sure / true - 1) <= 0.1)),
    }


if __name__ == "__main__":
    sys.exit(main())
