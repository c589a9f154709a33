"""How OIDN's error depends on its auxiliary features, on the crops of a rendered dataset.

    python experiments/aux_features.py --data data/test-high --out experiments/results/oidn-aux-features

For every crop of the split and input spp level s, albedo and normal are rendered afresh
(seed FEATURE_SEED + s) in each feature setting: ``aux`` (``first-hit``: Mitsuba's aov
integrator, what jaxden datasets store by default; ``specular-chain``: the first non-delta
surface behind mirrors and smooth glass, as OIDN's documentation recommends) and
``feature_spp`` F: like a dataset built with ``feature_spp = F``, the features of an s-spp
input average min(s, F) samples (jaxden datasets so far use F = 16). Every stored input render
of the crop is then denoised by OIDN with each variant: a feature setting plus OIDN's
``cleanAux`` flag (``clean``: the features are declared noise-free, jaxden's setting before
``OIDNConfig.clean_aux``, and its default; ``noisy``: OIDN is told they are not; ``auto``:
clean from 8 spp up). The errors are against the crop's reference.

A variant is written ``AUX:FEATURE_SPP:clean|noisy|auto``; the first one is the baseline that the
ratios divide by (ratio of crop means per spp). Two more variants render nothing: ``stored``
(the dataset's own features, cleanAux on) and ``none`` (OIDN on colour alone):

    python experiments/aux_features.py --data data/test-chain --variant stored --variant none \
        --out experiments/results/oidn-no-features
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

FEATURE_SEED = 424242
DEFAULT_VARIANTS = (
    "first-hit:16:clean", "first-hit:16:noisy", "first-hit:1024:clean", "specular-chain:16:clean",
    "specular-chain:1024:clean", "specular-chain:1024:noisy", "specular-chain:1024:auto",
)
CLEAN_AUX = {"clean": "yes", "noisy": "no", "auto": "auto"}  # variant word -> OIDNConfig
METRICS = ("rmse", "relmse", "mse_nc")


def parse_variant(text: str) -> tuple[str, int, str]:
    if text in ("stored", "none"):
        return text, 0, "clean"
    try:
        aux, spp, clean = text.split(":")
        spp = int(spp)
    except ValueError:
        raise SystemExit(f"--variant {text!r}: expected AUX:FEATURE_SPP:clean|noisy|auto"
                         ) from None
    if aux not in ("first-hit", "specular-chain") or clean not in CLEAN_AUX or spp < 1:
        raise SystemExit(f"--variant {text!r}: AUX is first-hit or specular-chain, "
                         f"FEATURE_SPP >= 1, then clean, noisy or auto")
    return aux, spp, clean


def evaluate(data: Path, split: str, names, spp=None, progress: bool = True):
    from jaxden import metrics
    from jaxden.data.layout import load_manifest
    from jaxden.denoisers import OIDNConfig, make_denoiser
    from jaxden.pdreport import iter_crops
    from jaxden.render.core import render_frame

    variants = [parse_variant(name) for name in names]
    oidn = {word: make_denoiser("oidn", OIDNConfig(clean_aux=value))
            for word, value in CLEAN_AUX.items()}
    size = tuple(load_manifest(data).config["size"])
    rows = []
    for crop, reference, inputs in iter_crops(data, split, spp):
        for level, frame in inputs:
            features = {}  # (aux, samples) -> Frame, shared by the variants of this input
            for aux, samples in sorted({(aux, min(level, f)) for aux, f, _ in variants
                                        if aux not in ("stored", "none")}):
                features[(aux, samples)] = render_frame(
                    crop.scene, samples, seed=FEATURE_SEED + level, size=size,
                    crop=tuple(crop.window), aux=aux, feature_spp=samples)
            row = {"crop": crop.id, "scene": crop.scene, "spp": level, "errors": {}}
            for name, (aux, fspp, clean) in zip(names, variants):
                if aux == "stored":
                    given = frame
                elif aux == "none":
                    given = frame.replace(albedo=None, normal=None)
                else:
                    f = features[(aux, min(level, fspp))]
                    given = frame.replace(albedo=f.albedo, normal=f.normal)
                y = np.asarray(oidn[clean](given), np.float32)
                row["errors"][name] = {
                    "rmse": float(metrics.rmse(y, reference.color)),
                    "relmse": float(metrics.relmse(y, reference.color)),
                    "mse_nc": float(metrics.noise_corrected_mse(y, reference.color,
                                                                reference.variance)),
                }
            rows.append(row)
        if progress:
            print(f"{crop.id} done", file=sys.stderr)
    return rows


def summarize(rows, names):
    base = names[0]
    by_spp: dict[int, list] = {}
    by_crop: dict[str, list] = {}
    for row in rows:
        by_spp.setdefault(row["spp"], []).append(row)
        by_crop.setdefault(row["crop"], []).append(row)

    def means(group):
        return {name: {m: float(np.mean([r["errors"][name][m] for r in group])) for m in METRICS}
                for name in names}

    def ratios(group):
        mean = means(group)
        return {name: {m: mean[name][m] / mean[base][m] for m in METRICS} for name in names}

    per_spp = {int(s): {"mean": means(g), "ratio": ratios(g)} for s, g in sorted(by_spp.items())}
    per_crop = {c: ratios(g) for c, g in sorted(by_crop.items())}
    mean_over_spp = {name: {m: float(np.mean([v["ratio"][name][m] for v in per_spp.values()]))
                            for m in METRICS} for name in names}
    return {"baseline": base, "per_spp": per_spp, "per_crop": per_crop,
            "mean_over_spp": mean_over_spp}


def markdown(summary, names) -> str:
    head = "| spp | " + " | ".join(names) + " |"
    rule = "|---:|" + "---:|" * len(names)
    title = (f"RMSE of OIDN with each feature variant / RMSE with `{summary['baseline']}` "
             f"(ratio of crop means); variant = aux : feature spp : cleanAux")
    lines = [title, "", head, rule]
    for spp, v in summary["per_spp"].items():
        lines.append(f"| {spp} | " + " | ".join(f"{v['ratio'][n]['rmse']:.3f}" for n in names)
                     + " |")
    lines.append("| mean over spp | " + " | ".join(
        f"{summary['mean_over_spp'][n]['rmse']:.3f}" for n in names) + " |")
    lines += ["", "relMSE, the same way:", "", head, rule]
    for spp, v in summary["per_spp"].items():
        lines.append(f"| {spp} | " + " | ".join(f"{v['ratio'][n]['relmse']:.3f}"
                                                for n in names) + " |")
    lines.append("| mean over spp | " + " | ".join(
        f"{summary['mean_over_spp'][n]['relmse']:.3f}" for n in names) + " |")
    lines += ["", "Per crop, RMSE ratio pooled over spp:", "",
              "| crop | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for crop, v in summary["per_crop"].items():
        lines.append(f"| {crop} | " + " | ".join(f"{v[n]['rmse']:.3f}" for n in names) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="complete dataset folder")
    parser.add_argument("--split", default="test", help="split to evaluate (test, val, all)")
    parser.add_argument("--variant", action="append", default=None,
                        help="AUX:FEATURE_SPP:clean|noisy|auto, stored or none (repeatable; the "
                             f"first is the baseline; default: {' '.join(DEFAULT_VARIANTS)})")
    parser.add_argument("--spp", type=int, nargs="+", default=None,
                        help="only these input spp levels (default: all)")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args(argv)
    names = list(dict.fromkeys(args.variant or DEFAULT_VARIANTS))
    for name in names:
        parse_variant(name)  # a bad --variant fails before any work

    from pd_report import provenance, write_report

    info = provenance(args, {"variants": names, "feature_seed": FEATURE_SEED})
    rows = evaluate(args.data, args.split, names, tuple(args.spp) if args.spp else None)
    summary = summarize(rows, names)
    write_report(args.out, {"provenance": info, "rows": rows, "summary": summary},
                 markdown(summary, names))
    return 0


if __name__ == "__main__":
    sys.exit(main())
