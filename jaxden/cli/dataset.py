"""`jaxden dataset build | import | refeature | verify | sure-cache`: datasets and their SURE
caches."""

from __future__ import annotations

import argparse

from jaxden.cli.options import (
    add_channels_option,
    add_sure_options,
    channel_map,
    positive_int,
    sure_settings,
)
from jaxden.cli.train import add_ray_address_option, check_ray_address


def cmd_dataset_build(args: argparse.Namespace) -> int:
    from jaxden.config import load_config
    from jaxden.data.builder import build_dataset
    from jaxden.data.config import DatasetConfig

    check_ray_address(args)
    config = load_config(args.config, DatasetConfig, args.overrides)
    manifest = build_dataset(config, args.out, executor=args.executor, workers=args.workers,
                             ray_address=args.ray_address)
    print(f"dataset complete: {args.out} ({len(manifest.items)} items)")
    return 0


#: import_dataset's parameters -> the flags of `jaxden dataset import` that set them.
IMPORT_FLAGS = {"out_dir": "--out", "convention": "--from", "layer": "--layer",
                "crop_size": "--crop", "crops_per_view": "--crops-per-view", "seed": "--seed",
                "held_out": "--held-out", "val": "--val", "reference_spp": "--reference-spp",
                "name": "--name", "nonfinite": "--nonfinite", "channel_map": "--channels"}


def cmd_dataset_import(args: argparse.Namespace) -> int:
    from jaxden.data.importer import ImportArgumentError, import_dataset
    from jaxden.errors import DatasetError

    try:
        manifest = import_dataset(
            args.source, args.out, convention=args.convention, layer=args.layer,
            crop_size=args.crop, crops_per_view=args.crops_per_view, seed=args.seed,
            held_out=_view_list(args.held_out), val=_view_list(args.val),
            reference_spp=args.reference_spp, name=args.name, half=args.half,
            nonfinite=args.nonfinite, progress=not args.quiet, channel_map=channel_map(args))
    except ImportArgumentError as error:  # named by the flags that set them
        raise DatasetError(error.naming(IMPORT_FLAGS)) from None
    config, counts = manifest.config, manifest.split_counts()
    print(f"dataset complete: {args.out} ({len(manifest.items)} items: {len(manifest.scenes)} "
          f"views x {config['crops_per_scene']} crops of {config['crop_size']} pixels, inputs "
          f"{', '.join(map(str, config['spp']))} spp, references {config['reference_spp']} spp; "
          f"crops train {counts['train']}, val {counts['val']}, test {counts['test']})")
    return 0


def _view_list(text: str | None) -> tuple[str, ...]:
    return tuple(name.strip() for name in (text or "").split(",") if name.strip())


IMPORT_DESCRIPTION = """\
Turn a folder of another renderer's EXRs into a jaxden dataset that `jaxden train`,
`jaxden sweep`, `jaxden evaluate` and `jaxden dataset verify` read like a built one.
Source layout, one folder per camera view:

  SRC/<view>/reference.exr          the reference, carrying its variance of the mean, or
  SRC/<view>/reference/b0.exr ..    K >= 2 independent renders of it (different seeds)
  SRC/<view>/spp<N>.exr             an N-spp input (with its variance when N > 1), or
  SRC/<view>/spp<N>/b0.exr ..       K >= 2 independent renders whose spp sum to N

Buffers are merged as `jaxden merge` merges them. Every view has the same levels N, every
file the same size, and the colour, albedo, normal and depth. Only raw Monte Carlo means are
imported: a denoised Cycles render gives its Noisy Image pass; a denoised image, and a render
made with adaptive sampling (Cycles' Debug Sample Count pass), are refused. Resumable: run the
same command again after an interruption. Example (docs/your-renderer.md):

  jaxden dataset import renders/ --from cycles --crop 128 --held-out v12,v13 \\
      --out $JAXDEN_HOME/data/cycles"""


def cmd_dataset_refeature(args: argparse.Namespace) -> int:
    import os

    from jaxden.data.refeature import refeature_dataset

    check_ray_address(args)
    if args.ray_address:  # refeature_dataset passes no address: the executor reads RAY_ADDRESS
        os.environ["RAY_ADDRESS"] = args.ray_address
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


def cmd_dataset_sequences(args: argparse.Namespace) -> int:
    from jaxden.data.sequences import build_sequences, load_sequence_config

    config = load_sequence_config(args.config, args.overrides)
    manifest = build_sequences(config, args.out, progress=not args.quiet)
    frames = sum(len(s["frames"]) for s in manifest["sequences"].values())
    print(f"sequences complete: {args.out} ({len(manifest['sequences'])} sequences, {frames} "
          f"frames with references)")
    return 0


def cmd_sure_cache(args: argparse.Namespace) -> int:
    """``jaxden dataset sure-cache DIR --denoiser SPEC``."""
    from jaxden.progressive.cache_build import build_sure_cache

    # unset SURE flags: a mixer's settings (build_sure_cache's base), what training reads
    cache = build_sure_cache(args.dir, args.denoiser, args.out, sure=sure_settings(args),
                             half=args.half, progress=not args.quiet)
    settings = cache.identity.get("settings", {})
    print(f"SURE cache complete: {cache.directory} ({len(cache.records)} items; "
          f"{settings.get('num_probes')} probes, {settings.get('method')}, "
          f"eps {settings.get('eps')}, seed {settings.get('seed')}"
          + ("; SURE from the colour covariance" if settings.get("covariance") else "") + ")")
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("dataset", help="build, import or verify a dataset")
    dsub = p.add_subparsers(dest="dataset_command", required=True, metavar="ACTION")
    b = dsub.add_parser("build", help="render a dataset from a TOML config (resumable)")
    b.add_argument("config", help="dataset config .toml")
    b.add_argument("overrides", nargs="*", help="key=value overrides")
    b.add_argument("--out", required=True, help="dataset folder")
    b.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local processes (default) or a Ray cluster (docs/scaling.md)")
    b.add_argument("--workers", type=positive_int, default=None,
                   help="renders at once (default: 1 per 8 cores locally, the cluster's CPUs on Ray)")
    add_ray_address_option(b)
    b.set_defaults(func=cmd_dataset_build)
    i = dsub.add_parser("import", help="a folder of another renderer's EXRs (one folder per "
                                       "view) -> a dataset (resumable)",
                        description=IMPORT_DESCRIPTION,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    i.add_argument("source", metavar="SRC", help="the source folder (layout above)")
    i.add_argument("--out", required=True, help="the dataset folder")
    from jaxden.io.conventions import CONVENTIONS

    i.add_argument("--from", dest="convention", choices=tuple(CONVENTIONS), default=None,
                   help="the renderer that wrote the files: its channel names, the meaning of "
                        "its variance and the header's sample count (docs/renderers.md; "
                        "default: jaxden's channels). A renderer that writes one file per "
                        "output (falcor) is merged into one file per render first")
    i.add_argument("--layer", default=None,
                   help="the render layer of a layered file (--from cycles) holding several")
    add_channels_option(i)
    i.add_argument("--crop", type=positive_int, default=128, metavar="N",
                   help="side of the square crops in pixels (default 128; at most the views' "
                        "smaller side: give it to keep whole square views)")
    i.add_argument("--crops-per-view", type=positive_int, default=4, metavar="N",
                   help="random crops per view, placed as `dataset build` places them "
                        "(default 4; they may overlap)")
    i.add_argument("--seed", type=int, default=0,
                   help="seeds the crop placement (default 0)")
    i.add_argument("--held-out", default=None, metavar="VIEW,...",
                   help="views of the test split (default: none)")
    i.add_argument("--val", default=None, metavar="VIEW,...",
                   help="views of the val split (default: none); every other view is train")
    i.add_argument("--reference-spp", type=positive_int, default=None, metavar="N",
                   help="the references' sample count, where their headers record none")
    i.add_argument("--name", default=None, help="the dataset's label (default: SRC's name)")
    i.add_argument("--half", action="store_true",
                   help="store the channels as float16 (the variance stays float32)")
    i.add_argument("--nonfinite", choices=("error", "zero"), default="error",
                   help="a NaN or inf in a source file: refuse it (default) or replace it by 0")
    i.add_argument("--quiet", action="store_true", help="no progress bars")
    i.set_defaults(func=cmd_dataset_import)
    r = dsub.add_parser("refeature", help="copy a dataset, re-rendering only its features "
                                          "(aux=..., feature_spp=...; resumable)")
    r.add_argument("source", help="a complete dataset folder")
    r.add_argument("overrides", nargs="*",
                   help="feature settings, e.g. aux=specular-chain feature_spp=4096")
    r.add_argument("--out", required=True, help="the new dataset folder")
    r.add_argument("--executor", choices=("local", "ray"), default="local")
    r.add_argument("--workers", type=positive_int, default=None)
    add_ray_address_option(r)
    r.set_defaults(func=cmd_dataset_refeature)
    v = dsub.add_parser("verify", help="check every file against the manifest")
    v.add_argument("dir")
    v.set_defaults(func=cmd_dataset_verify)

    q = dsub.add_parser("sequences", help="render camera-path sequences with motion vectors and "
                                          "per-frame references from a TOML config (resumable)")
    q.add_argument("config", help="sequence config .toml (jaxden.data.sequences)")
    q.add_argument("overrides", nargs="*", help="key=value overrides")
    q.add_argument("--out", required=True, help="sequence folder")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.set_defaults(func=cmd_dataset_sequences)

    c = dsub.add_parser(
        "sure-cache", help="denoise every dataset input once and cache it with its SURE map "
                           "(resumable; what mixer training reads)",
        description="Denoise every input of a dataset once and cache it with its SURE map "
                    "(resumable): what training a mixer reads. The SURE options left unset "
                    "are a mixer's defaults (4 normal probes, method auto, the measured step, "
                    "seed 0, per channel); a mixer reads the cache made with its own SURE "
                    "settings ([model_config.sure] of its config). --covariance: SURE from "
                    "the colour covariance (the dataset must record it), the cache of a mixer "
                    "with [model_config.sure] covariance = true, in "
                    "DIR/derived/<denoiser>-cov.")
    c.add_argument("dir", help="dataset folder")
    c.add_argument("--denoiser", required=True, help="oidn, a checkpoint folder or .msgpack")
    c.add_argument("--out", default=None,
                   help="cache folder (default: DIR/derived/<denoiser>, with -cov for "
                        "--covariance and -rademacher for --probe-dist rademacher)")
    add_sure_options(c, inherit="a mixer's")
    c.add_argument("--half", action="store_true", help="store float16 channels")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=cmd_sure_cache)
