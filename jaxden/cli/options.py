"""Option types and helpers shared by the command groups: sizes, counts, channel maps, the
checked .exr outputs, the SURE options (made from :class:`jaxden.sure.SureSettings`: one flag
a field, read back as one value), and reading an input frame for SURE."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from jaxden.errors import ConfigError, FrameError


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


def positive_float(text: str) -> float:
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
    from jaxden.frame import CHANNELS

    parser.add_argument(
        "--channels", type=_channel_spec, action="append", default=None, metavar="FIELD=NAMES",
        help="the input's channel names for a field, if not jaxden's, e.g. "
             "albedo=Albedo.R,Albedo.G,Albedo.B, normal=Ns.X,Ns.Y,Ns.Z or (Blender Cycles) "
             "emission=ViewLayer.Emit.R,ViewLayer.Emit.G,ViewLayer.Emit.B (repeatable; fields: "
             f"{', '.join(CHANNELS)})")


def add_convention_options(parser: argparse.ArgumentParser) -> None:
    """``--from RENDERER`` and ``--layer NAME``: read the input by another renderer's channel
    conventions (:mod:`jaxden.io.conventions`)."""
    from jaxden.io.conventions import CONVENTIONS

    parser.add_argument(
        "--from", dest="convention", choices=tuple(CONVENTIONS), default=None,
        help="the renderer that wrote the input: its channel names for colour, albedo, normal, "
             "depth and variance, the variance's meaning and the header's sample count "
             "(--channels wins where given); falcor: name any one file of a frame capture "
             "(e.g. Mogwai.AccumulatePass.output.256.exr) and the files of the same prefix and "
             "frame beside it are read with it (docs/renderers.md)")
    parser.add_argument("--layer", default=None,
                        help="the render layer of a layered file (--from cycles) holding several")


def convention_options(args: argparse.Namespace) -> dict:
    """The ``convention`` and ``layer`` keywords of :func:`jaxden.io.exr.read_frame`."""
    return {"convention": getattr(args, "convention", None),
            "layer": getattr(args, "layer", None)}


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


def feature_notice(frame, denoiser, path, said: set | None = None) -> None:
    """On stderr: a model is about to run on features made otherwise than those it was
    trained on (:mod:`jaxden.data.features`: the file's header against the checkpoint's
    record), or OIDN without albedo or normal, which raises its error (measured:
    experiments/results/oidn/oidn-no-features.md), and a mixer trained on OIDN with features
    then sees inputs unlike its training data. ``said``: the notes a command running over
    several files has given (each is said once, for the first file it concerns)."""
    from jaxden.data.features import warn_frame_features

    warn_frame_features(getattr(denoiser, "trained_features", None), path,
                        model=denoiser.name, fields=denoiser.fields_read())
    if denoiser.name.partition("+")[0] != "oidn":  # also oidn+emission-separate
        return
    lacking = [field for field in ("albedo", "normal") if getattr(frame, field) is None]
    if said is not None:
        if ("oidn-features", *lacking) in said:
            return
        said.add(("oidn-features", *lacking))
    if lacking:
        from jaxden.frame import CHANNELS

        expected = "; ".join(f"{f}: {','.join(CHANNELS[f])}" for f in lacking)
        stderr(f"jaxden: note: {path} has no {' or '.join(lacking)} channels ({expected}); "
                f"OIDN runs on colour alone, which is usually worse. Name your renderer's "
                f"channels with --channels FIELD=NAME,... if it has them")


def exr_outputs(*outputs: tuple[str, str | None], inputs=(),
                overwrite_input: bool = False, new_folders=()) -> list[Path | None]:
    """Check the output .exr files of a command, given as ``(option, path or None)`` pairs,
    before any work: .exr names, distinct, not folders, in existing writable folders
    (:func:`jaxden.fileio.check_outputs`), and none of them one of the command's ``inputs``
    (the same file, also through a link or another spelling of the path) unless
    ``overwrite_input``: writing a denoised image over the render would lose its variance
    and features. ``new_folders``: output folders that do not exist yet (from
    :func:`output_folder`): the command makes them before it writes, so their files are
    only checked for their names. Returns the paths (None where not given)."""
    from jaxden.fileio import check_outputs

    given = [(option, path) for option, path in outputs if path is not None]
    for option, path in given:
        if Path(path).suffix.lower() != ".exr":
            raise ConfigError(f"{option} must name an .exr file, got {path}")
    if not overwrite_input:
        sources = _file_keys(source for source in inputs if source is not None)
        for option, path in given:
            source = next((sources[key] for key in _keys_of(path) if key in sources), None)
            if source is not None:
                raise ConfigError(
                    f"{option} {path} is the input file {source}: writing there would "
                    f"replace the render (its variance and features would be lost); choose "
                    f"another output path, or pass --overwrite-input")
    later = {Path(folder) for folder in new_folders}
    checked = iter(check_outputs(*((option, path) for option, path in given
                                   if Path(path).parent not in later)))
    return [None if path is None else Path(path) if Path(path).parent in later
            else next(checked) for _, path in outputs]


def _keys_of(path) -> list:
    """What two spellings of one file share: the resolved path (links followed), and
    (device, inode) where the file exists (hard links); as :func:`same_file` compares."""
    path = Path(path)
    try:
        keys: list = [path.resolve()]
    except (RuntimeError, OSError):  # a symbolic link loop
        keys = [path.absolute()]
    try:
        status = os.stat(path)
    except OSError:
        return keys
    return [*keys, (status.st_dev, status.st_ino)]


def _file_keys(paths) -> dict:
    """``{key: path}`` over :func:`_keys_of` of each of ``paths`` (the first path a key
    names): a batch of N outputs is checked against N inputs in N look-ups, not N^2."""
    keys: dict = {}
    for path in paths:
        for key in _keys_of(path):
            keys.setdefault(key, path)
    return keys


def output_folder(option: str, folder) -> bool:
    """Check the output folder of ``option`` (``--out-dir DIR``) before any work: a folder,
    or a path that can be made one (its nearest existing parent a writable folder). Returns
    whether it must still be made (the command makes it just before its first write, so a
    refused command leaves no folder behind)."""
    folder = Path(folder)
    if folder.exists():
        if not folder.is_dir():
            raise ConfigError(f"{option} {folder}: is a file, not a folder")
        return False
    parent = folder.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{option} {folder}: cannot make it (no permission to write into "
                          f"{parent})")
    return True


def batch_outputs(inputs, file_option: tuple[str, str | None],
                  folder_option: tuple[str, str | None], *, required: bool = True
                  ) -> list[tuple[str, str | Path | None]]:
    """The output of each of ``inputs`` as ``(option, path)`` pairs for :func:`exr_outputs`:
    the file of ``file_option`` (``("--out", OUT.exr)``; one input only) or the input's own
    file name inside the folder of ``folder_option`` (``("--out-dir", DIR)``); with neither
    given, ``(option, None)`` each unless ``required``. One ConfigError line for both given,
    neither (when required), a file for several inputs, and two inputs of the same name."""
    (file_flag, file_path), (folder_flag, folder) = file_option, folder_option
    if file_path is not None and folder is not None:
        raise ConfigError(f"give {file_flag} or {folder_flag}, not both")
    if file_path is None and folder is None:
        if required:
            raise ConfigError(f"give {file_flag} OUT.exr (one input) or {folder_flag} DIR (each "
                              f"input written there under its own name)")
        return [(file_flag, None) for _ in inputs]
    if file_path is not None:
        if len(inputs) > 1:
            raise ConfigError(f"{file_flag} names one file, but {len(inputs)} inputs were given; "
                              f"pass {folder_flag} DIR to write each there under its own name")
        return [(file_flag, file_path)]
    seen: dict[str, str] = {}
    for source in inputs:
        name = Path(source).name
        if Path(name).suffix.lower() != ".exr":
            raise ConfigError(f"{folder_flag} writes each input under its own file name, which "
                              f"must end in .exr: {source}")
        if name in seen:
            first = seen[name]
            if same_file(first, source):
                raise ConfigError(f"{source} is given twice as an input")
            raise ConfigError(f"{first} and {source} have the same file name, so both would be "
                              f"written to {Path(folder) / name}; give inputs with distinct "
                              f"names, or run them separately")
        seen[name] = str(source)
    return [(f"{folder_flag} {folder}:", Path(folder) / Path(source).name) for source in inputs]


def same_file(a, b) -> bool:
    """Whether two paths name one file: the same resolved path (links followed), or the same
    inode where both exist (hard links)."""
    a, b = Path(a), Path(b)
    try:
        if a.resolve() == b.resolve():
            return True
    except (RuntimeError, OSError):  # a symbolic link loop: reading it names the problem
        return a.absolute() == b.absolute()
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def add_overwrite_input_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--overwrite-input", action="store_true",
                        help="allow an output path that is one of the input files (the input is "
                             "then replaced)")


def read_input_frame(args: argparse.Namespace, who: str, denoiser=None,
                     covariance: bool = True, path=None):
    """Read ``path`` (default ``args.input``) for SURE: colour and variance required (clear
    errors otherwise); with ``denoiser``, only the fields SURE and it read are kept (memory;
    ``covariance``: whether SURE reads the colour covariance)."""
    from jaxden.io.exr import read_frame, read_header

    path = args.input if path is None else path
    mapping = channel_map(args)
    keep = None
    if denoiser is not None:
        keep = ("color", "variance", *(("covariance",) if covariance else ()),
                *denoiser.fields_read())
    frame = read_frame(
        path,
        require=("color", *(mapping or {})),  # channels named on the command line must exist
        nonfinite=args.nonfinite,
        channel_map=mapping,
        variance_is_sample_variance=args.sample_variance,
        spp=args.spp,
        spp_override=args.override_spp,
        keep=keep,
        **convention_options(args),
    )
    if frame.variance is None:
        names = ", ".join((mapping or {}).get("variance", ("variance.R", "variance.G",
                                                              "variance.B")))
        header = read_header(path)
        found = ", ".join(header["channels"])
        if frame.spp is not None and float(frame.spp) < 2:
            raise FrameError(
                f"{path}: {who} needs SURE, and SURE needs the variance of the pixel "
                f"mean, which one sample per pixel cannot estimate: render >= 2 spp, or merge "
                f"K >= 2 renders with different seeds (jaxden merge R1.exr .. RK.exr --out X.exr)")
        if getattr(args, "convention", None) not in (None, "jaxden") and "variance" not in (
                mapping or {}):
            from jaxden.io.conventions import CONVENTIONS

            raise FrameError(
                f"{path}: {who} needs SURE, and SURE needs the variance of the pixel "
                f"mean, which a {args.convention} file does not hold: render the frame K >= 2 "
                f"times with different seeds and merge them (jaxden merge R1.exr .. RK.exr "
                f"--from {args.convention} --out X.exr), or name its variance channels with "
                f"--channels variance=R,G,B ({args.convention}: "
                f"{CONVENTIONS[args.convention].note})")
        raise FrameError(
            f"{path}: {who} needs SURE, and SURE needs the variance of the pixel mean "
            f"(channels {names}), which the file lacks (it has {found}); name your renderer's "
            f"variance channels with --channels variance=R,G,B (and --sample-variance if they "
            f"hold the per-sample variance)"
        )
    return frame


def stderr(message: str) -> None:
    print(message, file=sys.stderr)


def add_sure_options(parser: argparse.ArgumentParser, *, inherit: str | None = None) -> None:
    """One flag per option of :class:`jaxden.sure.SureSettings` (``--probes``, ``--method``,
    ``--eps``, ``--fd-scheme``, ``--probe-batch``, ``--probe-dist``, ``--covariance`` /
    ``--no-covariance``, ``--seed``), made from its fields: the type, choices, range and help
    are the field's, and every flag is unset unless given (read them back with
    :func:`sure_settings`). ``inherit``: what an unset flag takes, for the help (e.g. "the
    mixer's"; None: the option's default)."""
    import dataclasses
    import typing

    from jaxden.sure.settings import SureSettings

    hints = typing.get_type_hints(SureSettings)
    for field in dataclasses.fields(SureSettings):
        spec = field.metadata["sure"]
        kind = next(a for a in typing.get_args(hints[field.name]) if a is not type(None))
        default = spec["default_text"] or spec["default"]
        text = f"{spec['help']}; default: {inherit or default}"
        flag = "--" + field.name.replace("_", "-")
        if typing.get_origin(kind) is typing.Literal:
            parser.add_argument(flag, choices=typing.get_args(kind), default=None, help=text)
        elif kind is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=None,
                                help=text)
        else:
            parser.add_argument(flag, type=_sure_value(field.name, kind), default=None,
                                metavar=spec["metavar"] or field.name.upper(), help=text)


def _sure_value(name: str, kind: type):
    """An argparse type: the text as ``kind``, checked by SureSettings' own validation."""

    def parse(text: str):
        from jaxden.sure.settings import SureSettings

        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'a whole number' if kind is int else 'a number'}, got {text!r}"
            ) from None
        try:
            return getattr(SureSettings(**{name: value}), name)
        except ConfigError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    parse.__name__ = kind.__name__
    return parse


def sure_settings(args: argparse.Namespace):
    """The :class:`jaxden.sure.SureSettings` of the flags of :func:`add_sure_options`: the
    given ones set, the rest unset (``.over(base)`` fills them: the mixer's, or
    ``.resolved()`` the defaults)."""
    import dataclasses

    from jaxden.sure.settings import SureSettings

    return SureSettings(**{f.name: getattr(args, f.name, None)
                           for f in dataclasses.fields(SureSettings)})


def sure_input_options(parser: argparse.ArgumentParser, *, probes_from_mixer: bool = False,
                       several: bool = False) -> None:
    """The input and SURE options of ``jaxden sure`` and ``jaxden progressive``; with
    ``probes_from_mixer`` an unset SURE option is the mixer's (its training settings);
    ``several``: one input or more (``args.input`` is then a list)."""
    if several:
        parser.add_argument("input", nargs="+", metavar="IN",
                            help="input EXRs: colour and the variance of the pixel mean; "
                                 "several are run in turn by one loaded mixer and denoiser "
                                 "(with --out-dir)")
    else:
        parser.add_argument("input", help="input EXR: colour and the variance of the pixel mean")
    parser.add_argument("--denoiser", required=True,
                        help="oidn, a shipped model name, a checkpoint folder or a .msgpack file; "
                             "add :emission=separate to keep the emission out of the filter")
    add_sure_options(parser, inherit="the mixer's" if probes_from_mixer else None)
    add_channels_option(parser)
    add_convention_options(parser)
    parser.add_argument("--variance-channels", type=_channel_names, default=None,
                        metavar="R,G,B",
                        help="names of the variance channels if not variance.R/G/B (the same "
                             "as --channels variance=R,G,B)")
    parser.add_argument("--sample-variance", action="store_true",
                        help="the file stores the per-sample variance: divide it by spp")
    parser.add_argument("--spp", type=positive_float, default=None,
                        help="samples per pixel, when the header states none")
    parser.add_argument("--override-spp", action="store_true",
                        help="let --spp replace the sample count the header states")
    parser.add_argument("--nonfinite", choices=("error", "zero"), default="error",
                        help="NaN/inf or negative variance: refuse (default) or repair (NaN -> 0, "
                             "variance clipped at 0; the authors' policy)")


def check_finite_result(array, what: str, cause: str) -> None:
    """Refuse a non-finite command result before anything is written: a FrameError naming
    what was computed and what it came from (the input file, the denoiser and its weights)."""
    import numpy as np

    values = np.asarray(array)
    finite = np.isfinite(values)
    if not finite.all():
        bad = int(values.size - np.count_nonzero(finite))
        raise FrameError(f"{what} has {bad} non-finite value(s) (NaN or inf) of {values.size}, "
                         f"so nothing was written; it came from {cause}: look for huge or "
                         f"broken values there")


def add_memory_options(parser: argparse.ArgumentParser) -> None:
    """``--tile`` and ``--memory-limit``: how a frame is cut into tiles (jaxden.tiling)."""
    parser.add_argument("--tile", type=non_negative_int, default=None, metavar="PIXELS",
                        help="tile side for frames run in pieces (0: the whole frame at once); "
                             "default: the largest tile that fits the memory limit")
    parser.add_argument("--memory-limit", default=None, metavar="BYTES",
                        help="memory budget of this command, e.g. 8G (default: "
                             "JAXDEN_MEMORY_LIMIT, else half the machine's memory); tiles are "
                             "planned to fit it, and a frame that cannot fit is refused up front")


def non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def emission_spec(spec: str, path, args: argparse.Namespace) -> str:
    """The denoiser spec to run on ``path`` (:func:`emission_decision`), its note said on
    stderr."""
    decided, note = emission_decision(spec, path, args)
    if note is not None:
        stderr(f"jaxden: note: {path}: {note}")
    return decided


def emission_specs(spec: str, paths, args: argparse.Namespace) -> list[str]:
    """:func:`emission_spec` for each of several input files, each note said once for the
    files it concerns (one line for a batch whose files all decide alike, not one a file)."""
    decisions = [emission_decision(spec, path, args) for path in paths]
    notes: dict[str, list] = {}
    for path, (_, note) in zip(paths, decisions):
        if note is not None:
            notes.setdefault(note, []).append(path)
    for note, concerned in notes.items():
        if len(concerned) == 1:
            which = str(concerned[0])
        elif len(concerned) == len(paths):
            which = f"the {len(paths)} inputs"
        else:
            which = f"{len(concerned)} of the {len(paths)} inputs ({concerned[0]}, ...)"
        stderr(f"jaxden: note: {which}: {note}")
    return [decided for decided, _ in decisions]


def emission_decision(spec: str, path, args: argparse.Namespace) -> tuple[str, str | None]:
    """``(the denoiser spec to run on path, the note that says why, or None)``: ``spec`` with
    ``emission=separate`` added when the file's albedo was read from a renderer whose albedo
    carries the lamps' light
    (:attr:`jaxden.io.conventions.Convention.albedo_includes_emission`, Blender Cycles'
    Denoising Albedo: read clipped to [0, 1], so a lamp pixel's albedo is white, not its
    reflectance) and the file has the emission beside it; ``spec`` itself otherwise, and
    whenever it sets ``emission`` (``:emission=filter`` keeps the filter on the lamps).

    The renderer is ``--from`` or, for a file ``jaxden merge`` wrote, the convention its renders
    were read by (its header's buffer list). Why: a kernel predictor that divides the colour
    by that albedo spreads a lamp of strength 400 over its neighbours (WSKP-6: 16-72x MC's
    RMSE on Cycles frames with a visible lamp), and keeping the emission out of the filter puts
    it at or below MC (experiments/results/renderers/cycles-emission.md). The note (without
    the path) says what was decided."""
    from jaxden.data.merge import buffer_list
    from jaxden.denoise.registry import split_spec
    from jaxden.frame import CHANNELS
    from jaxden.io.conventions import CONVENTIONS, resolve
    from jaxden.io.exr import read_header

    if "emission" in split_spec(spec)[1]:
        return spec, None
    convention = getattr(args, "convention", None)
    header = read_header(path)
    names = dict(getattr(args, "channels", None) or ()).get("emission")  # --channels wins
    if convention in (None, "jaxden"):  # a file jaxden wrote: the renders it merged
        listed = buffer_list(header, str(path))
        if listed is None or listed.convention is None:
            return spec, None
        rule = CONVENTIONS.get(listed.convention)
        names = names or CHANNELS["emission"]
    else:
        rule = CONVENTIONS.get(convention)
        names = names or resolve(convention, header["channels"], header,
                                 layer=getattr(args, "layer", None),
                                 where=str(path)).mapping.get("emission")
    if (rule is None or not rule.albedo_includes_emission or names is None
            or not set(names) <= set(header["channels"])):
        return spec, None
    text = str(spec)
    joined = f"{text},emission=separate" if split_spec(spec)[1] else f"{text}:emission=separate"
    return joined, (f"the albedo comes from {rule.name}, whose albedo holds the lamps' emission "
                    f"(read clipped to [0, 1]); the emission is kept out of the filter "
                    f"({joined}; add :emission=filter to filter it)")
