"""The offline comparison (Tungsten-style, 64 spp): NFOR beside MC, OIDN, PD(OIDN), WSKP-6,
SVGF and BMFR (their single-frame forms) on whole frames of held-out scenes.

    python experiments/offline_nfor.py [--work $JAXDEN_HOME/offline-nfor] \
        [--out experiments/results/offline/offline-nfor]

Renders (cached in --work) each scene at 256 x 256 with ``jaxden render --spp 64 --buffers 2``
(the 64-spp frame and its two 32-spp halves, which NFOR needs: ``jaxden denoise IN --model
nfor --buffers IN.b0.exr IN.b1.exr``) and a 4096-spp reference of another seed; every method
runs through the command line a user types on the 64-spp frame. Scenes: procedural seeds
7000..7005 (the real-time held-out set's seeds: no training set of jaxden's models saw them)
and two built-in scenes with what breaks denoisers (``small-lights``: small bright emitters;
``glossy-glass``: glints and caustics; WSKP-6's training set holds other renders of these
two). Errors over the whole frame, linear HDR: RMSE,
noise-corrected MSE, relMSE, FLIP; PSNR and SSIM tone-mapped.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

SCENES = tuple(f"procedural:{seed}" for seed in range(7000, 7006)) + ("small-lights",
                                                                        "glossy-glass")
SIZE, SPP, REFERENCE_SPP, SEED, REFERENCE_SEED = "256x256", 64, 4096, 3, 9001
#: (label, ``jaxden`` arguments after the input; OUT is appended by :func:`run`).
METHODS = (("NFOR", ("denoise", "--model", "nfor", "--buffers", "{b0}", "{b1}")),
           ("OIDN", ("denoise", "--model", "oidn")),
           ("PD(OIDN)", ("progressive", "--denoiser", "oidn")),
           ("WSKP-6", ("denoise", "--model", "wskp-6")),
           ("SVGF", ("denoise", "--model", "svgf")),
           ("BMFR", ("denoise", "--model", "bmfr")))
COLUMNS = (("rmse", "RMSE", "{:.4g}"), ("mse_nc", "MSE (noise-corr.)", "{:.4g}"),
           ("relmse", "relMSE", "{:.4g}"), ("flip", "FLIP", "{:.4f}"),
           ("psnr", "PSNR (dB)", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"))


def jaxden(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "jaxden.cli", *map(str, args)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def rendered(work: Path, scene: str, spp: int, seed: int, buffers: bool) -> Path:
    path = work / f"{scene.replace(':', '-')}-{spp}spp-seed{seed}.exr"
    if not path.exists():
        jaxden("render", scene, "--spp", spp, "--size", SIZE, "--seed", seed,
               *(("--buffers", 2) if buffers else ()), "--out", path)
    return path


def run(work: Path, frame: Path, label: str, args: tuple[str, ...]) -> Path:
    out = work / f"{frame.stem}.{label.lower().replace('(', '-').replace(')', '')}.exr"
    if not out.exists():
        b0, b1 = (frame.with_name(f"{frame.stem}.b{i}.exr") for i in (0, 1))
        jaxden(args[0], frame, *(a.format(b0=b0, b1=b1) for a in args[1:]), "--out", out)
    return out


def main(argv=None) -> int:
    from jaxden.evaluate.denoise import image_errors
    from jaxden.io.exr import read_frame, read_image
    from jaxden.paths import jaxden_home
    from jaxden.provenance import result_provenance, run_identity, write_result

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work", type=Path, default=None,
                        help="render cache (default $JAXDEN_HOME/offline-nfor)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results"
                        / "offline" / "offline-nfor")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    args = parser.parse_args(argv)
    work = args.work or jaxden_home() / "offline-nfor"
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in args.scenes:
        frame = rendered(work, scene, SPP, SEED, buffers=True)
        reference = read_frame(rendered(work, scene, REFERENCE_SPP, REFERENCE_SEED, False),
                               require=("color", "variance"))
        row = {"scene": scene, "MC": image_errors(read_frame(frame).color, reference)}
        for label, method in METHODS:
            row[label] = image_errors(read_image(run(work, frame, label, method)), reference)
        rows.append(row)
        print(f"{scene}: " + ", ".join(f"{k} {v['rmse']:.4g}" for k, v in row.items()
                                         if isinstance(v, dict)), file=sys.stderr, flush=True)
    labels = ["MC", *(label for label, _ in METHODS)]
    means = {label: {key: float(np.mean([r[label][key] for r in rows]))
                     for key, _, _ in COLUMNS} for label in labels}
    best = {key: min(labels, key=lambda label, key=key: means[label][key] if key not in
                     ("psnr", "ssim") else -means[label][key]) for key, _, _ in COLUMNS}
    lines = ["## Offline denoising at 64 spp: NFOR and the others on whole frames", "",
             f"{SIZE}, {len(rows)} scenes ({', '.join(r['scene'] for r in rows)}), each "
             f"rendered at {SPP} spp (seed {SEED}) with two {SPP // 2}-spp halves for NFOR, "
             f"against a {REFERENCE_SPP}-spp reference (seed {REFERENCE_SEED}); every method "
             "by the command line on the same frame. Means over the scenes, linear HDR; PSNR and SSIM "
             "tone-mapped. The best of each column in bold.", "",
             "| method | " + " | ".join(title for _, title, _ in COLUMNS) + " |",
             "|---|" + "---:|" * len(COLUMNS)]
    for label in labels:
        cells = [(f"**{fmt.format(means[label][key])}**" if best[key] == label
                  else fmt.format(means[label][key])) for key, _, fmt in COLUMNS]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "Per scene, RMSE:", "",
              "| scene | " + " | ".join(labels) + " |", "|---|" + "---:|" * len(labels)]
    for row in rows:
        lines.append(f"| {row['scene']} | "
                     + " | ".join(f"{row[label]['rmse']:.4g}" for label in labels) + " |")
    result = {"rows": rows, "means": means, "size": SIZE, "spp": SPP,
              "reference_spp": REFERENCE_SPP}
    result["provenance"] = result_provenance(run_identity(argv), seed=SEED,
                                             reference_seed=REFERENCE_SEED)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_result(args.out, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
