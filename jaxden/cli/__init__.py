"""The ``jaxden`` command: a thin layer over the library functions.

User errors (:class:`jaxden.errors.JaxdenError`) print one line ``jaxden: error: ...`` and exit
with status 2; anything else is a bug and keeps its traceback.

One module per command group (:mod:`jaxden.cli.render`, ``dataset``, ``train``, ``denoise``,
``evaluate``, ``bench``, ``demo``, ``report``), each with ``cmd_*`` functions and ``add_commands(subparsers)``; shared
option types live in :mod:`jaxden.cli.options`.
"""

from __future__ import annotations

import argparse
import sys

from jaxden.cli import bench, dataset, demo, denoise, evaluate, render, report, train
from jaxden.errors import JaxdenError


class _Parser(argparse.ArgumentParser):
    """argparse with jaxden's one-line errors: ``jaxden: error: COMMAND: message``, exit 2
    (argparse prints the usage block first; ``--help`` still shows it)."""

    def error(self, message: str):
        command = self.prog.removeprefix("jaxden").strip()
        where = f"{command}: " if command else ""
        self.exit(2, f"jaxden: error: {where}{message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="jaxden", description="Monte Carlo denoising research in JAX (see README.md)."
    )
    from jaxden import __version__

    parser.add_argument("--version", action="version", version=f"jaxden {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in (demo, render, dataset, denoise, train, evaluate, bench, report):
        group.add_commands(sub)
    _add_plugin_option(parser)
    return parser


PLUGIN_HELP = ("import MODULE (a module name, or a .py file) before names resolve: its "
               "denoisers, models, mixers, losses and evaluators join jaxden's (repeatable; "
               "also JAXDEN_PLUGINS=a,b; docs/your-denoiser.md)")


def _add_plugin_option(parser: argparse.ArgumentParser) -> None:
    """``--plugin`` on every command and sub-command, for --help (main() takes the words out
    of the command line before parsing: plugins must be imported before the parser lists
    registered names)."""
    parser.add_argument("--plugin", action="append", metavar="MODULE", default=[],
                        help=PLUGIN_HELP)
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                _add_plugin_option(child)


def _is_allocation_failure(error: BaseException) -> bool:
    """XLA's allocation failures (``RESOURCE_EXHAUSTED``, "Out of memory allocating ...")."""
    text = str(error)
    return type(error).__name__ in ("JaxRuntimeError", "XlaRuntimeError") and (
        "RESOURCE_EXHAUSTED" in text or "Out of memory" in text or "out of memory" in text)


def main(argv: list[str] | None = None) -> int:
    from jaxden import plugins

    words = list(sys.argv[1:] if argv is None else argv)
    try:
        specs, rest = plugins.take_plugin_options(words)
        plugins.load_all(specs, origin="--plugin")
    except JaxdenError as error:
        print(f"jaxden: error: {error}", file=sys.stderr)
        return 2
    parser = build_parser()
    args, extra = parser.parse_known_args(rest)
    args.command_line = words  # results record it
    # argparse gives a trailing ``overrides`` positional nothing once an option comes between
    # it and the config (``CONFIG --out DIR key=value``); take key=value words left over.
    if extra and hasattr(args, "overrides") and all("=" in w and not w.startswith("-")
                                                    for w in extra):
        args.overrides = [*args.overrides, *extra]
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    from jaxden import distributed

    code = None
    try:
        if args.command in ("train", "sweep"):
            # One JAX device per core on a CPU (data-parallel steps; docs/scaling.md), before
            # JAX creates its backend; XLA_FLAGS or JAXDEN_CPU_DEVICES override. Not for
            # `bench`: it times single-device inference as `denoise` and `progressive` run it,
            # which a second device slows (measured: docs/history.md, "Benchmarks");
            # `bench sharding` starts its own two-device processes.
            distributed.use_all_cores()
        from jaxden.compile_cache import enable_compilation_cache

        enable_compilation_cache()
        code = int(args.func(args) or 0)
    except JaxdenError as error:
        print(f"jaxden: error: {error}", file=sys.stderr)
        code = 2
    except OSError as error:  # e.g. an output folder that cannot be made: name the path
        where = f"{error.filename}: " if error.filename else ""
        print(f"jaxden: error: {where}{error.strerror or error}", file=sys.stderr)
        code = 2
    except MemoryError:
        from jaxden.limits import address_space_room, format_bytes

        room = address_space_room()  # under ulimit -v / -d: say how much was left
        limit = f"; the {room[1]} leaves {format_bytes(room[0])}" if room else ""
        print(f"jaxden: error: out of memory (nothing was written{limit}); lower "
              f"--memory-limit or JAXDEN_MEMORY_LIMIT so that frames go in smaller tiles",
              file=sys.stderr)
        code = 2
    except Exception as error:
        if not _is_allocation_failure(error):
            raise
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        print(f"jaxden: error: out of memory ({first[:200]}; nothing was written); lower "
              f"--memory-limit or JAXDEN_MEMORY_LIMIT so that frames go in smaller tiles",
              file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        print("jaxden: interrupted (finished work is kept; run the same command to resume)",
              file=sys.stderr)
        code = 130
    if code and distributed.is_initialized():
        # A failed multi-process job: JAX's exit handler would wait for processes that may be
        # gone, then abort with pages of logs. The one line above is the message.
        distributed.exit_now(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
