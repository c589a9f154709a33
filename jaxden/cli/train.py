"""`jaxden train` and `jaxden sweep`: one training run from a TOML config, or every run of a sweep."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxden.cli.options import non_negative_int, positive_int


def check_ray_address(args: argparse.Namespace) -> None:
    """``--ray-address`` only means something with ``--executor ray``: say so, never ignore it."""
    if getattr(args, "ray_address", None) and args.executor != "ray":
        from jaxden.errors import ConfigError

        raise ConfigError(f"--ray-address is for --executor ray (given: --executor "
                          f"{args.executor})")


def add_ray_address_option(parser: argparse.ArgumentParser) -> None:
    """``--ray-address`` of the commands that take ``--executor ray``."""
    parser.add_argument(
        "--ray-address", default=None, metavar="ADDRESS",
        help="with --executor ray: the cluster to join, HOST:PORT of its head node (default: "
             "$RAY_ADDRESS), 'auto' (the cluster started on this machine) or 'local' (a private "
             "Ray on this machine only)")


def cmd_train(args: argparse.Namespace) -> int:
    from jaxden.distributed import initialize, is_primary

    # Before anything starts JAX's backend: a multi-process job must be joined first.
    initialize(args.coordinator, args.num_processes, args.process_id)
    from jaxden.train.config import load_train_config
    from jaxden.train.loop import train_and_evaluate

    config = load_train_config(args.config, args.overrides)
    result = train_and_evaluate(config, args.workdir, tensorboard=args.tensorboard)
    if not is_primary():
        return 0
    print("finished: " + ", ".join(f"{k}={v:.5g}" if isinstance(v, float) else f"{k}={v}"
                                   for k, v in result.items()))
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from jaxden.sweep import check_sweep, run_sweep

    if args.dry_run:  # the checks a real sweep makes before training, then the plan
        config, axes, base, runs, _ = check_sweep(args.config, tuple(args.overrides),
                                                  only=args.only or (),
                                                  allow_large=args.allow_large)
        print(f"{len(runs)} run(s) of {base} ({config.mode} over {', '.join(axes)}):")
        for run in runs:
            print(f"  {run.name}: {' '.join(run.overrides)}")
        return 0
    check_ray_address(args)
    results = run_sweep(args.config, args.workdir, args.overrides, executor=args.executor,
                        workers=args.workers, allow_large=args.allow_large,
                        ray_address=args.ray_address, only=args.only or ())
    done = sum(not r["skipped"] for r in results)
    if args.only:
        print(f"sweep: {len(results)} run(s) of --only ({done} run now, {len(results) - done} "
              f"already finished); no summary written (it covers the whole sweep): "
              + ", ".join(f"{r['run']} in {Path(args.workdir) / r['run']}" for r in results))
        return 0
    print(f"sweep complete: {len(results)} run(s) ({done} run now, {len(results) - done} "
          f"already finished); {Path(args.workdir) / 'summary.md'}:")
    print((Path(args.workdir) / "summary.md").read_text())
    return 0


def add_commands(sub) -> None:
    from jaxden.sweep import MAX_RUNS

    p = sub.add_parser(
        "train", help="train a denoiser or the mixer from a TOML config (resumable)",
        description="Train a denoiser or the mixer from a TOML config; the same command resumes "
                    "from the newest checkpoint in --workdir. Fine-tuning: set init = "
                    "\"wskp-6\" (a shipped model), a .msgpack weights file or a training "
                    "workdir in the config, with the source's model and [model_config]; the "
                    "parameters start from those weights, the optimiser state fresh.")
    p.add_argument("config", help="training config .toml")
    p.add_argument("overrides", nargs="*", help="key=value overrides, e.g. optim.steps=500")
    p.add_argument("--workdir", required=True,
                   help="run folder: config, metrics.jsonl, TensorBoard event files, checkpoints")
    p.add_argument("--no-tensorboard", dest="tensorboard", action="store_false",
                   help="write no TensorBoard event files (default: the scalars of metrics.jsonl "
                        "also go to WORKDIR/events.out.tfevents.*; view them with "
                        "`tensorboard --logdir WORKDIR`)")
    g = p.add_argument_group(
        "several processes (hosts), one model: start the same command in every process "
        "(docs/scaling.md)")
    g.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="process 0's address and a free port (default: $JAX_COORDINATOR_ADDRESS; "
                        "none: a single process)")
    g.add_argument("--num-processes", type=positive_int, default=None, metavar="N",
                   help="processes in the job (default: $JAX_NUM_PROCESSES, or Slurm / Open MPI)")
    g.add_argument("--process-id", type=non_negative_int, default=None, metavar="I",
                   help="this process, 0 .. N-1 (default: $JAX_PROCESS_ID, or Slurm / Open MPI)")
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
    add_ray_address_option(p)
    p.add_argument("--allow-large", action="store_true",
                   help=f"run a sweep of more than {MAX_RUNS} runs (refused without it)")
    p.add_argument("--only", action="append", metavar="NAME",
                   help="run just the run of this name (repeatable; see --dry-run for the "
                        "names); writes no summary")
    p.add_argument("--dry-run", action="store_true",
                   help="check every run's config and the [evaluate] datasets as a sweep does "
                        "before training (exit 2 on the first problem), then list the runs")
    p.set_defaults(func=cmd_sweep)

