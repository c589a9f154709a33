"""Mixers compared on the frames `jaxden demo` writes, and where their relMSE comes from.

    jaxden demo --out demo-out
    python experiments/demo_mixers.py --demo demo-out --mixer oidn-pd \
        --mixer 'oidn-pd|closed_form_stops=1' --mixer closed-form \
        --mixer closed-form:stops=1 --bands cornell-box:64 \
        --out experiments/results/demo-mixers

For every scene and spp of the demo folder and every mixer: PD(OIDN) as the demo computes it
(:func:`jaxden.progressive.progressive_denoise`, 4 finite-difference SURE probes from
``PRNGKey(0)``, the mixer config's t-statistic and swap averaging), with relMSE (eps 0.01),
RMSE and mean alpha' against the demo's reference. A mixer is a spec for
:func:`jaxden.progressive.load_mixer`, optionally followed by ``|KEY=VALUE,...`` overrides of
its :class:`MixerConfig` at inference.

``--bands SCENE:SPP`` (repeatable) adds, for that frame, relMSE and mean alpha per band of
reference brightness (channel mean): which surfaces a mixer's relMSE comes from.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

BANDS = (0.0, 0.02, 0.05, 0.1, 0.3, 1.0, float("inf"))


def load(spec: str):
    """``(params, config)`` of ``SPEC`` or ``SPEC|KEY=VALUE,...``."""
    from jaxden.config import load_config
    from jaxden.progressive import MixerConfig, load_mixer

    name, _, overrides = spec.partition("|")
    params, config = load_mixer(name)
    keys = [o.strip() for o in overrides.split(",") if o.strip()]
    if keys:
        config = load_config(config, MixerConfig, overrides=keys)
    return params, config


def frames(demo: Path):
    """``(scene, spp, frame, reference)`` for every ``SCENE/sppNNNNN.exr`` of a demo folder."""
    from jaxden.io.exr import read_frame

    scenes = sorted(p for p in demo.iterdir() if (p / "reference.exr").is_file())
    if not scenes:
        raise SystemExit(f"{demo}: no SCENE/reference.exr; run `jaxden demo --out {demo}` first")
    for folder in scenes:
        reference = read_frame(folder / "reference.exr").color
        for path in sorted(folder.glob("spp?????.exr")):
            yield folder.name, int(path.stem[3:]), read_frame(path, require=("color", "variance")), \
                reference


def relmse_map(image, reference) -> np.ndarray:
    """Per-pixel relMSE (mean over channels), eps 0.01 as in :func:`jaxden.metrics.relmse`."""
    image, reference = np.asarray(image, np.float64), np.asarray(reference, np.float64)
    return np.mean((image - reference) ** 2 / (reference ** 2 + 0.01), axis=-1)


def band_rows(reference, images: dict, alphas: dict) -> list[dict]:
    """relMSE and mean alpha of each image per band of reference brightness (:data:`BANDS`)."""
    brightness = np.mean(np.asarray(reference, np.float64), axis=-1)
    rows = []
    for lo, hi in itertools.pairwise(BANDS):
        mask = (brightness >= lo) & (brightness < hi)
        if not mask.any():
            continue
        row = {"band": [lo, hi], "fraction": float(mask.mean())}
        for name, image in images.items():
            row[name] = float(relmse_map(image, reference)[mask].mean())
        for name, alpha in alphas.items():
            row[f"alpha {name}"] = float(np.mean(np.asarray(alpha), axis=-1)[mask].mean())
        rows.append(row)
    return rows


def evaluate(demo: Path, specs: list[str], bands: set[tuple[str, int]]):
    import jax

    from jaxden import metrics
    from jaxden.denoisers import load_denoiser
    from jaxden.progressive import progressive_denoise

    mixers = {spec: load(spec) for spec in specs}
    oidn = load_denoiser("oidn")
    rows, band_tables = [], {}
    for scene, spp, frame, reference in frames(demo):
        images, alphas = {"mc": frame.color}, {}
        for spec, (params, config) in mixers.items():
            z, alpha, extras = progressive_denoise(frame, oidn, params, config,
                                                   jax.random.PRNGKey(0))
            images[spec], alphas[spec] = np.asarray(z), np.asarray(alpha)
        images["oidn"] = np.asarray(extras["denoised"])
        for method, image in images.items():
            rows.append({"scene": scene, "spp": spp, "method": method,
                         "relmse": float(metrics.relmse(image, reference)),
                         "rmse": float(metrics.rmse(image, reference)),
                         "alpha_prime": float(np.mean(alphas[method]))
                         if method in alphas else None})
        if (scene, spp) in bands:
            band_tables[f"{scene}:{spp}"] = band_rows(reference, images, alphas)
        print(scene, spp, file=sys.stderr, flush=True)
    return rows, band_tables


def markdown(rows: list[dict], band_tables: dict, specs: list[str]) -> str:
    methods = ["mc", "oidn", *specs]
    lines = ["relMSE / RMSE against the demo's reference; PD(OIDN) with each mixer.", "",
             "| scene | spp | " + " | ".join(f"`{m}`" for m in methods) + " |",
             "|---|---:|" + "---:|" * len(methods)]
    keyed = {(r["scene"], r["spp"], r["method"]): r for r in rows}
    for scene, spp in sorted({(r["scene"], r["spp"]) for r in rows}):
        cells = [f"{keyed[scene, spp, m]['relmse']:.5f} / {keyed[scene, spp, m]['rmse']:.4f}"
                 for m in methods]
        lines.append(f"| {scene} | {spp} | " + " | ".join(cells) + " |")
    for name, table in band_tables.items():
        lines += ["", f"{name}: relMSE (and mean alpha') per band of reference brightness.", "",
                  "| band | pixels | " + " | ".join(f"`{m}`" for m in methods) + " |",
                  "|---|---:|" + "---:|" * len(methods)]
        for row in table:
            cells = [f"{row[m]:.5f}" + (f" ({row['alpha ' + m]:.2f})" if f"alpha {m}" in row
                                        else "") for m in methods]
            lines.append(f"| [{row['band'][0]:g}, {row['band'][1]:g}) | {row['fraction']:.1%} | "
                         + " | ".join(cells) + " |")
    return "\n".join(lines)


def parse_band(text: str) -> tuple[str, int]:
    scene, _, spp = text.rpartition(":")
    if not scene or not spp.isdigit():
        raise argparse.ArgumentTypeError(f"expected SCENE:SPP, got {text!r}")
    return scene, int(spp)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--demo", type=Path, required=True, help="a `jaxden demo --out` folder")
    parser.add_argument("--mixer", action="append", required=True,
                        help="SPEC or 'SPEC|KEY=VALUE,...' (repeatable)")
    parser.add_argument("--bands", type=parse_band, action="append", default=[],
                        metavar="SCENE:SPP", help="relMSE per brightness band of this frame")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args(argv)

    from pd_report import run_identity, write_report

    from jaxden.errors import JaxdenError

    try:
        rows, band_tables = evaluate(args.demo, args.mixer, set(args.bands))
    except JaxdenError as error:
        print(f"demo_mixers: error: {error}", file=sys.stderr)
        return 2
    provenance = {**run_identity(argv), "probes": 4, "probe_key": "PRNGKey(0)",
                  "demo": str(args.demo)}
    write_report(args.out, {"provenance": provenance, "rows": rows, "bands": band_tables},
                 markdown(rows, band_tables, args.mixer))
    return 0


if __name__ == "__main__":
    sys.exit(main())
