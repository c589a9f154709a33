"""`jaxden evaluate NAME`: one evaluator (:mod:`jaxden.evaluate`) on a held-out set, written
as a result (OUT.json + OUT.md).

jaxden's own evaluators have hand-written flags (:data:`_OPTIONS` reads them back); every
other registered evaluator, a plugin's, gets a sub-command made from its options dataclass
(:func:`add_option_flags`: one flag a field, typed by its annotation, defaulting to the
field's default; :func:`options_from_flags` reads them back)."""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import types
import typing
from pathlib import Path

from jaxden.cli.options import add_sure_options, sure_settings

DESCRIPTION = """\
Measure one thing on a held-out set and write OUT.json (per-crop rows, per-spp summary,
headline ratios, provenance: the command, git commit, machine, versions, dataset manifest hash
and config, seeds, weights hashes) and OUT.md (the tables). Examples:

  # the paper's Table 3 / Fig. 10 on our data: MC, OIDN, PD(OIDN) per spp
  jaxden evaluate pd --data $JAXDEN_HOME/data/test-chain --denoiser oidn --mixer oidn-pd \\
      --out experiments/results/pd/pd-oidn-test-shipped
  # SURE accuracy: image-mean SURE vs noise-corrected true MSE, per denoiser and spp
  jaxden evaluate sure --data $JAXDEN_HOME/data/test-chain --denoiser oidn \\
      --denoiser wskp-6 --out experiments/results/sure/sure-fig2
  # the same on fresh renders made of 16 sub-buffers: Stein SURE vs sub-buffer SURE
  jaxden evaluate sure-buffers --data $JAXDEN_HOME/data/test-high --denoiser oidn \\
      --buffers 16 --spp 64 128 256 512 1024 --out OUT
  # the tile oracle cross-fitted on an independent render, beside a PD result
  jaxden evaluate oracle --data $JAXDEN_HOME/data/test-chain \\
      --report experiments/results/pd/pd-oidn-test-shipped.json --out OUT
  # a denoiser's PSNR / SSIM / relMSE / FLIP at 1 spp (and, where the frames carry the
  # emission, relMSE and mean brightness on the lamp pixels), or per frame of sequences
  jaxden evaluate denoise --data $JAXDEN_HOME/data/rt-test --denoiser wskp-6 --out OUT
  jaxden evaluate sequences --data $JAXDEN_HOME/data/rt-seq --denoiser wskp-6 --out OUT

--from-json OUT.json re-tabulates a finished result without measuring again. An evaluator of
your own (jaxden.evaluate.register_evaluator in a module named with --plugin FILE) is one more
NAME, with one flag per field of its options: jaxden evaluate NAME --plugin FILE --help."""


def logit_bound(text: str) -> float:
    """--logit-bound: a number > 0, or 'none' (0.0 here: no bound)."""
    if text.strip().lower() == "none":
        return 0.0
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a number > 0 or 'none', got {text!r}")
    return value


def _spp(values) -> tuple[int, ...] | None:
    return None if values is None else tuple(values)


#: Each evaluator's options from the parsed arguments.
_OPTIONS = {
    "pd": lambda a: {"denoiser": a.denoiser, "mixer": a.mixer, "split": a.split,
                     "sure": sure_settings(a), "spp": _spp(a.spp),
                     "swap_average": a.swap_average, "tstat": tuple(a.tstat),
                     "logit_bound": a.logit_bound, "mixer_set": tuple(a.mixer_set)},
    "oracle": lambda a: {"denoiser": a.denoiser, "split": a.split, "report": a.report},
    "sure": lambda a: {"denoisers": tuple(a.denoiser), "split": a.split,
                       "sure": sure_settings(a), "spp": _spp(a.spp)},
    "sure-buffers": lambda a: {"denoisers": tuple(a.denoiser), "split": a.split,
                               "sure": sure_settings(a), "spp": _spp(a.spp),
                               "buffers": a.buffers, "renders": a.renders},
    "denoise": lambda a: {"denoiser": a.denoiser, "split": a.split,
                          "spp": _spp(a.spp) or (1,), "include_input": a.include_input},
    "sequences": lambda a: {"denoiser": a.denoiser, "skip_frames": a.skip_frames},
}


def cmd_evaluate(args: argparse.Namespace) -> int:
    from jaxden.evaluate import get_evaluator, make_options, write_evaluation
    from jaxden.provenance import run_identity

    evaluator = get_evaluator(args.evaluator)
    options = None if args.from_json else make_options(evaluator.name,
                                                       **args.evaluate_options(args))
    # the command as typed: `jaxden evaluate NAME ...` (main() records its words)
    words = getattr(args, "command_line", None)
    identity = run_identity(list(sys.argv[1:] if words is None else words), program="jaxden")
    write_evaluation(evaluator, args.data, options, args.out, identity=identity,
                     from_json=args.from_json,
                     keep_current=getattr(args, "keep_current", False), progress=True)
    return 0


# ------------------------------------------------------------- flags from an options class
#: Where the flag of an options field keeps its value in the parsed arguments (apart from
#: the command's own: ``data``, ``out``, ...).
_DEST = "option:"
#: Field types a flag reads from its text (a tuple of them, or a Literal of their values, too).
_SCALARS = (str, int, float, Path)


def _field_types(options: type) -> dict[str, typing.Any]:
    """The annotations of ``options``' fields, resolved (a field whose annotation cannot be
    resolved: its plain built-in type where the text names one, else None)."""
    try:
        return typing.get_type_hints(options)
    except Exception:  # noqa: BLE001 - a plugin's forward reference: fields map one by one
        plain = {"str": str, "int": int, "float": float, "bool": bool}
        return {f.name: plain.get(f.type) if isinstance(f.type, str) else f.type
                for f in dataclasses.fields(options)}


def _without_none(kind):
    """``X`` of ``X | None`` (``Optional[X]``); ``kind`` otherwise."""
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        rest = [a for a in typing.get_args(kind) if a is not type(None)]
        if len(rest) == 1:
            return rest[0]
    return kind


def _scalar(kind) -> dict | None:
    """``add_argument`` keywords reading one value of ``kind`` (a scalar or a Literal)."""
    if typing.get_origin(kind) is typing.Literal:
        choices = typing.get_args(kind)
        kinds = {type(c) for c in choices}
        if len(kinds) == 1 and next(iter(kinds)) in _SCALARS:
            return {"type": next(iter(kinds)), "choices": choices}
        return None
    if kind in _SCALARS:
        return {"type": kind}
    return None


def field_flag(kind) -> dict | str | None:
    """How a field of type ``kind`` is given on the command line: ``add_argument`` keywords;
    "sure" for a SureSettings (the flags of :func:`add_sure_options`); None: no flag."""
    from jaxden.sure.settings import SureSettings

    kind = _without_none(kind)
    if kind is SureSettings:
        return "sure"
    if kind is bool:
        return {"action": argparse.BooleanOptionalAction}
    if kind is tuple:
        return {"type": str, "nargs": "+"}
    if typing.get_origin(kind) is tuple:
        items = typing.get_args(kind)
        if len(items) == 2 and items[1] is Ellipsis:
            one, count = _scalar(items[0]), "+"
        elif items and len(set(items)) == 1:
            one, count = _scalar(items[0]), len(items)
        else:
            one = None
        return None if one is None else {**one, "nargs": count}
    return _scalar(kind)


def _default(field: dataclasses.Field):
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


def _shown(value) -> str:
    if value is None:
        return "unset"
    if isinstance(value, (tuple, list)):
        return " ".join(map(str, value)) or "none"
    return str(value)


def add_option_flags(parser: argparse.ArgumentParser, options: type) -> list[str]:
    """One flag per field of the dataclass ``options``: ``--field-name VALUE`` (str, int,
    float, a path, a Literal's choices), ``--flag`` / ``--no-flag`` (bool), ``--field-name V
    [V ...]`` (a tuple), the flags of :func:`add_sure_options` (a SureSettings field); the
    help is the field's ``metadata["help"]`` and its default. An unset flag leaves the field
    at the dataclass's default; a field without one is a required flag. Returns the fields
    that have no flag (a type no flag reads): they keep their defaults."""
    types_ = _field_types(options)
    unflagged = []
    for field in dataclasses.fields(options):
        if not field.init:
            continue
        how = field_flag(types_.get(field.name))
        default = _default(field)
        if how is None:
            unflagged.append(field.name)
            continue
        if how == "sure":
            from jaxden.sure.settings import SureSettings

            inherited = isinstance(default, SureSettings) and default.given()
            add_sure_options(parser, inherit="the evaluator's" if inherited else None)
            continue
        text = field.metadata.get("help", "")
        required = default is dataclasses.MISSING
        shown = "required" if required else f"default: {_shown(default)}"
        if "action" not in how:
            how = {**how, "metavar": how.get("metavar") or field.name.upper()}
            if "choices" in how:
                del how["metavar"]  # argparse shows {a,b,c}
        parser.add_argument("--" + field.name.replace("_", "-"), dest=_DEST + field.name,
                            default=argparse.SUPPRESS, required=required,
                            help=f"{text}{'; ' if text else ''}{shown}", **how)
    return unflagged


def options_from_flags(args: argparse.Namespace, options: type) -> dict:
    """The keyword values of ``options``' fields given by the flags of
    :func:`add_option_flags` (tuples as tuples; a SureSettings field: the given SURE flags
    over the field's default); fields not given are left out (their defaults apply).
    ConfigError naming a field without a default that no flag can give."""
    from jaxden.errors import ConfigError
    from jaxden.sure.settings import SureSettings

    types_ = _field_types(options)
    values = {}
    for field in dataclasses.fields(options):
        if not field.init:
            continue
        how = field_flag(types_.get(field.name))
        default = _default(field)
        if how == "sure":
            given = sure_settings(args)
            if isinstance(default, SureSettings):
                values[field.name] = given.over(default)
            elif given.given() or default is dataclasses.MISSING:
                values[field.name] = given
        elif how is None:
            if default is dataclasses.MISSING:
                raise ConfigError(
                    f"option {field.name!r} of {options.__name__} ({types_.get(field.name)}) "
                    f"has no default and no command-line flag (flags read str, int, float, "
                    f"bool, a path, a Literal, a tuple of those and SureSettings)")
        elif hasattr(args, _DEST + field.name):
            value = getattr(args, _DEST + field.name)
            values[field.name] = tuple(value) if isinstance(value, list) else value
    return values


# --------------------------------------------------------------------------- the command
def add_evaluator_command(names, evaluator) -> argparse.ArgumentParser:
    """The sub-command of an evaluator without hand-written flags (a plugin's): ``--data``,
    ``--out``, ``--from-json``, ``--keep-current`` and one flag per field of its options
    (:func:`add_option_flags`)."""
    e = names.add_parser(evaluator.name, help=evaluator.description,
                         description=evaluator.description)
    e.add_argument("--data", required=True, help="the data it reads (a dataset folder)")
    e.add_argument("--out", required=True, help="output path without suffix")
    e.add_argument("--from-json", default=None,
                   help="re-tabulate the rows of a finished result (OUT.json) instead")
    e.add_argument("--keep-current", action="store_true",
                   help="keep OUT.json when it is current (when the evaluator can tell)")
    unflagged = add_option_flags(e, evaluator.options)
    if unflagged:
        e.epilog = (f"Options without a flag (their type has no command-line form) keep "
                    f"their defaults: {', '.join(unflagged)}.")
    e.set_defaults(func=cmd_evaluate,
                   evaluate_options=lambda args: options_from_flags(args, evaluator.options))
    return e


def add_commands(sub) -> None:
    p = sub.add_parser("evaluate", help="measure an evaluator (pd, sure, denoise, ...) on a "
                       "held-out set and write the result",
                       description=DESCRIPTION,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    names = p.add_subparsers(dest="evaluator", required=True, metavar="NAME")
    from jaxden.evaluate.registry import EVALUATORS

    for name, evaluator in EVALUATORS.items():
        if name in _OPTIONS:
            _add_built_in_command(names, name, evaluator)
        else:
            add_evaluator_command(names, evaluator)


def _add_built_in_command(names, name: str, evaluator) -> None:
    """The hand-written flags of one of jaxden's own evaluators (read by :data:`_OPTIONS`)."""
    e = names.add_parser(name, help=evaluator.description,
                         description=evaluator.description)
    e.add_argument("--data", required=True,
                   help="complete dataset folder (the test set; sequences: a sequence set)")
    if name != "sequences":
        e.add_argument("--split", default="test", help="split to evaluate (test, val, all)")
    if name in ("sure", "sure-buffers"):
        e.add_argument("--denoiser", action="append", required=True,
                       help="oidn, a shipped name or a checkpoint folder (repeatable)")
    else:
        e.add_argument("--denoiser", required=name != "oracle",
                       default="oidn" if name == "oracle" else None,
                       help="oidn, a shipped name or a checkpoint folder"
                            + (" (default oidn)" if name == "oracle" else ""))
    if name in ("pd", "sure", "sure-buffers"):  # item i's probes: fold_in(seed, i)
        add_sure_options(e, inherit="the mixer's" if name == "pd" else None)
    if name in ("pd", "sure", "sure-buffers", "denoise"):
        e.add_argument("--spp", type=int, nargs="+", default=None,
                       help="only these input spp levels (default: all; denoise: 1)")
    e.add_argument("--out", required=True, help="output path without suffix")
    e.add_argument("--from-json", default=None,
                   help="re-tabulate the rows of a finished result (OUT.json) instead")
    if name == "pd":
        e.add_argument("--mixer", default="oidn-pd", help="mixer spec (default oidn-pd)")
        e.add_argument("--swap-average", action=argparse.BooleanOptionalAction,
                       default=None, help="override the mixer config's swap_average")
        e.add_argument("--tstat", action="append", default=[], metavar="KEY=VALUE",
                       help="override a field of the mixer's t-statistic config "
                            "(jaxden.progressive.TStatConfig), e.g. sigma_min=1.0; "
                            "repeatable")
        e.add_argument("--logit-bound", default=None, type=logit_bound, metavar="B|none",
                       help="override a closed_form_logit mixer's logit_bound at inference "
                            "(an ablation: 'none' removes the bound it was trained with)")
        e.add_argument("--keep-current", action="store_true",
                       help="keep OUT.json when it was made on the same dataset build "
                            "with the same denoiser, mixer, config and options")
        e.add_argument("--mixer-set", action="append", default=[], metavar="KEY=VALUE",
                       help="override a field of the mixer's config "
                            "(jaxden.progressive.MixerConfig) at inference, e.g. "
                            "closed_form_stops=1; repeatable")
    if name == "oracle":
        e.add_argument("--report", default=None,
                       help="a PD result .json on the same data: its PD rows are compared")
    if name == "sure-buffers":
        e.add_argument("--buffers", type=int, default=16,
                       help="independent sub-buffers per render (spp / buffers each)")
        e.add_argument("--renders", type=int, default=1,
                       help="independent renders per crop and spp")
    if name == "denoise":
        e.add_argument("--no-input", dest="include_input", action="store_false",
                       help="do not score the noisy input beside the denoiser")
    if name == "sequences":
        e.add_argument("--skip-frames", type=int, default=1,
                       help="leading frames of each sequence left out (no history yet)")
    e.set_defaults(func=cmd_evaluate, evaluate_options=_OPTIONS[name])
