"""Lamps seen by the camera in Blender Cycles renders: the emission that Cycles adds to its
Denoising Albedo, before and after `--from cycles` takes it out, for MC, WSKP-6, OIDN (each
also with ``:emission=separate``) and progressive denoising (PD) on OIDN and WSKP-6 with
probe SURE and with sub-buffer SURE (``--buffers``), through the commands a Blender user
types (`jaxden merge --from cycles`, `jaxden denoise`, `jaxden progressive`).

    python experiments/renderers/cycles_emission.py --blender-python $BPY/bin/python \\
        --out experiments/results/renderers/cycles-emission

Renders (experiments/renderers/cycles_render.py --emission in Blender's own Python; cached in
--work, default $JAXDEN_HOME/renderers/cycles-emission): two scenes with a small lamp in view
(``window``: jaxden issue 48's, a lamp of strength 400, a sun through a window, a gold
Suzanne, a glossy torus; ``spheres``: a lamp of strength 50 beside a glossy metal sphere),
at --size. Each frame is K renders of S samples with seeds ``1000 * set + 100 * [S == 64]
+ 1 .. K`` merged by `jaxden merge --from cycles`; the reference is K renders of
--reference-spp / K samples (seeds 9001 ..), merged alike (its variance gives the
noise-corrected MSE; its Emission pass the emitter pixels).

The albedo a frame carries, four ways (the colour, variance and emission are the same):

- ``before``: the mean of the renders' raw Denoising Albedo, as jaxden read it before the fix
  (the lamps' emission in it: values up to the lamp's strength);
- ``after``: as `jaxden merge --from cycles` reads it now, clip(Denoising Albedo, 0, 1) per
  render, then the mean (a lamp pixel is white; checked against the renders here);
- ``reflectance``: the surfaces' own albedo, clip(Denoising Albedo - Emission, 0, 1) per
  render, then the mean (the reading first built for the issue, measured and not taken);
- ``subtract``: max(Denoising Albedo - Emission, 0), not clipped at 1 (the light that Cycles
  adds through mirror-like surfaces, which no pass holds, stays in it).

Errors against the reference: RMSE over the whole frame (linear HDR, every pixel and channel),
its noise-corrected form sqrt(MSE - mean reference variance), the mean and the peak of the
emitter pixels (those whose reference Emission pass is above 0, every channel) against the
reference's, and the RMSE off those pixels.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

RENDER_SCRIPT = Path(__file__).with_name("cycles_render.py")
ALBEDO = tuple(f"ViewLayer.Denoising Albedo.{c}" for c in "RGB")
EMISSION = tuple(f"ViewLayer.Emission.{c}" for c in "RGB")
#: name -> (command, denoiser, sub-buffer SURE)
METHODS = {
    "WSKP-6": ("denoise", "wskp-6", False),
    "WSKP-6:emission=separate": ("denoise", "wskp-6:emission=separate", False),
    "OIDN": ("denoise", "oidn", False),
    "OIDN:emission=separate": ("denoise", "oidn:emission=separate", False),
    "PD(OIDN)": ("progressive", "oidn", False),
    "PD(OIDN) --buffers": ("progressive", "oidn", True),
    "PD(OIDN:emission=separate)": ("progressive", "oidn:emission=separate", False),
    "PD(OIDN:emission=separate) --buffers": ("progressive", "oidn:emission=separate", True),
    "PD(WSKP-6)": ("progressive", "wskp-6", False),
    "PD(WSKP-6) --buffers": ("progressive", "wskp-6", True),
}
VARIANTS = ("before", "after", "reflectance", "subtract")


def render(blender_python: str, work: Path, scene: str, spp: int, seed: int, size: str) -> Path:
    path = work / f"{scene}-{size}-{spp}spp-seed{seed}.exr"
    if not path.exists():
        subprocess.run([blender_python, str(RENDER_SCRIPT), "--scene", scene, "--emission",
                        "--spp", str(spp), "--seed", str(seed), "--size", size, "--out",
                        str(path)], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
    return path


def jaxden(log: Path, *args: str) -> None:
    with open(log, "a") as stderr:
        stderr.write(f"$ jaxden {' '.join(args)}\n")
        stderr.flush()
        subprocess.run([sys.executable, "-m", "jaxden.cli", *args], check=True,
                       stdout=subprocess.DEVNULL, stderr=stderr)


def merged(blender_python, work, scene, spp, k, size, first_seed) -> tuple[Path, list[Path]]:
    """`jaxden merge --from cycles` over K renders of ``spp`` samples; (file, renders)."""
    renders = [render(blender_python, work, scene, spp, first_seed + i, size) for i in range(k)]
    out = work / f"{scene}-{size}-{k}x{spp}spp-seed{first_seed}.exr"
    if not out.exists():
        jaxden(work / "log.txt", "merge", *map(str, renders), "--from", "cycles", "--out",
               str(out))
    return out, renders


def variant(after: Path, renders: list[Path], name: str) -> Path:
    """The merged frame ``after`` with the albedo of ``name`` (module docstring), written
    beside it with the record of its renders (so that ``--buffers`` takes them)."""
    from jaxden.data.merge import read_buffer_list
    from jaxden.io.exr import read_channels, read_frame, write_frame

    raw = [np.stack([channels[c] for c in ALBEDO], axis=-1)
           for channels in (read_channels(r, ALBEDO)[0] for r in renders)]
    if name == "after":  # what the reading gives: checked, not made here
        albedo = np.asarray(read_frame(after).albedo)
        np.testing.assert_allclose(albedo, np.mean([np.clip(a, 0, 1) for a in raw], axis=0),
                                   rtol=1e-6, atol=1e-7, err_msg=str(after))
        return after
    out = after.with_name(f"{after.stem}.{name}.exr")
    if out.exists():
        return out
    if name in ("reflectance", "subtract"):
        emission = [np.stack([channels[c] for c in EMISSION], axis=-1)
                    for channels in (read_channels(r, EMISSION)[0] for r in renders)]
        raw = [np.maximum(a - e, 0.0) for a, e in zip(raw, emission)]
    if name == "reflectance":
        raw = [np.minimum(a, 1.0) for a in raw]
    frame = read_frame(after)
    write_frame(out, frame.replace(albedo=np.mean(raw, axis=0).astype(np.float32)),
                attributes=read_buffer_list(after).attributes())
    return out


def errors(image, reference, reference_variance, emitters) -> dict:
    squared = (np.asarray(image, np.float64) - reference) ** 2
    mse = float(squared.mean())
    return {"rmse": float(np.sqrt(mse)),
            "rmse_nc": float(np.sqrt(max(mse - float(np.mean(reference_variance)), 0.0))),
            "emitter_mean": float(image[emitters].mean()),
            "emitter_peak": float(image[emitters].max()),
            "rmse_off_emitters": float(np.sqrt(squared[~emitters].mean())),
            "emitter_share_of_se": float(squared[emitters].sum() / squared.sum())}


def run_frame(frame: Path, renders: list[Path], variant_name: str, reference, work) -> dict:
    from jaxden.io.exr import read_frame, read_image

    r, r_var, emitters = reference
    x = np.asarray(read_frame(frame).color)
    row = {"MC": errors(x, r, r_var, emitters)}
    log = work / "log.txt"
    for method, (command, denoiser, buffers) in METHODS.items():
        tag = (denoiser.replace(":", "_").replace("=", "-") + ("-buffers" if buffers else "")
               + ("-pd" if command == "progressive" else ""))
        out = frame.with_name(f"{frame.stem}.{tag}.exr")
        if not out.exists():
            argv = [command, str(frame), "--model" if command == "denoise" else "--denoiser",
                    denoiser, "--out", str(out)]
            if buffers:
                argv += ["--buffers", *map(str, renders)]
            jaxden(log, *argv)
        row[method] = errors(read_image(out), r, r_var, emitters)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--blender-python", required=True)
    parser.add_argument("--scenes", nargs="+", default=["window", "spheres"])
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 64],
                        help="samples of each render (default 16 64)")
    parser.add_argument("--seed-sets", type=int, default=2)
    parser.add_argument("--k", type=int, default=4, help="renders merged per frame")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--reference-spp", type=int, default=4096)
    parser.add_argument("--work", type=Path, default=None,
                        help="render cache (default $JAXDEN_HOME/renderers/cycles-emission)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    from jaxden.io.exr import read_frame
    from jaxden.paths import jaxden_home
    from jaxden.provenance import result_provenance, run_identity, write_result

    work = args.work or jaxden_home() / "renderers" / "cycles-emission"
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in args.scenes:
        ref_path, _ = merged(args.blender_python, work, scene, args.reference_spp // args.k,
                             args.k, args.size, 9001)
        ref = read_frame(ref_path, require=("color", "variance", "emission"))
        reference = (np.asarray(ref.color, np.float64), np.asarray(ref.variance),
                     np.asarray(ref.emission).max(axis=-1) > 0)
        emitters = reference[2]
        for spp in args.spp:
            for seed_set in range(1, args.seed_sets + 1):
                first = 1000 * seed_set + (100 if spp == 64 else 0) + 1
                after, renders = merged(args.blender_python, work, scene, spp, args.k,
                                        args.size, first)
                for name in VARIANTS:
                    frame = variant(after, renders, name)
                    result = run_frame(frame, renders, name, reference, work)
                    rows.append({"scene": scene, "spp": spp, "k": args.k, "seeds": first,
                                 "variant": name, "methods": result,
                                 "reference": {"emitter_mean": float(ref.color[emitters].mean()),
                                               "emitter_peak": float(ref.color[emitters].max()),
                                               "emitter_pixels": int(emitters.sum())}})
                    print(f"{scene} {args.k}x{spp} seeds {first} {name}: " + ", ".join(
                        f"{m} {e['rmse']:.3f}" for m, e in result.items()), flush=True)
    blender = subprocess.run([args.blender_python, "-c",
                              "import bpy; print(bpy.app.version_string)"],
                             capture_output=True, text=True, check=True).stdout.split()[-1]
    result = {"rows": rows, "k": args.k, "size": args.size,
              "reference_spp": args.reference_spp}
    result["provenance"] = result_provenance(
        run_identity(argv, program="python experiments/renderers/cycles_emission.py"),
        blender=blender, seeds="frames 1000 * set + 100 * [spp == 64] + 1 .. K, "
                              "reference 9001 ..")
    write_result(args.out, result, table(rows, args, blender))
    return 0


def table(rows: list[dict], args, blender: str) -> str:
    lines = [
        f"## Lamps in Blender {blender} Cycles renders: the emission in the Denoising Albedo",
        "",
        (f"{args.size}; each frame `jaxden merge --from cycles` of {args.k} renders of S "
         f"samples (seed sets 1..{args.seed_sets}); reference {args.reference_spp} spp merged "
         f"alike. Albedo `before`: the raw Denoising Albedo (the lamps' emission in it); "
         f"`after`: what `--from cycles` reads now, clip(Denoising Albedo, 0, 1); "
         f"`reflectance`: clip(Denoising Albedo - Emission, 0, 1) (measured, not taken); "
         f"`subtract`: max(Denoising Albedo - Emission, 0), not clipped at 1. RMSE: whole "
         f"frame, linear HDR, against the reference (not noise-corrected; the JSON has that "
         f"and the RMSE off the emitter pixels too), one value per seed set; emitter mean and "
         f"peak: over the pixels whose reference Emission pass is above 0 (all channels), "
         f"mean over the seed sets; PD: the shipped mixer, probe SURE unless `--buffers`."),
        ""]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    levels = list(dict.fromkeys(r["spp"] for r in rows))
    methods = ["MC", *METHODS]
    for scene in scenes:
        for spp in levels:
            group = [r for r in rows if r["scene"] == scene and r["spp"] == spp]
            if not group:
                continue
            seeds = list(dict.fromkeys(r["seeds"] for r in group))
            ref = group[0]["reference"]
            lines += [(f"### `{scene}`, {args.k} x {spp} spp (reference emitter mean "
                       f"{ref['emitter_mean']:.4g}, peak {ref['emitter_peak']:.4g}, "
                       f"{ref['emitter_pixels']} emitter pixels)"), ""]
            header = ["method"]
            for name in VARIANTS:
                header += [f"RMSE {name} (seeds {', '.join(map(str, seeds))})"]
            header += [f"emitter mean {name}" for name in VARIANTS]
            header += [f"emitter peak {name}" for name in VARIANTS]
            lines += ["| " + " | ".join(header) + " |",
                      "|---|" + "---:|" * (len(header) - 1)]
            for method in methods:
                cells = [method]
                for key in ("rmse", "emitter_mean", "emitter_peak"):
                    for name in VARIANTS:
                        values = [r["methods"][method][key] for s in seeds for r in group
                                  if r["seeds"] == s and r["variant"] == name
                                  and method in r["methods"]]
                        if not values:
                            cells.append("")
                        elif key == "rmse":
                            cells.append(" / ".join(f"{v:.4g}" for v in values))
                        else:
                            cells.append(f"{np.mean(values):.4g}")
                lines.append("| " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
