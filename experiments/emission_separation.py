"""Does keeping the emission out of the filter stop a denoiser's lamp bleed?

    python experiments/emission_separation.py --out experiments/results/rt/emission-separation

Renders the built-in scene ``small-lights`` (four tiny, very bright sphere lamps in a dark
room) at 96 x 96 as ``jaxden render small-lights --size 96x96 --seed 1801 --spp S`` does, for
S in 1, 4, 64 and 1024, and an 8192-spp reference (seed 999); denoises each frame with every
``--model`` as it is and with ``:emission=separate`` (``D(colour - emission) + emission``,
:mod:`jaxden.denoise.emission`); and reports, in linear HDR, the MSE, the relMSE
(``(x - r)^2 / (r^2 + 0.01)``) and the MSE over MC's (the noisy input's), over the whole frame
and split into emitter pixels (the reference's emission > 0: every pixel an emitter covers,
even partly) and the rest. The reference's own noise (the mean variance of its pixel mean) is
listed beside: it adds to every MSE alike. Off the emitters, the share of the error in the 50
worst pixels and the worst pixel show what separation leaves (a lamp's glossy reflection is
not emission).

``--frames DIR`` keeps the renders as EXR files there and reuses them on a rerun.
Writes OUT.md (the table) and OUT.json (rows, seeds, spp, size, models, commit).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SCENE = "small-lights"
SIZE = (96, 96)
SEED = 1801
SPP = (1, 4, 64, 1024)
REFERENCE_SEED = 999
REFERENCE_SPP = 8192
REGIONS = ("all", "emitters", "rest")
TOP = 50  # worst pixels off the emitters whose share of the error is reported


def commit() -> str:
    from jaxden.provenance import git_commit

    return git_commit()


def render(spp: int, seed: int, frames: Path | None):
    """The frame of ``jaxden render small-lights --size 96x96 --seed SEED --spp SPP``."""
    from jaxden.io.exr import read_frame, write_frame
    from jaxden.render.core import render_frame

    path = None if frames is None else frames / f"{SCENE}-{seed}-{spp}.exr"
    if path is not None and path.is_file():
        return read_frame(path)
    frame = render_frame(SCENE, spp=spp, seed=seed, size=SIZE)
    if path is not None:
        write_frame(path, frame, attributes={"seed": seed, "scene": SCENE})
    return frame


def region_metrics(image, reference, masks: dict) -> dict:
    """{region: (MSE, relMSE)} of ``image`` (H, W, 3) against ``reference``, linear HDR."""
    import numpy as np

    from jaxden.metrics import EPS

    squared = (np.asarray(image, np.float64) - reference) ** 2
    relative = squared / (reference ** 2 + EPS)
    return {name: (float(squared[mask].mean()), float(relative[mask].mean()))
            for name, mask in masks.items()}


def worst_rest(image, reference, rest, top: int) -> dict:
    """Where the error off the emitters sits: the share of its squared error in the ``top``
    worst pixels, and the worst pixel's position, reference and value (linear HDR)."""
    import numpy as np

    error = ((np.asarray(image, np.float64) - reference) ** 2).mean(-1) * rest
    order = np.argsort(error.ravel())[::-1]
    y, x = (int(v) for v in np.unravel_index(order[0], error.shape))
    return {"top_share": float(error.ravel()[order[:top]].sum() / error.sum()),
            "pixel": [y, x], "reference": [round(float(v), 3) for v in reference[y, x]],
            "value": [round(float(v), 3) for v in np.asarray(image)[y, x]]}


def table(rows: list[dict], models: list[str], noise: dict) -> str:
    lines = [f"# Emission kept out of the filter: `{SCENE}` at {SIZE[0]}x{SIZE[1]}",
             "",
             f"Input renders seed {SEED}, reference {REFERENCE_SPP} spp seed {REFERENCE_SEED}; "
             f"linear HDR; emitter pixels: the reference's emission > 0 "
             f"({noise['emitter_pixels']} of {SIZE[0] * SIZE[1]} pixels). D+sep: "
             f"`D:emission=separate` = D(colour - emission) + emission. The reference's own "
             f"noise (mean variance of its pixel mean, in every MSE) is "
             + ", ".join(f"{noise[r]:.3g} ({r})" for r in REGIONS) + ".",
             ""]
    header = "| spp | pixels | MC MSE |"
    rule = "|---:|---|---:|"
    for model in models:
        header += f" {model} MSE | {model}+sep MSE | {model} / MC | {model}+sep / MC |"
        rule += "---:|---:|---:|---:|"
    header += " MC relMSE |" + "".join(f" {m} relMSE | {m}+sep relMSE |" for m in models)
    rule += "---:|" + "---:|---:|" * len(models)
    lines += [header, rule]
    for row in rows:
        mc = row["mc"]["mse"]
        line = f"| {row['spp']} | {row['region']} | {mc:.4g} |"
        for model in models:
            plain, separate = row[model]["mse"], row[f"{model}+sep"]["mse"]
            line += f" {plain:.4g} | {separate:.4g} | {plain / mc:.3g} | {separate / mc:.3g} |"
        line += f" {row['mc']['relmse']:.4g} |"
        line += "".join(f" {row[m]['relmse']:.4g} | {row[m + '+sep']['relmse']:.4g} |"
                        for m in models)
        lines.append(line)
    lines += ["", (f"Where the error off the emitters sits: the share of the rest's squared "
                   f"error in its {TOP} worst pixels, and the worst pixel (y, x): reference -> "
                   f"value."), "",
              "| spp | denoiser | share | worst pixel |", "|---:|---|---:|---|"]
    for row in rows:
        if row["region"] != "rest":
            continue
        for name in [n for m in models for n in (m, f"{m}+sep")]:
            worst = row[name]["worst"]
            lines.append(f"| {row['spp']} | {name} | {worst['top_share']:.3f} | "
                         f"{tuple(worst['pixel'])}: {worst['reference']} -> {worst['value']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    import numpy as np

    from jaxden.denoise.registry import load_denoiser
    from jaxden.fileio import atomic_write_text

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", action="append", default=None,
                        help="denoiser spec (repeatable; default wskp-6)")
    parser.add_argument("--spp", type=int, nargs="+", default=list(SPP))
    parser.add_argument("--frames", type=Path, default=None,
                        help="keep the renders here (EXR) and reuse them on a rerun")
    parser.add_argument("--out", type=Path,
                        default=REPO / "experiments" / "results" / "rt" / "emission-separation",
                        help="OUT.md and OUT.json")
    args = parser.parse_args(argv)
    models = args.model or ["wskp-6"]
    if args.frames is not None:
        args.frames.mkdir(parents=True, exist_ok=True)
    started = commit()
    reference = render(REFERENCE_SPP, REFERENCE_SEED, args.frames)
    truth = np.asarray(reference.color, np.float64)
    emitters = np.asarray(reference.emission).max(-1) > 0
    masks = {"all": np.ones_like(emitters), "emitters": emitters, "rest": ~emitters}
    variance = np.asarray(reference.variance, np.float64)
    noise = {name: float(variance[mask].mean()) for name, mask in masks.items()}
    noise["emitter_pixels"] = int(emitters.sum())
    denoisers = {}
    for model in models:
        denoisers[model] = load_denoiser(model)
        denoisers[f"{model}+sep"] = load_denoiser(f"{model}:emission=separate")
    rows = []
    for spp in args.spp:
        frame = render(spp, SEED, args.frames)
        results = {"mc": region_metrics(frame.color, truth, masks)}
        worst = {}
        for name, denoiser in denoisers.items():
            image = np.asarray(denoiser(frame))
            results[name] = region_metrics(image, truth, masks)
            worst[name] = worst_rest(image, truth, masks["rest"], TOP)
        for region in REGIONS:
            rows.append({"spp": spp, "region": region, **{
                name: {"mse": value[region][0], "relmse": value[region][1],
                       **({"worst": worst[name]} if region == "rest" and name in worst else {})}
                for name, value in results.items()}})
        print(f"{spp} spp done", file=sys.stderr)
    text = table(rows, models, noise)
    command = "python experiments/emission_separation.py " + " ".join(argv or sys.argv[1:])
    result = {"scene": SCENE, "size": list(SIZE), "seed": SEED, "spp": list(args.spp),
              "reference_seed": REFERENCE_SEED, "reference_spp": REFERENCE_SPP,
              "models": models, "emitter_pixels": noise["emitter_pixels"],
              "reference_noise": {r: noise[r] for r in REGIONS}, "rows": rows,
              "command": command.strip(), "commit": started}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out.with_suffix(".json"), json.dumps(result, indent=1) + "\n")
    atomic_write_text(args.out.with_suffix(".md"),
                      f"<!-- generated by: {result['command']} (commit {started}) -->\n"
                      + text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
