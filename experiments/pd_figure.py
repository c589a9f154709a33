"""The paper's Figures 2 and 10 on our data: SURE against the true error, convergence plots
and a progressive image series.

    # error vs spp (log-log), mean over the test crops, from `jaxden evaluate pd`'s JSON (no rendering)
    python experiments/pd_figure.py convergence \
        --report experiments/results/pd/pd-oidn-test-high-shipped.json \
        --out experiments/results/pd/fig10-convergence-high
    # one held-out crop at several spp: MC | OIDN | PD(OIDN) | alpha' | reference (sRGB previews)
    python experiments/pd_figure.py images --data $JAXDEN_HOME/data/test-high-chain \
        --crop s002-c000 --spp 64 512 4096 --out experiments/results/pd/fig10-s002
    # the same over another base denoiser and its mixer: MC | WSKP-6 | PD(WSKP-6) | ...
    python experiments/pd_figure.py images --data DIR --crop ID --spp 64 512 \
        --denoiser wskp-6 --mixer wskp-6-pd --probes 1 --out OUT

    # the paper's Figure 2: SURE and the input's variance against the true errors, per spp
    python experiments/pd_figure.py sure --report experiments/results/sure/sure-fig2.json \
        --out experiments/results/sure/fig2-sure

The base denoiser is named as the mixers' model cards name it (``jaxden.evaluate.denoiser_label``):
OIDN for ``oidn``, WSKP-6 for ``wskp-6``, a checkpoint by its folder's name; ``convergence``
takes it from the report's provenance, ``images`` from ``--denoiser``.

``convergence`` writes OUT.svg (RMSE and relMSE panels: MC, the denoiser, PD(denoiser), the
oracle mix) and OUT.json (the plotted means and the report's provenance). ``images`` writes
OUT.png (rows: spp; columns as above, one exposure for the whole figure: 1 / the 99th
percentile of the reference's channel values unless ``--exposure``; alpha' shown per channel
as colour, 1 = all denoised) and OUT.json (provenance, per-panel RMSE against the reference). Previews are
8-bit sRGB and clip; the numbers come from the float images.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jaxden.evaluate import denoiser_label
from jaxden.evaluate.plot import METHODS, PANELS, convergence_methods, svg_plot


def mean_curves(rows) -> dict:
    """{metric: {method: [(spp, mean over crops), ...]}} from the rows of a PD result."""
    levels = sorted({row["spp"] for row in rows})
    curves = {}
    for metric, _ in PANELS:
        curves[metric] = {
            method: [(spp, float(np.mean([r[f"{method}_{metric}"] for r in rows
                                          if r["spp"] == spp]))) for spp in levels]
            for method, _, _ in METHODS}
    return curves


def _write_plot(out: Path, svg: str, curves: dict, report_path, report: dict) -> None:
    """OUT.svg and OUT.json (the plotted means, this command and the report's provenance)."""
    from jaxden.fileio import atomic_write_text

    atomic_write_text(out.with_suffix(".svg"), svg)
    command = "python experiments/pd_figure.py " + " ".join(sys.argv[1:])
    atomic_write_text(out.with_suffix(".json"), json.dumps(
        {"curves": curves, "provenance": {"command": command, "report": str(report_path),
                                          "report_provenance": report["provenance"]}},
        indent=1, sort_keys=True) + "\n")
    print(f"wrote {out.with_suffix('.svg')} and {out.with_suffix('.json')}")


def cmd_convergence(args) -> None:
    report = json.loads(Path(args.report).read_text())
    curves = mean_curves(report["rows"])
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    title = args.title or f"{report['provenance']['dataset']['config']['name']}: error vs spp"
    # reports from before other bases were measured name none: they are OIDN's
    label = denoiser_label(report["provenance"].get("denoiser", "oidn"))
    svg = svg_plot(curves, title, methods=convergence_methods(label))
    _write_plot(out, svg, curves, args.report, report)


#: Figure 2's curves: each error next to its estimate (dashed).
SURE_METHODS = (("input_mse_nc", "MC input: true MSE", "#7f7f7f"),
                ("input_var", "MC input: estimate (variance of the mean)", "#7f7f7f"),
                ("mse_nc", "denoised: true MSE", "#1f77b4"),
                ("sure", "denoised: SURE", "#1f77b4"))


#: On data with a colour covariance the report also has the paper's per-channel SURE.
SURE_DIAG = ("sure_diag", "denoised: SURE, per-channel (the paper's)", "#ff7f0e")


def sure_methods(report: dict) -> tuple:
    """The curves a `jaxden evaluate sure` JSON has: SURE_METHODS, plus SURE_DIAG when every row
    has the per-channel SURE beside the covariance one."""
    rows = [r for group in report["rows"].values() for r in group]
    return SURE_METHODS + ((SURE_DIAG,) if rows and all("sure_diag" in r for r in rows) else ())


def sure_curves(report: dict) -> dict:
    """{denoiser: {curve: [(spp, mean over crops), ...]}} from a `jaxden evaluate sure` JSON."""
    curves = {}
    for denoiser, rows in report["rows"].items():
        levels = sorted({row["spp"] for row in rows})
        curves[denoiser] = {
            key: [(spp, float(np.mean([r[key] for r in rows if r["spp"] == spp])))
                  for spp in levels]
            for key, _, _ in sure_methods(report)}
    return curves


def cmd_sure(args) -> None:
    report = json.loads(Path(args.report).read_text())
    missing = [k for k, _, _ in SURE_METHODS
               if any(k not in r for rows in report["rows"].values() for r in rows)]
    if missing:
        raise SystemExit(f"{args.report}: rows lack {missing}: a report from before they were "
                         "recorded; rerun jaxden evaluate sure")
    curves = sure_curves(report)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    panels = [(name, Path(name).name) for name in curves]
    title = args.title or (f"{report['provenance']['dataset']['config']['name']}: "
                           "estimated and true error vs spp")
    _write_plot(out, svg_plot(curves, title, panels=panels, methods=sure_methods(report),
                              dashed=("input_var", "sure", "sure_diag")), curves, args.report,
                report)


def cmd_images(args) -> None:
    import jax

    from jaxden import metrics
    from jaxden.data.crops import iter_crops
    from jaxden.denoise.registry import load_denoiser
    from jaxden.evaluate import dataset_provenance, weights_identity
    from jaxden.fileio import atomic_write_text
    from jaxden.io.png import preview, write_png
    from jaxden.progressive.mixer import load_mixer
    from jaxden.progressive.pipeline import progressive_denoise
    from jaxden.sure.settings import SureSettings
    from jaxden.provenance import result_provenance, run_identity

    if args.mixer is None:
        from jaxden.progressive.pipeline import SHIPPED_MIXERS

        if args.denoiser not in SHIPPED_MIXERS:
            raise SystemExit(f"--mixer: no mixer ships for denoiser {args.denoiser!r}; name one")
        args.mixer = SHIPPED_MIXERS[args.denoiser]
    label = denoiser_label(args.denoiser)
    found = None
    for crop, reference, inputs in iter_crops(args.data, "all", tuple(args.spp)):
        if crop.id == args.crop:
            found = crop, reference, inputs
            break
    if found is None:
        raise SystemExit(f"{args.data}: no crop {args.crop!r}")
    crop, reference, inputs = found
    missing = sorted(set(args.spp) - {spp for spp, _ in inputs})
    if missing:
        raise SystemExit(f"{args.data}: crop {args.crop} has no inputs at spp {missing}")
    source = result_provenance(run_identity(), dataset_provenance(args.data, None),
                               seed=args.seed, probes=args.probes or 4,
                               denoiser=args.denoiser, mixer=weights_identity(args.mixer),
                               crop=crop.id, scene=crop.scene)
    model = load_denoiser(args.denoiser)
    params, config = load_mixer(args.mixer)
    ref = np.asarray(reference.color, np.float64)
    exposure = args.exposure or 1.0 / max(float(np.percentile(ref, 99)), 1e-6)
    rows, errors = [], []
    for index, (spp, frame) in enumerate(inputs):
        z, alpha_prime, extras = progressive_denoise(
            frame, model, params, config, jax.random.fold_in(jax.random.PRNGKey(args.seed), index),
            sure=SureSettings(probes=args.probes))
        panels = {"MC": frame.color, label: extras["denoised"], f"PD({label})": z}
        errors.append({"spp": spp, "alpha_prime_mean": float(np.mean(alpha_prime)),
                       **{name: float(metrics.rmse(np.asarray(image, np.float64), ref))
                          for name, image in panels.items()}})
        tiles = [preview(np.asarray(image), exposure) for image in panels.values()]
        tiles.append(preview(np.clip(np.asarray(alpha_prime, np.float64), 0, 1)))
        tiles.append(preview(ref, exposure))
        rows.append(_hstack(tiles))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_png(out.with_suffix(".png"), _vstack(rows))
    result = {"columns": ["MC", label, f"PD({label})", "alpha'", "reference"],
              "rows_spp": [e["spp"] for e in errors], "exposure": exposure, "rmse": errors,
              "provenance": source}
    atomic_write_text(out.with_suffix(".json"), json.dumps(result, indent=1, sort_keys=True)
                      + "\n")
    for e in errors:
        print(e)
    print(f"wrote {out.with_suffix('.png')} and {out.with_suffix('.json')}")


GAP = 4


def _hstack(tiles):
    h = tiles[0].shape[0]
    gap = np.full((h, GAP, 3), 255, np.uint8)
    parts = []
    for tile in tiles:
        parts += [tile, gap]
    return np.concatenate(parts[:-1], axis=1)


def _vstack(rows):
    gap = np.full((GAP, rows[0].shape[1], 3), 255, np.uint8)
    parts = []
    for row in rows:
        parts += [row, gap]
    return np.concatenate(parts[:-1], axis=0)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("convergence", help="error vs spp from a jaxden evaluate pd JSON")
    p.add_argument("--report", required=True)
    p.add_argument("--title", default=None)
    p.add_argument("--out", required=True, help="output path without suffix")
    p.set_defaults(run=cmd_convergence)
    p = sub.add_parser("sure", help="Figure 2: SURE and the input's variance against the "
                                    "true errors, per spp, from a jaxden evaluate sure JSON")
    p.add_argument("--report", required=True)
    p.add_argument("--out", required=True, help="output path without suffix")
    p.add_argument("--title", default=None)
    p.set_defaults(run=cmd_sure)
    p = sub.add_parser("images", help="one crop at several spp: MC, the denoiser, PD, alpha', "
                                      "reference")
    p.add_argument("--data", required=True)
    p.add_argument("--crop", required=True)
    p.add_argument("--spp", type=int, nargs="+", required=True)
    p.add_argument("--denoiser", default="oidn",
                   help="base denoiser: oidn, a shipped name (wskp-6) or a checkpoint folder")
    p.add_argument("--mixer", default=None,
                   help="mixer (default: the one shipped for --denoiser, oidn-pd for oidn)")
    p.add_argument("--seed", type=int, default=0, help="seed of the SURE probes")
    p.add_argument("--probes", type=int, default=4)
    p.add_argument("--exposure", type=float, default=None)
    p.add_argument("--out", required=True, help="output path without suffix")
    p.set_defaults(run=cmd_images)
    args = parser.parse_args(argv)
    args.run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
