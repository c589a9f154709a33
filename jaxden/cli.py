"""The ``jaxden`` command: a thin layer over the library functions.

User errors (:class:`jaxden.errors.JaxdenError`) print one line ``jaxden: error: ...`` and exit
with status 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from jaxden.errors import JaxdenError


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' -> (W, H), both positive."""
    parts = text.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 256x256 (WxH), got {text!r}") from None
    if width <= 0 or height <= 0:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return width, height


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return value


# ---------------------------------------------------------------------------------- commands
def cmd_scenes(args: argparse.Namespace) -> int:
    from jaxden.render.scenes import list_scenes

    scenes = list_scenes()
    width = max(len(name) for name in scenes)
    for name, description in scenes.items():
        print(f"{name:<{width}}  {description}")
    print(f"{'procedural:SEED':<{width}}  a random scene from the seeded procedural generator")
    print(f"{'path/to/scene.xml':<{width}}  your own Mitsuba 3 scene (box filter, independent sampler enforced)")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from jaxden.cli_pd import exr_outputs
    from jaxden.io.exr import write_frame
    from jaxden.render.core import render_frame

    if args.buffers is not None:
        return _render_buffers(args, Path(args.out))
    (out,) = exr_outputs(("--out", args.out))
    frame = render_frame(args.scene, spp=args.spp, seed=args.seed, size=args.size, aux=args.aux,
                         feature_spp=args.feature_spp)
    write_frame(out, frame, half=args.half, attributes={
        "seed": args.seed, "scene": args.scene, "aux": args.aux,
        "feature_spp": min(args.spp, args.feature_spp)})
    print(f"wrote {out} ({frame.width}x{frame.height}, {args.spp} spp, channels: "
          f"{', '.join(frame.features())})")
    return 0


def _render_buffers(args: argparse.Namespace, out: Path) -> int:
    """``jaxden render ... --buffers K``: K independent sub-buffers at spp / K (render seeds
    seed * K + k) written as OUT.b<k>.exr, and their combination (one render of all samples)
    as OUT; for ``jaxden sure OUT --buffers OUT.b*.exr``."""
    import numpy as np

    from jaxden.cli_pd import exr_outputs
    from jaxden.data.builder import render_cached
    from jaxden.fileio import all_or_nothing
    from jaxden.io.exr import write_frame
    from jaxden.sure import combine_buffers

    k = args.buffers
    if k < 2 or args.spp % k or args.spp // k < 2:
        raise JaxdenError(f"--buffers {k}: needs K >= 2 dividing --spp {args.spp} into >= 2 "
                          f"samples per buffer")
    paths = [out.with_name(f"{out.stem}.b{i}.exr") for i in range(k)]
    out, *paths = exr_outputs(("--out", out), *((f"sub-buffer {i}", p)
                                                 for i, p in enumerate(paths)))
    seeds = [args.seed * k + i for i in range(k)]
    parts = [render_cached(args.scene, args.spp // k, seed=s, size=args.size, aux=args.aux,
                           feature_spp=args.feature_spp).numpy() for s in seeds]
    full = combine_buffers(parts)
    full = full.replace(**{name: np.asarray(getattr(full, name), np.float32)
                           for name in full.features()}, spp=np.float32(args.spp))
    with all_or_nothing():  # the sub-buffers and their combination: all or none
        for i, (path, part) in enumerate(zip(paths, parts)):
            write_frame(path, part, half=args.half, attributes={
                "seed": seeds[i], "scene": args.scene, "buffer": i, "buffers": k,
                "aux": args.aux})
        write_frame(out, full, half=args.half, attributes={
            "seed": args.seed, "scene": args.scene, "buffers": k, "aux": args.aux})
    print(f"wrote {out} ({full.width}x{full.height}, {args.spp} spp = {k} sub-buffers of "
          f"{args.spp // k}) and {paths[0].name} .. {paths[-1].name}; sub-buffer SURE: jaxden "
          f"sure {out} --buffers {' '.join(str(p) for p in paths)} --denoiser oidn --out "
          f"{out.with_name(out.stem + '.sure.exr')}")
    return 0


def cmd_dataset_build(args: argparse.Namespace) -> int:
    from jaxden.config import load_config
    from jaxden.data.builder import build_dataset
    from jaxden.data.config import DatasetConfig

    config = load_config(args.config, DatasetConfig, args.overrides)
    manifest = build_dataset(config, args.out, executor=args.executor, workers=args.workers)
    print(f"dataset complete: {args.out} ({len(manifest.items)} items)")
    return 0


def cmd_dataset_refeature(args: argparse.Namespace) -> int:
    from jaxden.data.builder import refeature_dataset

    manifest = refeature_dataset(args.source, args.out, args.overrides, executor=args.executor,
                                 workers=args.workers)
    config = manifest.config
    print(f"dataset complete: {args.out} ({len(manifest.items)} items; colour from "
          f"{args.source}, features: aux={config['aux']}, feature_spp={config['feature_spp']})")
    return 0


def cmd_dataset_verify(args: argparse.Namespace) -> int:
    from jaxden.data.verify import verify_dataset

    report = verify_dataset(args.dir)
    for problem in report.problems:
        print(f"PROBLEM {problem}")
    for warning in report.warnings:
        print(f"warning {warning}")
    print(report.summary())
    return 0 if report.ok else 1


def cmd_train(args: argparse.Namespace) -> int:
    from jaxden.train import load_train_config, train_and_evaluate

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


def cmd_denoise(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxden.cli_pd import channel_map, exr_outputs, feature_notice
    from jaxden.denoisers import load_denoiser
    from jaxden.io.exr import read_frame, write_image

    (out,) = exr_outputs(("--out", args.out))
    denoiser = load_denoiser(args.model)
    required = denoiser.definition.required(denoiser.config)
    mapping = channel_map(args) or {}
    frame = read_frame(args.input, require=(*required, *(f for f in mapping if f not in required)),
                       nonfinite=args.nonfinite, channel_map=mapping or None)
    feature_notice(frame, denoiser, args.input)
    image = np.asarray(denoiser(frame))
    write_image(out, image, attributes={"denoiser": denoiser.name, "source": str(args.input)})
    print(f"wrote {args.out} (denoised by {denoiser.name})")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from jaxden import bench

    bench.run(args.name, as_json=args.json, quick=args.quick)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from jaxden.demo import run_demo

    run_demo(Path(args.out), quick=args.quick)
    return 0


# ---------------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxden", description="Monte Carlo denoising research in JAX (see README.md)."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="render, denoise and compare on the built-in scenes")
    p.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    p.add_argument("--quick", action="store_true", help="smaller images and fewer spp levels")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("scenes", help="list the built-in scenes")
    p.set_defaults(func=cmd_scenes)

    p = sub.add_parser("render", help="render one frame (colour, variance, features) to EXR")
    p.add_argument("scene", help="built-in name, procedural:SEED, or a Mitsuba XML path")
    p.add_argument("--spp", type=positive_int, required=True, help="samples per pixel")
    p.add_argument("--size", type=parse_size, default=None, help="WxH (default: the scene's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--half", action="store_true", help="store channels as float16")
    p.add_argument("--aux", choices=("specular-chain", "first-hit"), default="specular-chain",
                   help="albedo and normal of the first non-delta surface behind mirrors and "
                        "smooth glass (default, as OIDN recommends), or of the first hit")
    p.add_argument("--feature-spp", type=positive_int, default=1024, metavar="N",
                   help="the features average min(spp, N) samples (default 1024)")
    p.add_argument("--buffers", type=positive_int, default=None, metavar="K",
                   help="also keep K independent sub-buffers of spp / K samples each "
                        "(OUT.b0.exr ..; OUT is their combination), for `jaxden sure --buffers`")
    p.add_argument("--out", required=True, help="output .exr")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("dataset", help="build or verify a dataset")
    dsub = p.add_subparsers(dest="dataset_command", required=True, metavar="ACTION")
    b = dsub.add_parser("build", help="render a dataset from a TOML config (resumable)")
    b.add_argument("config", help="dataset config .toml")
    b.add_argument("overrides", nargs="*", help="key=value overrides")
    b.add_argument("--out", required=True, help="dataset folder")
    b.add_argument("--executor", choices=("local", "ray"), default="local")
    b.add_argument("--workers", type=positive_int, default=None)
    b.set_defaults(func=cmd_dataset_build)
    r = dsub.add_parser("refeature", help="copy a dataset, re-rendering only its features "
                                          "(aux=..., feature_spp=...; resumable)")
    r.add_argument("source", help="a complete dataset folder")
    r.add_argument("overrides", nargs="*",
                   help="feature settings, e.g. aux=specular-chain feature_spp=4096")
    r.add_argument("--out", required=True, help="the new dataset folder")
    r.add_argument("--executor", choices=("local", "ray"), default="local")
    r.add_argument("--workers", type=positive_int, default=None)
    r.set_defaults(func=cmd_dataset_refeature)
    v = dsub.add_parser("verify", help="check every file against the manifest")
    v.add_argument("dir")
    v.set_defaults(func=cmd_dataset_verify)

    from jaxden.cli_pd import add_channels_option, add_pd_commands

    add_pd_commands(sub, dsub)

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

    p = sub.add_parser("denoise", help="denoise an EXR with a registered or trained denoiser")
    p.add_argument("input", help="input EXR (colour and the features the model needs)")
    p.add_argument("--model", required=True, help="oidn, a shipped model name, or a checkpoint folder")
    p.add_argument("--out", required=True, help="output .exr")
    p.add_argument("--nonfinite", choices=("error", "zero"), default="error",
                   help="NaN/inf in the input: refuse (default) or replace by 0")
    add_channels_option(p)
    p.set_defaults(func=cmd_denoise)

    p = sub.add_parser("bench", help="run a benchmark (ratios against a peer in the same run)")
    p.add_argument("name", help="benchmark name (e.g. render, decoder)")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    p.add_argument("--quick", action="store_true", help="smaller problem, fewer repeats")
    p.set_defaults(func=cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    # argparse gives a trailing ``overrides`` positional nothing once an option comes between
    # it and the config (``CONFIG --out DIR key=value``); take key=value words left over.
    if extra and hasattr(args, "overrides") and all("=" in w and not w.startswith("-")
                                                    for w in extra):
        args.overrides = [*args.overrides, *extra]
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    from jaxden.compile_cache import enable_compilation_cache

    enable_compilation_cache()
    try:
        return int(args.func(args) or 0)
    except JaxdenError as error:
        print(f"jaxden: error: {error}", file=sys.stderr)
        return 2
    except OSError as error:  # e.g. an output folder that cannot be made: name the path
        where = f"{error.filename}: " if error.filename else ""
        print(f"jaxden: error: {where}{error.strerror or error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxden: interrupted (finished work is kept; run the same command to resume)",
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
