"""OIDN in JAX against pyoidn: relative RMSE of the output, per filter configuration, quality and
frame size, on rendered frames.

    python experiments/oidn_jax_closeness.py --out experiments/results/oidn/oidn-jax-closeness

Frames: the built-in Cornell box rendered by jaxden at 4 spp (seed 3) at odd sizes and one
HD size, with its albedo and normal. For each of OIDN's HDR configurations (colour; +albedo;
+albedo+normal with clean and with noisy features) and quality (high, balanced, fast), the
output of :func:`jaxden.denoise.oidn_jax.oidn_denoise` against ``pyoidn.denoise`` on the same
inputs: sqrt(mean (ours - theirs)^2 / mean theirs^2), and the largest per-pixel relative
difference. Sizes above OIDN's tiling threshold (2160^2 padded pixels) are not measured here:
OIDN tiles those, this function does not.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

CONFIGS = {"hdr": (False, False, False), "hdr+alb": (True, False, False),
           "hdr+alb+nrm clean": (True, True, True), "hdr+alb+nrm noisy": (True, True, False)}
QUALITIES = ("high", "balanced", "fast")


def measure(sizes, seed: int):
    import pyoidn

    from jaxden.denoise.oidn_jax import load_oidn, oidn_denoise
    from jaxden.denoise.oidn_weights import load_blobs
    from jaxden.render import render_frame

    blobs = load_blobs()
    rows = []
    for width, height in sizes:
        frame = render_frame("cornell-box", spp=4, seed=seed, size=(width, height))
        color = np.asarray(frame.color, np.float32)
        albedo = np.clip(np.asarray(frame.albedo, np.float32), 0, 1)
        normal = np.clip(np.asarray(frame.normal, np.float32), -1, 1)
        for config, (use_albedo, use_normal, clean) in CONFIGS.items():
            for quality in QUALITIES:
                params, spec = load_oidn(albedo=use_albedo, normal=use_normal, clean_aux=clean,
                                         quality=quality, blobs=blobs)
                aux = (albedo if use_albedo else None, normal if use_normal else None)
                ours = np.asarray(oidn_denoise(params, spec, color, *aux), np.float64)
                theirs = pyoidn.denoise(color, *aux, hdr=True, clean_aux=clean,
                                        quality=quality).astype(np.float64)
                relative = float(np.sqrt(np.mean((ours - theirs) ** 2) / np.mean(theirs ** 2)))
                worst = float(np.max(np.abs(ours - theirs) / (np.abs(theirs) + 1e-3)))
                rows.append({"size": f"{width}x{height}", "config": config, "quality": quality,
                             "blob": spec.blob, "relative_rmse": relative,
                             "max_pixel_relative": worst})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", nargs="+", default=["61x47", "161x121", "9x130", "1281x719"])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    from jaxden.provenance import package_version, result_provenance, run_identity, write_result

    sizes = [tuple(int(v) for v in size.lower().split("x")) for size in args.size]
    rows = measure(sizes, args.seed)
    result = {"rows": rows, "worst_relative_rmse": max(r["relative_rmse"] for r in rows)}
    result["provenance"] = result_provenance(run_identity(argv), seed=args.seed,
                                             pyoidn=package_version("pyoidn"))
    lines = ["## OIDN in JAX against pyoidn", "",
             f"Relative RMSE of the output (and the largest per-pixel relative difference) on "
             f"the Cornell box at 4 spp (seed {args.seed}); pyoidn "
             f"{package_version('pyoidn')} on this CPU.", "",
             "| size | configuration | quality | weights | relative RMSE | worst pixel |",
             "|---|---|---|---|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['size']} | {row['config']} | {row['quality']} | {row['blob']} | "
                     f"{row['relative_rmse']:.2e} | {row['max_pixel_relative']:.2e} |")
    lines += ["", f"Worst relative RMSE: {result['worst_relative_rmse']:.2e}."]
    write_result(args.out, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
