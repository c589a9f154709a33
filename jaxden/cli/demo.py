"""`jaxden demo`: render, denoise and compare on the built-in scenes, and show the results."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_demo(args: argparse.Namespace) -> int:
    import dataclasses

    from jaxden.demo import QUICK, DemoSettings, run_demo

    settings = QUICK if args.quick else DemoSettings()
    if args.denoiser:
        settings = dataclasses.replace(settings, realtime=tuple(dict.fromkeys(args.denoiser)))
    run_demo(Path(args.out), settings=settings, report=not args.no_report)
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser(
        "demo", help="render, denoise and compare on the built-in scenes",
        description="Render the built-in scenes at several spp with a high-spp reference, "
                    "denoise with OIDN and PD(OIDN), print an error table, and write under "
                    "--out: EXR frames with PNG previews, summary.json/.md, convergence.svg/.png "
                    "and report.html (open it in a browser; see `jaxden report --help`).")
    p.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    p.add_argument("--quick", action="store_true", help="smaller images and fewer spp levels")
    p.add_argument("--denoiser", action="append", metavar="NAME",
                   help="a denoiser run beside OIDN at every level, repeatable (default: "
                        "wskp-6): a shipped name, oidn-jax, a checkpoint folder or a .msgpack "
                        "file; PD over it too where a mixer ships for it (wskp-6, oidn-jax)")
    p.add_argument("--no-report", action="store_true",
                   help="skip the plots and report.html (EXRs, previews and tables only)")
    p.set_defaults(func=cmd_demo)
