"""`jaxden train` and `jaxden sweep`: one training run from a TOML config, or every run of a sweep."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxden.cli.options import positive_int


def cmd_train(args: argparse.Namespace) -> int:
    from jaxden.train.config import load_train_config
    from jaxden.train.loop import train_and_evaluate

    config = load_train_config(args.config, args.overrides)
    result = train_and_evaluate(config, args.workdir)
    print("finished: " + ", ".join(f"{k}={v:.5g}" if isinstance(v, float) else f"{k}={v}"
                                   for k, v in result.items()))
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from jaxden.sweep import load_sweep, plan_runs, run_sweep

    if args.dry_run:
        config, axes, base = load_sweep(args.config, tuple(args.overrides))
        runs = plan_runs(config, axes)
        print(f"{len(runs)} run(s) of {base} ({config.mode} over {', '.join(axes)}):")
        for run in runs:
            print(f"  {run.name}: {' '.join(run.overrides)}")
        return 0
    results = run_sweep(args.config, args.workdir, args.overrides, executor=args.executor,
                        workers=args.workers)
    done = sum(not r["skipped"] for r in results)
    print(f"sweep complete: {len(results)} run(s) ({done} run now, {len(results) - done} "
          f"already finished); {Path(args.workdir) / 'summary.md'}:")
    print((Path(args.workdir) / "summary.md").read_text())
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("train", help="train a denoiser or the mixer from a TOML config (resumable)")
    p.add_argument("config", help="training config .toml")
    p.add_argument("overrides", nargs="*", help="key=value overrides, e.g. optim.steps=500")
    p.add_argument("--workdir", required=True, help="run folder: config, metrics.jsonl, checkpoints")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("sweep", help="train (and evaluate) every run of a sweep file (resumable)")
    p.add_argument("config", help="sweep .toml: base training config, [axes], [evaluate]")
    p.add_argument("overrides", nargs="*", help="key=value overrides for every run")
    p.add_argument("--workdir", required=True, help="sweep folder: one run folder per point, "
                   "summary.json and summary.md")
    p.add_argument("--executor", choices=("serial", "local", "ray"), default="serial",
                   help="serial (default: one run at a time in this process), local processes "
                        "or a Ray cluster")
    p.add_argument("--workers", type=positive_int, default=None, help="runs at once (local / ray)")
    p.add_argument("--dry-run", action="store_true", help="list the runs and their overrides")
    p.set_defaults(func=cmd_sweep)

