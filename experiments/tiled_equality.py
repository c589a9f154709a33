"""Tiles against the whole frame: progressive denoising, SURE and denoising over tiles equal the
whole-frame result to float rounding, for every shipped mixer and denoiser.

    python experiments/tiled_equality.py --out experiments/results/pd/tiled-equality

Frame: the built-in Cornell box at 4 spp (seed 1, the benchmarks' frame) at 1920 x 1080, with
its ceiling lamp and the boxes' edges; tiles of 256 pixels (balanced per axis: 8 x 5 of 240 x
216), so seams cross the lamp and edges everywhere. Each row runs the same computation whole
(one tile) and over tiles with the overlap of the stages' receptive fields, and reports
sqrt(mean (tiled - whole)^2 / mean whole^2) per output, and the same with an overlap 8
pixels short of the fields: how much that shows depends on the weight the stages put at the
edge of their fields (a Gaussian's last taps weigh little; tests/test_tiled.py shows the
seams with overlaps that leave a stage out). Pipelines: PD(OIDN) with the shipped
``oidn-pd`` (OIDN whole-frame, finite-difference SURE one probe at a time; mixer and
t-statistic over tiles), PD(WSKP-6) with ``wskp-6-pd`` (everything per tile, SURE by jvp),
WSKP-3 and the U-Net (``unet-rt``) with the closed-form mixer, SURE by jvp of WSKP-6 alone,
and the three JAX denoisers alone. One SURE probe throughout (the equality does not depend
on the number; four would quadruple the U-Net's jvp on the 2 cores).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

TILE = 256
SHORT = 8


def _rel(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2) / np.mean(b ** 2)))


def measure(size, seed: int):
    import jax

    from jaxden.bench import bench_frame
    from jaxden.denoise.registry import load_denoiser
    from jaxden.denoise.tiled import denoise_frame
    from jaxden.progressive.mixer_checkpoints import load_mixer
    from jaxden.progressive.mixer_config import closed_form_mixer
    from jaxden.progressive.pipeline import shipped_mixer_path
    from jaxden.progressive.tiled import progressive_frame, tile_halo
    from jaxden.sure.settings import SureSettings
    from jaxden.sure.tiled import sure_frame

    frame = bench_frame(size).numpy()
    key = jax.random.PRNGKey(seed)
    rows = []
    pipelines = [("oidn", "oidn-pd"), ("wskp-6", "wskp-6-pd"), ("wskp-3", "closed-form"),
                 ("unet-rt", "closed-form")]
    for denoiser_name, mixer_name in pipelines:
        denoiser = load_denoiser(denoiser_name)
        if mixer_name == "closed-form":
            params, config = closed_form_mixer()
        else:
            params, config = load_mixer(str(shipped_mixer_path(denoiser_name)))
        keep = ("z", "alpha_prime", "denoised", "sure")
        start = time.perf_counter()
        one_probe = SureSettings(probes=1)
        whole, _ = progressive_frame(frame, denoiser, params, config, key, keep=keep, tile=0,
                                     sure=one_probe)
        whole_s = time.perf_counter() - start
        start = time.perf_counter()
        tiled, plan = progressive_frame(frame, denoiser, params, config, key, keep=keep,
                                        tile=TILE, sure=one_probe)
        tiled_s = time.perf_counter() - start
        halo = tile_halo(denoiser, config, config.tstat)
        from jaxden.progressive.tiled import progressive_denoise_tiled

        short, _ = progressive_denoise_tiled(
            frame, denoiser, params, config, key, sure=one_probe, tstat=config.tstat,
            keep=("z",), tile=TILE, halo=halo - SHORT)
        rows.append({"pipeline": f"PD({denoiser_name}) + {mixer_name}", "halo": halo,
                     "tiles": len_tiles(size, TILE, halo, plan.multiple),
                     **{f"{name}_relative_rmse": _rel(tiled[name], whole[name]) for name in keep},
                     "short_z_relative_rmse": _rel(short["z"], whole["z"]),
                     "whole_s": whole_s, "tiled_s": tiled_s})
        print(rows[-1], flush=True)
    for denoiser_name in ("wskp-6", "wskp-3", "unet-rt"):
        denoiser = load_denoiser(denoiser_name)
        whole, _ = denoise_frame(denoiser, frame, tile=0)
        tiled, plan = denoise_frame(denoiser, frame, tile=TILE)
        rows.append({"pipeline": f"{denoiser_name} alone", "halo": plan.halo,
                     "tiles": len_tiles(size, TILE, plan.halo,
                                        denoiser.tile_spec().multiple),
                     "z_relative_rmse": _rel(tiled, whole)})
    denoiser = load_denoiser("wskp-6")
    whole, _ = sure_frame(denoiser, frame, key, sure=SureSettings(probes=1), tile=0)
    tiled, _ = sure_frame(denoiser, frame, key, sure=SureSettings(probes=1), tile=TILE)
    rows.append({"pipeline": "SURE of wskp-6 by jvp (1 probe)",
                 "halo": denoiser.tile_spec().radius,
                 "tiles": len_tiles(size, TILE, denoiser.tile_spec().radius, 1),
                 "sure_relative_rmse": _rel(tiled.sure, whole.sure),
                 "denoised_relative_rmse": _rel(tiled.denoised, whole.denoised)})
    return rows


def len_tiles(size, tile, halo, multiple) -> int:
    from jaxden.tiling import tile_grid

    return len(tile_grid(size[1], size[0], tile, halo, multiple))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--seed", type=int, default=0, help="seed of the SURE probes")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    from jaxden.provenance import result_provenance, run_identity, write_result

    size = tuple(int(v) for v in args.size.lower().split("x"))
    rows = measure(size, args.seed)
    worst = max(v for row in rows for k, v in row.items()
                if k.endswith("relative_rmse") and not k.startswith("short"))
    result = {"rows": rows, "size": args.size, "tile": TILE, "worst_relative_rmse": worst}
    result["provenance"] = result_provenance(run_identity(argv), seed=args.seed,
                                             frame="cornell-box, 4 spp, seed 1")
    lines = ["## Tiles against the whole frame", "",
             f"The Cornell box at 4 spp (seed 1), {args.size}, tiles of {TILE} px (balanced), "
             f"SURE probes from seed {args.seed}. Relative RMSE of each output over tiles "
             f"against the whole frame; the last column with an overlap {SHORT} px short of the "
             f"receptive fields.", "",
             "| pipeline | overlap px | tiles | z | alpha' | y | SURE | z, overlap short |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]

    def cell(row, key):
        return f"{row[key]:.1e}" if key in row else "-"

    for row in rows:
        lines.append(f"| {row['pipeline']} | {row['halo']} | {row['tiles']} | "
                     f"{cell(row, 'z_relative_rmse')} | {cell(row, 'alpha_prime_relative_rmse')} | "
                     f"{cell(row, 'denoised_relative_rmse')} | {cell(row, 'sure_relative_rmse')} | "
                     f"{cell(row, 'short_z_relative_rmse')} |")
    lines += ["", f"Worst relative RMSE over tiles with the full overlap: {worst:.1e}."]
    write_result(args.out, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
