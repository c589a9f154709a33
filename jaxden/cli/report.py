"""`jaxden report DIR`: one self-contained HTML page over rendered results."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxden.cli.options import positive_int, stderr

DESCRIPTION = """\
Write one self-contained HTML page (images embedded, no network) over a folder of EXRs:
per scene an A/B comparison slider between any two methods and the reference, every method
at a chosen spp, false-colour error maps (relative squared error, FLIP) and mixer alpha maps,
one zoom and pan for all views, an exposure control in stops, a convergence plot (log-log
error vs spp with MC's 1/spp rate as a guide) and the metrics table; per training run its
curves (train loss and validation metrics against the step).

DIR follows the layout `jaxden demo` writes:
  DIR/SCENE/reference.exr           the reference of SCENE (required)
  DIR/SCENE/sppN.exr                the Monte Carlo input at N spp (method "mc")
  DIR/SCENE/sppN.METHOD.exr         METHOD's result at N spp (N may be zero-padded)
  DIR/SCENE/sppN.METHOD.alpha.exr   optional: the mixer's alpha map behind METHOD
  DIR/*.json                        optional: `jaxden evaluate pd` results (metrics only)
  DIR/RUN/metrics.jsonl             optional: a training run (a `jaxden train` workdir or
                                    a sweep's run folder): its loss curves
DIR may also be one scene folder, one training workdir (jaxden report RUNS/wskp6 draws its
curves), or a single `jaxden evaluate pd` JSON file."""


def cmd_report(args: argparse.Namespace) -> int:
    from jaxden.fileio import check_outputs
    from jaxden.report import ReportError, build_report, default_output, discover

    found = discover(args.dir)  # before the output checks: a bad DIR is the first error
    out = Path(args.out) if args.out else default_output(args.dir)
    check_outputs(("--out", out))
    if found.ignored:
        names = ", ".join(str(p) for p in found.ignored[:5])
        more = f" and {len(found.ignored) - 5} more" if len(found.ignored) > 5 else ""
        stderr(f"jaxden: note: ignored {len(found.ignored)} .exr file(s) not named by the "
               f"convention (see jaxden report --help): {names}{more}")
    try:
        path = build_report(args.dir, out, title=args.title, max_size=args.max_size,
                            progress=True, found=found)
    except ReportError as error:  # the library names its parameter out=, the CLI --out
        parameter = f"out={out}:"
        if not str(error).startswith(parameter):
            raise
        raise ReportError(f"--out {out}:{str(error)[len(parameter):]}") from None
    scenes = len(found.scenes)
    print(f"wrote {path} ({scenes} scene{'s' * (scenes != 1)}, "
          f"{len(found.metric_files)} metric file(s), {len(found.runs)} training run(s), "
          f"{path.stat().st_size / 1e6:.1f} MB)")
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("report", help="an HTML page comparing methods on a folder of EXRs "
                                      "(and training runs' loss curves)",
                       description=DESCRIPTION,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dir", metavar="DIR",
                   help="results folder (layout above), a training workdir or a PD result's JSON")
    p.add_argument("--out", default=None,
                   help="the .html file to write (default: DIR/report.html)")
    p.add_argument("--title", default=None, help="page title (default: from DIR)")
    p.add_argument("--max-size", type=positive_int, default=1024, metavar="PIXELS",
                   help="longest side of the images shown; larger ones are box-filtered for "
                        "display (metrics use the full images; default 1024)")
    p.set_defaults(func=cmd_report)
