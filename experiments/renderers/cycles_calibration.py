"""Is the variance `jaxden merge` estimates from K Cycles renders calibrated? R independent merges
of K renders each (all seeds distinct), against the empirical variance of the R merged means.

    python experiments/renderers/cycles_calibration.py --blender-python $BPY/bin/python \
        --out experiments/results/renderers/cycles-merge-calibration

Renders (cached in --work) are made by experiments/renderers/cycles_render.py in Blender's own
Python (``pip install bpy`` in a venv of its own); everything else runs in jaxden's. Per pixel:
the empirical variance of the R merged colours (R - 1 degrees of freedom) over the mean of the
R estimates (each from K - 1 degrees of freedom). Pixels that see an emitter (merged colour
above --emitter radiance) and pixels without variance (background) are left out. The ratio of
two noisy variances has a median below 1 even when both are unbiased, so the script also
draws the same ratio under a Gaussian null with the same degrees of freedom (seed 0) and
reports the observed median over the null's: 1 is calibrated. Also the ratio of the pixel
sums of the two variances.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

RENDER_SCRIPT = Path(__file__).with_name("cycles_render.py")


def render_all(blender_python: str, work: Path, count: int, spp: int, size: str) -> list[Path]:
    work.mkdir(parents=True, exist_ok=True)
    paths = []
    for seed in range(1, count + 1):
        path = work / f"r{spp}spp-{size}-seed{seed}.exr"
        if not path.exists():
            subprocess.run([blender_python, str(RENDER_SCRIPT), "--spp", str(spp), "--seed",
                            str(seed), "--size", size, "--out", str(path)], check=True,
                           stdout=subprocess.DEVNULL)
        paths.append(path)
    return paths


def null_median(merges: int, k: int, pixels: int, seed: int = 0) -> float:
    """Median over pixels of (empirical variance of R merged means) / (mean of R spread
    estimates) for Gaussian noise of unit variance, the same R and K."""
    rng = np.random.default_rng(seed)
    renders = rng.standard_normal((merges, k, pixels))
    means = renders.mean(axis=1)
    estimates = renders.var(axis=1, ddof=1) / k
    return float(np.median(means.var(axis=0, ddof=1) / estimates.mean(axis=0)))


def measure(paths: list[Path], merges: int, k: int, emitter: float) -> dict:
    from jaxden.data.merge import merge_renders
    from jaxden.io.exr import read_frame

    frames = [read_frame(p, convention="cycles") for p in paths]
    merged = [merge_renders(frames[i * k:(i + 1) * k]) for i in range(merges)]
    colours = np.stack([np.asarray(m.color, np.float64) for m in merged])
    estimates = np.stack([np.asarray(m.variance, np.float64) for m in merged])
    empirical = colours.var(axis=0, ddof=1)
    estimate = estimates.mean(axis=0)
    keep = (colours.mean(axis=0).max(axis=-1, keepdims=True) < emitter) & (estimate > 0)
    keep = np.broadcast_to(keep, estimate.shape)
    ratio = empirical[keep] / estimate[keep]
    null = null_median(merges, k, int(keep.sum()))
    return {"merges": merges, "renders_per_merge": k, "values": int(keep.sum()),
            "values_total": int(keep.size), "median_ratio": float(np.median(ratio)),
            "null_median_ratio": null,
            "median_over_null": float(np.median(ratio) / null),
            "sum_ratio": float(empirical[keep].sum() / estimate[keep].sum())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--blender-python", required=True)
    parser.add_argument("--merges", type=int, default=16)
    parser.add_argument("--k", type=int, default=4, help="renders per merge")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--size", default="64x48")
    parser.add_argument("--emitter", type=float, default=5.0)
    parser.add_argument("--work", type=Path, default=None,
                        help="render cache (default $JAXDEN_HOME/cycles-calibration)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    from jaxden.paths import jaxden_home
    from jaxden.provenance import result_provenance, run_identity, write_result

    work = args.work or jaxden_home() / "cycles-calibration"
    paths = render_all(args.blender_python, work, args.merges * args.k, args.spp, args.size)
    result = measure(paths, args.merges, args.k, args.emitter)
    blender = subprocess.run([args.blender_python, "-c", "import bpy; print(bpy.app.version_string)"],
                             capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
    result["provenance"] = result_provenance(
        run_identity(argv, program="python experiments/renderers/cycles_calibration.py"),
        blender=blender, spp=args.spp, size=args.size, seeds=f"1..{args.merges * args.k}")
    markdown = "\n".join([
        "## Is `jaxden merge`'s variance calibrated on real Cycles renders?", "",
        (f"{args.merges} merges of {args.k} Blender {blender} Cycles renders each ({args.size}, "
        f"{args.spp} spp, seeds 1..{args.merges * args.k}); per pixel and channel, the empirical "
        f"variance of the merged colours over the mean of the merges' estimates; "
        f"{result['values']} of {result['values_total']} values (emitters above radiance "
        f"{args.emitter:g} and background without variance left out)."), "",
        "| median ratio | its median under a Gaussian null | observed / null | sum ratio |",
        "|---:|---:|---:|---:|",
        (f"| {result['median_ratio']:.3f} | {result['null_median_ratio']:.3f} | "
        f"{result['median_over_null']:.3f} | {result['sum_ratio']:.3f} |"), ""])
    write_result(args.out, result, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
