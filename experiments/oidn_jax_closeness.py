"""OIDN in JAX against pyoidn: relative RMSE of the output, per filter configuration, quality and
frame size, on rendered frames.

    python experiments/oidn_jax_closeness.py --out experiments/results/oidn/oidn-jax-closeness

Frames: the built-in Cornell box rendered by jaxden at 4 spp (seed 3) at odd sizes and one
HD size, with its albedo and normal. For each of OIDN's HDR configurations (colour; +albedo;
+albedo+normal with clean and with noisy features) and quality (high, balanced, fast), the
output of :func:`jaxden.denoise.oidn_jax.oidn_denoise` against ``pyoidn.denoise`` on the same
inputs: sqrt(mean (ours - theirs)^2 / mean theirs^2), and the largest per-pixel relative
difference.

Sizes above OIDN's tiling threshold (2160^2 padded pixels; ``--tiled-size``, default 4000x1300:
OIDN splits it into 2 x 1 tiles) are measured for the colour-only (base network) and the
albedo + normal clean (large network) configurations at high quality, over OIDN's tiles as
``oidn_denoise`` runs them by default (``tiling="oidn"``). The large network's tile
(1312 x 2112) peaks at about 7 GB of host memory in float32 on the CPU.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

TILED_CONFIGS = ("hdr", "hdr+alb+nrm clean")
CONFIGS = {"hdr": (False, False, False), "hdr+alb": (True, False, False),
           "hdr+alb+nrm clean": (True, True, True), "hdr+alb+nrm noisy": (True, True, False)}
QUALITIES = ("high", "balanced", "fast")


def measure(sizes, seed: int, tiled_sizes=()):
    import pyoidn

    from jaxden.denoise.oidn_jax import load_oidn, oidn_denoise, oidn_tile_plan
    from jaxden.denoise.oidn_weights import load_blobs
    from jaxden.render import render_frame

    blobs = load_blobs()
    rows = []
    cases = [(size, config, quality, "oidn") for size in sizes for config in CONFIGS
             for quality in QUALITIES]
    cases += [(size, config, "high", "oidn") for size in tiled_sizes
              for config in TILED_CONFIGS]
    frames: dict = {}
    for (width, height), config, quality, tiling in cases:
        if (width, height) not in frames:
            frames.clear()  # one size at a time: the large frames are large
            frame = render_frame("cornell-box", spp=4, seed=seed, size=(width, height))
            frames[width, height] = (np.asarray(frame.color, np.float32),
                                     np.clip(np.asarray(frame.albedo, np.float32), 0, 1),
                                     np.clip(np.asarray(frame.normal, np.float32), -1, 1))
        color, albedo, normal = frames[width, height]
        use_albedo, use_normal, clean = CONFIGS[config]
        params, spec = load_oidn(albedo=use_albedo, normal=use_normal, clean_aux=clean,
                                 quality=quality, blobs=blobs)
        aux = (albedo if use_albedo else None, normal if use_normal else None)
        ours = np.asarray(oidn_denoise(params, spec, color, *aux, tiling=tiling), np.float64)
        theirs = pyoidn.denoise(color, *aux, hdr=True, clean_aux=clean,
                                quality=quality).astype(np.float64)
        relative = float(np.sqrt(np.mean((ours - theirs) ** 2) / np.mean(theirs ** 2)))
        worst = float(np.max(np.abs(ours - theirs) / (np.abs(theirs) + 1e-3)))
        plan = oidn_tile_plan(height, width, spec.size)
        tiles = f"{len(plan.columns)} x {len(plan.rows)}"
        rows.append({"size": f"{width}x{height}", "config": config, "quality": quality,
                     "blob": spec.blob, "tiles": tiles, "relative_rmse": relative,
                     "max_pixel_relative": worst})
        del ours, theirs
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", nargs="+", default=["61x47", "161x121", "9x130", "1281x719"])
    parser.add_argument("--tiled-size", nargs="*", default=["4000x1300"],
                        help="sizes above OIDN's tiling threshold, measured over its tiles for "
                             "two configurations (give none to skip them)")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    from jaxden.provenance import package_version, result_provenance, run_identity, write_result

    sizes = [tuple(int(v) for v in size.lower().split("x")) for size in args.size]
    tiled = [tuple(int(v) for v in size.lower().split("x")) for size in args.tiled_size]
    rows = measure(sizes, args.seed, tiled)
    result = {"rows": rows, "worst_relative_rmse": max(r["relative_rmse"] for r in rows)}
    result["provenance"] = result_provenance(run_identity(argv), seed=args.seed,
                                             pyoidn=package_version("pyoidn"))
    lines = ["## OIDN in JAX against pyoidn", "",
             (f"Relative RMSE of the output (and the largest per-pixel relative difference) "
              f"on the Cornell box at 4 spp (seed {args.seed}); pyoidn "
              f"{package_version('pyoidn')} on this CPU. Tiles: OIDN's tile grid (columns x "
              f"rows), as both ran it."), "",
             "| size | configuration | quality | weights | tiles | relative RMSE | worst pixel |",
             "|---|---|---|---|---|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['size']} | {row['config']} | {row['quality']} | {row['blob']} | "
                     f"{row['tiles']} | {row['relative_rmse']:.2e} | "
                     f"{row['max_pixel_relative']:.2e} |")
    lines += ["", f"Worst relative RMSE: {result['worst_relative_rmse']:.2e}."]
    write_result(args.out, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
