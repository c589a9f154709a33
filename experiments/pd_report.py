"""Progressive-denoising reports on a held-out rendered test set (jaxden.progressive.report).

    # the paper's Table 3 / Fig. 10 on our data: MC, OIDN, PD(OIDN) per spp
    python experiments/pd_report.py pd --data $JAXDEN_HOME/data/test-chain --denoiser oidn \
        --mixer oidn-pd --out experiments/results/pd-oidn-test-shipped
    # SURE accuracy: image-mean SURE vs noise-corrected true MSE, per denoiser and spp
    python experiments/pd_report.py sure --data $JAXDEN_HOME/data/test --denoiser oidn \
        --denoiser $JAXDEN_HOME/runs/wskp-default --out experiments/results/sure-accuracy
    # the same on fresh renders made of 16 sub-buffers: Stein SURE vs sub-buffer SURE
    python experiments/pd_report.py sure-buffers --data $JAXDEN_HOME/data/test-high \
        --denoiser oidn --denoiser $JAXDEN_HOME/runs/wskp-default --buffers 16 \
        --spp 64 128 256 512 1024 \
        --out experiments/results/sure-buffers-high

Each run writes OUT.json (per-crop rows, per-spp summary, headline ratios, provenance: the
command, git commit, dataset manifest hash and config, seeds, weights hash) and OUT.md (the
tables). The test sets come from experiments/configs/dataset-test{,-high}.toml; every
report in experiments/results/ and its command is listed in experiments/README.md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import sys
from pathlib import Path

from jaxden.provenance import (  # noqa: F401  (package_version, run_identity: scripts' API)
    ROOT,
    file_sha256,
    package_version,
    run_identity,
    write_report,
)


def provenance(args: argparse.Namespace, extra: dict) -> dict:
    """Where a result comes from; taken when the run starts (the commit it ran)."""
    from jaxden.data.layout import load_manifest, manifest_path

    manifest = load_manifest(args.data)
    return {
        **run_identity(),
        "date": datetime.date.today().isoformat(),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
        "versions": {name: package_version(name) for name in ("pyoidn", "mitsuba", "jax")},
        "dataset": {"dir": str(args.data), "split": getattr(args, "split", None),
                    "manifest_sha256": file_sha256(manifest_path(args.data)),
                    "config": manifest.config},
        "seed": getattr(args, "seed", None), "probes": getattr(args, "probes", None) or 4,
        **extra,
    }


def _weights_identity(spec: str) -> dict:
    from jaxden.denoise.registry import WEIGHTS_DIR

    path = Path(spec)
    if not path.exists() and (WEIGHTS_DIR / f"{spec}.msgpack").is_file():
        path = WEIGHTS_DIR / f"{spec}.msgpack"
    if path.is_file():
        return {"spec": spec, "file": str(path), "sha256": file_sha256(path)}
    return {"spec": spec}


def cmd_pd(args: argparse.Namespace) -> None:
    from jaxden.progressive import report as pdreport

    if args.from_json:  # re-tabulate a finished run (its rows and provenance) without rerunning
        previous = json.loads(Path(args.from_json).read_text())
        rows, source = previous["rows"], previous["provenance"]
        denoiser = source["denoiser"]
    else:
        import dataclasses

        from jaxden.config import config_to_dict, load_config
        from jaxden.progressive.mixer import MixerConfig, load_mixer
        from jaxden.progressive.tstat import TStatConfig

        params, config = load_mixer(args.mixer)
        if args.swap_average is not None:
            config = dataclasses.replace(config, swap_average=args.swap_average)
        if args.tstat:
            config = dataclasses.replace(
                config, tstat=load_config(config.tstat, TStatConfig, overrides=args.tstat))
        if args.logit_bound is not None:
            config = dataclasses.replace(config, logit_bound=args.logit_bound or None)
        if args.mixer_set:
            config = load_config(config, MixerConfig, overrides=args.mixer_set)
        source = provenance(args, {"denoiser": args.denoiser[0],
                                   "mixer": _weights_identity(args.mixer),
                                   "swap_average": config.swap_average,
                                   "logit_bound": config.logit_bound,
                                   "mixer_overrides": args.mixer_set,
                                   "closed_form_stops": config.closed_form_stops,
                                   "tstat": config_to_dict(config.tstat),
                                   "mixer_config": config_to_dict(config),
                                   "spp": args.spp,
                                   "probes": args.probes or config.sure_probes})
        if args.keep_current and report_is_current(Path(args.out), source):
            print(f"pd_report: {args.out}.json is current (same data, denoiser, mixer and "
                  f"options); kept")
            return
        rows = pdreport.evaluate_progressive(args.data, args.denoiser[0], (params, config),
                                             split=args.split, seed=args.seed,
                                             num_probes=args.probes, spp=args.spp, progress=True)
        denoiser = args.denoiser[0]
    summary = pdreport.summarize_progressive(rows)
    from ship_mixer import denoiser_label

    name = denoiser_label(denoiser)
    result = {"summary": summary, "rows": rows, "provenance": source}
    write_report(Path(args.out), result, pdreport.markdown_progressive(summary, name))


#: What a PD report must share with a new run to stand for it (``--keep-current``).
_SAME_RUN = ("denoiser", "mixer", "mixer_config", "seed", "probes", "spp")


def report_is_current(out: Path, source: dict) -> bool:
    """Whether OUT.json is what this run would write: made on the same build of the dataset
    (manifest hash) and split, with the same denoiser, mixer weights, effective mixer config,
    probe seed, probes and spp, and with a column for every method the report now has."""
    from jaxden.progressive.report import PD_METHODS

    try:
        old = json.loads(out.with_suffix(".json").read_text())
        made = old["provenance"]
        columns = old["rows"][0] if old["rows"] else {}
    except (OSError, ValueError, KeyError, TypeError):
        return False
    now = json.loads(json.dumps(source, sort_keys=True, default=float))  # as it would be saved
    for entry in (made, now):  # weights by their content, wherever the file lies
        if isinstance(entry.get("mixer"), dict):
            entry["mixer"] = {k: entry["mixer"].get(k) for k in ("spec", "sha256")}
    same_data = all(made.get("dataset", {}).get(k) == now["dataset"][k]
                    for k in ("manifest_sha256", "split"))
    return (same_data and all(made.get(k) == now.get(k) for k in _SAME_RUN)
            and all(f"{m}_rmse" in columns for m in PD_METHODS))


def _logit_bound(text: str) -> float:
    """--logit-bound: a number > 0, or 'none' (0.0 here: no bound)."""
    if text.strip().lower() == "none":
        return 0.0
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a number > 0 or 'none', got {text!r}")
    return value


def cmd_sure(args: argparse.Namespace) -> None:
    from jaxden.progressive import report as pdreport

    if args.from_json:  # re-tabulate a finished run (its rows and provenance) without rerunning
        previous = json.loads(Path(args.from_json).read_text())
        rows, source = previous["rows"], previous["provenance"]
    else:
        source = provenance(args, {"denoisers": [_weights_identity(s) for s in args.denoiser]})
        from jaxden.paths import portable

        rows = {portable(spec): pdreport.sure_accuracy(
                    args.data, spec, split=args.split, seed=args.seed,
                    num_probes=args.probes or 4, spp=args.spp, progress=True)
                for spec in args.denoiser}
    summaries = {spec: pdreport.summarize_sure(r) for spec, r in rows.items()}
    # Frames with a colour covariance: SURE from it, and the paper's per-channel form beside
    for spec, r in rows.items():
        if r and all("sure_diag" in row for row in r):
            summaries[f"{spec} (per-channel, the paper's)"] = pdreport.summarize_sure(
                r, key="sure_diag")
    checks = median_crop_checks(summaries)
    result = {"summary": summaries, "rows": rows, "provenance": source, "checks": checks}
    write_report(Path(args.out), result,
                 pdreport.markdown_sure(summaries) + "\n" + markdown_checks(checks))


#: The issue's accuracy target for SURE: the median crop's SURE / noise-corrected true MSE
#: within this tolerance at every spp level from MIN_SPP on.
MEDIAN_CROP_TOLERANCE, MIN_SPP = 0.05, 64


def median_crop_checks(summaries: dict, tolerance: float = MEDIAN_CROP_TOLERANCE,
                       min_spp: int = MIN_SPP) -> dict:
    """Per denoiser: the spp level (>= ``min_spp``) where the median crop's ratio is farthest
    from 1, that ratio, and whether every level is within ``tolerance``."""
    checks = {}
    for name, summary in summaries.items():
        levels = {int(level): m["median_crop_ratio"] for level, m in summary["per_spp"].items()
                  if int(level) >= min_spp}
        if not levels:
            continue
        worst = max(levels, key=lambda level: abs(levels[level] - 1.0))
        checks[name] = {"worst_spp": worst, "worst_ratio": levels[worst],
                        "within": all(abs(r - 1.0) <= tolerance for r in levels.values()),
                        "tolerance": tolerance, "min_spp": min_spp}
    return checks


def markdown_checks(checks: dict) -> str:
    lines = [(f"\nMedian crop's SURE / true MSE within ±{MEDIAN_CROP_TOLERANCE:.0%} at every spp "
              f">= {MIN_SPP}:\n")]
    for name, c in checks.items():
        lines.append(f"- {name}: {'yes' if c['within'] else 'NO'} (farthest from 1: "
                     f"{c['worst_ratio']:.3f} at {c['worst_spp']} spp)")
    return "\n".join(lines) + "\n"


def cmd_sure_buffers(args: argparse.Namespace) -> None:
    from jaxden.progressive import report as pdreport

    if args.from_json:  # re-tabulate a finished run (its rows and provenance) without rerunning
        previous = json.loads(Path(args.from_json).read_text())
        rows, source = previous["rows"], previous["provenance"]
        buffers, renders = source["buffers"], source.get("renders", 1)
    else:
        source = provenance(args, {"denoisers": [_weights_identity(s) for s in args.denoiser],
                                   "buffers": args.buffers, "renders": args.renders,
                                   "render_seed_base": pdreport.BUFFER_SEED_BASE})
        rows = pdreport.sure_accuracy_buffers(args.data, args.denoiser, buffers=args.buffers,
                                              renders=args.renders, split=args.split,
                                              seed=args.seed, num_probes=args.probes or 4,
                                              spp=args.spp, progress=True)
        buffers, renders = args.buffers, args.renders
    keys = {"stein": "sure", "buffers": "sure_buffers", "extrapolated": "sure_buffers_rx"}
    keys = {k: v for k, v in keys.items()
            if all(row.get(v) is not None for r in rows.values() for row in r)}
    summaries = {name: {kind: pdreport.summarize_sure(r, key=key) for kind, key in keys.items()}
                 for name, r in rows.items()}
    names = " / ".join({"stein": "Stein (probes)", "buffers": "sub-buffers",
                        "extrapolated": "sub-buffers extrapolated in 1/K"}[k] for k in keys)
    lines = [(f"{renders} fresh render(s) per crop and spp, each the mean of {buffers} "
              "independent sub-buffers. Estimate / noise-corrected true MSE: of the means over "
              "all crop-renders, of the median crop-render, and the share of crop-renders "
              f"within ±10 % ({names}); the 95 % interval of the ratio of means is a crop "
              f"bootstrap ({pdreport.BOOTSTRAP_RESAMPLES} resamples of the crops with all their "
              "renders, seed 0)."), "",
             ("| denoiser | spp | true MSE | ratio of means | 95 % interval | median | "
              "within ±10 % |"),
             "|---|---:|---:|---:|---:|---:|---:|"]

    def cells(per, field, fmt):
        return " / ".join(format(per[kind][field], fmt) for kind in keys)

    def intervals(per):
        return " / ".join("{:.2f}..{:.2f}".format(*per[kind]["ratio_ci95"]) for kind in keys)

    for name, by_kind in summaries.items():
        for level in by_kind["stein"]["per_spp"]:
            per = {kind: by_kind[kind]["per_spp"][level] for kind in keys}
            lines.append(f"| {name} | {level} | {per['stein']['mse_nc']:.4g} | "
                         f"{cells(per, 'ratio', '.3f')} | {intervals(per)} | "
                         f"{cells(per, 'median_crop_ratio', '.3f')} | "
                         f"{cells(per, 'within_10pct', '.0%')} |")
    crops = sorted({r["crop"] for r in next(iter(rows.values()))})
    lines += ["", f"Per crop, all spp and renders pooled (ratio of means, {names}):",
              "", "| denoiser | " + " | ".join(crops) + " |",
              "|---|" + "---:|" * len(crops)]
    for name, r in rows.items():
        crop_cells = []
        for crop in crops:
            group = [row for row in r if row["crop"] == crop]
            true = sum(row["mse_nc"] for row in group)
            crop_cells.append(" / ".join(f"{sum(row[key] for row in group) / true:.2f}"
                                         for key in keys.values()))
        lines.append(f"| {name} | " + " | ".join(crop_cells) + " |")
    result = {"summary": summaries, "rows": rows, "provenance": source}
    write_report(Path(args.out), result, "\n".join(lines))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, func in (("pd", cmd_pd), ("sure", cmd_sure), ("sure-buffers", cmd_sure_buffers)):
        p = sub.add_parser(name)
        p.add_argument("--data", required=True, help="complete dataset folder (the test set)")
        p.add_argument("--split", default="test", help="split to evaluate (test, val, all)")
        p.add_argument("--denoiser", action="append", required=True,
                       help="oidn, a shipped name or a checkpoint folder (sure: repeatable)")
        p.add_argument("--seed", type=int, default=0, help="seed of the SURE probes")
        p.add_argument("--probes", type=int, default=None,
                       help="SURE probes per image (default: pd, the mixer's training probes; "
                            "sure / sure-buffers, 4)")
        p.add_argument("--spp", type=int, nargs="+", default=None,
                       help="only these input spp levels (default: all)")
        p.add_argument("--out", required=True, help="output path without suffix")
        if name == "pd":
            p.add_argument("--mixer", default="oidn-pd", help="mixer spec (default oidn-pd)")
            p.add_argument("--swap-average", action=argparse.BooleanOptionalAction,
                           default=None, help="override the mixer config's swap_average")
            p.add_argument("--tstat", action="append", default=[], metavar="KEY=VALUE",
                           help="override a field of the mixer's t-statistic config "
                                "(jaxden.progressive.TStatConfig), e.g. sigma_min=1.0; "
                                "repeatable")
            p.add_argument("--logit-bound", default=None, type=_logit_bound, metavar="B|none",
                           help="override a closed_form_logit mixer's logit_bound at inference "
                                "(an ablation: 'none' removes the bound it was trained with)")
            p.add_argument("--keep-current", action="store_true",
                           help="keep OUT.json when it was made on the same dataset build "
                                "with the same denoiser, mixer, config and options")
            p.add_argument("--mixer-set", action="append", default=[], metavar="KEY=VALUE",
                           help="override a field of the mixer's config "
                                "(jaxden.progressive.MixerConfig) at inference, e.g. "
                                "closed_form_stops=1; repeatable")
        if name == "sure-buffers":
            p.add_argument("--buffers", type=int, default=16,
                           help="independent sub-buffers per render (spp / buffers each)")
            p.add_argument("--renders", type=int, default=1,
                           help="independent renders per crop and spp")
        if name in ("pd", "sure", "sure-buffers"):
            p.add_argument("--from-json", default=None,
                           help="re-tabulate the rows of a finished run (OUT.json) instead")
        p.set_defaults(func=func)
    args = parser.parse_args(argv)
    from jaxden.compile_cache import enable_compilation_cache

    enable_compilation_cache()
    from jaxden.errors import JaxdenError

    try:
        args.func(args)
    except JaxdenError as error:  # a bad mixer, dataset or override: its message, no traceback
        print(f"pd_report: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
