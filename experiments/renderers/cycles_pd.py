"""Progressive denoising of real Blender Cycles renders, through the command line a Blender user
would type: `jaxden merge --from cycles`, then `jaxden denoise` and `jaxden progressive` on the
merged frame, against a 4096-spp reference merged the same way.

    python experiments/renderers/cycles_pd.py --blender-python $BPY/bin/python \
        --out experiments/results/renderers/cycles-pd

Renders (experiments/renderers/cycles_render.py in Blender's own Python; cached in --work):
for each level, K renders of spp / K samples with distinct seeds; the reference is K renders
of 4096 / K samples (its variance from their spread gives the noise-corrected MSE). Errors
over the whole frame, the lamp and its glossy reflections included: noise-corrected MSE,
RMSE and relMSE of MC (the merged render), OIDN and PD(OIDN) with the shipped mixer.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

RENDER_SCRIPT = Path(__file__).with_name("cycles_render.py")
REFERENCE_SPP = 4096


def render(blender_python: str, work: Path, spp: int, seed: int, size: str) -> Path:
    path = work / f"r{spp}spp-{size}-seed{seed}.exr"
    if not path.exists():
        subprocess.run([blender_python, str(RENDER_SCRIPT), "--spp", str(spp), "--seed",
                        str(seed), "--size", size, "--out", str(path)], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return path


def jaxden(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "jaxden.cli", *args], check=True,
                   stdout=subprocess.DEVNULL)


def merged(blender_python, work, total_spp, k, size, first_seed) -> Path:
    """`jaxden merge --from cycles` over K renders of total_spp / K samples."""
    out = work / f"merged-{total_spp}spp-{size}-k{k}-seed{first_seed}.exr"
    if not out.exists():
        renders = [render(blender_python, work, total_spp // k, first_seed + i, size)
                   for i in range(k)]
        jaxden("merge", *map(str, renders), "--from", "cycles", "--out", str(out))
    return out


def errors(image, reference, reference_variance) -> dict:
    from jaxden.metrics import relmse

    mse = float(np.mean((image - reference) ** 2) - np.mean(reference_variance))
    return {"mse_nc": mse, "rmse_nc": float(np.sqrt(max(mse, 0.0))),
            "relmse": float(relmse(image, reference))}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--blender-python", required=True)
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--k", type=int, default=4, help="renders merged per frame")
    parser.add_argument("--size", default="128x96")
    parser.add_argument("--work", type=Path, default=None,
                        help="render cache (default $JAXDEN_HOME/cycles-pd)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    from jaxden.io.exr import read_frame, read_image
    from jaxden.paths import jaxden_home
    from jaxden.provenance import result_provenance, run_identity, write_result

    work = args.work or jaxden_home() / "cycles-pd"
    work.mkdir(parents=True, exist_ok=True)
    reference = read_frame(merged(args.blender_python, work, REFERENCE_SPP, args.k, args.size,
                                  9001), require=("color", "variance"))
    r, r_var = np.asarray(reference.color), np.asarray(reference.variance)
    rows = []
    for index, spp in enumerate(args.spp):
        frame_path = merged(args.blender_python, work, spp, args.k, args.size, 101 + 10 * index)
        oidn_path, pd_path = (work / f"{frame_path.stem}.{name}.exr" for name in ("oidn", "pd"))
        jaxden("denoise", str(frame_path), "--model", "oidn", "--out", str(oidn_path))
        jaxden("progressive", str(frame_path), "--denoiser", "oidn", "--out", str(pd_path))
        x = np.asarray(read_frame(frame_path).color)
        row = {"spp": spp, "mc": errors(x, r, r_var),
               "oidn": errors(read_image(oidn_path), r, r_var),
               "pd": errors(read_image(pd_path), r, r_var)}
        best = min(row["mc"]["mse_nc"], row["oidn"]["mse_nc"])
        row["pd_over_best_mse"] = row["pd"]["mse_nc"] / best
        rows.append(row)
    blender = subprocess.run([args.blender_python, "-c", "import bpy; print(bpy.app.version_string)"],
                             capture_output=True, text=True, check=True).stdout.split()[-1]
    result = {"rows": rows, "k": args.k, "size": args.size, "reference_spp": REFERENCE_SPP}
    result["provenance"] = result_provenance(
        run_identity(argv, program="python experiments/renderers/cycles_pd.py"),
        blender=blender, seeds="levels 101.., reference 9001..")
    lines = [f"## Progressive denoising of Blender {blender} Cycles renders", "",
             (f"{args.size}, each level `jaxden merge --from cycles` of {args.k} renders; "
             f"reference {REFERENCE_SPP} spp merged alike. Whole frame (lamp and glossy "
             f"reflections included): noise-corrected MSE, relMSE."), "",
             ("| spp | MC MSE | OIDN MSE | PD(OIDN) MSE | PD / min(MC, OIDN) | MC relMSE | "
             "OIDN relMSE | PD relMSE |"), "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['spp']} | {row['mc']['mse_nc']:.4g} | {row['oidn']['mse_nc']:.4g} "
                     f"| {row['pd']['mse_nc']:.4g} | {row['pd_over_best_mse']:.3f} | "
                     f"{row['mc']['relmse']:.4g} | {row['oidn']['relmse']:.4g} | "
                     f"{row['pd']['relmse']:.4g} |")
    write_result(args.out, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
