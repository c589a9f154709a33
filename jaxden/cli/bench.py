"""`jaxden bench NAME`: benchmarks, each a ratio against a peer measured in the same run."""

from __future__ import annotations

import argparse


def cmd_bench(args: argparse.Namespace) -> int:
    from jaxden import bench

    bench.run(args.name, as_json=args.json, quick=args.quick)
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark (ratios against a peer in the same run)")
    p.add_argument("name", help="benchmark name (e.g. render, decoder)")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    p.add_argument("--quick", action="store_true", help="smaller problem, fewer repeats")
    p.set_defaults(func=cmd_bench)
