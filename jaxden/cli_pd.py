"""Progressive-denoising commands of the ``jaxden`` CLI: ``sure``, ``progressive`` and
``dataset sure-cache``. :func:`add_pd_commands` adds them to the main parser.

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
:mod:`jaxden.pdcache`).

Output of ``jaxden progressive``: ``R,G,B`` = z' = x + alpha' (y - x); with ``--alpha A.exr``
also ``R,G,B`` = alpha' (after the t-statistic scaling) and ``unscaled.R/G/B`` = alpha (before).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from jaxden.errors import CheckpointError, ConfigError, FrameError

__all__ = ["add_pd_commands", "cmd_progressive", "cmd_sure", "cmd_sure_cache"]


def _positive_int(text: str) -> int:
    from jaxden.cli import positive_int

    return positive_int(text)


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return value


def _channel_names(text: str) -> tuple[str, str, str]:
    names = tuple(part.strip() for part in text.split(","))
    if len(names) != 3 or not all(names):
        raise argparse.ArgumentTypeError(f"give three channel names like A.R,A.G,A.B, got {text!r}")
    return names  # type: ignore[return-value]


def _channel_spec(text: str) -> tuple[str, tuple[str, ...]]:
    """``FIELD=NAME,NAME,...`` of ``--channels``: a Frame field and its channel names."""
    from jaxden.frame import CHANNELS

    field, sep, names = text.partition("=")
    field = field.strip()
    if not sep or field not in CHANNELS:
        raise argparse.ArgumentTypeError(
            f"expected FIELD=NAME,... with FIELD one of {', '.join(CHANNELS)}, got {text!r}")
    parts = tuple(part.strip() for part in names.split(","))
    want = len(CHANNELS[field])
    if len(parts) != want or not all(parts):
        raise argparse.ArgumentTypeError(
            f"{field} takes {want} channel name(s) (default {','.join(CHANNELS[field])}), "
            f"got {names!r}")
    return field, parts


def add_channels_option(parser: argparse.ArgumentParser) -> None:
    """``--channels FIELD=NAME,...``: the input file's channel names for a Frame field."""
    parser.add_argument(
        "--channels", type=_channel_spec, action="append", default=None, metavar="FIELD=NAMES",
        help="the input's channel names for a field, if not jaxden's, e.g. "
             "albedo=Albedo.R,Albedo.G,Albedo.B or normal=Ns.X,Ns.Y,Ns.Z (repeatable; fields: "
             "color, variance, albedo, normal, depth, position, motion)")


def channel_map(args: argparse.Namespace) -> dict[str, tuple[str, ...]] | None:
    """The ``channel_map`` of :func:`jaxden.io.exr.read_frame` from ``--channels`` (and
    ``--variance-channels``); None when neither is given."""
    mapping: dict[str, tuple[str, ...]] = {}
    given = list(getattr(args, "channels", None) or ())
    if getattr(args, "variance_channels", None):
        given.append(("variance", tuple(args.variance_channels)))
    for field, names in given:
        if mapping.get(field, names) != names:
            raise ConfigError(f"the channels of {field} are given twice, differently: "
                              f"{','.join(mapping[field])} and {','.join(names)}")
        mapping[field] = names
    return mapping or None


def feature_notice(frame, denoiser, path) -> None:
    """On stderr: OIDN is about to run without albedo or normal. On jaxden's test crops that
    raises its error by 4 % (RMSE) and 13 % (relMSE) on average over 2..1024 spp, up to 10 % and
    25 % at 16-64 spp (experiments/results/oidn-no-features.md), and a mixer trained on OIDN
    with features then sees inputs unlike its training data."""
    if denoiser.name != "oidn":
        return
    lacking = [field for field in ("albedo", "normal") if getattr(frame, field) is None]
    if lacking:
        from jaxden.frame import CHANNELS

        expected = "; ".join(f"{f}: {','.join(CHANNELS[f])}" for f in lacking)
        _stderr(f"jaxden: note: {path} has no {' or '.join(lacking)} channels ({expected}); "
                f"OIDN runs on colour alone, which is usually worse. Name your renderer's "
                f"channels with --channels FIELD=NAME,... if it has them")


def exr_outputs(*outputs: tuple[str, str | None]) -> list[Path | None]:
    """Check the output .exr files of a command, given as ``(option, path or None)`` pairs,
    before any work: .exr names, distinct, not folders, in existing writable folders
    (:func:`jaxden.fileio.check_outputs`). Returns the paths (None where not given)."""
    from jaxden.fileio import check_outputs

    given = [(option, path) for option, path in outputs if path is not None]
    for option, path in given:
        if Path(path).suffix.lower() != ".exr":
            raise ConfigError(f"{option} must name an .exr file, got {path}")
    checked = iter(check_outputs(*given))
    return [None if path is None else next(checked) for _, path in outputs]


def read_input_frame(args: argparse.Namespace, who: str):
    """Read ``args.input`` for SURE: colour and variance required (clear errors otherwise)."""
    from jaxden.io.exr import read_frame, read_header

    mapping = channel_map(args)
    frame = read_frame(
        args.input,
        require=("color", *(mapping or {})),  # channels named on the command line must exist
        nonfinite=args.nonfinite,
        channel_map=mapping,
        variance_is_sample_variance=args.sample_variance,
        spp=args.spp,
    )
    if frame.variance is None:
        names = ", ".join((mapping or {}).get("variance", ("variance.R", "variance.G",
                                                              "variance.B")))
        header = read_header(args.input)
        found = ", ".join(header["channels"])
        if header["parts"] > 1:
            found += f" in the first of its {header['parts']} parts, the one jaxden reads"
        raise FrameError(
            f"{args.input}: {who} needs SURE, and SURE needs the variance of the pixel mean "
            f"(channels {names}), which the file lacks (it has {found}); name your renderer's "
            f"variance channels with --channels variance=R,G,B (and --sample-variance if they "
            f"hold the per-sample variance)"
        )
    return frame


def _stderr(message: str) -> None:
    print(message, file=sys.stderr)


# ---------------------------------------------------------------------------------- commands
def cmd_sure(args: argparse.Namespace) -> int:
    """``jaxden sure IN.exr --denoiser NAME|CKPT --out SURE.exr``."""
    import jax
    import numpy as np

    from jaxden.denoisers import load_denoiser
    from jaxden.pdcache import default_eps, denoise_with_sure, resolve_method, write_sure_exr

    (out,) = exr_outputs(("--out", args.out))
    frame = read_input_frame(args, "jaxden sure")
    denoiser = load_denoiser(args.denoiser)
    feature_notice(frame, denoiser, args.input)
    if args.buffers:
        return _sure_from_buffers(args, frame, denoiser, out)
    if args.extrapolate:
        raise ConfigError("--extrapolate needs --buffers")
    method = resolve_method(args.method, denoiser)
    eps = args.eps if args.eps is not None else default_eps(method, denoiser.differentiable)
    result, _ = denoise_with_sure(
        denoiser, frame, jax.random.PRNGKey(args.seed), num_probes=args.probes, method=method,
        eps=eps, probe_batch=args.probe_batch, nonfinite=args.nonfinite, where=str(args.input),
    )
    write_sure_exr(out, result, attributes={
        "source": str(args.input), "denoiser": denoiser.name, "probes": args.probes,
        "method": method, "eps": -1.0 if eps is None else float(eps), "seed": args.seed,
    })
    mse = float(np.mean(np.asarray(result.sure)))
    print(f"wrote {out}: R,G,B = denoised by {denoiser.name}, sure.* = per-pixel SURE "
          f"({args.probes} probes, {method}); image SURE (MSE estimate) = {mse:.6g}")
    return 0


def _sure_from_buffers(args: argparse.Namespace, frame, denoiser, out: Path) -> int:
    """``jaxden sure IN.exr --buffers B1.exr ... BK.exr``: sub-buffer SURE (no probes)."""
    import numpy as np

    from jaxden.io.exr import read_frame
    from jaxden.pdcache import write_sure_exr
    from jaxden.sure import sure_buffers

    if len(args.buffers) < 2:
        raise ConfigError(f"--buffers needs at least 2 files, got {len(args.buffers)}")
    colours, counts = [], {}
    for path in args.buffers:
        buffer = read_frame(path, require=("color",), nonfinite=args.nonfinite)
        if np.shape(buffer.color) != np.shape(frame.color):
            raise FrameError(f"{path}: shape {np.shape(buffer.color)[:-1]}, but {args.input} "
                             f"is {np.shape(frame.color)[:-1]}")
        if buffer.spp is not None:
            counts.setdefault(float(buffer.spp), path)
        colours.append(np.asarray(buffer.color))
    if len(counts) > 1:
        raise FrameError(f"--buffers: the sub-buffers must have equal spp, but their headers "
                         f"say {', '.join(f'{c:g} ({p})' for c, p in sorted(counts.items()))}")
    try:
        result = sure_buffers(denoiser, frame, np.stack(colours), extrapolate=args.extrapolate,
                              nonfinite=args.nonfinite)
    except FrameError as error:
        raise FrameError(f"{args.input} with --buffers {' '.join(map(str, args.buffers))}: "
                         f"{error}") from None
    write_sure_exr(out, result, attributes={
        "source": str(args.input), "denoiser": denoiser.name,
        "method": "buffers-extrapolated" if args.extrapolate else "buffers",
        "buffers": len(colours)})
    mse = float(np.mean(result.sure))
    print(f"wrote {out}: R,G,B = denoised by {denoiser.name}, sure.* = per-pixel SURE "
          f"(sub-buffer covariance from {len(colours)} buffers); image SURE (MSE estimate) = "
          f"{mse:.6g}")
    return 0


def cmd_progressive(args: argparse.Namespace) -> int:
    """``jaxden progressive IN.exr --denoiser NAME|CKPT --mixer CKPT --out OUT.exr``."""
    import jax
    import numpy as np

    from jaxden.denoisers import load_denoiser
    from jaxden.fileio import all_or_nothing
    from jaxden.io.exr import write_channels, write_image
    from jaxden.progressive import load_mixer, progressive_denoise

    out, alpha_out = exr_outputs(("--out", args.out), ("--alpha", args.alpha))
    if args.mixer is None:
        from jaxden.progressive import SHIPPED_MIXERS, shipped_mixer_path

        if shipped_mixer_path(args.denoiser) is None:
            raise CheckpointError(
                f"jaxden progressive: no mixer ships for denoiser {args.denoiser!r} (shipped: "
                f"{', '.join(f'{m} for {d}' for d, m in SHIPPED_MIXERS.items())}); pass "
                f"--mixer CKPT, or --mixer closed-form (no training, any denoiser)"
            )
        args.mixer = SHIPPED_MIXERS[args.denoiser]
    params, config = load_mixer(args.mixer)
    frame = read_input_frame(args, "jaxden progressive")
    denoiser = load_denoiser(args.denoiser)
    feature_notice(frame, denoiser, args.input)
    if (config.kind == "network" and config.denoiser != denoiser.name
            and Path(config.denoiser).name != Path(args.denoiser).name):
        _stderr(f"jaxden: note: the mixer was trained on the output of denoiser "
                f"{config.denoiser!r}; mixing {denoiser.name!r} instead")
    z, alpha_prime, extras = progressive_denoise(
        frame, denoiser, params, config, jax.random.PRNGKey(args.seed), num_probes=args.probes,
        method=args.method, eps=args.eps, probe_batch=args.probe_batch,
        tstat=None if args.no_tstat else config.tstat, nonfinite=args.nonfinite,
        swap_average=args.swap_average,
    )
    swap_average = config.swap_average if args.swap_average is None else args.swap_average
    attributes = {"source": str(args.input), "denoiser": denoiser.name, "mixer": str(args.mixer),
                  "probes": args.probes, "seed": args.seed, "tstat": int(not args.no_tstat),
                  "swap_average": int(swap_average)}
    message = f"wrote {out} (progressive denoising: {denoiser.name} + mixer {args.mixer})"
    with all_or_nothing():  # --out and --alpha: both or neither
        write_image(out, np.asarray(z), attributes=attributes)
        if alpha_out is not None:
            alpha_prime = np.asarray(alpha_prime)
            alpha = np.asarray(extras["alpha"])
            channels = {name: alpha_prime[..., i] for i, name in enumerate(("R", "G", "B"))}
            channels |= {f"unscaled.{c}": alpha[..., i] for i, c in enumerate("RGB")}
            write_channels(alpha_out, channels, attributes=attributes)
            message += (f"; alpha in {alpha_out} (mean alpha {alpha.mean():.4f}, after the "
                        f"t-test {alpha_prime.mean():.4f})")
    print(message)
    return 0


def cmd_sure_cache(args: argparse.Namespace) -> int:
    """``jaxden dataset sure-cache DIR --denoiser SPEC``."""
    from jaxden.pdcache import build_sure_cache

    cache = build_sure_cache(
        args.dir, args.denoiser, args.out, num_probes=args.probes, method=args.method,
        eps=args.eps, seed=args.seed, fd_scheme=args.fd_scheme, probe_batch=args.probe_batch,
        half=args.half, progress=not args.quiet,
    )
    settings = cache.identity.get("settings", {})
    print(f"SURE cache complete: {cache.directory} ({len(cache.records)} items; "
          f"{settings.get('num_probes')} probes, {settings.get('method')}, "
          f"eps {settings.get('eps')}, seed {settings.get('seed')})")
    return 0


# ---------------------------------------------------------------------------------- parser
def _input_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="input EXR: colour and the variance of the pixel mean")
    parser.add_argument("--denoiser", required=True,
                        help="oidn, a shipped model name, a checkpoint folder or a .msgpack file")
    parser.add_argument("--probes", type=_positive_int, default=4,
                        help="SURE probes K (default 4)")
    parser.add_argument("--method", choices=("auto", "jvp", "fd"), default="auto",
                        help="SURE divergence: jvp (JAX denoisers), fd (finite differences; the "
                             "only choice for OIDN), auto (default)")
    parser.add_argument("--eps", type=_positive_float, default=None,
                        help="finite-difference step (default: 1e-2 for OIDN, 1e-3 for JAX fd)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the SURE probes")
    parser.add_argument("--probe-batch", type=_positive_int, default=None,
                        help="probes per jvp pass (1 bounds the memory for big images)")
    add_channels_option(parser)
    parser.add_argument("--variance-channels", type=_channel_names, default=None,
                        metavar="R,G,B",
                        help="names of the variance channels if not variance.R/G/B (the same "
                             "as --channels variance=R,G,B)")
    parser.add_argument("--sample-variance", action="store_true",
                        help="the file stores the per-sample variance: divide it by spp")
    parser.add_argument("--spp", type=_positive_float, default=None,
                        help="samples per pixel, when the header has no jaxden.spp")
    parser.add_argument("--nonfinite", choices=("error", "zero"), default="error",
                        help="NaN/inf or negative variance: refuse (default) or repair (NaN -> 0, "
                             "variance clipped at 0; the authors' policy)")


def add_pd_commands(subparsers, dataset_subparsers=None) -> None:
    """Add ``sure`` and ``progressive`` to the top-level ``subparsers`` and ``sure-cache`` to
    the ``dataset`` command's subparsers (found through ``subparsers`` when not given)."""
    p = subparsers.add_parser(
        "sure", help="denoise an EXR and write the per-pixel SURE of the result",
        description="Writes one EXR: R,G,B = the denoised image, sure.R/G/B = its per-pixel SURE "
                    "(squared-error estimate), divergence.R/G/B = var * dy/dx.",
    )
    _input_options(p)
    p.add_argument("--out", required=True, help="output .exr (denoised + sure + divergence)")
    p.add_argument("--buffers", nargs="+", default=None, metavar="BUFFER.exr",
                   help="K >= 2 independent sub-buffer renders (equal spp) whose mean is IN: "
                        "the covariance term comes from leave-one-buffer-out denoising instead "
                        "of Stein's identity (no Gaussian assumption, K + 1 denoiser calls; "
                        "see jaxden.sure.sure_buffers); divergence.* then holds that term")
    p.add_argument("--extrapolate", action="store_true",
                   help="with --buffers (even K >= 4): cancel the O(1/K) bias of nonlinear "
                        "denoisers by Richardson extrapolation from K and K/2 merged buffers")
    p.set_defaults(func=cmd_sure)

    p = subparsers.add_parser(
        "progressive", help="progressive denoising: denoise, SURE, mixer, t-statistic scaling",
        description="Writes z' = x + alpha' (y - x) as R,G,B; --alpha writes alpha' (R,G,B) and "
                    "alpha before the t-statistic scaling (unscaled.R/G/B).",
    )
    _input_options(p)
    p.add_argument("--mixer", default=None,
                   help="trained mixer: a shipped name (oidn-pd), a checkpoint folder of "
                        "`jaxden train` or a .msgpack file; or closed-form[:sigma=S] (the "
                        "paper's Eq. 9 with local means: no weights, any denoiser); default: "
                        "the mixer shipped for --denoiser (oidn-pd for oidn)")
    p.add_argument("--out", required=True, help="output .exr")
    p.add_argument("--alpha", default=None, help="also write the mixing weights to this .exr")
    p.add_argument("--no-tstat", action="store_true",
                   help="skip the t-statistic scaling (the paper's 'w/o t-test' ablation)")
    p.add_argument("--swap-average", action=argparse.BooleanOptionalAction, default=None,
                   help="average alpha with 1 - alpha of the swapped inputs (a second mixer "
                        "call); default: the mixer's config (on for oidn-pd)")
    p.set_defaults(func=cmd_progressive)

    if dataset_subparsers is None:
        dataset_parser = subparsers.choices.get("dataset")
        if dataset_parser is None:
            raise ValueError("add_pd_commands: the parser has no 'dataset' command")
        dataset_subparsers = next(
            action for action in dataset_parser._actions
            if isinstance(action, argparse._SubParsersAction)
        )
    c = dataset_subparsers.add_parser(
        "sure-cache", help="denoise every dataset input once and cache it with its SURE map "
                           "(resumable; what mixer training reads)")
    c.add_argument("dir", help="dataset folder")
    c.add_argument("--denoiser", required=True, help="oidn, a checkpoint folder or .msgpack")
    c.add_argument("--out", default=None, help="cache folder (default: DIR/derived/<denoiser>)")
    c.add_argument("--probes", type=_positive_int, default=4)
    c.add_argument("--method", choices=("auto", "jvp", "fd"), default="auto")
    c.add_argument("--eps", type=_positive_float, default=None)
    c.add_argument("--fd-scheme", choices=("forward", "central"), default="forward")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--probe-batch", type=_positive_int, default=None)
    c.add_argument("--half", action="store_true", help="store float16 channels")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=cmd_sure_cache)
