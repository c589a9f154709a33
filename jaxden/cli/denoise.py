"""`jaxden denoise`, `jaxden sure` and `jaxden progressive`: one EXR in, one (or two) out.

Input EXRs: jaxden's own channels (``R,G,B``, ``variance.R/G/B``, optional ``albedo.*`` and
``normal.*``). Files from other renderers work when they have colour and the variance of the
pixel mean; name their channels with ``--channels FIELD=NAME,...`` (repeatable, any field of
:data:`jaxden.frame.CHANNELS`; ``--variance-channels`` is the older spelling for the variance),
and pass ``--sample-variance`` (with ``--spp`` if the header has no ``jaxden.spp``) when the
file stores the per-sample variance. OIDN uses albedo and normal only when the file has them,
and says so on stderr when it has not (see :func:`feature_notice`).

Output of ``jaxden sure``: one EXR with ``R,G,B`` = the denoised image (so any viewer shows
it), ``sure.R/G/B`` = the per-pixel SURE of it (an estimate of its squared error, radiance^2,
can be negative) and ``divergence.R/G/B`` = var * dy/dx (the same format as the SURE cache,
:mod:`jaxden.progressive.cache`).

Output of ``jaxden progressive``: ``R,G,B`` = z' = x + alpha' (y - x); with ``--alpha A.exr``
also ``R,G,B`` = alpha' (after the t-statistic scaling) and ``unscaled.R/G/B`` = alpha (before).

``--buffers B1.exr .. BK.exr`` (both commands): SURE from K independent sub-buffers whose mean
is the input (:func:`jaxden.sure.sure_buffers`) instead of probes; the header's ``method`` says
``buffers``. An input made from buffers (``jaxden merge``, ``jaxden render --buffers``) lists
them in its header, and ``--buffers`` must then name exactly those (:func:`read_buffers`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxden.cli.batch import (
    add_skip_existing_option,
    batch_summary,
    check_sequence,
    denoisers_by_input,
    input_sizes,
    run_jobs,
    sequence_step,
)
from jaxden.cli.options import (
    add_channels_option,
    add_convention_options,
    add_memory_options,
    add_overwrite_input_option,
    batch_outputs,
    channel_map,
    check_finite_result,
    emission_spec,
    exr_outputs,
    feature_notice,
    output_folder,
    read_input_frame,
    same_file,
    stderr,
    sure_input_options,
    sure_settings,
)
from jaxden.errors import CheckpointError, ConfigError, FrameError


def cmd_denoise(args: argparse.Namespace) -> int:
    """``jaxden denoise IN [IN ...] --model SPEC (--out OUT.exr | --out-dir DIR)``: each
    input read, denoised and written in turn by one loaded denoiser (compiled once per frame
    size); ``--sequence``: the inputs are consecutive frames, a temporal denoiser carries its
    history from one to the next."""
    import numpy as np

    from jaxden.cli.options import convention_options
    from jaxden.denoise.nfor import BUFFER_DENOISERS, buffer_denoiser
    from jaxden.denoise.registry import load_denoiser
    from jaxden.denoise.tiled import denoise_frame
    from jaxden.io.exr import read_frame, write_image

    found = buffer_denoiser(args.model)  # a name of one, or a trained one's run (NJS)
    if args.buffers or found is not None:
        return _denoise_buffers(args, BUFFER_DENOISERS, found)
    inputs = list(args.input)
    targets = batch_outputs(inputs, ("--out", args.out), ("--out-dir", args.out_dir))
    make = args.out_dir is not None and output_folder("--out-dir", args.out_dir)
    outputs = exr_outputs(*targets, inputs=inputs, overwrite_input=args.overwrite_input,
                          new_folders=(args.out_dir,) if make else ())
    base = load_denoiser(args.model)  # first: a spec that cannot load is the error
    several = len(inputs) > 1
    sizes = input_sizes(inputs) if several or args.sequence else None
    denoisers = denoisers_by_input(base, args.model, inputs, args)
    temporal = args.sequence and base.temporal
    if temporal:
        check_sequence(args, inputs, sizes, denoisers)
    elif args.sequence and several:
        stderr(f"jaxden: note: {args.model} has no temporal form: --sequence changes nothing, "
               f"each frame is denoised alone")
    elif base.temporal and several:
        stderr(f"jaxden: note: {args.model} has a temporal form, which --sequence uses (the "
               f"inputs in order as consecutive frames, its history carried from one to the "
               f"next); without it each frame is denoised alone by its single-frame form")
    mapping = channel_map(args) or {}
    limit = _memory_limit(args)
    said: set = set()
    history = {"state": None, "step": None}

    def denoise_one(source, out, denoiser):
        required = denoiser.definition.required(denoiser.config)
        keep = (*denoiser.fields_read(), *(("motion",) if temporal else ()))
        frame = read_frame(source, require=(*required, *(f for f in mapping if f not in required)),
                           nonfinite=args.nonfinite, channel_map=mapping or None, keep=keep,
                           **convention_options(args))
        feature_notice(frame, denoiser, source, said if several else None)
        if temporal:
            if history["step"] is None:
                history["step"] = sequence_step(denoiser, frame, limit, source)
            elif frame.motion is None and "motion" not in said:
                said.add("motion")
                stderr(f"jaxden: note: {source} has no motion vectors (motion.X/Y; name a "
                       f"renderer's with --channels motion=X,Y): {denoiser.name} carries its "
                       f"history as if nothing moved")
            image, history["state"] = history["step"](history["state"], frame)
            image = np.asarray(image, np.float32)
        else:
            def tell(plan):
                if plan.tile and (plan.tile, plan.halo) not in said:
                    stderr(f"jaxden: {source}: tiles of {plan.tile} px + {plan.halo} px overlap")
                    if several:
                        said.add((plan.tile, plan.halo))

            image, _ = denoise_frame(denoiser, frame, tile=args.tile, limit=limit,
                                     progress=True, on_plan=tell)
        check_finite_result(image, "the denoised image",
                            f"{source} denoised by {denoiser.name} ({args.model})")
        write_image(out, image, attributes={"denoiser": denoiser.name, "source": str(source)})

    jobs = [(source, (out,), denoiser) for source, out, denoiser
            in zip(inputs, outputs, denoisers)]
    done = run_jobs(jobs, denoise_one, skip_existing=args.skip_existing,
                     folders=(args.out_dir,) if make else (), sequence=temporal)
    if done is None:
        return 130
    names = ", ".join(dict.fromkeys(denoiser.name for denoiser in denoisers))
    if not several:
        written = args.out if args.out is not None else outputs[0]
        print(f"skipped {written}: it exists (--skip-existing)" if done[1] else
              f"wrote {written} (denoised by {names})")
        return 0
    print(batch_summary(done, args.out_dir, f"denoised by {names}"
                   + (", its history carried through the sequence" if temporal else "")))
    return 0


def _denoise_buffers(args: argparse.Namespace, registry, found) -> int:
    """``jaxden denoise IN --model nfor --buffers B1.exr .. BK.exr --out OUT.exr``: a denoiser
    of K >= 2 independent sub-buffers whose mean is IN (checked as ``progressive --buffers``
    checks them), each read with the features it needs. ``found``: ``(definition, config)``
    of ``--model`` (:func:`jaxden.denoise.nfor.buffer_denoiser`; a trained one's run, e.g.
    NJS's, gives its config), None when it names no sub-buffer denoiser."""
    from jaxden.cli.options import convention_options
    from jaxden.io.exr import read_frame, write_image

    definition, config = found or (None, None)
    if definition is None:
        raise ConfigError(f"--buffers: {args.model} denoises a single frame; the denoisers of "
                          f"K >= 2 sub-buffers are {', '.join(registry)} (drop --buffers)")
    if not args.buffers or len(args.buffers) < definition.min_buffers:
        raise ConfigError(
            f"{args.model} denoises K >= {definition.min_buffers} independent renders of the "
            f"frame: give them with --buffers B1.exr B2.exr ... (their mean is IN: `jaxden "
            f"render --buffers 2` writes both, `jaxden merge` the mean of renders with "
            f"different seeds)")
    if len(args.input) != 1 or args.sequence or args.out_dir is not None or args.out is None:
        raise ConfigError(f"--buffers: {args.model} takes one input (the buffers' mean) and "
                          f"--out OUT.exr")
    source = args.input[0]
    (out,) = exr_outputs(("--out", args.out), inputs=(source, *args.buffers),
                         overwrite_input=args.overwrite_input)
    mapping = channel_map(args) or {}
    mean = read_frame(source, require=("color",), nonfinite=args.nonfinite, keep=("color",),
                      channel_map=mapping or None, **convention_options(args))
    required = definition.required(config)
    buffers = read_buffer_frames(  # K >= 2, one size, their mean IN's colour
        args, mean, source, require=(*required, *(f for f in mapping if f not in required)),
        keep=(*required, "variance", "position"), channel_map=mapping or None,
        reading=convention_options(args))
    image = definition.denoise(buffers, config, tile=args.tile, limit=_memory_limit(args),
                               progress=True)
    check_finite_result(image, "the denoised image", f"{source} denoised by {args.model} from "
                        f"{len(buffers)} buffers")
    write_image(out, image, attributes={"denoiser": args.model, "source": str(source),
                                        "buffers": len(buffers)})
    print(f"wrote {args.out} (denoised by {args.model} from {len(buffers)} sub-buffers)")
    return 0


def cmd_sure(args: argparse.Namespace) -> int:
    """``jaxden sure IN.exr --denoiser NAME|CKPT --out SURE.exr``."""
    import jax
    import numpy as np

    from jaxden.denoise.registry import load_denoiser
    from jaxden.progressive.cache import write_sure_exr
    from jaxden.sure.denoiser import for_denoiser
    from jaxden.sure.tiled import sure_frame

    (out,) = exr_outputs(("--out", args.out), inputs=(args.input, *(args.buffers or ())),
                         overwrite_input=args.overwrite_input)
    settings = sure_settings(args).resolved()
    denoiser = load_denoiser(emission_spec(args.denoiser, args.input, args))
    frame = read_input_frame(args, "jaxden sure", None if args.buffers else denoiser,
                             covariance=settings.covariance)
    feature_notice(frame, denoiser, args.input)
    if args.buffers:
        return _sure_from_buffers(args, frame, denoiser, out)
    if args.extrapolate:
        raise ConfigError("--extrapolate needs --buffers")
    buffers_notice(args.input)
    settings = for_denoiser(settings, denoiser)

    def tell(tile, halo):
        if tile:
            stderr(f"jaxden: {args.input}: tiles of {tile} px + {halo} px overlap")

    result, _ = sure_frame(
        denoiser, frame, jax.random.PRNGKey(settings.seed), sure=settings,
        nonfinite=args.nonfinite, where=str(args.input), tile=args.tile,
        limit=_memory_limit(args), progress=True, on_plan=tell,
    )
    for name in ("denoised", "sure"):
        check_finite_result(getattr(result, name), f"the {name} image",
                            f"{args.input} and denoiser {args.denoiser}")
    covariance = settings.covariance and frame.covariance is not None
    write_sure_exr(out, result, attributes={
        "source": str(args.input), "denoiser": denoiser.name, "probes": settings.probes,
        "method": settings.method, "eps": -1.0 if settings.eps is None else float(settings.eps),
        "seed": settings.seed, "covariance": int(covariance), "probe_dist": settings.probe_dist,
    })
    mse = float(np.mean(np.asarray(result.sure)))
    probes = ("from the colour covariance" if covariance
              else "per channel: the file has no covariance.RG/GB/BR"
              if frame.covariance is None else "per channel (--no-covariance)")
    print(f"wrote {out}: R,G,B = denoised by {denoiser.name}, sure.* = per-pixel SURE "
          f"({settings.probes} {settings.probe_dist} probes {probes}, {settings.method}); image "
          f"SURE (MSE estimate) = {mse:.6g}")
    return 0


def _sure_from_buffers(args: argparse.Namespace, frame, denoiser, out: Path) -> int:
    """``jaxden sure IN.exr --buffers B1.exr ... BK.exr``: sub-buffer SURE (no probes)."""
    import numpy as np

    from jaxden.progressive.cache import write_sure_exr
    from jaxden.sure.buffers import sure_buffers

    colours = read_buffers(args, frame)
    try:
        result = sure_buffers(denoiser, frame, colours, extrapolate=args.extrapolate,
                              nonfinite=args.nonfinite)
    except FrameError as error:
        raise FrameError(f"{args.input} with --buffers {' '.join(map(str, args.buffers))}: "
                         f"{error}") from None
    for name in ("denoised", "sure"):
        check_finite_result(getattr(result, name), f"the {name} image",
                            f"{args.input}, its sub-buffers and denoiser {args.denoiser}")
    write_sure_exr(out, result, attributes={
        "source": str(args.input), "denoiser": denoiser.name,
        "method": "buffers-extrapolated" if args.extrapolate else "buffers",
        "buffers": len(colours)})
    mse = float(np.mean(result.sure))
    print(f"wrote {out}: R,G,B = denoised by {denoiser.name}, sure.* = per-pixel SURE "
          f"(sub-buffer covariance from {len(colours)} buffers); image SURE (MSE estimate) = "
          f"{mse:.6g}")
    return 0


def read_buffers(args: argparse.Namespace, frame, path=None):
    """The colours of ``args.buffers`` as one (K, H, W, 3) float32 array, read and checked by
    :func:`read_buffer_frames` (for ``jaxden sure`` and ``jaxden progressive``)."""
    import numpy as np

    return np.stack([np.asarray(buffer.color, np.float32)
                     for buffer in read_buffer_frames(args, frame, path)])


def read_buffer_frames(args: argparse.Namespace, frame, path=None, *, require=("color",),
                       keep=("color",), channel_map=None, reading=None) -> list:
    """The Frames of ``args.buffers`` (fields ``require`` and ``keep``), checked against
    ``frame`` (``path``, default ``args.input``, as read) by
    :func:`jaxden.sure.buffers.check_sub_buffers` (each failure one FrameError naming the
    files): at least 2, each of the input's size, none given twice, equal spp where their
    headers state one, and their mean equal to the input's colour; where the input's header
    lists the buffers it was made from (:func:`jaxden.data.merge.read_buffer_list`), exactly
    those, read by the convention they were merged with (``jaxden merge --from``), else by
    ``reading`` (``convention`` and ``layer`` of :func:`jaxden.io.exr.read_frame`).
    """
    import numpy as np

    from jaxden.data.merge import read_buffer_list
    from jaxden.io.exr import read_frame
    from jaxden.sure.buffers import check_sub_buffers

    source = args.input if path is None else path
    paths = [str(p) for p in args.buffers]
    listed = read_buffer_list(source)
    if listed is not None:
        reading = {"convention": listed.convention, "layer": listed.layer}
    buffers = [read_frame(path, require=require, nonfinite=args.nonfinite, keep=keep,
                          channel_map=channel_map, **(reading or {})) for path in paths]
    colours = np.stack([np.asarray(buffer.color, np.float32) for buffer in buffers])
    check_sub_buffers(frame.color, colours, where="--buffers", names=paths,
                      spp=[None if b.spp is None else float(b.spp) for b in buffers],
                      made_from=listed, frame_name=str(source))
    return buffers


def buffers_notice(path, batch: bool = False) -> bool:
    """One stderr line when the input at ``path`` lists the buffers it was made from and
    ``--buffers`` was not given: they would give sub-buffer SURE (``batch``: the input is one
    of several, which run with --buffers one at a time). Returns whether it was said."""
    from jaxden.data.merge import read_buffer_list
    from jaxden.errors import ExrError

    try:
        listed = read_buffer_list(path)
    except ExrError:  # a record --buffers would refuse; without --buffers it changes nothing
        return False
    if listed is None:
        return False
    if batch:
        stderr(f"jaxden: note: {path} (and maybe other inputs) was made from "
               f"{len(listed.files)} buffers; one input at a time with --buffers gives "
               f"sub-buffer SURE (no probes, no Gaussian assumption) instead of probe SURE")
    else:
        stderr(f"jaxden: note: {path} was made from {len(listed.files)} buffers; --buffers "
               f"{' '.join(listed.files)} gives sub-buffer SURE (no probes, no Gaussian "
               f"assumption) instead of probe SURE")
    return True


def _memory_limit(args: argparse.Namespace) -> int | None:
    from jaxden.limits import parse_bytes

    return None if args.memory_limit is None else parse_bytes(args.memory_limit,
                                                              "--memory-limit")


def cmd_progressive(args: argparse.Namespace) -> int:
    """``jaxden progressive IN [IN ...] --denoiser NAME|CKPT --mixer CKPT (--out OUT.exr |
    --out-dir DIR)``: the mixer and the denoiser loaded once, each input run in turn."""
    import warnings

    import jax
    import numpy as np

    from jaxden.denoise.registry import load_denoiser
    from jaxden.fileio import all_or_nothing
    from jaxden.io.exr import write_channels, write_image
    from jaxden.progressive.mixer_checkpoints import load_mixer
    from jaxden.progressive.pipeline import MixerDenoiserWarning, warn_if_other_denoiser
    from jaxden.progressive.tiled import progressive_frame

    inputs = list(args.input)
    several = len(inputs) > 1
    if args.buffers and several:
        raise ConfigError(f"--buffers names the sub-buffers of one input, but {len(inputs)} "
                          f"inputs were given; run each input with its own --buffers")
    targets = batch_outputs(inputs, ("--out", args.out), ("--out-dir", args.out_dir))
    alphas = batch_outputs(inputs, ("--alpha", args.alpha), ("--alpha-dir", args.alpha_dir),
                           required=False)
    if args.out_dir is not None and args.alpha_dir is not None and same_file(args.out_dir,
                                                                             args.alpha_dir):
        raise ConfigError(f"--alpha-dir {args.alpha_dir} is the --out-dir folder: each input's "
                          f"name would be written twice there; give another folder")
    folders = [folder for option, folder in (("--out-dir", args.out_dir),
                                             ("--alpha-dir", args.alpha_dir))
               if folder is not None and output_folder(option, folder)]
    checked = exr_outputs(*(pair for both in zip(targets, alphas) for pair in both),
                          inputs=(*inputs, *(args.buffers or ())),
                          overwrite_input=args.overwrite_input, new_folders=folders)
    outputs = list(zip(checked[0::2], checked[1::2]))
    if args.mixer is None:
        from jaxden.denoise.registry import split_spec
        from jaxden.progressive.pipeline import SHIPPED_MIXERS, load_shipped_mixer

        base, _ = split_spec(args.denoiser)  # wskp-6:emission=separate -> wskp-6's mixer
        shipped = load_shipped_mixer(base) if isinstance(base, str) else None
        if shipped is None:
            raise CheckpointError(
                f"jaxden progressive: no mixer ships for denoiser {args.denoiser!r} (shipped: "
                f"{', '.join(f'{m} for {d}' for d, m in SHIPPED_MIXERS.items())}); pass "
                f"--mixer CKPT, or --mixer closed-form (no training, any denoiser)"
            )
        args.mixer = SHIPPED_MIXERS[base]
        params, config = shipped  # a twin's with its SURE settings (TWIN_SURE)
    else:
        params, config = load_mixer(args.mixer)
    if args.tstat:
        if args.no_tstat:
            raise ConfigError("jaxden progressive: --tstat sets fields of the t-statistic "
                              "that --no-tstat turns off; give one of them")
        from jaxden.progressive.mixer_config import with_tstat_overrides

        config = with_tstat_overrides(config, args.tstat)
    settings = sure_settings(args).over(config.sure)  # an unset option: the mixer's
    base = load_denoiser(args.denoiser)  # first: a spec that cannot load is the error
    if several:
        input_sizes(inputs)  # every input readable before any work
    denoisers = denoisers_by_input(base, args.denoiser, inputs, args)
    keep = ("z", "alpha_prime", "alpha") if args.alpha or args.alpha_dir else ("z",)
    said: set = set()
    results: dict = {}

    def run_one(source, out, alpha_out, denoiser):
        frame = read_input_frame(args, "jaxden progressive", denoiser,
                                 covariance=settings.covariance and not args.buffers,
                                 path=source)
        feature_notice(frame, denoiser, source, said if several else None)
        buffers = read_buffers(args, frame, source) if args.buffers else None
        if buffers is None and "buffers" not in said and buffers_notice(source, several) \
                and several:
            said.add("buffers")
        if ("mixer", id(denoiser)) not in said:  # once for each denoiser
            said.add(("mixer", id(denoiser)))
            with warnings.catch_warnings():  # said here in one line; the library stays quiet
                warnings.simplefilter("ignore", MixerDenoiserWarning)
                note = warn_if_other_denoiser(config, denoiser, args.denoiser)
            if note is not None:
                stderr(f"jaxden: note: {note}")
        if settings.covariance and frame.covariance is None and buffers is None and (
                "covariance" not in said):
            stderr(f"jaxden: note: the mixer was trained on SURE from the colour covariance, "
                   f"but {source} has none (channels covariance.RG/GB/BR): SURE falls back to "
                   f"the per-channel form, which underestimates the error of a denoiser that "
                   f"mixes channels")
            if several:
                said.add("covariance")

        def tell(plan):
            text = plan.describe(*np.shape(frame.color)[-3:-1])
            if plan.tile and text not in said:
                stderr(f"jaxden: {source}: {text}")
                if several:
                    said.add(text)

        produced, _ = progressive_frame(
            frame, denoiser, params, config, jax.random.PRNGKey(settings.seed), sure=settings,
            tstat=None if args.no_tstat else config.tstat, nonfinite=args.nonfinite,
            swap_average=args.swap_average, tile=args.tile, limit=_memory_limit(args),
            keep=keep, progress=True, on_plan=tell, buffers=buffers)
        z = produced["z"]
        swap_average = config.swap_average if args.swap_average is None else args.swap_average
        attributes = {"source": str(source), "denoiser": denoiser.name,
                      "mixer": str(args.mixer), "probes": settings.probes,
                      "probe_dist": settings.probe_dist, "seed": settings.seed,
                      "tstat": int(not args.no_tstat), "swap_average": int(swap_average)}
        if args.tstat:
            attributes["tstat_overrides"] = " ".join(args.tstat)
        message = f"wrote {out} (progressive denoising: {denoiser.name} + mixer {args.mixer}"
        if buffers is None:
            message += ")"
        else:  # SURE from the sub-buffers: no probes, no seed
            del attributes["probes"], attributes["probe_dist"], attributes["seed"]
            attributes |= {"method": "buffers", "buffers": len(buffers)}
            message += f", SURE from {len(buffers)} sub-buffers)"
        check_finite_result(z, "the progressive-denoising result",
                            f"{source}, denoiser {args.denoiser} and mixer {args.mixer}")
        with all_or_nothing():  # the image and its alpha: both or neither
            write_image(out, np.asarray(z), attributes=attributes)
            if alpha_out is not None:
                alpha_prime, alpha = produced["alpha_prime"], produced["alpha"]
                channels = {name: alpha_prime[..., i] for i, name in enumerate(("R", "G", "B"))}
                channels |= {f"unscaled.{c}": alpha[..., i] for i, c in enumerate("RGB")}
                write_channels(alpha_out, channels, attributes=attributes)
                message += (f"; alpha in {alpha_out} (mean alpha {alpha.mean():.4f}, after the "
                            f"t-test {alpha_prime.mean():.4f})")
        results["message"] = message

    jobs = [(source, pair, denoiser) for source, pair, denoiser
            in zip(inputs, outputs, denoisers)]
    done = run_jobs(jobs, run_one, skip_existing=args.skip_existing, folders=folders)
    if done is None:
        return 130
    if not several:
        print(results["message"] if done[0] else
              f"skipped {outputs[0][0]}: it exists (--skip-existing)")
        return 0
    names = ", ".join(dict.fromkeys(denoiser.name for denoiser in denoisers))
    alpha_text = f"; alpha in {args.alpha_dir}" if args.alpha_dir is not None else ""
    print(batch_summary(done, args.out_dir, f"progressive denoising: {names} + mixer {args.mixer}")
          + alpha_text)
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser(
        "sure", help="denoise an EXR and write the per-pixel SURE of the result",
        description="Writes one EXR: R,G,B = the denoised image, sure.R/G/B = its per-pixel SURE "
                    "(squared-error estimate), divergence.R/G/B = var * dy/dx.",
    )
    sure_input_options(p)
    p.add_argument("--out", required=True, help="output .exr (denoised + sure + divergence)")
    p.add_argument("--buffers", nargs="+", default=None, metavar="BUFFER.exr",
                   help="K >= 2 independent sub-buffer renders (equal spp) whose mean is IN, "
                        "e.g. the renders `jaxden merge` made IN from (then exactly those): "
                        "the covariance term comes from leave-one-buffer-out denoising instead "
                        "of Stein's identity (no Gaussian assumption, K + 1 denoiser calls; "
                        "see jaxden.sure.sure_buffers); divergence.* then holds that term")
    p.add_argument("--extrapolate", action="store_true",
                   help="with --buffers (even K >= 4): cancel the O(1/K) bias of nonlinear "
                        "denoisers by Richardson extrapolation from K and K/2 merged buffers")
    add_memory_options(p)
    add_overwrite_input_option(p)
    p.set_defaults(func=cmd_sure)

    p = sub.add_parser(
        "progressive", help="progressive denoising: denoise, SURE, mixer, t-statistic scaling",
        description="Writes z' = x + alpha' (y - x) as R,G,B; --alpha writes alpha' (R,G,B) and "
                    "alpha before the t-statistic scaling (unscaled.R/G/B). SURE comes from "
                    "random probes, or with --buffers from K sub-buffers of the input.",
    )
    sure_input_options(p, probes_from_mixer=True, several=True)
    p.add_argument("--mixer", default=None,
                   help="trained mixer: a shipped name (oidn-pd), a checkpoint folder of "
                        "`jaxden train` or a .msgpack file; or closed-form[:sigma=S] (the "
                        "paper's Eq. 9 with local means: no weights, any denoiser); default: "
                        "the mixer shipped for --denoiser (oidn-pd for oidn and oidn-jax)")
    p.add_argument("--out", default=None, help="output .exr (one input)")
    p.add_argument("--out-dir", default=None, metavar="DIR",
                   help="output folder (made if missing): each input written there under its "
                        "own file name")
    p.add_argument("--alpha", default=None,
                   help="also write the mixing weights to this .exr (one input)")
    p.add_argument("--alpha-dir", default=None, metavar="DIR",
                   help="also write each input's mixing weights into this folder, under the "
                        "input's file name")
    add_skip_existing_option(p)
    p.add_argument("--buffers", nargs="+", default=None, metavar="BUFFER.exr",
                   help="K >= 2 independent sub-buffer renders (equal spp) whose mean is IN, "
                        "e.g. the renders `jaxden merge` made IN from (then exactly those): "
                        "SURE is their sub-buffer SURE (K + 1 whole-frame denoiser calls, no "
                        "probes: the SURE options --probes ... --seed do not apply), fed to "
                        "the mixer and the t-statistic as probe SURE is; the header records "
                        "method=buffers")
    p.add_argument("--no-tstat", action="store_true",
                   help="skip the t-statistic scaling (the paper's 'w/o t-test' ablation)")
    p.add_argument("--tstat", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the mixer's t-statistic and error-guard config "
                        "(jaxden.progressive.TStatConfig), e.g. guard_cap_spp=16 (the guard's "
                        "wider cap below 16 spp: docs/results.md); repeatable; recorded in "
                        "the output's header")
    p.add_argument("--swap-average", action=argparse.BooleanOptionalAction, default=None,
                   help="average alpha with 1 - alpha of the swapped inputs (a second mixer "
                        "call); default: the mixer's config (on for oidn-pd)")
    add_memory_options(p)
    add_overwrite_input_option(p)
    p.set_defaults(func=cmd_progressive)

    p = sub.add_parser(
        "denoise", help="denoise EXRs with a registered or trained denoiser",
        description="Denoises one EXR (--out) or several (--out-dir): the denoiser is loaded "
                    "once and compiled once per frame size, and each input is read, denoised "
                    "and written in turn. --sequence: the inputs are consecutive frames of one "
                    "animation, in the order given, and a temporal denoiser (svgf) carries its "
                    "history from frame to frame.")
    p.add_argument("input", nargs="+", metavar="IN",
                   help="input EXRs (colour and the features the model needs)")
    p.add_argument("--model", required=True,
                   help="oidn, a shipped model name, or a checkpoint folder; add "
                        ":emission=separate to keep the emission (emission.R/G/B) out of the "
                        "filter: D(colour - emission) + emission")
    p.add_argument("--out", default=None, help="output .exr (one input)")
    p.add_argument("--out-dir", default=None, metavar="DIR",
                   help="output folder (made if missing): each input written there under its "
                        "own file name")
    p.add_argument("--sequence", action="store_true",
                   help="the inputs are consecutive frames of one animation, in the order "
                        "given: a temporal denoiser (svgf) carries its history from one to the "
                        "next (whole frames of one size; without it each frame is denoised "
                        "alone)")
    add_skip_existing_option(p)
    p.add_argument("--buffers", nargs="+", default=None, metavar="BUFFER.exr",
                   help="K >= 2 independent sub-buffer renders (equal spp) whose mean is IN, "
                        "for a denoiser of sub-buffers: nfor (NFOR, Bitterli et al. 2016); "
                        "`jaxden render --buffers 2` writes them")
    p.add_argument("--nonfinite", choices=("error", "zero"), default="error",
                   help="NaN/inf in the input: refuse (default) or replace by 0")
    add_channels_option(p)
    add_convention_options(p)
    add_memory_options(p)
    add_overwrite_input_option(p)
    p.set_defaults(func=cmd_denoise)

