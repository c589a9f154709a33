"""Where a result comes from: the command and git commit a run started at, the machine, package
versions, the data build and file hashes, and the atomic writer of a result's .json + .md pair.

Every writer of results (``jaxden evaluate``, ``jaxden sweep``'s summaries, the scripts under
experiments/ and the shipped weights' records) takes these from here, so each number can be
traced to the command, code and data that made it. A leaf module: it imports nothing of
jaxden's but :mod:`jaxden.paths`, :mod:`jaxden.fileio` and :mod:`jaxden.plugins` (itself a
leaf), so every floor may use it.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

#: The repository root of a source checkout (an editable install); git runs there.
ROOT = Path(__file__).resolve().parent.parent
#: Paths whose changes do not make a run "+dirty": finished results being rewritten, and
#: re-shipped weights and cards (a result names the weights it used by their sha256).
CLEAN_EXCLUDES = ("experiments/results", "jaxden/weights")
#: The packages whose versions a result records.
VERSIONED_PACKAGES = ("pyoidn", "mitsuba", "jax")


def file_sha256(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """The sha256 of a file's bytes (hex), read in ``chunk``-byte blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def package_version(name: str) -> str:
    """An installed package's version from its metadata, or "not installed"."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return "not installed"


def versions(names: tuple[str, ...] = VERSIONED_PACKAGES) -> dict[str, str]:
    """``{package: version}`` of ``names`` (:func:`package_version`)."""
    return {name: package_version(name) for name in names}


def machine() -> str:
    """The machine a result was measured on: architecture, CPU count, platform."""
    return f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}"


def today() -> str:
    return datetime.date.today().isoformat()


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], capture_output=True, text=True, cwd=ROOT,
                              timeout=10, check=False).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def git_commit(*, dirty: bool = True, excludes: tuple[str, ...] = CLEAN_EXCLUDES) -> str:
    """The short git commit of the checkout ("unknown" outside one); with ``dirty``,
    "+dirty" when a tracked file outside ``excludes`` has uncommitted changes."""
    commit = _git("rev-parse", "--short", "HEAD") or "unknown"
    if dirty and _git("status", "--porcelain", "--untracked-files=no", "--", ".",
                      *(f":(exclude){path}" for path in excludes)):
        commit += "+dirty"
    return commit


def run_identity(argv: list[str] | None = None, program: str | None = None) -> dict:
    """The command line and the git commit (:func:`git_commit`) a run started at.

    ``program``: the command's words before ``argv`` (default ``python experiments/<the
    running script's name>``); ``argv``: default ``sys.argv[1:]``. Paths under $JAXDEN_HOME
    are written as ``$JAXDEN_HOME/...`` (:func:`jaxden.paths.portable`)."""
    from jaxden.paths import portable

    argv = sys.argv[1:] if argv is None else argv
    program = program or f"python experiments/{Path(sys.argv[0]).name}"
    identity = {"command": portable(f"{program} {shlex.join(argv)}".rstrip()),
                "commit": git_commit()}
    return {**identity, **plugin_record()}


def plugin_record() -> dict:
    """``{"plugins": [{module, sha256, file}, ...]}`` of the plugins this process imported
    (:mod:`jaxden.plugins`: a result computed with a user's code records which code), or
    ``{}`` when there are none."""
    from jaxden import plugins

    loaded = plugins.provenance()
    return {"plugins": loaded} if loaded else {}


def dataset_identity(directory, manifest_file, config: dict, split: str | None) -> dict:
    """Which build of a dataset a result was measured on: its folder, the split, the sha256 of
    its manifest (a rebuild changes it) and the dataset config the manifest records."""
    return {"dir": str(directory), "split": split, "manifest_sha256": file_sha256(manifest_file),
            "config": config}


def result_provenance(identity: dict, dataset: dict | None = None, **extra) -> dict:
    """A result's ``provenance`` entry: the run's ``identity`` (:func:`run_identity`), the
    date, the machine, the package versions, the ``dataset`` (:func:`dataset_identity`) and
    ``extra`` (seeds, weights, options), in that order."""
    out = {**identity, "date": today(), "machine": machine(), "versions": versions()}
    if dataset is not None:
        out["dataset"] = dataset
    return {**out, **extra}


def write_result(out: str | os.PathLike, result: dict, table: str, *,
                 echo: bool = True) -> None:
    """OUT.json (``result``, with a ``provenance`` entry) and OUT.md (``table`` under a
    generated-by line), both written atomically; with ``echo`` the table is printed too."""
    from jaxden.fileio import atomic_write_text

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out.with_suffix(".json"),
                      json.dumps(result, indent=1, sort_keys=True, default=float) + "\n")
    header = (f"<!-- generated by: {result['provenance']['command']} "
              f"(commit {result['provenance']['commit']}) -->\n")
    atomic_write_text(out.with_suffix(".md"), header + table + "\n")
    if echo:
        print(table)
        print(f"\nwrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")
