"""`jaxden scenes` and `jaxden render`: the built-in scenes, one frame (or K sub-buffers) to EXR."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxden.cli.options import (
    add_channels_option,
    add_convention_options,
    exr_outputs,
    parse_size,
    positive_int,
)
from jaxden.errors import JaxdenError
from jaxden.render.scene_xml import parse_parameters


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
    from jaxden.io.exr import write_frame
    from jaxden.render.core import render_frame

    if args.buffers is not None:
        return _render_buffers(args, Path(args.out))
    from jaxden.render.core import feature_attributes

    (out,) = exr_outputs(("--out", args.out))
    parameters = parse_parameters(args.define)
    frame = render_frame(args.scene, spp=args.spp, seed=args.seed, size=args.size, aux=args.aux,
                         feature_spp=args.feature_spp, parameters=parameters or None,
                         statistics=args.statistics)
    write_frame(out, frame, half=args.half, attributes={
        "seed": args.seed, "scene": args.scene,
        **feature_attributes(args.spp, args.aux, args.feature_spp)})
    print(f"wrote {out} ({frame.width}x{frame.height}, {args.spp} spp, channels: "
          f"{', '.join(frame.features())})")
    return 0


def _render_buffers(args: argparse.Namespace, out: Path) -> int:
    """``jaxden render ... --buffers K``: K independent sub-buffers at spp / K (render seeds
    seed * K + k) written as OUT.b<k>.exr, and their combination (one render of all samples)
    as OUT; for ``jaxden sure OUT --buffers OUT.b*.exr``."""
    import numpy as np

    from jaxden.data.merge import BufferList, colour_digest
    from jaxden.fileio import all_or_nothing
    from jaxden.io.exr import write_frame
    from jaxden.render.core import feature_attributes
    from jaxden.render.scene_cache import render_cached
    from jaxden.sure.buffers import combine_buffers

    k = args.buffers
    if k < 2 or args.spp % k or args.spp // k < 2:
        raise JaxdenError(f"--buffers {k}: needs K >= 2 dividing --spp {args.spp} into >= 2 "
                          f"samples per buffer")
    paths = [out.with_name(f"{out.stem}.b{i}.exr") for i in range(k)]
    out, *paths = exr_outputs(("--out", out), *((f"sub-buffer {i}", p)
                                                 for i, p in enumerate(paths)))
    seeds = [args.seed * k + i for i in range(k)]
    parameters = parse_parameters(args.define)
    parts = [render_cached(args.scene, args.spp // k, seed=s, size=args.size, aux=args.aux,
                           feature_spp=args.feature_spp, parameters=parameters or None,
                           statistics=args.statistics).numpy()
             for s in seeds]
    full = combine_buffers(parts)
    full = full.replace(**{name: np.asarray(getattr(full, name), np.float32)
                           for name in full.features()}, spp=np.float32(args.spp))
    stored = np.float16 if args.half else np.float32  # the colour as it reads back
    listed = BufferList(tuple(str(p) for p in paths),
                        tuple(colour_digest(np.asarray(part.color, stored)) for part in parts))
    with all_or_nothing():  # the sub-buffers and their combination: all or none
        for i, (path, part) in enumerate(zip(paths, parts)):
            write_frame(path, part, half=args.half, attributes={
                "seed": seeds[i], "scene": args.scene, "buffer": i, "buffers": k,
                **feature_attributes(args.spp // k, args.aux, args.feature_spp)})
        # the combination averages the K buffers' features
        combined = feature_attributes(args.spp // k, args.aux, args.feature_spp)
        combined["feature_spp"] = min(args.spp, k * combined["feature_spp"])
        write_frame(out, full, half=args.half, attributes={
            "seed": args.seed, "scene": args.scene, "buffers": k, **combined,
            **listed.attributes()})
    print(f"wrote {out} ({full.width}x{full.height}, {args.spp} spp = {k} sub-buffers of "
          f"{args.spp // k}) and {paths[0].name} .. {paths[-1].name}; sub-buffer SURE: jaxden "
          f"sure {out} --buffers {' '.join(str(p) for p in paths)} --denoiser oidn --out "
          f"{out.with_name(out.stem + '.sure.exr')}")
    return 0


def cmd_merge(args: argparse.Namespace) -> int:
    """K independent renders of one frame -> one EXR with the variance of its mean."""
    from jaxden.cli.options import channel_map, convention_options, stderr
    from jaxden.data.merge import BufferList, colour_digest, merge_renders
    from jaxden.io.exr import read_frame, write_frame

    (out,) = exr_outputs(("--out", args.out), inputs=tuple(args.renders))
    if len(set(map(str, (Path(r).resolve() for r in args.renders)))) != len(args.renders):
        raise JaxdenError("merge: a render is named twice")
    mapping = channel_map(args)
    notes: dict[str, list[str]] = {}  # one line per note, naming the renders it is about
    frames = [read_frame(path, nonfinite="error", require=("color", *(mapping or {})),
                         channel_map=mapping, refuse_denoised=True,
                         on_note=lambda note, path=path: notes.setdefault(note, []).append(path),
                         **convention_options(args))
              for path in args.renders]
    merged = merge_renders(frames, names=args.renders)
    for note, paths in notes.items():
        stderr(f"jaxden: note: {', '.join(map(str, paths))}: {note}")
    pooled = all(f.variance is not None for f in frames)
    convention = convention_options(args)
    listed = BufferList(tuple(str(Path(r)) for r in args.renders),
                        tuple(colour_digest(f.color) for f in frames),
                        convention["convention"], convention["layer"],
                        tuple((mapping or {}).items()))
    write_frame(out, merged, attributes={
        **listed.attributes(),
        "buffers": ";".join(str(Path(r)) for r in args.renders),
        "variance_source": (f"pooled from {len(frames)} renders' own variances" if pooled else
                            f"spread of {len(frames)} independent renders "
                            f"({len(frames) - 1} degrees of freedom)")})
    print(f"wrote {args.out} ({len(frames)} renders merged"
          + (", no sample count" if merged.spp is None else f", {float(merged.spp):g} spp")
          + f", variance of {float(merged.variance_dof):g} degrees of freedom); sub-buffer "
          f"SURE: jaxden progressive {args.out} --buffers {' '.join(map(str, args.renders))} "
          f"--denoiser oidn --out OUT.exr")
    return 0


def add_commands(sub) -> None:
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
    p.add_argument("--statistics", action="store_true",
                   help="also write the per-pixel sample statistics StatMC tests with "
                        "(boxcox.mean/m2/m3.R/G/B: Box-Cox(0.5) mean and central moments)")
    p.add_argument("-D", dest="define", action="append", default=[], metavar="NAME=VALUE",
                   help="set $NAME in an XML scene, as Mitsuba's -D (repeatable; wins over the "
                        "scene's <default>)")
    p.add_argument("--out", required=True, help="output .exr")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("merge", help="K independent renders of one frame (different seeds) -> "
                                     "one frame with the variance of its mean",
                       description="Writes one EXR in jaxden's layout: the mean colour and "
                                   "features, the variance of the mean (pooled from the renders' "
                                   "own variances, else from their spread) and its degrees of "
                                   "freedom (jaxden.variance_dof), and a record of the renders "
                                   "(names and a sha256 of each colour) that `jaxden sure` and "
                                   "`jaxden progressive` check --buffers against. Only raw Monte "
                                   "Carlo means are merged: a denoised Cycles render gives its "
                                   "Noisy Image pass, and a denoised image is refused.")
    p.add_argument("renders", nargs="+", help="the renders' EXR files (K >= 2)")
    add_convention_options(p)
    add_channels_option(p)
    p.add_argument("--out", required=True, help="output .exr (jaxden's layout)")
    p.set_defaults(func=cmd_merge)

