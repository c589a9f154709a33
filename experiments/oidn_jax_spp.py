"""OIDN in JAX against pyoidn over the sample counts jaxden works at: held-out crops at every spp
level of a dataset (and the built-in Cornell box rendered at 1 spp and at 4096 spp), for each
of OIDN's HDR configurations at high quality.

    python experiments/oidn_jax_spp.py --data $JAXDEN_HOME/data/test-chain \
        --data $JAXDEN_HOME/data/test-high-chain --out experiments/results/oidn/oidn-jax-spp

The size table (`oidn_jax_closeness.py`) fixes the input (the Cornell box at 4 spp) and varies
the frame; this one fixes the network's quality and varies the input statistics: 1-spp noise
with its fireflies, the smooth inputs at 4096 spp, and the held-out crops' scenes. Per dataset
and spp: the median and the worst relative RMSE over the crops, sqrt(mean (ours - theirs)^2 /
mean theirs^2), and the worst pixel's relative difference over them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

CONFIGS = {"hdr": (False, False, False), "hdr+alb": (True, False, False),
           "hdr+alb+nrm clean": (True, True, True), "hdr+alb+nrm noisy": (True, True, False)}
#: The rendered frame (beside the datasets): size and the sample counts.
RENDERED = ("cornell-box", (128, 128), (1, 4096))


def _inputs(frame):
    return (np.asarray(frame.color, np.float32),
            None if frame.albedo is None else np.clip(np.asarray(frame.albedo, np.float32), 0, 1),
            None if frame.normal is None else np.clip(np.asarray(frame.normal, np.float32), -1, 1))


def frames(datasets, seed: int):
    """``(source label, spp, crop id, (color, albedo, normal))`` of every held-out crop and
    spp level of each dataset, then of the rendered Cornell box."""
    from jaxden.data.crops import iter_crops
    from jaxden.render import render_frame

    for data in datasets:
        for crop, _, inputs in iter_crops(data, "test", None, min_spp=1):
            for spp, frame in inputs:
                yield Path(data).name, spp, crop.id, _inputs(frame)
    scene, size, levels = RENDERED
    for spp in levels:
        yield f"{scene} {size[0]}x{size[1]}", spp, scene, _inputs(
            render_frame(scene, spp=spp, seed=seed, size=size))


def measure(datasets, seed: int) -> list[dict]:
    import pyoidn

    from jaxden.denoise.oidn_jax import load_oidn, oidn_denoise
    from jaxden.denoise.oidn_weights import load_blobs

    blobs = load_blobs()
    networks = {name: load_oidn(albedo=a, normal=n, clean_aux=c, blobs=blobs)
                for name, (a, n, c) in CONFIGS.items()}
    rows = []
    for source, spp, crop, (color, albedo, normal) in frames(datasets, seed):
        for name, (use_albedo, use_normal, clean) in CONFIGS.items():
            params, spec = networks[name]
            aux = (albedo if use_albedo else None, normal if use_normal else None)
            ours = np.asarray(oidn_denoise(params, spec, color, *aux), np.float64)
            theirs = np.asarray(pyoidn.denoise(color, *aux, hdr=True, clean_aux=clean,
                                               quality="high"), np.float64)
            error = np.sqrt(np.mean((ours - theirs) ** 2) / np.mean(theirs ** 2))
            worst = np.max(np.abs(ours - theirs) / (np.abs(theirs) + 1e-3))
            rows.append({"source": source, "spp": int(spp), "crop": crop, "config": name,
                         "relative_rmse": float(error), "worst_pixel": float(worst)})
    return rows


def summarize(rows: list[dict]) -> list[dict]:
    groups: dict = {}
    for row in rows:
        groups.setdefault((row["source"], row["spp"], row["config"]), []).append(row)
    out = []
    for (source, spp, config), members in groups.items():
        errors = [m["relative_rmse"] for m in members]
        out.append({"source": source, "spp": spp, "config": config, "crops": len(members),
                    "median_relative_rmse": float(np.median(errors)),
                    "worst_relative_rmse": float(max(errors)),
                    "worst_pixel": float(max(m["worst_pixel"] for m in members))})
    return out


def markdown(summary: list[dict]) -> str:
    worst = max(s["worst_relative_rmse"] for s in summary)
    lines = ["## OIDN in JAX against pyoidn, by spp", "",
             "High quality; relative RMSE of the output over the crops of each source and spp "
             "(median, worst) and the largest per-pixel relative difference (|ours - theirs| / "
             "(|theirs| + 1e-3)). Held-out crops: the test split of each dataset; the Cornell "
             "box rendered by jaxden (seed given in the command).", "",
             "| source | spp | configuration | crops | relative RMSE: median | worst | "
             "worst pixel |", "|---|---:|---|---:|---:|---:|---:|"]
    for s in sorted(summary, key=lambda s: (s["source"], s["spp"], s["config"])):
        lines.append(f"| {s['source']} | {s['spp']} | {s['config']} | {s['crops']} | "
                     f"{s['median_relative_rmse']:.2e} | {s['worst_relative_rmse']:.2e} | "
                     f"{s['worst_pixel']:.2e} |")
    lines += ["", f"Worst of all: {worst:.2e} (target: float32 rounding, about 1e-5)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", action="append", default=[],
                        help="a complete dataset whose test split to score (repeatable)")
    parser.add_argument("--seed", type=int, default=3, help="seed of the rendered frames")
    parser.add_argument("--out", required=True, help="output path without suffix")
    args = parser.parse_args(argv)
    from jaxden.errors import JaxdenError

    try:
        rows = measure(args.data, args.seed)
    except JaxdenError as error:
        print(f"oidn_jax_spp: error: {error}", file=sys.stderr)
        return 2
    from jaxden.provenance import result_provenance, run_identity, write_result

    summary = summarize(rows)
    identity = run_identity(argv)
    result = {"provenance": result_provenance(identity, seed=args.seed,
                                              datasets=[str(d) for d in args.data]),
              "summary": summary, "rows": rows}
    write_result(args.out, result, markdown(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
