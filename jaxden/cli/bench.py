"""`jaxden bench NAME`: benchmarks, each a ratio against a peer measured in the same run.

``--size WxH[,WxH...]`` runs the frame-size form of a benchmark that has one (``progressive``,
``denoisers``: :mod:`jaxden.bench.frames`): the commands users run, each in its own process, on
whole frames of those sizes, with wall time and peak memory per megapixel."""

from __future__ import annotations

import argparse


def _sizes(text: str) -> list[tuple[int, int]]:
    from jaxden.bench.frames import parse_sizes

    try:
        return parse_sizes(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def cmd_bench(args: argparse.Namespace) -> int:
    from jaxden import bench

    sizes = getattr(args, "size", None)
    if sizes is None:
        bench.run(args.name, as_json=args.json, quick=args.quick)
    else:
        bench.run(args.name, as_json=args.json, quick=args.quick, sizes=sizes)
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark (ratios against a peer in the same run)")
    p.add_argument("name", help="benchmark name (e.g. render, decoder)")
    p.add_argument("--json", action="store_true",
                   help="print the result as one JSON object, alone on stdout (the table and "
                        "progress go to stderr)")
    p.add_argument("--quick", action="store_true", help="smaller problem, fewer repeats")
    p.add_argument("--size", type=_sizes, default=None, metavar="WxH[,WxH...]",
                   help="progressive, denoisers: instead of the crop benchmark, time the "
                        "`jaxden denoise` / `jaxden progressive` commands (each in its own "
                        "process) on whole frames of these sizes, e.g. "
                        "1280x720,1920x1080,3840x2160,7680x4320: wall time and peak memory, "
                        "per megapixel and against `jaxden denoise --model oidn`")
    p.set_defaults(func=cmd_bench)
