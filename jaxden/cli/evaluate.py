"""`jaxden evaluate NAME`: one evaluator (:mod:`jaxden.evaluate`) on a held-out set, written
as a result (OUT.json + OUT.md)."""

from __future__ import annotations

import argparse
import math

from jaxden.cli.options import add_sure_options, sure_settings

DESCRIPTION = """\
Measure one thing on a held-out set and write OUT.json (per-crop rows, per-spp summary,
headline ratios, provenance: the command, git commit, machine, versions, dataset manifest hash
and config, seeds, weights hashes) and OUT.md (the tables). Examples:

  # the paper's Table 3 / Fig. 10 on our data: MC, OIDN, PD(OIDN) per spp
  jaxden evaluate pd --data $JAXDEN_HOME/data/test-chain --denoiser oidn --mixer oidn-pd \\
      --out experiments/results/pd/pd-oidn-test-shipped
  # SURE accuracy: image-mean SURE vs noise-corrected true MSE, per denoiser and spp
  jaxden evaluate sure --data $JAXDEN_HOME/data/test-chain --denoiser oidn \\
      --denoiser wskp-6 --out experiments/results/sure/sure-fig2
  # the same on fresh renders made of 16 sub-buffers: Stein SURE vs sub-buffer SURE
  jaxden evaluate sure-buffers --data $JAXDEN_HOME/data/test-high --denoiser oidn \\
      --buffers 16 --spp 64 128 256 512 1024 --out OUT
  # the tile oracle cross-fitted on an independent render, beside a PD result
  jaxden evaluate oracle --data $JAXDEN_HOME/data/test-chain \\
      --report experiments/results/pd/pd-oidn-test-shipped.json --out OUT
  # a denoiser's PSNR / SSIM / relMSE / FLIP at 1 spp, or per frame of sequences
  jaxden evaluate denoise --data $JAXDEN_HOME/data/rt-test --denoiser wskp-6 --out OUT
  jaxden evaluate sequences --data $JAXDEN_HOME/data/rt-seq --denoiser wskp-6 --out OUT

--from-json OUT.json re-tabulates a finished result without measuring again."""


def logit_bound(text: str) -> float:
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


def _spp(values) -> tuple[int, ...] | None:
    return None if values is None else tuple(values)


#: Each evaluator's options from the parsed arguments.
_OPTIONS = {
    "pd": lambda a: {"denoiser": a.denoiser, "mixer": a.mixer, "split": a.split,
                     "sure": sure_settings(a), "spp": _spp(a.spp),
                     "swap_average": a.swap_average, "tstat": tuple(a.tstat),
                     "logit_bound": a.logit_bound, "mixer_set": tuple(a.mixer_set)},
    "oracle": lambda a: {"denoiser": a.denoiser, "split": a.split, "report": a.report},
    "sure": lambda a: {"denoisers": tuple(a.denoiser), "split": a.split,
                       "sure": sure_settings(a), "spp": _spp(a.spp)},
    "sure-buffers": lambda a: {"denoisers": tuple(a.denoiser), "split": a.split,
                               "sure": sure_settings(a), "spp": _spp(a.spp),
                               "buffers": a.buffers, "renders": a.renders},
    "denoise": lambda a: {"denoiser": a.denoiser, "split": a.split,
                          "spp": _spp(a.spp) or (1,), "include_input": a.include_input},
    "sequences": lambda a: {"denoiser": a.denoiser, "skip_frames": a.skip_frames},
}


def cmd_evaluate(args: argparse.Namespace) -> int:
    import sys

    from jaxden.evaluate import get_evaluator, make_options, write_evaluation
    from jaxden.provenance import run_identity

    evaluator = get_evaluator(args.evaluator)
    options = None if args.from_json else make_options(evaluator.name,
                                                       **_OPTIONS[evaluator.name](args))
    # the command as typed: `jaxden evaluate NAME ...` (main() records its words)
    words = getattr(args, "command_line", None)
    identity = run_identity(list(sys.argv[1:] if words is None else words), program="jaxden")
    write_evaluation(evaluator, args.data, options, args.out, identity=identity,
                     from_json=args.from_json,
                     keep_current=getattr(args, "keep_current", False), progress=True)
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("evaluate", help="measure an evaluator (pd, sure, denoise, ...) on a "
                       "held-out set and write the result",
                       description=DESCRIPTION,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    names = p.add_subparsers(dest="evaluator", required=True, metavar="NAME")
    from jaxden.evaluate.registry import EVALUATORS

    for name, evaluator in EVALUATORS.items():
        e = names.add_parser(name, help=evaluator.description,
                             description=evaluator.description)
        e.add_argument("--data", required=True,
                       help="complete dataset folder (the test set; sequences: a sequence set)")
        if name != "sequences":
            e.add_argument("--split", default="test", help="split to evaluate (test, val, all)")
        if name in ("sure", "sure-buffers"):
            e.add_argument("--denoiser", action="append", required=True,
                           help="oidn, a shipped name or a checkpoint folder (repeatable)")
        else:
            e.add_argument("--denoiser", required=name != "oracle",
                           default="oidn" if name == "oracle" else None,
                           help="oidn, a shipped name or a checkpoint folder"
                                + (" (default oidn)" if name == "oracle" else ""))
        if name in ("pd", "sure", "sure-buffers"):  # item i's probes: fold_in(seed, i)
            add_sure_options(e, inherit="the mixer's" if name == "pd" else None)
        if name in ("pd", "sure", "sure-buffers", "denoise"):
            e.add_argument("--spp", type=int, nargs="+", default=None,
                           help="only these input spp levels (default: all; denoise: 1)")
        e.add_argument("--out", required=True, help="output path without suffix")
        e.add_argument("--from-json", default=None,
                       help="re-tabulate the rows of a finished result (OUT.json) instead")
        if name == "pd":
            e.add_argument("--mixer", default="oidn-pd", help="mixer spec (default oidn-pd)")
            e.add_argument("--swap-average", action=argparse.BooleanOptionalAction,
                           default=None, help="override the mixer config's swap_average")
            e.add_argument("--tstat", action="append", default=[], metavar="KEY=VALUE",
                           help="override a field of the mixer's t-statistic config "
                                "(jaxden.progressive.TStatConfig), e.g. sigma_min=1.0; "
                                "repeatable")
            e.add_argument("--logit-bound", default=None, type=logit_bound, metavar="B|none",
                           help="override a closed_form_logit mixer's logit_bound at inference "
                                "(an ablation: 'none' removes the bound it was trained with)")
            e.add_argument("--keep-current", action="store_true",
                           help="keep OUT.json when it was made on the same dataset build "
                                "with the same denoiser, mixer, config and options")
            e.add_argument("--mixer-set", action="append", default=[], metavar="KEY=VALUE",
                           help="override a field of the mixer's config "
                                "(jaxden.progressive.MixerConfig) at inference, e.g. "
                                "closed_form_stops=1; repeatable")
        if name == "oracle":
            e.add_argument("--report", default=None,
                           help="a PD result .json on the same data: its PD rows are compared")
        if name == "sure-buffers":
            e.add_argument("--buffers", type=int, default=16,
                           help="independent sub-buffers per render (spp / buffers each)")
            e.add_argument("--renders", type=int, default=1,
                           help="independent renders per crop and spp")
        if name == "denoise":
            e.add_argument("--no-input", dest="include_input", action="store_false",
                           help="do not score the noisy input beside the denoiser")
        if name == "sequences":
            e.add_argument("--skip-frames", type=int, default=1,
                           help="leading frames of each sequence left out (no history yet)")
        e.set_defaults(func=cmd_evaluate)
